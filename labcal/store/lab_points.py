"""A run's measured points as the lab database holds them: what the server's pages plot and the
approval certifies, read from the lab's copy rather than a bench's journal (which the server may not
reach)."""

from __future__ import annotations

from dataclasses import fields
from typing import TYPE_CHECKING

from sqlalchemy import func, select

from labcal.store.journal import PointRecord
from labcal.store.schema import points, runs

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection


def ok_points(connection: Connection, run_id: int) -> list[PointRecord]:
    """The run's good points in the order they were measured (none: an empty list)."""
    names = [f.name for f in fields(PointRecord)]
    rows = connection.execute(select(*(points.c[n] for n in names))
                              .where(points.c.run_id == run_id, points.c.status == "ok")
                              .order_by(points.c.seq))
    return [PointRecord(**dict(zip(names, r, strict=True))) for r in rows]


def points_state(connection: Connection, run_id: int) -> tuple[str, int, int, int | None]:
    """What changes whenever the run's good points do: the database (its URL without a password), the
    run, how many good points it has and the last one's number — the key under which something drawn
    from them can be kept."""
    count, last = connection.execute(select(func.count(), func.max(points.c.seq))
                                     .where(points.c.run_id == run_id, points.c.status == "ok")).one()
    return connection.engine.url.render_as_string(hide_password=True), run_id, int(count), last


def run_status_and_folder(connection: Connection, run_id: int) -> tuple[str | None, str | None]:
    """The run's status and the folder it was journaled with (None, None: no such run)."""
    row = connection.execute(select(runs.c.status, runs.c.run_dir).where(runs.c.id == run_id)).first()
    return (None, None) if row is None else (row.status, row.run_dir)
