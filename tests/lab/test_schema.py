"""The lab database's schema: one history (Alembic) that arrives at one schema (SQLAlchemy's
`labcal.store.schema.METADATA`) on SQLite and PostgreSQL alike, and that matches, table by table, what
labcal's SQLite files held before Alembic kept the history (`labcal.store.labdb`'s SQL, written before
either of the others: the independent reference here)."""

from __future__ import annotations

import sqlite3
from contextlib import closing

import pytest
import sqlalchemy as sa
from legacy_schema import legacy_file

from labcal.store import migrations
from labcal.store.schema import METADATA


def affinity(declared: str) -> str:
    """SQLite's type affinity of a declared type (https://sqlite.org/datatype3.html §3.1): what the
    file stores, whether SQL wrote REAL or SQLAlchemy wrote FLOAT."""
    name = declared.upper()
    if "INT" in name:
        return "INTEGER"
    if any(word in name for word in ("CHAR", "CLOB", "TEXT")):
        return "TEXT"
    if "BLOB" in name or "BINARY" in name or "BYTEA" in name:
        return "BLOB"
    return "REAL"


def shape(connection: sa.engine.Connection) -> dict:
    """Tables → columns (name, type affinity, nullable), primary key, unique indexes and indexes.
    A primary key column counts as NOT NULL (SQLite lets a non-integer key be NULL only by an old
    bug its documentation keeps for compatibility; no labcal row ever had one)."""
    inspector = sa.inspect(connection)
    out = {}
    for table in sorted(inspector.get_table_names()):
        if table == "alembic_version":
            continue
        pk = tuple(inspector.get_pk_constraint(table)["constrained_columns"])
        columns = tuple((c["name"], affinity(str(c["type"].compile(dialect=connection.dialect))),
                         c["nullable"] and c["name"] not in pk)
                        for c in inspector.get_columns(table))
        indexes = sorted((i["name"], tuple(i["column_names"]), bool(i["unique"]))
                         for i in inspector.get_indexes(table))
        out[table] = (columns, pk, indexes)
    return out


def migrated(url: str) -> dict:
    engine = sa.create_engine(url)
    with engine.begin() as connection:
        migrations.upgrade(connection)
    with engine.connect() as connection:
        assert migrations.current(connection) == migrations.head()
        found = shape(connection)
    engine.dispose()
    return found


def created(url: str) -> dict:
    engine = sa.create_engine(url)
    METADATA.create_all(engine)
    with engine.connect() as connection:
        found = shape(connection)
    engine.dispose()
    return found


def test_the_history_arrives_at_the_schema_on_sqlite(tmp_path):
    assert migrated(f"sqlite:///{tmp_path / 'a.sqlite'}") == created(f"sqlite:///{tmp_path / 'b.sqlite'}")


def test_the_history_arrives_at_the_schema_on_postgresql(postgres_cluster):
    first, second = postgres_cluster.create_database(), postgres_cluster.create_database()
    assert migrated(postgres_cluster.url(first).replace("postgresql://", "postgresql+psycopg://")) == \
        created(postgres_cluster.url(second).replace("postgresql://", "postgresql+psycopg://"))


def test_revision_0005_is_the_schema_sqlite_files_carried_as_user_version_5(tmp_path):
    legacy = legacy_file(tmp_path / "legacy.sqlite", 5)  # the statements of 1–5, as labcal wrote them
    with closing(sqlite3.connect(legacy)) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 5
    engine = sa.create_engine(f"sqlite:///{tmp_path / 'alembic.sqlite'}")
    with engine.begin() as connection:
        migrations.upgrade(connection, "0005")
    with engine.connect() as connection:
        ours = shape(connection)
    old = sa.create_engine(f"sqlite:///{legacy}")
    with old.connect() as connection:
        theirs = shape(connection)
    assert ours == theirs


def test_every_revision_is_known_in_order():
    assert migrations.revisions() == [f"{n:04d}" for n in range(len(migrations.revisions()))]
    assert migrations.head() == migrations.revisions()[-1]


@pytest.mark.parametrize("column", ["vx", "vy", "vz", "sd_vx", "sd_vy", "sd_vz", "temp_c"])
def test_the_readings_keep_the_journals_column_names(column):
    assert column in METADATA.tables["points"].columns


def test_the_head_labcal_checks_on_open_is_alembics():
    """`migrations.HEAD` spares every open the loading of Alembic; it must be Alembic's head."""
    assert migrations.HEAD == migrations.head()
