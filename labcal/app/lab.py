"""The lab's view, as the lab server shows it: the lab's runs, a run's progress and events, the next
batch of a run's live stream; pure reads (every bench and its state: `labcal.app.overview`; a run's
residual plot and its certificate: `labcal.app.desk`).

The server (`labcal.server`) turns these into JSON, pages and server-sent events and calls nothing
below this layer. The public use cases take the open lab database (`labcal.app.labdatabase`) and a
run id or a typed request; the runs and events they return are the API's JSON objects (their field
names are the API's: `GET /api/runs`, `GET /api/runs/{id}`), built here once for the API, the pages
and the streams alike.

Everything here is a SELECT through `labcal.store.schema`'s tables, on SQLite or PostgreSQL alike;
nothing is written (a reader must never change what it shows, docs/design.md §4).

Progress is the journal's: ``points_done`` counts the points journaled (measured or failed, each once
per step of the schedule), ``points_ok`` those measured. ``points_total`` is the run's own
(`runs.points_total`) or, for a run journaled before the lab columns, the length of its plan's
schedule (replicates × mounts × points, `labcal.run.sequencer.schedule`'s blocks).

The next remount and the ETA come from the run's latest ``status`` event where the run journals one
(`labcal.run.events.Status`, journaled at each milestone: a mount confirmed, a resume): its
``next_remount_in_s`` and ``eta_s`` are the plan's estimates on the rig's clock at that moment, less
the rig time since (the latest point's end) — ``estimate: "status"``. A run journaled without them is
estimated here from the plan and the rig time per point so far, and says so (``estimate:
"points"``). A run that is not running has neither.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from labcal.analysis.kinematics import MOUNTS
from labcal.app.labdatabase import LabDatabase
from labcal.app.station_state import PACE_POINTS, Heard, on_the_wall
from labcal.config.plans import parse_plan
from labcal.config.run_metadata import RunMetadata, listed_metadata
from labcal.config.snapshot import is_simulated, parse_snapshot
from labcal.errors import LabcalError
from labcal.run.events import STAYS_OPEN, JournaledPrompt
from labcal.store import lab_view
from labcal.store.lab_certificates import approved_by, file_names

if TYPE_CHECKING:
    from labcal.store.handles import Connection

RunJson = dict[str, Any]  # a run as the API states it
EventJson = dict[str, Any]  # a journaled event as the API states it

RUNNING = "running"
STATUS_KIND, FAULT_KIND, PROMPT_KIND, ANSWER_KIND = "status", "fault", "prompt", "answer"


@dataclass(frozen=True)
class PlanShape:
    """How a run's schedule is laid out: blocks of ``block`` points, one mount each, ``total`` points."""

    total: int
    block: int


def plan_shape(plan_text: str) -> PlanShape | None:
    """The schedule's shape from the plan as journaled (None: a plan this labcal cannot read)."""
    try:
        plan = parse_plan(plan_text, "the run's plan")
    except (LabcalError, ValueError):
        return None
    return PlanShape(plan.replicates * len(plan.mounts) * len(plan.points), len(plan.points))


def _json(text: str | None) -> Any:
    if not text:
        return None
    try:
        return json.loads(text)
    except ValueError:
        return None


def simulated(metadata: RunMetadata, station_text: str | None) -> bool:
    """A dry run (simulated rig or emulators), by the rule a run's record applies
    (`labcal.config.snapshot.is_simulated`): shown on the pages so that nobody mistakes one for a
    calibration (approving it is refused by the approval itself, whatever a page shows)."""
    return is_simulated(metadata, parse_snapshot(station_text))


def _summary(row: Any, counts: tuple[int, int, int | None]) -> dict:
    total = row.points_total
    if total is None:  # a run journaled before the lab columns: its plan's length
        shape = plan_shape(row.plan_text)
        total = shape.total if shape else None
    metadata = listed_metadata(row.metadata)
    station = row.station or metadata.station
    done, ok, _ = counts
    # named as `labcal runs --json` names them: the lab's run number is ``id`` everywhere
    return {"id": row.id, "label": str(row.id), "uuid": row.uuid, "status": row.status,
            "simulated": simulated(metadata, row.station_text),
            "station": station, "serial": row.instrument_serial,
            "operator": row.operator, "plan": row.plan_name, "points_done": done, "points_ok": ok,
            "points_failed": done - ok, "points_total": total, "started_utc": row.started_utc,
            "ended_utc": row.ended_utc, "reason": row.reason, "run_dir": row.run_dir}


def _list_runs(conn: Connection) -> list[dict]:
    """Every run of the lab, newest first, with its progress."""
    counts = lab_view.counts(conn)
    rows = lab_view.summaries(conn)
    return [_summary(r, counts.get(r.id, (0, 0, None))) for r in rows]


def _event_json(row: Any) -> dict:
    data = _json(row.data)
    return {"id": row.id, "utc": row.utc, "station_time": row.station_time, "kind": row.kind,
            "message": row.message, "data": data, "text": _text(row.kind, row.message, data)}


def _text(kind: str, message: str, data: Any) -> str:
    """The event in words for people: a prompt with what it asks (its arguments), else its message."""
    if kind == PROMPT_KIND and isinstance(data, dict):
        try:
            return JournaledPrompt.read(message, data).text()
        except ValidationError:  # not a prompt labcal journaled: its message
            return message
    return message


def _latest(conn: Connection, run_id: int, kind: str) -> dict | None:
    row = lab_view.latest_event(conn, run_id, kind)
    return None if row is None else _event_json(row)


def _progress(conn: Connection, run_id: int) -> dict | None:
    """The run's summary with where it stands: mount, next remount, ETA, last fault (None: no run)."""
    row = lab_view.summary(conn, run_id)
    if row is None:
        return None
    counts = lab_view.counts(conn, [run_id]).get(run_id, (0, 0, None))
    summary = _summary(row, counts)
    last = lab_view.last_point(conn, run_id)
    summary["mount"] = _mount(conn, run_id, last)
    fault = _latest(conn, run_id, FAULT_KIND)
    summary["last_fault"] = None if fault is None else {"utc": fault["utc"], "message": fault["message"]}
    summary["waiting"] = _waiting(conn, run_id) if row.status == RUNNING else None
    summary["last_heard_utc"] = _last_heard(conn, run_id)
    summary.update(_ahead(conn, row, counts, None if last is None else last.t_end))
    summary["done_at_utc"] = None if summary["waiting"] else _done_at(conn, run_id, summary["eta_s"])
    return summary


def _done_at(conn: Connection, run_id: int, eta_s: float | None) -> str | None:
    """When the run will be done on the wall clock: its ETA on the rig's clock at the pace the rig's
    clock has kept against the wall's over its latest points (`labcal.app.station_state.on_the_wall`)."""
    if eta_s is None:
        return None
    latest = lab_view.latest_points(conn, run_id, PACE_POINTS)
    heard = [Heard(datetime.fromisoformat(r.utc), "point", data={"t_end": r.t_end}) for r in reversed(latest)]
    when = on_the_wall(heard, eta_s)
    return None if when is None else when.isoformat(timespec="milliseconds")


def _mount(conn: Connection, run_id: int, last: Any) -> dict | None:
    """The mount on the plate: the latest point's, unless a remount was confirmed since (the status
    the run journals then names the mount, Soto Table 3's number) and no point has been measured on
    it yet."""
    status = _latest(conn, run_id, STATUS_KIND)
    number = status["data"].get("mount") if status and isinstance(status["data"], dict) else None
    if number in (1, 2, 3, 4) and status is not None and (last is None or status["utc"] > last.utc):
        mounted = MOUNTS[number - 1]
        return {"y_deg": mounted.y_deg, "u_deg": mounted.u_deg}
    return None if last is None else {"y_deg": last.y_deg, "u_deg": last.u_deg}


def _last_heard(conn: Connection, run_id: int) -> str | None:
    """When the run last journaled anything (a point or an event), UTC. A station that has gone
    quiet (its process killed, a power cut) leaves its run "running" until it is resumed; this says
    since when nothing has come from it."""
    heard = lab_view.last_written(conn, run_id)
    return max((t for t in heard if t), default=None)  # both ISO 8601 in UTC, as the journal writes them


def _waiting(conn: Connection, run_id: int) -> dict | None:
    """The prompt the run waits at for someone at the station (a remount, a pause), None when none
    is open: its newest prompt until an answer closes it. An answer that keeps it open ("not yet",
    a reply that is not one of the answers) says so in its journal line (`STAYS_OPEN`); other
    writers' events in between (the lab database's sync, an export) close nothing."""
    prompt = _latest(conn, run_id, PROMPT_KIND)
    if prompt is None:
        return None
    answers = lab_view.answers_after(conn, run_id, prompt["id"], ANSWER_KIND)
    if any(STAYS_OPEN not in message for message in answers):
        return None
    return {"utc": prompt["utc"], "text": prompt["text"]}


def _ahead(conn: Connection, row: Any, counts: tuple[int, int, int | None], rig_s: float | None) -> dict:
    """next_remount_in_s and eta_s (rig seconds), and what they are estimated from."""
    none = {"next_remount_in_s": None, "eta_s": None, "estimate": None}
    if row.status != RUNNING:
        return none
    status = _latest(conn, row.id, STATUS_KIND)
    data = status["data"] if status and isinstance(status["data"], dict) else None
    if data is not None and data.get("status") == RUNNING and status is not None:
        # the run's own estimate at its last milestone (a mount confirmed, a resume), less the rig
        # time that has passed since (its latest point's end)
        since = max(0.0, (rig_s or 0.0) - (status["station_time"] or 0.0))
        remount, eta = data.get("next_remount_in_s"), data.get("eta_s")
        return {"next_remount_in_s": None if remount is None else max(0.0, remount - since),
                "eta_s": None if eta is None else max(0.0, eta - since), "estimate": "status"}
    shape = plan_shape(row.plan_text)
    done, _, last_seq = counts
    if shape is None or last_seq is None or not rig_s or rig_s <= 0:
        return none
    position = last_seq + 1  # the next step of the schedule
    per_point = rig_s / position  # rig seconds per step so far, remounts included
    total = row.points_total or shape.total
    boundary = -(-position // shape.block) * shape.block  # the next block's first step (or this one)
    remount = None if boundary >= total else max(0.0, (boundary - position) * per_point)
    return {"next_remount_in_s": remount, "eta_s": max(0, total - position) * per_point, "estimate": "points"}


def _run_events(conn: Connection, run_id: int, after: int = 0, limit: int | None = None) -> list[dict]:
    """The run's journaled events after event id ``after``, oldest first."""
    return [_event_json(r) for r in lab_view.events_after(conn, run_id, after, limit)]


def _run_points(conn: Connection, run_id: int, after: int = -1, limit: int | None = None) -> list[dict]:
    """The run's journaled points with seq above ``after`` (raw samples left out), in order."""
    return lab_view.points_after(conn, run_id, after, limit)


# --- the use cases ------------------------------------------------------------------------------
QUIET_KINDS = frozenset({"move", "status", "settle_pool", "segment"})  # many per run: a page lists the rest
RECENT = 30  # events a run's page lists
BATCH = 500  # rows per stream batch and kind: a client far behind catches up in bounded steps


def lab_runs(lab: LabDatabase) -> list[RunJson]:
    """Every run of the lab, newest first, with its progress (`GET /api/runs`)."""
    with lab.engine.connect() as conn:
        return _list_runs(conn)


def run_progress(lab: LabDatabase, run_id: int) -> RunJson | None:
    """The run's summary with where it stands: mount, next remount, ETA, last fault (None: no run)."""
    with lab.engine.connect() as conn:
        return _progress(conn, run_id)


def run_detail(lab: LabDatabase, run_id: int) -> RunJson | None:
    """`GET /api/runs/{id}`: the run's progress and every event it journaled (None: no run)."""
    with lab.engine.connect() as conn:
        found = _progress(conn, run_id)
        if found is not None:
            found["events"] = _run_events(conn, run_id)
        return found


@dataclass(frozen=True)
class Cursor:
    """Where a reader of a run's stream stands: the last point's seq and the last event's id seen."""

    seq: int = -1
    event_id: int = 0


@dataclass(frozen=True)
class RunView:
    """A run's page: its progress, its latest events worth a person's eye, and where the page's
    live stream starts (what the page shows already)."""

    run: RunJson
    recent: tuple[EventJson, ...]
    cursor: Cursor


def run_view(lab: LabDatabase, run_id: int) -> RunView | None:
    with lab.engine.connect() as conn:
        found = _progress(conn, run_id)
        if found is None:
            return None
        journal = _run_events(conn, run_id)
        seq, _ = lab_view.newest(conn, run_id)
        found["approval"] = approved_by(conn, run_id)  # who approved its certificate, and when
        found["approved_files"] = file_names(conn, found["uuid"]) if found.get("uuid") else []
    recent = [e for e in journal if e["kind"] not in QUIET_KINDS][-RECENT:]
    cursor = Cursor(seq, journal[-1]["id"] if journal else 0)
    return RunView(found, tuple(recent), cursor)


@dataclass(frozen=True)
class NextBatch:
    run_id: int
    cursor: Cursor  # what the reader has seen
    status: str | None  # the run's status as the reader last heard it (None: not yet)
    first: bool = False  # the reader's first batch: always ends with the run's progress


@dataclass(frozen=True)
class StreamItem:
    kind: str  # "point", an event's kind ("prompt", "fault", "status", …), "run" or "progress"
    data: dict
    cursor: Cursor  # where a reader stands once it has this item


@dataclass(frozen=True)
class Batch:
    items: tuple[StreamItem, ...]
    cursor: Cursor
    status: str | None


def next_batch(lab: LabDatabase, request: NextBatch) -> Batch:
    """What the run journaled after the reader's cursor: one item per new point and per journaled
    event (at most `BATCH` of each), one ``run`` item when the run's status changed since the reader
    heard it, and after any news (or on a first batch) one ``progress`` item."""
    seq, event_id = request.cursor.seq, request.cursor.event_id
    status, first = request.status, request.first
    items: list[StreamItem] = []
    with lab.engine.connect() as conn:
        for _ in range(3):  # until the progress is read from nothing newer than the items carry
            for point in _run_points(conn, request.run_id, seq, BATCH):
                seq = point["seq"]
                items.append(StreamItem("point", point, Cursor(seq, event_id)))
            for event in _run_events(conn, request.run_id, event_id, BATCH):
                event_id = event["id"]
                items.append(StreamItem(event["kind"], event, Cursor(seq, event_id)))
            now = _progress(conn, request.run_id)
            # Rows are only ever added: if none lies beyond the cursor now, none did while the
            # progress was read, so it states exactly what the reader has been sent.
            consistent = lab_view.newest(conn, request.run_id) == (seq, event_id)
            if consistent:
                break
    cursor = Cursor(seq, event_id)
    if now is not None and now["status"] != status:
        if status is not None:
            items.append(StreamItem("run", {"status": now["status"], "reason": now["reason"]}, cursor))
        status = now["status"]
        first = True
    if now is not None and consistent and (items or first):  # else the next batch carries it
        items.append(StreamItem("progress", now, cursor))
    return Batch(tuple(items), cursor, status)


def run_folder(lab: LabDatabase, run_id: int) -> str | None:
    """Where the run's folder is, as its station journaled it (None: no such run)."""
    return lab_view.run_dir(lab.engine, run_id)

