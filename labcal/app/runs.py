"""Listing the lab's runs and reading one run's log: pure reads of the lab database."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.app.desk import run_attention
from labcal.config.run_metadata import RunMetadata, listed_metadata
from labcal.documents.overrides import run_overrides
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labquery
from labcal.store.journal import EventRow  # already loaded with labquery: the type of a run's events
from labcal.store.lab_view import run_row
from labcal.store.labquery import LabRun, Source, from_lab, lab_runs, run_events
from labcal.store.lock import held_by

if TYPE_CHECKING:
    from labcal.app import journals
    from labcal.documents.overrides import Override
    from labcal.store import journal as store_journal
    from labcal.store import rundir
    from labcal.store.handles import Connection
else:
    journals = lazy("labcal.app.journals")  # start-up without scipy, numpy, pydantic
    rundir = lazy("labcal.store.rundir")  # start-up without scipy, numpy, pydantic
    store_journal = lazy("labcal.store.journal")  # start-up without scipy, numpy, pydantic


@dataclass(frozen=True)
class ListRuns:
    db: str | None = None
    serial: str | None = None
    statuses: tuple[str, ...] = ()  # only runs in one of these (empty: all)
    attention: bool = False  # only runs an approver must look at (`labcal.app.desk.run_attention`)


@dataclass(frozen=True)
class RunLine:
    """One run as a list shows it, its fields named as the lab server's API names them. ``id`` is the
    lab's run number (None until the lab has numbered it: ``label`` is then its provisional name);
    ``status`` is as seen: a "running" run of this bench that nobody holds is interrupted."""

    id: int | None
    label: str
    uuid: str | None
    station: str | None
    serial: str | None
    plan: str
    status: str
    reason: str | None
    started_utc: str
    ended_utc: str | None
    points_ok: int
    points_failed: int
    operator: str | None
    run_dir: str
    attention: tuple[str, ...] = ()  # what an approver must know (`labcal.app.desk.run_attention`)

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class RunList:
    database: str  # where the list was read: the lab database, or the journal standing in for it
    exists: bool  # False: no database yet (nothing was created)
    runs: tuple[RunLine, ...]
    stale: str | None = None  # the lab could not be reached: what this bench shows instead, how old


def seen_status(db: Path, status: str, run_id: int) -> str:
    """The journal's status, except that a "running" run whose lock nobody holds was interrupted:
    its process ended without closing it (a kill, a power cut). `labcal resume` goes on with it."""
    if status == "running" and held_by(db, run_id) is None:
        return "interrupted"
    return status


def _line(run: LabRun, journal: Path | None, noted: tuple[str, ...] = ()) -> RunLine:
    status = run.status if run.local_id is None or journal is None else \
        seen_status(journal, run.status, run.local_id)
    return RunLine(run.number, run.label, run.uuid, run.station, run.serial, run.plan, status,
                   run.reason, run.started_utc, run.ended_utc, run.points_ok, run.points_failed,
                   run.operator, run.run_dir, noted)


def _attention(db: str | None, found: list[LabRun], source: Source) -> dict[int, tuple[str, ...]]:
    """What needs an approver's eye in each of ``found`` (by its place in the list), by the desk's one
    rule (`labcal.app.desk.run_attention`) on the lab record the list was read from: the lab
    database, or this bench's journal for a run the lab has not seen yet (or cannot be reached)."""
    # deferred: the desk reads certificates (pydantic, numpy); a plain `labcal runs` need not load them
    def read(conn: Connection, wanted: dict[int, LabRun], by_uuid: bool) -> dict[int, tuple[str, ...]]:
        noted: dict[int, tuple[str, ...]] = {}
        for at, run in wanted.items():
            row = run_row(conn, uuid=run.uuid) if by_uuid else run_row(conn, local_id=run.local_id)
            if row is not None:
                noted[at] = run_attention(conn, row.id, row.uuid, row.metadata)
        return noted

    lab = {at: r for at, r in enumerate(found) if r.uuid}
    none: dict[int, tuple[str, ...]] = {}
    noted, _ = from_lab(db, lambda conn: read(conn, lab, True), none)
    rest = {at: r for at, r in enumerate(found) if at not in noted and r.local_id is not None}
    if rest and source.journal is not None:
        more, _ = from_lab(str(source.journal), lambda conn: read(conn, rest, False), none)
        noted |= more
    return noted


def _metadata(run: LabRun) -> RunMetadata:
    return listed_metadata(run.metadata)


def list_runs(request: ListRuns) -> RunList:
    """The lab's runs in the order the lab numbered them (this bench's runs it has not seen yet
    last); a missing database is an empty list, and is not created."""
    wanted = request.statuses
    # an interrupted run may still say "running" in the journal: ask for both, then sort out
    asked = wanted + (("running",) if "interrupted" in wanted else ())
    found, source = lab_runs(request.db, request.serial, asked)
    noted = _attention(request.db, found, source) if request.attention else {}
    lines = [_line(r, source.journal, noted.get(at, ())) for at, r in enumerate(found)]
    exists = source.journal is not None or source.target is not None and source.stale is None
    return RunList(source.shown, exists, tuple(r for r in lines if (not wanted or r.status in wanted)
                                               and (not request.attention or r.attention)), source.stale)


@dataclass(frozen=True)
class ReadLog:
    run: str  # a lab run number, a run's uuid (or its first digits), or a run folder (its run.json)
    db: str | None = None


@dataclass(frozen=True)
class RunLog:
    id: int | None  # the lab's run number (None: not numbered yet)
    label: str
    uuid: str | None
    station: str | None
    status: str
    reason: str | None
    plan: str
    serial: str | None
    operator: str | None
    run_dir: str
    started_utc: str
    ended_utc: str | None
    points_ok: int
    events: tuple[EventRow, ...]
    stale: str | None = None  # the lab could not be reached: read from this bench's journal

    def to_json(self) -> dict:
        doc = {**asdict(self), "events": [e.to_json() for e in self.events]}
        doc.pop("stale")
        return doc


UUID_DIGITS = frozenset("0123456789abcdef-")


def _run_of(request: ReadLog) -> tuple[str | None, int | None, str | None]:
    """RUN as a lab run number, a uuid (or its first digits), or a run folder (whose run.json names
    its journal and its row there): the database to read, and the run's number or uuid there. A
    folder's run is read from the journal it names unless the lab is a server (then by its uuid)."""
    if request.run.isdigit():
        return request.db, int(request.run), None
    if Path(request.run).is_dir():
        info = rundir.read_run_json(Path(request.run))
        try:
            journal, run_id = Path(str(info["journal"])), int(info["run_id"])
        except (KeyError, TypeError, ValueError):
            raise LabcalError(f"{request.run}: run.json does not name its journal and run id") from None
        if not labquery.is_server(request.db):
            return str(journal), run_id, None
        with store_journal.Journal(journals.existing(journal)) as opened:
            return request.db, None, opened.run(run_id).uuid or ""
    if len(request.run) >= 8 and set(request.run.lower()) <= UUID_DIGITS:
        return request.db, None, request.run.lower()
    raise LabcalError(f"{request.run}: neither a run number (see labcal runs), a run's uuid nor a run "
                      "directory")


def read_log(request: ReadLog) -> RunLog:
    """A run's journaled events in order: prompts and answers, retries, faults, pauses, resumes."""
    db, number, uuid = _run_of(request)
    found, source = run_events(db, number, uuid)
    run = _line(found.run, source.journal)
    return RunLog(run.id, run.label, run.uuid, run.station, run.status, run.reason, run.plan, run.serial,
                  run.operator, run.run_dir, run.started_utc, run.ended_utc, run.points_ok,
                  tuple(found.events), source.stale)


def overrides_in(run: LabRun, events: Iterable[EventRow]) -> tuple[Override, ...]:
    """Every override a run was measured under (`labcal.documents.overrides`: the warm-up and other
    checklist items gone on regardless of, overdue standards used under an approver's override, faults
    accepted), from its row in the lab database and its journaled events, as its certificate states them."""
    meta = _metadata(run).model_copy(update={"operator": run.operator, "started_utc": run.started_utc})
    return tuple(run_overrides(meta, events))


def overrides_of(request: ReadLog) -> tuple[Override, ...]:
    """`overrides_in` of the run ``request.run`` names (a lab run number, a uuid or a run folder), read
    from the lab database (or this bench's journal where the lab cannot be reached): what the approver's
    view shows of a run before it is signed."""
    db, number, uuid = _run_of(request)
    found, _ = run_events(db, number, uuid)
    return overrides_in(found.run, found.events)
