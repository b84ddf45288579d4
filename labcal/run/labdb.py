"""The lab database: one SQLite file, one schema, owned here, versioned and migrated on open.

Every run of the lab (the journal: ``runs``, ``points``, ``events``) and every certificate issued
(``certificates``) live in one file (`labcal.run.journal.db_path`). The journal and the history
each used to create their own tables in it; now both open it through `connect`, which is the only
place that knows the schema. ``PRAGMA user_version`` is its version, and `MIGRATIONS` is the
ordered list of steps from each version to the next.

Version 0 is the schema as labcal created it before it was versioned: tables made with
``CREATE TABLE IF NOT EXISTS`` by whichever of the journal or the history opened the file first,
so a version-0 file may hold all four tables, only the journal's, only ``certificates``, or none.
`BASELINE` (idempotent) brings any of those to the full version-0 schema, and the migrations take
it from there; a new file goes the same way, so a new database and a migrated one cannot differ.

On open, a file older than this labcal is migrated in one transaction, under SQLite's write lock
(so two programs opening it at once migrate it once), after a consistent copy of it is written
beside it as ``<name>.v<old>.bak`` with SQLite's online backup (correct for a WAL database whose
latest pages are still in the -wal file). A failure rolls every step back: the file stays at its
old version, and says so in one line. A file newer than this labcal is refused, untouched.

Reads and writes name their columns (no ``SELECT *``, no ``INSERT … VALUES`` without a column
list), so a migration that adds a column never breaks the code that came before it.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import uuid
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

from labcal.config.files import size_text
from labcal.errors import LabcalError

# Version 0, exactly as the unversioned labcal created it (journal.py and history.py, a8863ee).
BASELINE: tuple[str, ...] = (
    """CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY,
    run_dir TEXT NOT NULL,
    plan_name TEXT NOT NULL, plan_text TEXT NOT NULL, plan_hash TEXT NOT NULL,
    station_text TEXT NOT NULL, station_hash TEXT NOT NULL,
    software_version TEXT NOT NULL, instrument_serial TEXT, device_id TEXT, operator TEXT,
    settings TEXT NOT NULL, metadata TEXT NOT NULL,
    started_utc TEXT NOT NULL, status TEXT NOT NULL, reason TEXT, ended_utc TEXT
)""",
    """CREATE TABLE IF NOT EXISTS points (
    run_id INTEGER NOT NULL REFERENCES runs(id), seq INTEGER NOT NULL,
    replicate INTEGER NOT NULL, y_deg REAL NOT NULL, u_deg REAL NOT NULL,
    pitch_deg REAL NOT NULL, roll_deg REAL NOT NULL, pitch_read REAL, roll_read REAL,
    attempt INTEGER NOT NULL, status TEXT NOT NULL, t_start REAL, t_end REAL, utc TEXT NOT NULL,
    n_samples INTEGER NOT NULL, vx REAL, vy REAL, vz REAL, sd_vx REAL, sd_vy REAL, sd_vz REAL,
    temp_c REAL, settle_s REAL, settle_verdict TEXT, samples BLOB,
    PRIMARY KEY (run_id, seq)
)""",
    """CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY, run_id INTEGER NOT NULL REFERENCES runs(id),
    utc TEXT NOT NULL, station_time REAL, kind TEXT NOT NULL, message TEXT NOT NULL, data TEXT
)""",
    """CREATE TABLE IF NOT EXISTS certificates (
    certificate_id TEXT PRIMARY KEY,
    serial TEXT NOT NULL,
    calibrated_utc TEXT NOT NULL,
    issued_utc TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    document TEXT NOT NULL
)""",
    "CREATE INDEX IF NOT EXISTS certificates_by_serial ON certificates (serial, calibrated_utc)",
)


@dataclass(frozen=True)
class Migration:
    """One step: from version ``version - 1`` to ``version``, inside the caller's transaction.

    ``apply`` must not commit (no ``executescript``, which commits first): the whole chain of
    steps commits together or not at all.
    """

    version: int
    why: str
    apply: Callable[[sqlite3.Connection], None]


def _v1_events_by_run(db: sqlite3.Connection) -> None:
    db.execute("CREATE INDEX events_by_run ON events (run_id, id)")


def _v2_run_identity_and_exports(db: sqlite3.Connection) -> None:
    db.execute("ALTER TABLE runs ADD COLUMN uuid TEXT")
    for (run_id,) in db.execute("SELECT id FROM runs").fetchall():
        db.execute("UPDATE runs SET uuid=? WHERE id=?", (str(uuid.uuid4()), run_id))
    db.execute("CREATE UNIQUE INDEX runs_by_uuid ON runs (uuid)")
    db.execute("CREATE TABLE run_exports (run_id INTEGER NOT NULL REFERENCES runs(id), name TEXT NOT NULL, "
               "sha256 TEXT NOT NULL, PRIMARY KEY (run_id, name))")


def _v3_device_estimates(db: sqlite3.Connection) -> None:
    db.execute("""CREATE TABLE device_estimates (
    device_id TEXT NOT NULL,
    source TEXT NOT NULL,
    calibrated_utc TEXT NOT NULL,
    stored_utc TEXT NOT NULL,
    document TEXT NOT NULL,
    PRIMARY KEY (device_id, source)
)""")
    db.execute("CREATE INDEX device_estimates_by_date ON device_estimates (device_id, calibrated_utc)")


def _v4_approvers(db: sqlite3.Connection) -> None:
    # One row per registration: a revoked row stays (it names who signed the certificates of the
    # past); a name is active at most once and a key is registered once, ever, so that a key can
    # never sign under two names and a revoked key never comes back.
    db.execute("""CREATE TABLE approvers (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    role TEXT NOT NULL,
    public_key TEXT NOT NULL,
    key_id TEXT NOT NULL UNIQUE,
    added_utc TEXT NOT NULL,
    revoked_utc TEXT
)""")
    db.execute("CREATE UNIQUE INDEX approvers_active_name ON approvers (name) WHERE revoked_utc IS NULL")


def _v5_settle_pools(db: sqlite3.Connection) -> None:
    db.execute("""CREATE TABLE settle_pools (
    pool_key TEXT PRIMARY KEY,
    identity TEXT NOT NULL,
    records INTEGER NOT NULL,
    sources TEXT NOT NULL,
    mismatch TEXT NOT NULL,
    sums BLOB NOT NULL,
    updated_utc TEXT NOT NULL
)""")


MIGRATIONS: tuple[Migration, ...] = (
    Migration(1, "index events by run: `Journal.events(run)` (the audit trail of prompts, faults, "
                 "retries and pauses) read the whole lab's events table for every run, and "
                 "events.run_id is a foreign key that SQLite advises indexing (points are already "
                 "indexed by their primary key (run_id, seq)). An index only, so the previous labcal "
                 "still reads and writes a version-1 file.", _v1_events_by_run),
    Migration(2, "run identity and export hashes: a run gets a UUID (runs.uuid, written into its "
                 "run.json), so a run folder whose database was restored or re-created (ids reused) is "
                 "recognised as another run's; run_exports keeps the SHA-256 of every file labcal last "
                 "wrote into a run folder, so a missing, stale or hand-edited export is detected and "
                 "rewritten from the journal. Existing runs get a UUID here. Additive only.",
              _v2_run_identity_and_exports),
    Migration(3, "the calibration device's own history (issue 12): each run's device-model estimate of "
                 "the misalignments a…k per calibration-device id, for `labcal device history`. A new "
                 "table only, so the previous labcal still reads and writes a version-2 file.",
              _v3_device_estimates),
    Migration(4, "approvers registered by the lab (issue 23): name, role and Ed25519 public key of each "
                 "person who may approve a certificate, with the time of registration and of revocation, "
                 "so that `certificate approve` and `attitude --cert` accept only signatures by a "
                 "registered, unrevoked key under its own name and role. A new table only.",
              _v4_approvers),
    Migration(5, "model settling's pooled step records (issue 27): per instrument (or type) and station, "
                 "the sums `labcal.run.settle.TailPool` keeps over its records, so that a run starts with "
                 "the records of the runs before it (`labcal.run.settle_pool`). A new table only, so the "
                 "previous labcal still reads and writes a version-3 file.", _v5_settle_pools),
)
SCHEMA_VERSION = MIGRATIONS[-1].version


def backup_path(path: Path, version: int) -> Path:
    """Where the copy made before migrating from ``version`` goes: beside the database."""
    return path.with_name(f"{path.name}.v{version}.bak")


def version_of(db: sqlite3.Connection) -> int:
    return int(db.execute("PRAGMA user_version").fetchone()[0])


def connect(path: str | Path, migrations: tuple[Migration, ...] = MIGRATIONS) -> sqlite3.Connection:
    """Open the lab database at the current schema (its folder made if need be): WAL,
    synchronous=FULL, foreign keys on, autocommit (callers open their own transactions), migrated
    first if older.

    ``migrations`` is the schema's history; only tests give another one (a step that fails).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabcalError(f"{path.parent}: cannot create the database folder ({exc.strerror})") from None
    try:
        db = sqlite3.connect(path, timeout=10.0, isolation_level=None)
    except sqlite3.Error as exc:
        raise failure(path, exc) from None
    try:
        db.execute("PRAGMA journal_mode=WAL")  # readers never block the journal's writer
        db.execute("PRAGMA synchronous=FULL")  # a committed point survives a power cut
        db.execute("PRAGMA foreign_keys=ON")
        migrate(db, path, migrations)
    except sqlite3.Error as exc:
        db.close()
        raise failure(path, exc) from None
    except BaseException:
        db.close()
        raise
    return db


def failure(path: Path, exc: sqlite3.Error) -> LabcalError:
    """One line for a database that cannot be used: which file, what is wrong, what to do.

    A full disk, a read-only file and a damaged file are the lab's to fix, not labcal's; each says
    so without a traceback, and nothing committed before is lost (SQLite rolls the open
    transaction back)."""
    text = str(exc)
    code = getattr(exc, "sqlite_errorcode", None)
    if code == sqlite3.SQLITE_FULL or "full" in text:
        free = _free_bytes(path.parent)
        return LabcalError(f"{path}: disk full ({size_text(free)} free in {path.parent}); free at least "
                           f"{size_text(FREE_SPACE_WANTED)} there and run the command again (every "
                           "committed reading is kept)")
    cannot_write = path.exists() and not (os.access(path, os.W_OK) and os.access(path.parent, os.W_OK))
    if code == sqlite3.SQLITE_READONLY or "readonly" in text or "read-only" in text or cannot_write:
        return LabcalError(f"{path}: the lab database is read-only ({text}); make the file and its folder "
                           "writable (or give --db / set LABCAL_DB to a writable copy) and run it again")
    damaged = code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
    if damaged or "malformed" in text or "not a database" in text:
        return LabcalError(f"{path}: the lab database is damaged ({text}); check it with sqlite3 {path} "
                           "'PRAGMA integrity_check' and restore it from its latest backup")
    if code == sqlite3.SQLITE_BUSY or "locked" in text:
        return LabcalError(f"{path}: the lab database is busy ({text}); another labcal is writing it: "
                           "wait for it and run the command again")
    return LabcalError(f"{path}: cannot use the lab database ({text})")


FREE_SPACE_WANTED = 10_000_000  # a run's points and events, with room for SQLite's write-ahead log


def _free_bytes(folder: Path) -> int:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return 0


def migrate(db: sqlite3.Connection, path: Path, migrations: tuple[Migration, ...] = MIGRATIONS) -> int:
    """Bring the open database to the last version of ``migrations``; returns the version found.

    Nothing to do (the usual case) costs one pragma. Otherwise, under the write lock: read the
    version again (another program may have just migrated it), back the file up if it holds
    anything, and apply the baseline and every later step in one transaction.
    """
    target = migrations[-1].version if migrations else 0
    found = version_of(db)
    if found == target:
        return found
    if found > target:
        raise _newer(path, found, target)
    db.execute("BEGIN IMMEDIATE")
    try:
        found = version_of(db)  # another program may have migrated it while we waited for the lock
        if found < target:
            if db.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]:
                _backup(path, backup_path(path, found))
            if found == 0:
                for statement in BASELINE:
                    db.execute(statement)
            for step in migrations:
                if step.version > found:
                    step.apply(db)
            db.execute(f"PRAGMA user_version = {int(target)}")
        db.execute("COMMIT")
    except BaseException as exc:
        if db.in_transaction:  # some errors (a full disk) have rolled it back already
            db.execute("ROLLBACK")
        if isinstance(exc, sqlite3.Error):
            raise LabcalError(f"{path}: cannot migrate the lab database from schema {found} to {target} "
                              f"({exc}); the file is unchanged") from None
        raise
    if found > target:
        raise _newer(path, found, target)
    return found


def _newer(path: Path, found: int, target: int) -> LabcalError:
    return LabcalError(f"{path}: lab database schema {found} is newer than this labcal ({target}); "
                       "upgrade labcal")


def _backup(path: Path, target: Path) -> None:
    """A consistent copy of the database (WAL included) at ``target``, written whole or not at all.

    Called while the migrating connection holds the write lock, so nobody writes during the copy;
    the copy reads through a second connection because SQLite's backup cannot read from a
    connection that is in a write transaction.
    """
    partial = target.with_name(target.name + ".partial")
    try:
        with closing(sqlite3.connect(path, timeout=10.0)) as source, \
                closing(sqlite3.connect(partial)) as copy:
            source.backup(copy)
        os.replace(partial, target)
    except (sqlite3.Error, OSError) as exc:
        partial.unlink(missing_ok=True)
        raise LabcalError(f"{target}: cannot back up the lab database before migrating it ({exc}); "
                          "nothing was changed") from None
