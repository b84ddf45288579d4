"""The lab database and a run as the use cases name them: by run id, or by the run folder whose
run.json names its journal and run. Opening for a read never creates a database."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.journal import Journal, RunRow, db_path
from labcal.store.rundir import open_run

if TYPE_CHECKING:
    from labcal.store import labquery
else:
    labquery = lazy("labcal.store.labquery")  # start-up without scipy, numpy, pydantic


def existing(db: str | Path | None) -> Path:
    """The lab database's path; one line when there is none (a read must not create one)."""
    path = db_path(db)
    if path.exists() and not path.is_file():
        raise LabcalError(f"{path}: not a database file; {{0}} or $LABCAL_DB names the lab's database",
                          "db")
    if not path.exists():
        raise LabcalError(f"{path}: no lab database here; {{0}} or $LABCAL_DB names the lab's database",
                          "db")
    return path


def open_named(run: str, db: str | Path | None) -> tuple[Journal, RunRow, Path | None]:
    """The journal (open: the caller closes it), the run's row, and the folder when ``run`` named
    one (a run number names none: its folder may be gone; the journal has all of it). A number is the
    lab's (`labcal runs`), as every command names runs."""
    if run.isdigit():
        journal = Journal(existing(db))
        try:
            return journal, journal.run(labquery.journal_run(db, int(run))), None
        except BaseException:
            journal.close()
            raise
    _, journal, row = open_run(Path(run))
    return journal, row, Path(run)
