"""The approvers register's rows in a bench's journal (``approvers``): registered and revoked here,
sent to the lab database with the bench's other records (`labcal.store.sync`), and read from the lab
through `labcal.store.labquery.records`. What a registration means is `labcal.documents.approvers`'s.
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

from labcal.store import labdb

COLUMNS = ("name", "role", "public_key", "key_id", "added_utc", "revoked_utc")
_NAMES = ", ".join(COLUMNS)


def _rows(conn: sqlite3.Connection, where: str, params: tuple) -> list[tuple]:
    return [tuple(r) for r in conn.execute(f"SELECT {_NAMES} FROM approvers {where}", params)]


def same_key_or_active_name(path: Path, key_id: str, name: str) -> list[tuple]:
    """The journal's registrations of the key ``key_id``, and ``name``'s active one, as `COLUMNS`."""
    with closing(labdb.connect(path)) as conn:
        return _rows(conn, "WHERE key_id = ? OR (name = ? AND revoked_utc IS NULL)", (key_id, name))


def active(path: Path, name: str) -> list[tuple]:
    """``name``'s active registrations in the journal, as `COLUMNS`."""
    with closing(labdb.connect(path)) as conn:
        return _rows(conn, "WHERE name = ? AND revoked_utc IS NULL", (name,))


def insert(path: Path, row: tuple) -> bool:
    """Journal the registration ``row`` (`COLUMNS`); False when the name or the key was registered
    meanwhile (the unique constraints refused it)."""
    with closing(labdb.connect(path)) as conn:
        try:
            conn.execute(f"INSERT INTO approvers ({_NAMES}) VALUES (?, ?, ?, ?, ?, ?)", row)
        except sqlite3.IntegrityError:
            return False
    return True


def revoke(path: Path, row: tuple, when: str) -> None:
    """Journal the revocation, at ``when``, of the registration ``row`` (`COLUMNS`, registered at
    another bench: copied here first), in one transaction."""
    with closing(labdb.connect(path)) as conn:
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.execute(f"INSERT INTO approvers ({_NAMES}) VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT DO NOTHING",
                         (*row[:5], None))
            conn.execute("UPDATE approvers SET revoked_utc = ? WHERE key_id = ? AND revoked_utc IS NULL",
                         (when, row[3]))
            conn.execute("COMMIT")
        except BaseException:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
