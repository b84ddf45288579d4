"""Alembic's migration scripts for the lab database (`labcal.store.schema`): one history for SQLite and
PostgreSQL. Revisions 0000–0005 are the schema versions SQLite files carried as ``PRAGMA
user_version`` before Alembic kept the history; 0006 on are the lab's."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from labcal.lazy import lazy

if TYPE_CHECKING:
    from alembic import command
    from alembic import config as alembic_config
    from alembic import script as alembic_script
    from alembic.runtime import migration
    from sqlalchemy.engine import Connection
else:
    alembic_config = lazy("alembic.config")  # start-up without sqlalchemy, alembic
    alembic_script = lazy("alembic.script")  # start-up without sqlalchemy, alembic
    command = lazy("alembic.command")  # start-up without sqlalchemy, alembic
    migration = lazy("alembic.runtime.migration")  # start-up without sqlalchemy, alembic

HERE = Path(__file__).parent
HEAD = "0015"  # `head()` without loading Alembic (opening a database checks it); a test keeps them equal


def _config(connection: Connection):
    config = alembic_config.Config()
    config.set_main_option("script_location", str(HERE))
    config.attributes["connection"] = connection
    return config


def head() -> str:
    """The newest revision this labcal knows."""
    config = _config(None)  # type: ignore[arg-type]
    revision = alembic_script.ScriptDirectory.from_config(config).get_current_head()
    assert revision is not None
    return revision


def revisions() -> list[str]:
    """Every revision this labcal knows, oldest first."""
    walk = alembic_script.ScriptDirectory.from_config(_config(None)).walk_revisions()  # type: ignore[arg-type]
    return [script.revision for script in reversed(list(walk))]


def current(connection: Connection) -> str | None:
    """The revision the database is at (None: never stamped by Alembic)."""
    return migration.MigrationContext.configure(connection).get_current_revision()


def upgrade(connection: Connection, target: str = "head") -> None:
    """Apply every step from the database's revision to ``target``, inside the caller's transaction."""
    command.upgrade(_config(connection), target)


def stamp(connection: Connection, revision: str) -> None:
    """Record that the database is at ``revision`` without running anything (a legacy SQLite file
    whose ``PRAGMA user_version`` already says which of 0000–0005 it is)."""
    command.stamp(_config(connection), revision)
