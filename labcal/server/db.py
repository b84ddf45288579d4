"""The lab database as a SQLAlchemy engine, for the server and `labcal user`.

A location is what `LABCAL_DB`, ``--db`` or the lab file's ``database`` says: a path or
``sqlite:///PATH`` (resolved as the journal resolves it, `labcal.run.journal.db_path`), or
``postgresql://USER@HOST:PORT/DBNAME`` (through psycopg 3).

The server only reads, and refuses in one line a database whose schema is not this labcal's
(`labcal.run.schema`, at the migrations' head). `labcal user add` writes, and brings a SQLite lab
file that the journal has kept at its pre-Alembic ``PRAGMA user_version`` (0–5) to the head first
(stamp the revision that version is, then upgrade: the users table and the lab columns of
revision 0006 are additive, so the journal still reads and writes it).

Until the lab-database work (`labcal.run`'s own engine helper) lands, this small module is the
server's way in; it keeps to the same resolution so both agree on which database is the lab's.
"""

from __future__ import annotations

import os
from pathlib import Path

from sqlalchemy import create_engine, event, inspect, text
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import SQLAlchemyError

from labcal.errors import LabcalError
from labcal.run import migrations
from labcal.run.journal import db_path

SERVER_SCHEMES = ("postgresql", "postgres", "postgresql+psycopg")


def location(option: str | Path | None = None) -> str:
    """The lab database as the user named it: --db, else $LABCAL_DB, else the lab file's (a path)."""
    named = str(option) if option else os.environ.get("LABCAL_DB", "")
    if named.partition("://")[0] in SERVER_SCHEMES:
        return named
    return str(db_path(option))


def url_of(where: str) -> str:
    """SQLAlchemy's URL for a location: PostgreSQL through psycopg 3, else the SQLite file."""
    scheme, sep, rest = where.partition("://")
    if sep and scheme in SERVER_SCHEMES:
        return f"postgresql+psycopg://{rest}"
    return f"sqlite:///{Path(where).resolve()}"


def shown(where: str) -> str:
    """The location for messages, without a password."""
    scheme, sep, rest = where.partition("://")
    if sep and "@" in rest:
        cred, _, host = rest.rpartition("@")
        return f"{scheme}://{cred.split(':')[0]}@{host}"
    return where


def engine(where: str, must_exist: bool = True) -> Engine:
    """An engine on the lab database at ``where`` (a location as `location` gives it)."""
    url = url_of(where)
    if url.startswith("sqlite"):
        path = Path(url.removeprefix("sqlite:///"))
        if must_exist and not path.is_file():
            raise LabcalError(f"{where}: no lab database there; give --db or set LABCAL_DB to the lab's "
                              "database (a labcal run creates it)")
        eng = create_engine(url, connect_args={"timeout": 10.0, "check_same_thread": False})

        @event.listens_for(eng, "connect")
        def _pragmas(dbapi_connection, _record) -> None:  # as the journal opens it (labcal.run.labdb)
            dbapi_connection.execute("PRAGMA foreign_keys=ON")
        return eng
    try:
        import psycopg  # noqa: F401
    except ImportError:
        raise LabcalError(f"{shown(where)}: PostgreSQL needs psycopg: pip install 'labcal[lab]'") from None
    return create_engine(url, pool_pre_ping=True)


def revision(conn: Connection) -> str | None:
    """The schema revision of the database (None: never stamped by Alembic)."""
    return migrations.current(conn)


def check_head(eng: Engine, where: str) -> None:
    """Refuse, in one line, a database whose schema is not this labcal's."""
    head = migrations.head()
    try:
        with eng.connect() as conn:
            found = revision(conn)
            legacy = _legacy_version(conn) if found is None else None
    except SQLAlchemyError as exc:
        raise LabcalError(f"{shown(where)}: cannot read the lab database ({_first_line(exc)})") from None
    if found == head:
        return
    if found is None and legacy is None:
        raise LabcalError(f"{shown(where)}: not a lab database (no labcal schema); a labcal run or `labcal "
                          "user add` creates one")
    if found is not None and found not in migrations.revisions():
        raise LabcalError(f"{shown(where)}: schema revision {found} is newer than this labcal ({head}); "
                          "upgrade labcal")
    at = found if found is not None else f"the journal's version {legacy}"
    raise LabcalError(f"{shown(where)}: the lab database's schema is at {at}, this labcal needs {head}; "
                      "`labcal user add` (or `labcal db upgrade`) brings it there")


def upgrade(eng: Engine) -> None:
    """Bring the database to the head: a new one is created, a SQLite file the journal kept at
    ``PRAGMA user_version`` N (0–5) is stamped as revision 000N first."""
    with eng.begin() as conn:
        if revision(conn) is None:
            legacy = _legacy_version(conn)
            if legacy is not None:
                migrations.stamp(conn, f"{legacy:04d}")
        migrations.upgrade(conn)
        if conn.dialect.name == "sqlite":
            # the journal of this labcal still versions the file by user_version (labcal.run.labdb):
            # say it holds that version's tables, as it now does, so the journal opens it as it is
            from labcal.run.labdb import SCHEMA_VERSION

            if int(conn.execute(text("PRAGMA user_version")).scalar_one()) < SCHEMA_VERSION:
                conn.execute(text(f"PRAGMA user_version = {int(SCHEMA_VERSION)}"))


def _legacy_version(conn: Connection) -> int | None:
    """A SQLite lab file's journal version, where it has the journal's tables; else None."""
    if conn.dialect.name != "sqlite" or not inspect(conn).has_table("runs"):
        return None
    return int(conn.execute(text("PRAGMA user_version")).scalar_one())


def _first_line(exc: BaseException) -> str:
    return str(getattr(exc, "orig", None) or exc).strip().splitlines()[0]
