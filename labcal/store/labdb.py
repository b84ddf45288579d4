"""The lab database: one schema (`labcal.store.schema`), one migration history (Alembic,
`labcal.store.migrations`), for a SQLite file and for a PostgreSQL server alike; opened here only.

Opening never migrates. A new database (a missing or empty SQLite file, an empty PostgreSQL
database) is created at the newest revision by the same Alembic steps an upgrade runs, so the
README's first command needs no setup and a new database and an upgraded one cannot differ. A
database at the newest revision opens; one behind it (an older Alembic revision, or a file of the
labcal before Alembic, which carried its schema version 0–5 as ``PRAGMA user_version``) or ahead of
it (written by a newer labcal) is refused in one line saying what to do, before a run moves
anything: `labcal db upgrade`, or upgrade labcal. A file made or upgraded here carries
``user_version`` `ALEMBIC_USER_VERSION`, which the labcal before Alembic refuses as newer.

`upgrade` (``labcal db upgrade``) migrates a SQLite file in one transaction, under SQLite's write
lock (so two programs upgrading it at once upgrade it once), after a consistent copy of it is
written beside it as ``<name>.v<revision>.bak`` with SQLite's online backup (correct for a WAL
database whose latest pages are still in the -wal file). A failure rolls every step back: the file
stays at its old revision, and says so in one line. A pre-Alembic file at user_version N is
stamped at revision N first; a version-0 file may hold only some of its tables (the journal and the
history each created their own, whichever opened it first), so `BASELINE` (idempotent) completes it
before. A PostgreSQL database is upgraded in one transaction too (its DDL is transactional), under
an advisory lock; its backups are the lab's (pg_dump).

Reads and writes name their columns (no ``SELECT *``, no ``INSERT … VALUES`` without a column
list), so a migration that adds a column never breaks the code that came before it.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.config.files import size_text
from labcal.config.lab import DRIVER_HINT, ServerDatabase, database_location, load_lab_config
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import migrations
from labcal.store.migrations import HEAD

if TYPE_CHECKING:
    import sqlalchemy
    from sqlalchemy import event, pool
    from sqlalchemy import exc as sqlalchemy_exc
    from sqlalchemy.engine import Connection, Engine
else:
    event = lazy("sqlalchemy.event")  # start-up without sqlalchemy
    pool = lazy("sqlalchemy.pool")  # start-up without sqlalchemy
    sqlalchemy = lazy("sqlalchemy")  # start-up without sqlalchemy
    sqlalchemy_exc = lazy("sqlalchemy.exc")  # start-up without sqlalchemy


def lab_database(option: str | Path | None = None) -> Path | ServerDatabase:
    """The lab database: --db, else $LABCAL_DB, else the lab file's, else the user's data folder
    (`labcal.config.lab.LabConfig.database`) — not a folder relative to where the command started."""
    if option:
        return database_location(str(option), "--db")
    return load_lab_config().database()


def lab_server(option: str | Path | None = None) -> ServerDatabase | None:
    """The lab's server database, where the lab database is one (None: a SQLite file, the journal)."""
    where = lab_database(option)
    return None if isinstance(where, Path) else where


ALEMBIC_USER_VERSION = 6  # > 5: the labcal before Alembic refuses an Alembic-kept file as newer
PG_LOCK = 0x6C616263  # "labc": the advisory lock that serialises creating and upgrading on a server
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
class Revision:
    """Where a database's schema is: ``revision`` (None: empty, nothing in it), and whether it is a
    file of the labcal before Alembic (its revision read from ``PRAGMA user_version``)."""

    revision: str | None
    legacy: bool = False

    @property
    def behind(self) -> bool:
        return self.revision is not None and self.revision.isdigit() and self.revision < HEAD \
            and len(self.revision) == len(HEAD)

    @property
    def ahead(self) -> bool:
        return self.revision is not None and self.revision != HEAD and not self.behind

    def __str__(self) -> str:
        if self.revision is None:
            return "empty"
        if self.legacy and self.revision.isdigit():
            return f"{self.revision} (user_version {int(self.revision)}, before Alembic)"
        return self.revision


def backup_path(path: Path, revision: str) -> Path:
    """Where the copy made before upgrading from ``revision`` goes: beside the database."""
    return path.with_name(f"{path.name}.v{revision}.bak")


def revision_of(db: sqlite3.Connection) -> Revision:
    """A SQLite file's revision, read with plain SQL (no Alembic: every open asks)."""
    names = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    if "alembic_version" in names:
        row = db.execute("SELECT version_num FROM alembic_version").fetchone()
        return Revision(row[0] if row else None)
    if not names:
        return Revision(None)
    version = int(db.execute("PRAGMA user_version").fetchone()[0])
    return Revision(f"{version:04d}" if version <= 5 else f"user_version {version}", legacy=True)


def refusal(where: object, found: Revision, db_option: str) -> LabcalError:
    """The one line for a database behind or ahead of this labcal."""
    if found.ahead:
        return LabcalError(f"{where}: the lab database is at schema {found}, newer than this labcal's "
                           f"({HEAD}); upgrade labcal")
    backup = " (it backs the file up beside it first)" if isinstance(where, Path) else \
        " (back the database up first: pg_dump)"
    return LabcalError(f"{where}: the lab database is at schema {found}, older than this labcal's ({HEAD}); "
                       f"run: labcal db upgrade{db_option}{backup}")


def _db_option(where: object) -> str:
    return f" --db {where}" if isinstance(where, Path) else ""


def empty_in_file(option: str | Path | None, table: str) -> bool:
    """True where the lab database is a SQLite file that holds no row of ``table`` (or no such file
    or table): a check that then has nothing to read need not load SQLAlchemy, which costs a dry run
    a third of a second. False for a lab server, or a file whose ``table`` has rows."""
    where = lab_database(option)
    if not isinstance(where, Path):
        return False
    if not where.is_file():
        return True
    try:
        with closing(sqlite3.connect(f"file:{where}?mode=ro", uri=True)) as db:
            return db.execute(f"SELECT 1 FROM {table} LIMIT 1").fetchone() is None  # noqa: S608 - our name
    except sqlite3.OperationalError:  # no such table (a lab file of an older labcal): nothing in it
        return True


def connect(path: str | Path) -> sqlite3.Connection:
    """Open the lab database file at the current schema (its folder made if need be): WAL,
    synchronous=FULL, foreign keys on, autocommit (callers open their own transactions). A new
    file is created at the newest revision; one behind or ahead is refused (`refusal`)."""
    path = Path(path)
    owner_only(path)
    try:
        db = sqlite3.connect(path, timeout=10.0, isolation_level=None)
    except sqlite3.Error as exc:
        raise failure(path, exc) from None
    try:
        _into_wal(db)  # readers never block the journal's writer
        db.execute("PRAGMA synchronous=FULL")  # a committed point survives a power cut
        db.execute("PRAGMA foreign_keys=ON")
        found = revision_of(db)
        if found.revision is None:
            _create_sqlite(db)
            found = revision_of(db)
        if found.revision != HEAD:
            raise refusal(path, found, _db_option(path))
    except sqlite3.Error as exc:
        db.close()
        raise failure(path, exc) from None
    except BaseException:
        db.close()
        raise
    return db


def _into_wal(db: sqlite3.Connection, wait_s: float = 10.0) -> None:
    """``PRAGMA journal_mode=WAL``, tried again while the file is busy, for up to ``wait_s`` (the
    connection's own timeout). Switching a new file to WAL takes an exclusive lock, and so does the
    clean-up of the last connection to close; SQLite may answer SQLITE_BUSY at once there instead of
    calling the busy handler that the timeout installs (SQLite's C interface, sqlite3_busy_handler:
    "the presence of a busy handler does not guarantee that it will be invoked"). Six threads, each
    with its own connection as six programs would have, opening and closing one new lab file at once
    three times each, met it in 7 of 100 trials. The pragma changes nothing the second time, so
    trying it again is safe."""
    deadline = time.monotonic() + wait_s
    pause = 0.005
    while True:
        try:
            db.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as exc:
            if not _busy(exc) or time.monotonic() + pause > deadline:
                raise
        time.sleep(pause)
        pause = min(2 * pause, 0.1)


def owner_only(path: Path) -> None:
    """A new database file (journal, lab file, backup) readable and writable by its owner only, in a
    folder only its owner may enter where labcal makes the folder: a SQLite lab database is one
    machine, one trust domain, and its files say so from the start (SQLite gives the -wal and -shm
    files the database file's permissions). An existing file or folder is left as it is."""
    if not path.parent.is_dir():
        try:
            path.parent.mkdir(parents=True, mode=0o700)
        except OSError as exc:
            if not path.parent.is_dir():  # not made meanwhile by another process: a file there
                raise LabcalError(f"{path.parent}: cannot create the database folder "
                                  f"({exc.strerror})") from None
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError:
        pass  # it exists; or a read-only folder, say, which sqlite3 reports in `failure`'s words


def others_may_write(path: Path) -> str | None:
    """The chmod that would keep others from writing a SQLite lab database (None: only its owner
    may): group or others may write the file, its -wal or -shm, or the folder it is in (where a
    file can be replaced)."""
    for item in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm"), path.parent):
        try:
            mode = item.stat().st_mode
        except FileNotFoundError:
            continue
        if mode & 0o022:
            return f"chmod go-w {item}"
    return None


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
                           "writable (or give {0} / set LABCAL_DB to a writable copy) and run it again", "db")
    damaged = code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
    if damaged or "malformed" in text or "not a database" in text:
        return LabcalError(f"{path}: the lab database is damaged ({text}); check it with sqlite3 {path} "
                           "'PRAGMA integrity_check' and restore it from its latest backup")
    if _busy(exc):
        return LabcalError(f"{path}: the lab database is busy ({text}); another labcal is writing it: "
                           "wait for it and run the command again")
    return LabcalError(f"{path}: cannot use the lab database ({text})")


def _busy(exc: sqlite3.Error) -> bool:
    """SQLite's "busy": another connection holds the lock this one needs (a `failure` to report, or a
    WAL switch to try again)."""
    return getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_BUSY or "locked" in str(exc)


FREE_SPACE_WANTED = 10_000_000  # a run's points and events, with room for SQLite's write-ahead log


def _free_bytes(folder: Path) -> int:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return 0


def _backup(path: Path, target: Path) -> None:
    """A consistent copy of the database (WAL included) at ``target``, written whole or not at all.

    Called while the migrating connection holds the write lock, so nobody writes during the copy;
    the copy reads through a second connection because SQLite's backup cannot read from a
    connection that is in a write transaction.
    """
    partial = target.with_name(target.name + ".partial")
    try:
        owner_only(partial)
        with closing(sqlite3.connect(path, timeout=10.0)) as source, \
                closing(sqlite3.connect(partial)) as copy:
            source.backup(copy)
        os.replace(partial, target)
    except (sqlite3.Error, OSError) as exc:
        partial.unlink(missing_ok=True)
        raise LabcalError(f"{target}: cannot back up the lab database before migrating it ({exc}); "
                          "nothing was changed") from None


# --- upgrading -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Upgraded:
    """What `upgrade` did: the revision found, the one reached, the copy written first (SQLite)."""

    found: Revision
    reached: str
    backup: Path | None


def _sqlite_engine(path: Path) -> Engine:
    """A SQLAlchemy engine on the file whose transactions are SQLite's own, begun with BEGIN
    IMMEDIATE (the write lock at once), so that DDL is inside them and a failure rolls all back
    (SQLAlchemy's recipe for pysqlite: the driver's own transaction handling is switched off)."""
    engine = sqlalchemy.create_engine(
        f"sqlite:///{path}", poolclass=pool.NullPool, connect_args={"timeout": 10.0}
    )

    @event.listens_for(engine, "connect")
    def _autocommit_driver(dbapi_connection: sqlite3.Connection, _record: object) -> None:
        dbapi_connection.isolation_level = None

    @event.listens_for(engine, "begin")
    def _write_lock(connection: Connection) -> None:
        connection.exec_driver_sql("BEGIN IMMEDIATE")

    return engine


def _steps(connection: Connection, found: Revision) -> None:
    """From ``found`` to the newest revision, inside the caller's transaction: a pre-Alembic file
    completed (version 0) and stamped at its version first."""
    if found.legacy:
        if found.revision == "0000":
            for statement in BASELINE:
                connection.exec_driver_sql(statement)
        migrations.stamp(connection, found.revision or "0000")
    migrations.upgrade(connection)


def _upgrade_sqlite(path: Path) -> Upgraded:
    """Bring the file to the newest revision under its write lock."""
    engine = _sqlite_engine(path)
    found = Revision(None)
    backup = None
    try:
        with engine.connect() as connection:
            with connection.begin():
                raw = connection.connection.driver_connection
                assert isinstance(raw, sqlite3.Connection)
                found = revision_of(raw)  # again, under the lock: another program may have done it
                if found.ahead:
                    raise refusal(path, found, "")
                if found.revision == HEAD:
                    return Upgraded(found, HEAD, None)
                if found.revision is not None:
                    backup = backup_path(path, found.revision)
                    _backup(path, backup)
                _steps(connection, found)
                connection.exec_driver_sql(f"PRAGMA user_version = {ALEMBIC_USER_VERSION}")
    except (sqlalchemy_exc.SQLAlchemyError, sqlite3.Error) as exc:
        original = getattr(exc, "orig", None) or exc
        if isinstance(original, sqlite3.Error) and found.revision is None:
            raise failure(path, original) from None
        raise LabcalError(f"{path}: cannot upgrade the lab database from schema {found} to {HEAD} "
                          f"({_first_line(original)}); the file is unchanged") from None
    finally:
        engine.dispose()
    return Upgraded(found, HEAD, backup)


# --- a new file -----------------------------------------------------------------------------------
HEAD_SCRIPT = Path(__file__).with_name("migrations") / "head.sqlite.sql"


def head_statements(script: str) -> list[str]:
    """The SQL statements of a script, one per entry (a statement may span lines)."""
    statements, pending = [], ""
    for line in script.splitlines(keepends=True):
        pending += line
        if sqlite3.complete_statement(pending):
            statements.append(pending.strip())
            pending = ""
    return statements


def _create_sqlite(db: sqlite3.Connection) -> None:
    """An empty file brought to the newest revision by `HEAD_SCRIPT`, under the file's write lock
    (two programs creating it at once create it once; anything found once the lock is held is left
    for the caller to judge). The script is the dump of a file that Alembic's steps created
    (`alembic_head_script`; a test keeps the two equal, statement by statement), so a new file is the
    file an upgrade makes, without loading SQLAlchemy and Alembic and replaying every migration in
    each new journal."""
    statements = head_statements(HEAD_SCRIPT.read_text(encoding="utf-8"))
    db.execute("BEGIN IMMEDIATE")
    try:
        if revision_of(db).revision is None:
            for statement in statements:
                db.execute(statement)
            db.execute(f"PRAGMA user_version = {ALEMBIC_USER_VERSION}")
        db.execute("COMMIT")
    except BaseException:
        db.execute("ROLLBACK")
        raise


def alembic_head_script(folder: Path) -> str:
    """What `HEAD_SCRIPT` must hold: the dump (schema and rows) of an empty file in ``folder`` brought
    to the newest revision by Alembic's steps, as `labcal db upgrade` runs them.
    Rewrite it after adding a migration:
    ``python -c "from pathlib import Path; import tempfile; from labcal.store import labdb;
    labdb.HEAD_SCRIPT.write_text(labdb.alembic_head_script(Path(tempfile.mkdtemp())))"``."""
    path = folder / "head.sqlite"
    _upgrade_sqlite(path)
    with closing(sqlite3.connect(path)) as db:
        lines = [line for line in db.iterdump() if line not in ("BEGIN TRANSACTION;", "COMMIT;")]
    return "".join(f"{line}\n" for line in lines)


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def server_engine(server: ServerDatabase, connect_timeout_s: float = 5.0) -> Engine:
    """A SQLAlchemy engine on the lab's PostgreSQL server (psycopg 3); nothing is opened yet.
    Every connection gives up after ``connect_timeout_s`` (a run's sender and `labcal sync` must
    not hang on a server that is gone)."""
    try:
        from sqlalchemy import create_engine

        return create_engine(server.sqlalchemy_url, pool_pre_ping=True,
                             connect_args={"connect_timeout": max(1, round(connect_timeout_s))})
    except ImportError:
        raise LabcalError(f"{server.source}: {server} is a PostgreSQL server, and its driver (psycopg 3) is "
                          f"not installed; {DRIVER_HINT}") from None


class Unreachable(LabcalError):
    """The lab's server cannot be reached (a run goes on without it; a command says so and exits 2)."""


def unreachable(server: ServerDatabase, exc: BaseException) -> Unreachable:
    """One line for a server that cannot be reached or refuses us."""
    why = _first_line(getattr(exc, "orig", None) or exc)
    return Unreachable(f"{server}: cannot reach the lab database ({why}); "
                       "check that its server is running and reachable, then run the command again")


def _server_revision(connection: Connection) -> Revision:
    names = set(sqlalchemy.inspect(connection).get_table_names())
    if "alembic_version" in names:
        row = connection.execute(sqlalchemy.text("SELECT version_num FROM alembic_version")).fetchone()
        return Revision(row[0] if row else None)
    return Revision(None) if not names else Revision("unknown tables, no alembic_version")


def _upgrade_server(server: ServerDatabase, create_only: bool = False) -> Upgraded:
    engine = server_engine(server)
    try:
        with engine.begin() as connection:
            connection.execute(sqlalchemy.text("SELECT pg_advisory_xact_lock(:key)"), {"key": PG_LOCK})
            found = _server_revision(connection)
            if found.ahead:
                raise refusal(server, found, "")
            if found.revision == HEAD or (create_only and found.revision is not None):
                return Upgraded(found, found.revision or HEAD, None)
            _steps(connection, found)
    except sqlalchemy_exc.SQLAlchemyError as exc:
        if (
            isinstance(exc, sqlalchemy_exc.DBAPIError)
            and exc.connection_invalidated
            or _is_connection_error(exc)
        ):
            raise unreachable(server, exc) from None
        raise LabcalError(f"{server}: cannot upgrade the lab database to {HEAD} ({_first_line(exc)}); "
                          "nothing was changed") from None
    finally:
        engine.dispose()
    return Upgraded(found, HEAD, None)


def _is_connection_error(exc: BaseException) -> bool:
    return isinstance(exc, sqlalchemy_exc.OperationalError)


def upgrade(where: Path | ServerDatabase) -> Upgraded:
    """`labcal db upgrade`: the lab database at the newest revision (see the module's docstring)."""
    if isinstance(where, ServerDatabase):
        return _upgrade_server(where)
    if not where.exists():
        connect(where).close()  # created at the newest revision: nothing to upgrade
        return Upgraded(Revision(None), HEAD, None)
    return _upgrade_sqlite(where)


def status(where: Path | ServerDatabase) -> Revision:
    """`labcal db status`: the revision the lab database is at (nothing changed, nothing created)."""
    if isinstance(where, ServerDatabase):
        engine = server_engine(where)
        try:
            with engine.connect() as connection:
                return _server_revision(connection)
        except Exception as exc:
            if _is_connection_error(exc):
                raise unreachable(where, exc) from None
            raise
        finally:
            engine.dispose()
    if not where.exists():
        return Revision(None)
    try:
        with closing(sqlite3.connect(f"file:{where}?mode=ro", uri=True, timeout=10.0)) as db:
            return revision_of(db)
    except sqlite3.Error as exc:
        raise failure(where, exc) from None


def lab_engine(db: str | Path | None = None) -> Engine:
    """The lab database (--db, else $LABCAL_DB, else the lab file's `database`, else the user's data
    folder) as a SQLAlchemy engine, for those who read it as a whole (the lab server): a new one is
    created at the newest revision; one behind or ahead is refused in one line (`LabcalError`); a
    server that cannot be reached too. The tables are `labcal.store.schema`'s."""
    where = lab_database(db)
    if isinstance(where, Path):
        connect(where).close()  # created if new, refused if behind or ahead
        return sqlalchemy.create_engine(f"sqlite:///{where}", connect_args={"timeout": 10.0})
    return open_server(where)


def open_server(server: ServerDatabase) -> Engine:
    """An engine on the lab's server at the newest revision: an empty database is created at it,
    one behind or ahead refused, an unreachable server refused (each in one line)."""
    _upgrade_server(server, create_only=True)
    engine = server_engine(server)
    try:
        with engine.connect() as connection:
            found = _server_revision(connection)
    except Exception as exc:
        engine.dispose()
        if _is_connection_error(exc):
            raise unreachable(server, exc) from None
        raise
    if found.revision != HEAD:
        engine.dispose()
        raise refusal(server, found, "")
    return engine
