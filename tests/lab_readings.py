"""A station's journal and the lab's PostgreSQL, read without labcal (sqlite3 and psycopg directly):
what the sync tests and benchmarks/lab_load.py compare, reading by reading."""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

import psycopg

# Every column of a point (the journal's names on both sides), written out here rather than taken
# from labcal's schema, so that a column the sync forgot is a difference and not a silent agreement.
POINT_COLUMNS = ("seq", "replicate", "y_deg", "u_deg", "pitch_deg", "roll_deg", "pitch_read", "roll_read",
                 "attempt", "status", "t_start", "t_end", "utc", "n_samples", "vx", "vy", "vz", "sd_vx",
                 "sd_vy", "sd_vz", "temp_c", "settle_s", "settle_verdict", "samples")
SELECT = (f"SELECT r.uuid, {', '.join('p.' + c for c in POINT_COLUMNS)} "
          "FROM points p JOIN runs r ON r.id = p.run_id")


def _plain(values) -> tuple:
    return tuple(bytes(v) if isinstance(v, (bytes, memoryview)) else v for v in values)


def journal_points(journal: Path) -> dict[tuple[str, int], tuple]:
    """Every point of a station's journal, keyed by (run uuid, seq)."""
    with closing(sqlite3.connect(journal)) as db:
        rows = db.execute(SELECT).fetchall()
    return {(row[0], row[1]): _plain(row[1:]) for row in rows}


def server_points(url: str) -> list[tuple]:
    """Every point in PostgreSQL with its run's uuid, duplicates kept (they are what is counted)."""
    with psycopg.connect(url) as conn:
        rows = conn.execute(SELECT).fetchall()
    return [(row[0], *_plain(row[1:])) for row in rows]
