"""The server's audit trail as the lab database keeps it: the ``audit`` table, read.

Each row carries the digest of the one before it; a row is appended by `labcal.store.chain.append_audit`
(the one place that chains it), and `labcal.app.audit` says what a row means and checks the chain.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sqlalchemy import desc, func, select

from labcal.store.schema import audit

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

COLUMNS = (audit.c.id, audit.c.utc, audit.c.kind, audit.c.account, audit.c.actor, audit.c.client,
           audit.c.detail, audit.c.prev, audit.c.digest)


def newest(engine: Engine, limit: int, before: int | None = None) -> list[tuple]:
    """The newest ``limit`` rows (before the row id ``before``), newest first, as `COLUMNS`."""
    query = select(*COLUMNS).order_by(desc(audit.c.id)).limit(limit)
    if before is not None:
        query = query.where(audit.c.id < before)
    with engine.connect() as conn:
        return [tuple(r) for r in conn.execute(query)]


def count(engine: Engine) -> int:
    with engine.connect() as conn:
        return int(conn.execute(select(func.count()).select_from(audit)).scalar_one())


def in_order(engine: Engine) -> list[tuple]:
    """Every row, oldest first, as `COLUMNS`."""
    with engine.connect() as conn:
        return [tuple(r) for r in conn.execute(select(*COLUMNS).order_by(audit.c.id))]


def account_rows(engine: Engine, account: str, kinds: tuple[str, ...], limit: int,
                 latest_of: tuple[str, ...]) -> tuple[list[tuple[str, str]], str | None]:
    """``account``'s newest ``limit`` rows of the ``kinds`` as (kind, utc), newest first, and the kind
    of its newest row of the kinds ``latest_of`` (None: it has none), read together."""
    query = (select(audit.c.kind, audit.c.utc).where(audit.c.account == account, audit.c.kind.in_(kinds))
             .order_by(desc(audit.c.id)).limit(limit))
    latest = (select(audit.c.kind).where(audit.c.account == account, audit.c.kind.in_(latest_of))
              .order_by(desc(audit.c.id)).limit(1))
    with engine.connect() as conn:
        rows = [(k, u) for k, u in conn.execute(query)]
        return rows, conn.execute(latest).scalar()
