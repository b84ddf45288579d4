"""A run folder written from the journal: a copy elsewhere (a read of the run: neither the run's
folder nor the lab database changes), or the run's own folder rebuilt (a write, and its own use
case: missing, stale and edited files rewritten, an edited one kept as NAME.edited)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.app.journals import open_named
from labcal.errors import LabcalError
from labcal.store import exports, labdb
from labcal.store.lab_certificates import files_of, write_files
from labcal.store.labquery import lab_number_of
from labcal.store.rundir import RUN, check_identity, read_run_json, recorded_folder

if TYPE_CHECKING:
    from labcal.store.journal import Journal, RunRow


@dataclass(frozen=True)
class ExportRun:
    """Write a run's files (plan.toml, readings.csv, fit.json, run.json) into ``out``."""

    run: str  # a run id in the lab database, or a run folder
    out: str
    db: str | None = None


@dataclass(frozen=True)
class RebuildRunFolder:
    """Rewrite a run's own folder from the journal (given by id: where the journal records it)."""

    run: str
    db: str | None = None


@dataclass(frozen=True)
class FolderWritten:
    run_id: int
    run_uuid: str | None
    folder: Path
    status: str
    notes: tuple[str, ...]  # what was rewritten, and why
    recorded: str | None = None  # a rebuild that moved the run's folder: the folder it was recorded in
    label: str = ""  # the run as the lab names it (`labcal.store.labquery.run_label`)

    @property
    def number(self) -> int | None:
        """The lab's run number (None: the lab has not numbered it yet)."""
        return int(self.label) if self.label.isdigit() else None


def _label(journal: Journal, run_id: int, db: str | None) -> str:
    return lab_number_of(journal.path, run_id, db)


def _target(folder: Path, row) -> None:
    """A folder a run's files may be written into: new, empty, or one that shows this very run."""
    if folder.exists() and not folder.is_dir():
        raise LabcalError(f"{folder}: exists and is not a folder; give another {{0}}", "out")
    if (folder / RUN).exists():  # a folder that shows another run is never written over
        check_identity(folder, read_run_json(folder), row)
    elif folder.exists() and any(folder.iterdir()):
        raise LabcalError(f"{folder}: folder is not empty and is no run's; give an empty or new {{0}}", "out")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabcalError(f"{folder}: cannot create the run folder ({exc.strerror})") from None


def export_run(request: ExportRun) -> FolderWritten:
    """The run's files in another folder, as the journal gives them. The run's own folder and the
    lab database are left as they were: the run stays recorded where it was (`rebuild_run_folder`
    of the copy makes the copy the run's folder)."""
    journal, row, named = open_named(request.run, request.db)
    folder = Path(request.out)
    with journal:
        own = {os.path.abspath(p) for p in (row.run_dir, named) if p is not None and os.path.isabs(p)}
        own |= {os.path.abspath(named)} if named is not None else set()
        if os.path.abspath(folder) in own:
            raise LabcalError(f"{folder}: is run {row.id}'s own folder; `labcal export {request.run}` "
                              "without --out rebuilds it")
        fresh = not (folder / RUN).exists()  # else an earlier copy: what differed is said
        _target(folder, row)
        notes, _ = exports.sync(journal, row, folder, remember=False)
        label = _label(journal, row.id, request.db)
    return FolderWritten(row.id, row.uuid, folder, row.status, () if fresh else tuple(notes), label=label)


def rebuild_run_folder(request: RebuildRunFolder) -> FolderWritten:
    """Check the run's own folder against the journal and rewrite every file that is missing, out
    of date or edited (an edited one kept as NAME.edited); a deleted folder is made again. A folder
    given by its path that the journal records elsewhere becomes the run's folder (journaled)."""
    journal, row, named = open_named(request.run, request.db)
    with journal:
        folder = named if named is not None else recorded_folder(journal, row)
        created = not (folder / RUN).exists()  # else the run's own folder, perhaps recorded anew
        _target(folder, row)
        notes, _ = exports.sync(journal, row, folder)
        moved = record_folder(journal, row, folder, "export", "run folder recreated in {}" if created else "")
        label = _label(journal, row.id, request.db)
    notes += _approved_by_the_lab(folder, row.uuid, request.db)
    return FolderWritten(row.id, row.uuid, folder, row.status, tuple(notes), moved, label)


def _approved_by_the_lab(folder: Path, run_uuid: str | None, db: str | None) -> list[str]:
    """The certificate the lab server approved for the run, with its DCC and report, written into
    its folder (a note naming them); nothing where the lab is not a server or cannot be reached."""
    where = labdb.lab_database(db)
    if isinstance(where, Path) or run_uuid is None:
        return []
    try:
        engine = labdb.open_server(where)
    except labdb.Unreachable:
        return []
    try:
        with engine.connect() as connection:
            written = write_files(folder, files_of(connection, run_uuid))
    finally:
        engine.dispose()
    return [f"the lab server's approved {', '.join(written)} written"] if written else []


def record_folder(journal: Journal, row: RunRow, folder: Path, kind: str, message: str = "") -> str | None:
    """Record ``folder`` as the run's (absolute: found from any folder) when the journal has it
    elsewhere, with an event ``kind`` (``message``: its words, {} the folder); returns the folder it
    was recorded in before, None when it was this one. The folder a run is rebuilt or resumed in
    is its folder: where its files are."""
    where = os.path.abspath(folder)
    if where == row.run_dir:
        return None
    journal.set_run_dir(row.id, where)
    journal.event(row.id, kind, message.format(where) if message
                  else f"run folder recorded as {where} (was {row.run_dir})")
    return row.run_dir
