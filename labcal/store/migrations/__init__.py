"""Alembic's migration scripts for the lab database (`labcal.store.schema`): one history for SQLite and
PostgreSQL. Revisions 0000–0005 are the schema versions SQLite files carried as ``PRAGMA
user_version`` before Alembic kept the history; 0006 on are the lab's."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection

HERE = Path(__file__).parent
HEAD = "0015"  # `head()` without loading Alembic (opening a database checks it); a test keeps them equal


def _config(connection: Connection):
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(HERE))
    config.attributes["connection"] = connection
    return config


def head() -> str:
    """The newest revision this labcal knows."""
    from alembic.script import ScriptDirectory

    config = _config(None)  # type: ignore[arg-type]
    revision = ScriptDirectory.from_config(config).get_current_head()
    assert revision is not None
    return revision


def revisions() -> list[str]:
    """Every revision this labcal knows, oldest first."""
    from alembic.script import ScriptDirectory

    walk = ScriptDirectory.from_config(_config(None)).walk_revisions()  # type: ignore[arg-type]
    return [script.revision for script in reversed(list(walk))]


def current(connection: Connection) -> str | None:
    """The revision the database is at (None: never stamped by Alembic)."""
    from alembic.runtime.migration import MigrationContext

    return MigrationContext.configure(connection).get_current_revision()


def upgrade(connection: Connection, target: str = "head") -> None:
    """Apply every step from the database's revision to ``target``, inside the caller's transaction."""
    from alembic import command

    command.upgrade(_config(connection), target)


def stamp(connection: Connection, revision: str) -> None:
    """Record that the database is at ``revision`` without running anything (a legacy SQLite file
    whose ``PRAGMA user_version`` already says which of 0000–0005 it is)."""
    from alembic import command

    command.stamp(_config(connection), revision)
