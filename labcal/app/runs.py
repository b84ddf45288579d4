"""Listing the lab's runs and reading one run's log: pure reads of the lab database."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from labcal.config.run_metadata import RunMetadata, listed_metadata
from labcal.errors import LabcalError
from labcal.run.labquery import LabRun


@dataclass(frozen=True)
class ListRuns:
    db: str | None = None
    serial: str | None = None
    statuses: tuple[str, ...] = ()  # only runs in one of these (empty: all)
    attention: bool = False  # only runs an approver must look at (`attention`)


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
    attention: tuple[str, ...] = ()  # what an approver must know (`attention`); listed with --attention

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
    from labcal.run.lock import held_by

    if status == "running" and held_by(db, run_id) is None:
        return "interrupted"
    return status


def attention(metadata: RunMetadata) -> tuple[str, ...]:
    """What an approver must know of how a run was measured, from its journaled checklist: the items
    it went on regardless of (as the certificate states them, `checklist_overrides`), and a
    reference standard the checklist found overdue or unnamed, and a serial the instrument register
    did not hold."""
    from labcal.documents.issuing import checklist_overrides

    checklist = metadata.checklist
    found = [f"went on regardless: {item}" for item in checklist_overrides(checklist)]
    if isinstance(checklist, dict):
        found += [f"{i.get('item')}: {i.get('message')}" for i in checklist.get("items") or []
                  if isinstance(i, dict) and i.get("item") == "reference standards"
                  and i.get("status") == "warning"]
    if metadata.unregistered_serial:
        found.append(f"serial {metadata.unregistered_serial}")
    return tuple(found)


def _line(run: LabRun, journal: Path | None, noted: bool = False) -> RunLine:
    status = run.status if run.local_id is None or journal is None else \
        seen_status(journal, run.status, run.local_id)
    return RunLine(run.number, run.label, run.uuid, run.station, run.serial, run.plan, status,
                   run.reason, run.started_utc, run.ended_utc, run.points_ok, run.points_failed,
                   run.operator, run.run_dir, attention(listed_metadata(run.metadata)) if noted else ())


def list_runs(request: ListRuns) -> RunList:
    """The lab's runs in the order the lab numbered them (this bench's runs it has not seen yet
    last); a missing database is an empty list, and is not created."""
    from labcal.run.labquery import lab_runs

    wanted = request.statuses
    # an interrupted run may still say "running" in the journal: ask for both, then sort out
    asked = wanted + (("running",) if "interrupted" in wanted else ())
    found, source = lab_runs(request.db, request.serial, asked)
    lines = [_line(r, source.journal, request.attention) for r in found]
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
    events: tuple[dict, ...]  # kind, utc, station_time, message, data
    stale: str | None = None  # the lab could not be reached: read from this bench's journal

    def to_json(self) -> dict:
        doc = {**asdict(self), "events": list(self.events)}
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
        from labcal.app.journals import existing
        from labcal.run.journal import Journal
        from labcal.run.labquery import is_server
        from labcal.run.rundir import read_run_json

        info = read_run_json(Path(request.run))
        try:
            journal, run_id = Path(str(info["journal"])), int(info["run_id"])
        except (KeyError, TypeError, ValueError):
            raise LabcalError(f"{request.run}: run.json does not name its journal and run id") from None
        if not is_server(request.db):
            return str(journal), run_id, None
        with Journal(existing(journal)) as opened:
            return request.db, None, opened.run(run_id).uuid or ""
    if len(request.run) >= 8 and set(request.run.lower()) <= UUID_DIGITS:
        return request.db, None, request.run.lower()
    raise LabcalError(f"{request.run}: neither a run number (see labcal runs), a run's uuid nor a run "
                      "directory")


def read_log(request: ReadLog) -> RunLog:
    """A run's journaled events in order: prompts and answers, retries, faults, pauses, resumes."""
    from labcal.run.labquery import run_events

    db, number, uuid = _run_of(request)
    found, source = run_events(db, number, uuid)
    run = _line(found.run, source.journal)
    return RunLog(run.id, run.label, run.uuid, run.station, run.status, run.reason, run.plan, run.serial,
                  run.operator, run.run_dir, run.started_utc, run.ended_utc, run.points_ok,
                  tuple(found.events), source.stale)
