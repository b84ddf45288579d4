"""The lab overview's queries over the lab database's runs, points, events and benches' roles: what
the lab server's pages and API (`labcal.app.lab`, `labcal.app.overview`, the approver's desk) show of
each run and its stream, read here.

Rows come back as SQLAlchemy rows read by attribute (``row.status``, ``row.plan_text``) under the
names of the columns selected (`SUMMARY`, `EVENT_COLUMNS`, `POINT_COLUMNS`).
"""

from __future__ import annotations

from collections.abc import Collection
from typing import TYPE_CHECKING, Any

from sqlalchemy import case, func, select

from labcal.store.journal import EventRow
from labcal.store.schema import events, points, runs, station_roles

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection, Engine

SUMMARY = (runs.c.id, runs.c.status, runs.c.station, runs.c.metadata, runs.c.instrument_serial,
           runs.c.operator, runs.c.plan_name, runs.c.plan_text, runs.c.points_total, runs.c.started_utc,
           runs.c.ended_utc, runs.c.reason, runs.c.run_dir, runs.c.station_text, runs.c.uuid)
EVENT_COLUMNS = (events.c.id, events.c.utc, events.c.station_time, events.c.kind, events.c.message,
                 events.c.data)
POINT_COLUMNS = (points.c.seq, points.c.replicate, points.c.y_deg, points.c.u_deg, points.c.pitch_deg,
                 points.c.roll_deg, points.c.status, points.c.t_end, points.c.utc, points.c.vx, points.c.vy,
                 points.c.vz)


def counts(conn: Connection, run_ids: list[int] | None = None) -> dict[int, tuple[int, int, int | None]]:
    """Per run: points journaled, points measured, the last step's seq."""
    ok = func.sum(case((points.c.status == "ok", 1), else_=0))
    query = select(points.c.run_id, func.count(), ok, func.max(points.c.seq)).group_by(points.c.run_id)
    if run_ids is not None:
        query = query.where(points.c.run_id.in_(run_ids))
    return {r: (int(n), int(k or 0), s) for r, n, k, s in conn.execute(query)}


def summaries(conn: Connection) -> list[Any]:
    """Every run (`SUMMARY`), newest first."""
    return list(conn.execute(select(*SUMMARY).order_by(runs.c.id.desc())).all())


def summary(conn: Connection, run_id: int) -> Any | None:
    """Run ``run_id`` (`SUMMARY`; None: no such run)."""
    return conn.execute(select(*SUMMARY).where(runs.c.id == run_id)).first()


def latest_event(conn: Connection, run_id: int, kind: str) -> Any | None:
    """The run's newest event of ``kind`` (`EVENT_COLUMNS`; None: none)."""
    return conn.execute(select(*EVENT_COLUMNS).where(events.c.run_id == run_id, events.c.kind == kind)
                        .order_by(events.c.id.desc()).limit(1)).first()


def last_point(conn: Connection, run_id: int) -> Any | None:
    """The run's last journaled point's ``y_deg``, ``u_deg``, ``t_end`` and ``utc`` (None: none yet)."""
    return conn.execute(select(points.c.y_deg, points.c.u_deg, points.c.t_end, points.c.utc)
                        .where(points.c.run_id == run_id).order_by(points.c.seq.desc()).limit(1)).first()


def latest_points(conn: Connection, run_id: int, n: int) -> list[Any]:
    """The run's latest ``n`` journaled points' ``utc`` and ``t_end`` (rig seconds), newest first."""
    return list(conn.execute(select(points.c.utc, points.c.t_end).where(points.c.run_id == run_id)
                             .order_by(points.c.seq.desc()).limit(n)).all())


def last_written(conn: Connection, run_id: int) -> list[str | None]:
    """When the run last journaled a point, and an event (UTC; None: never)."""
    return [conn.execute(select(func.max(table.c.utc)).where(table.c.run_id == run_id)).scalar()
            for table in (points, events)]


def answers_after(conn: Connection, run_id: int, event_id: int, kind: str) -> list[str]:
    """The messages of the run's events of ``kind`` after event ``event_id``."""
    return list(conn.execute(select(events.c.message).where(
        events.c.run_id == run_id, events.c.id > event_id, events.c.kind == kind)).scalars())


def events_after(conn: Connection, run_id: int, after: int = 0, limit: int | None = None) -> list[Any]:
    """The run's events (`EVENT_COLUMNS`) after event id ``after``, oldest first."""
    query = (select(*EVENT_COLUMNS).where(events.c.run_id == run_id, events.c.id > after)
             .order_by(events.c.id))
    if limit is not None:
        query = query.limit(limit)
    return list(conn.execute(query))


def points_after(conn: Connection, run_id: int, after: int = -1, limit: int | None = None) -> list[dict]:
    """The run's points (`POINT_COLUMNS`) with seq above ``after``, in order, as dicts."""
    query = (select(*POINT_COLUMNS).where(points.c.run_id == run_id, points.c.seq > after)
             .order_by(points.c.seq))
    if limit is not None:
        query = query.limit(limit)
    return [dict(r._mapping) for r in conn.execute(query)]


def newest(conn: Connection, run_id: int) -> tuple[int, int]:
    """The run's last journaled point's seq and last event's id (-1 and 0 when none: a new cursor)."""
    seq = conn.execute(select(func.max(points.c.seq)).where(points.c.run_id == run_id)).scalar()
    event_id = conn.execute(select(func.max(events.c.id)).where(events.c.run_id == run_id)).scalar()
    return (-1 if seq is None else int(seq), 0 if event_id is None else int(event_id))


def run_dir(engine: Engine, run_id: int) -> str | None:
    """Where the run's folder is, as its station journaled it (None: no such run)."""
    with engine.connect() as conn:
        return conn.execute(select(runs.c.run_dir).where(runs.c.id == run_id)).scalar()


def run_row(conn: Connection, *, uuid: str | None = None, local_id: int | None = None) -> Any | None:
    """A run's ``id``, ``uuid`` and journaled ``metadata`` by its uuid (the lab's) or its id in this
    database (a bench's journal); None: not here."""
    where = runs.c.uuid == uuid if uuid is not None else runs.c.id == local_id
    return conn.execute(select(runs.c.id, runs.c.uuid, runs.c.metadata).where(where)).first()


def complete_runs(conn: Connection) -> list[Any]:
    """Every complete run (`SUMMARY`), oldest first."""
    return list(conn.execute(select(*SUMMARY).where(runs.c.status == "complete").order_by(runs.c.id)).all())


def faults(conn: Connection, run_id: int) -> list[str]:
    """The messages of the run's fault events, in the order journaled."""
    query = select(events.c.message).where(events.c.run_id == run_id, events.c.kind == "fault")
    return list(conn.execute(query.order_by(events.c.id)).scalars())


def events_of_kind(conn: Connection, run_id: int, kind: str) -> list[EventRow]:
    """The run's events of one ``kind``, as the journal's readers take them."""
    rows = conn.execute(select(events.c.utc, events.c.station_time, events.c.kind, events.c.message,
                               events.c.data)
                        .where(events.c.run_id == run_id, events.c.kind == kind).order_by(events.c.id))
    return [EventRow.read(*row) for row in rows]


def run_place(conn: Connection, *, uuid: str | None = None, run_id: int | None = None) -> Any | None:
    """A run's ``id``, ``uuid``, ``station``, ``run_dir`` and journaled ``metadata``, by its uuid or its
    id in the lab (None: not here)."""
    where = runs.c.uuid == uuid if uuid is not None else runs.c.id == run_id
    return conn.execute(select(runs.c.id, runs.c.uuid, runs.c.station, runs.c.run_dir, runs.c.metadata)
                        .where(where)).first()


def registered_stations(conn: Connection) -> list[str]:
    """The benches granted a role of their own (none on SQLite, where nothing grants one)."""
    return list(conn.execute(select(station_roles.c.station).distinct()).scalars())


def timeline_rows(conn: Connection, run_id: int, kinds: Collection[str], n: int
                  ) -> tuple[list[Any], list[Any]]:
    """The run's events of ``kinds`` (``utc``, ``kind``, ``message``, ``data``), oldest first, and its
    latest ``n`` points (``utc``, ``t_end``, ``y_deg``, ``u_deg``), oldest first."""
    found = list(conn.execute(select(events.c.utc, events.c.kind, events.c.message, events.c.data).where(
        events.c.run_id == run_id, events.c.kind.in_(kinds)).order_by(events.c.id)))
    latest = conn.execute(select(points.c.utc, points.c.t_end, points.c.y_deg, points.c.u_deg)
                          .where(points.c.run_id == run_id).order_by(points.c.seq.desc()).limit(n))
    return found, list(reversed(list(latest)))
