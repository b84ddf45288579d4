"""Listing the lab's runs and reading one run's log: pure reads of the lab database."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from labcal.errors import LabcalError


@dataclass(frozen=True)
class ListRuns:
    db: str | None = None
    serial: str | None = None
    statuses: tuple[str, ...] = ()  # only runs in one of these (empty: all)
    attention: bool = False  # only runs an approver must look at (`attention`)


@dataclass(frozen=True)
class RunLine:
    """One run as a list shows it; ``status`` is as seen: a "running" run nobody holds is interrupted."""

    id: int
    instrument: str | None
    plan: str
    status: str
    reason: str | None
    started_utc: str
    ended_utc: str | None
    points: int
    points_failed: int
    operator: str | None
    run_dir: str
    attention: tuple[str, ...] = ()  # what an approver must know (`attention`); listed with --attention

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class RunList:
    database: Path
    exists: bool  # False: no database yet (nothing was created)
    runs: tuple[RunLine, ...]


def seen_status(db: Path, status: str, run_id: int) -> str:
    """The journal's status, except that a "running" run whose lock nobody holds was interrupted:
    its process ended without closing it (a kill, a power cut). `labcal resume` goes on with it."""
    from labcal.run.lock import held_by

    if status == "running" and held_by(db, run_id) is None:
        return "interrupted"
    return status


def attention(metadata: dict) -> tuple[str, ...]:
    """What an approver must know of how a run was measured, from its journaled checklist: the items
    it went on regardless of (as the certificate states them, `checklist_overrides`), and a
    reference standard the checklist found overdue or unnamed, and a serial the instrument register
    did not hold."""
    from labcal.documents.issuing import checklist_overrides

    checklist = metadata.get("checklist")
    found = [f"went on regardless: {item}" for item in checklist_overrides(checklist)]
    if isinstance(checklist, dict):
        found += [f"{i.get('item')}: {i.get('message')}" for i in checklist.get("items") or []
                  if isinstance(i, dict) and i.get("item") == "reference standards"
                  and i.get("status") == "warning"]
    if metadata.get("unregistered_serial"):
        found.append(f"serial {metadata['unregistered_serial']}")
    return tuple(found)


def list_runs(request: ListRuns) -> RunList:
    """The lab's runs, oldest first; a missing database is an empty list, and is not created."""
    from labcal.run.journal import Journal, db_path

    path = db_path(request.db)
    if not path.exists():
        return RunList(path, False, ())
    if not path.is_file():
        raise LabcalError(f"{path}: not a database file; --db or $LABCAL_DB names the lab's database")
    wanted = request.statuses
    with Journal(path) as journal:
        # an interrupted run may still say "running" in the journal: ask for both, then sort out
        asked = wanted + (("running",) if "interrupted" in wanted else ())
        rows = journal.runs(request.serial, asked)
        noted = {r.id: attention(journal.run(r.id).metadata) for r in rows} if request.attention else {}
    lines = [RunLine(r.id, r.instrument_serial, r.plan_name, seen_status(path, r.status, r.id), r.reason,
                     r.started_utc, r.ended_utc, r.points_ok, r.points_failed, r.operator, r.run_dir,
                     noted.get(r.id, ())) for r in rows]
    return RunList(path, True, tuple(r for r in lines if (not wanted or r.status in wanted)
                                     and (not request.attention or r.attention)))


@dataclass(frozen=True)
class ReadLog:
    run: str  # a run id in the lab database, or a run folder (whose run.json names both)
    db: str | None = None


@dataclass(frozen=True)
class RunLog:
    run_id: int
    status: str
    reason: str | None
    plan: str
    instrument: str | None
    operator: str | None
    run_dir: str
    started_utc: str
    ended_utc: str | None
    points: int
    events: tuple[dict, ...]  # kind, utc, station_time, message, data

    def to_json(self) -> dict:
        return {**asdict(self), "events": list(self.events)}


def _run_of(request: ReadLog) -> tuple[str | None, int]:
    """RUN as a run id in the lab's database or as a run directory (whose run.json names both)."""
    if request.run.isdigit():
        return request.db, int(request.run)
    from labcal.run.rundir import read_run_json

    if not Path(request.run).is_dir():
        raise LabcalError(f"{request.run}: neither a run id (see labcal runs) nor a run directory")
    info = read_run_json(Path(request.run))
    try:
        return str(info["journal"]), int(info["run_id"])
    except (KeyError, TypeError, ValueError):
        raise LabcalError(f"{request.run}: run.json does not name its journal and run id") from None


def read_log(request: ReadLog) -> RunLog:
    """A run's journaled events in order: prompts and answers, retries, faults, pauses, resumes."""
    from labcal.app.journals import existing
    from labcal.run.journal import Journal

    db, run_id = _run_of(request)
    with Journal(existing(db)) as journal:
        run = journal.run(run_id)
        events = journal.events(run_id)
        done = len(journal.points(run_id, status="ok"))
    return RunLog(run_id, run.status, run.reason, run.plan_name, run.instrument_serial, run.operator,
                  run.run_dir, run.started_utc, run.ended_utc, done, tuple(events))
