"""The settling pools' rows in the journal (``settle_pools``): what `labcal.run.settle_pool` keeps
between runs, read and replaced here.

A row holds a pool's sufficient statistics (``sums``, an ``.npy`` blob), how many step records made
them, the runs they came from (``sources``, JSON) and any model mismatch seen; its ``identity`` is
the JSON its key was hashed from, written once when the row is made.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from labcal.store.journal import utc_now

if TYPE_CHECKING:
    import sqlite3


@dataclass(frozen=True)
class PoolRow:
    records: int
    sources: str  # JSON: [{"run": ..., "noise": ...}, ...]
    mismatch: str
    sums: bytes


def read(db: sqlite3.Connection, pool_key: str) -> PoolRow | None:
    """The row kept under ``pool_key`` (None: there is none)."""
    row = db.execute("SELECT records, sources, mismatch, sums FROM settle_pools WHERE pool_key=?",
                     (pool_key,)).fetchone()
    return None if row is None else PoolRow(int(row[0]), row[1], row[2], row[3])


def replace(db: sqlite3.Connection, pool_key: str, identity: str,
            change: Callable[[PoolRow | None], PoolRow]) -> None:
    """Replace the row under ``pool_key`` by ``change(the row there now)``, in one write transaction,
    so that two runs keeping the same pool at once each add to what the other kept."""
    db.execute("BEGIN IMMEDIATE")
    try:
        new = change(read(db, pool_key))
        db.execute("INSERT INTO settle_pools (pool_key, identity, records, sources, mismatch, sums, "
                   "updated_utc) VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (pool_key) DO UPDATE SET "
                   "records=excluded.records, sources=excluded.sources, mismatch=excluded.mismatch, "
                   "sums=excluded.sums, updated_utc=excluded.updated_utc",
                   (pool_key, identity, new.records, new.sources, new.mismatch, new.sums, utc_now()))
        db.execute("COMMIT")
    except BaseException:
        if db.in_transaction:
            db.execute("ROLLBACK")
        raise
