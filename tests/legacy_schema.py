"""The schema steps labcal applied to its SQLite files before Alembic kept the history, verbatim
from `labcal/store/labdb.py` as it was (commit 9c7cfd8, ``MIGRATIONS``): version N of a file was
``PRAGMA user_version = N``. Kept here, apart from labcal, to make the files the labcal of then
wrote, so that tests can check what this labcal does with them."""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

V0 = Path(__file__).parent / "data" / "v0" / "labcal.sqlite"  # made by labcal a8863ee

STEPS: dict[int, tuple[str, ...]] = {
    1: ("CREATE INDEX events_by_run ON events (run_id, id)",),
    2: ("ALTER TABLE runs ADD COLUMN uuid TEXT",
        "CREATE UNIQUE INDEX runs_by_uuid ON runs (uuid)",
        "CREATE TABLE run_exports (run_id INTEGER NOT NULL REFERENCES runs(id), name TEXT NOT NULL, "
        "sha256 TEXT NOT NULL, PRIMARY KEY (run_id, name))"),
    3: ("""CREATE TABLE device_estimates (
    device_id TEXT NOT NULL,
    source TEXT NOT NULL,
    calibrated_utc TEXT NOT NULL,
    stored_utc TEXT NOT NULL,
    document TEXT NOT NULL,
    PRIMARY KEY (device_id, source)
)""", "CREATE INDEX device_estimates_by_date ON device_estimates (device_id, calibrated_utc)"),
    4: ("""CREATE TABLE approvers (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    role TEXT NOT NULL,
    public_key TEXT NOT NULL,
    key_id TEXT NOT NULL UNIQUE,
    added_utc TEXT NOT NULL,
    revoked_utc TEXT
)""", "CREATE UNIQUE INDEX approvers_active_name ON approvers (name) WHERE revoked_utc IS NULL"),
    5: ("""CREATE TABLE settle_pools (
    pool_key TEXT PRIMARY KEY,
    identity TEXT NOT NULL,
    records INTEGER NOT NULL,
    sources TEXT NOT NULL,
    mismatch TEXT NOT NULL,
    sums BLOB NOT NULL,
    updated_utc TEXT NOT NULL
)""",),
}


def legacy_file(path: Path, version: int) -> Path:
    """An empty file at user_version ``version`` as that labcal made it: the version-0 tables with
    the statements of labcal a8863ee (read from tests/data/v0), then each step up to ``version``."""
    with closing(sqlite3.connect(V0)) as old, closing(sqlite3.connect(path)) as con:
        for (sql,) in old.execute("SELECT sql FROM sqlite_master WHERE sql IS NOT NULL ORDER BY rowid"):
            con.execute(sql)
        for step in range(1, version + 1):
            for sql in STEPS[step]:
                con.execute(sql)
        con.execute(f"PRAGMA user_version = {version}")
        con.commit()
    return path
