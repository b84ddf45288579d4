"""Opening the lab database for the lab server and `labcal user`: `labcal.store.labdb.lab_engine`, plus
the two things the server needs to know about where it is.

A location is what ``--db``, `LABCAL_DB` or the lab file's ``database`` says (a path,
``sqlite:///PATH`` or ``postgresql://USER@HOST:PORT/DBNAME``), resolved as every labcal command
resolves it (`labcal.store.labdb.lab_database`). `lab_engine` creates a new database at the newest
schema and refuses, in one line, one that is behind (``labcal db upgrade``) or ahead.

The server only reads: it refuses a SQLite path where there is no file rather than create an empty
lab database there (a mistyped --db would otherwise serve an empty lab). `labcal user add` may
create it (``must_exist=False``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.errors import LabcalError
from labcal.store.labdb import lab_database, lab_engine

if TYPE_CHECKING:
    from labcal.config.lab import ServerDatabase
    from labcal.store.handles import Engine


@dataclass(frozen=True)
class OpenLab:
    db: str | None = None  # as --db gives it (None: $LABCAL_DB, else the lab file's)
    must_exist: bool = True  # False: a SQLite lab database is created where there is none


@dataclass(frozen=True)
class LabDatabase:
    """An open lab database: what the lab's use cases (`labcal.app.lab`, `labcal.app.users`) read."""

    engine: Engine
    shown: str  # the location for people (a server's URL without its password)
    file: Path | None  # the SQLite file, where the lab database is one
    server: ServerDatabase | None = None  # the PostgreSQL server, where the lab database is one

    def close(self) -> None:
        self.engine.dispose()


def open_lab(request: OpenLab) -> LabDatabase:
    """The lab database, at this labcal's schema; one line when it is missing, behind or ahead."""
    where = lab_database(request.db)
    if isinstance(where, Path) and request.must_exist and not where.is_file():
        raise LabcalError(f"{where}: no lab database there; give {{0}} or set LABCAL_DB to the lab's "
                          "database (a labcal run creates it)", "db")
    return LabDatabase(lab_engine(request.db), str(where), where if isinstance(where, Path) else None,
                       None if isinstance(where, Path) else where)
