"""The lab database for the server and `labcal user`: `labcal.run.labdb.lab_engine`, plus the two
things the server needs to know about where it is.

A location is what ``--db``, `LABCAL_DB` or the lab file's ``database`` says (a path,
``sqlite:///PATH`` or ``postgresql://USER@HOST:PORT/DBNAME``), resolved as every labcal command
resolves it (`labcal.run.journal.lab_database`). `lab_engine` creates a new database at the newest
schema and refuses, in one line, one that is behind (``labcal db upgrade``) or ahead.

The server only reads: it refuses a SQLite path where there is no file rather than create an empty
lab database there (a mistyped --db would otherwise serve an empty lab).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sqlalchemy.engine import Engine

from labcal.errors import LabcalError


@dataclass(frozen=True)
class LabDatabase:
    engine: Engine
    shown: str  # the location for people (a server's URL without its password)
    file: Path | None  # the SQLite file, where the lab database is one


def open_lab(option: str | None, must_exist: bool) -> LabDatabase:
    from labcal.run.journal import lab_database
    from labcal.run.labdb import lab_engine

    where = lab_database(option)
    if isinstance(where, Path) and must_exist and not where.is_file():
        raise LabcalError(f"{where}: no lab database there; give --db or set LABCAL_DB to the lab's database "
                          "(a labcal run creates it)")
    return LabDatabase(lab_engine(option), str(where), where if isinstance(where, Path) else None)
