"""What a station is doing, read from what its run journaled: the lab overview's one truthful word
per bench (running, waiting for a person, paused on a fault, not heard from, complete, idle).

The journal is the only thing a bench shares with the lab server, so the state is a replay of it:
the run's points and the events that change what a person should do (prompts and their answers,
faults, resumes, the status milestones), in the order they were journaled, then the run's status
and the time now. Nothing is written and nothing is asked of the bench.

Why each rule is what it is:

- **Waiting** and **paused on a fault** are an open prompt (one no answer has closed, an answer that
  keeps it open says so in its line, `labcal.run.events.STAYS_OPEN`); a pause with a fault journaled
  and not yet cleared is the fault state, any other prompt (a remount, a pause after Ctrl-C) is a
  person being waited for, since when the prompt was journaled. A bench at a prompt journals nothing
  until someone answers, so silence there is expected and never turns into "not heard from".
- **Not heard from**: a run the journal says is running, with no prompt open, from which nothing has
  been journaled for longer than several times its usual interval between points (the median gap of
  its latest points, on the wall clock of the journal's UTC stamps, robust to the long gaps of a
  remount), and never less than a floor (the lab server's setting; one minute by default). A process
  killed (kill -9, a power cut) cannot say it died; its run stays "running" in the journal until it
  is resumed, so this is the only honest reading the lab can make of it. It has no ETA.
- **Done at** is a time on the wall clock: the run's own estimate (on the rig's clock) scaled by how
  fast the rig's clock has gone against the wall clock between the latest points (a simulated rig
  paced at 20 × is 20 times faster than its clock says; a real one is 1:1), counted from its latest
  point.
- **The mount** is the one on the plate now: the latest of the points' mounts and the mount a status
  milestone names once a remount is confirmed (before the first point on it).
- **A fault is cleared** once the run went on past it: a point journaled after it, or a resume.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timedelta
from enum import StrEnum
from typing import Any

from labcal.analysis.kinematics import MOUNTS
from labcal.run.events import STAYS_OPEN, JournaledPrompt, mount_number


class State(StrEnum):
    RUNNING = "running"
    WAITING = "waiting"  # at a prompt, for a person (a remount, a pause after Ctrl-C)
    FAULT = "fault"  # paused on a fault, for a person to resume or abort
    SILENT = "silent"  # running in the journal, but nothing heard for several expected intervals
    COMPLETE = "complete"
    IDLE = "idle"  # no run going on (none yet, or the latest stopped, failed or was interrupted)


LABELS = {State.RUNNING: "running", State.WAITING: "waiting for a person", State.FAULT: "paused on a fault",
          State.SILENT: "not heard from", State.COMPLETE: "complete", State.IDLE: "idle"}

RUNNING, COMPLETE = "running", "complete"
TIMELINE_KINDS = ("prompt", "answer", "fault", "resume", "status")  # the events the replay reads
PACE_POINTS = 20  # the latest points whose gaps give the usual interval and the clocks' ratio


@dataclass(frozen=True)
class Silence:
    """When a running station counts as not heard from: silent for ``factor`` times its usual
    interval between points, and at least ``floor_s`` (also the limit before it has two points)."""

    floor_s: float = 60.0
    factor: float = 5.0

    def limit_s(self, interval_s: float | None) -> float:
        return self.floor_s if interval_s is None else max(self.floor_s, self.factor * interval_s)


@dataclass(frozen=True)
class Heard:
    """One thing the run journaled: an event (its kind, message, data) or a point (kind "point",
    ``data`` with its ``t_end`` on the rig's clock and its mount's ``y_deg`` and ``u_deg``)."""

    utc: datetime
    kind: str
    message: str = ""
    data: dict[str, Any] | None = None


@dataclass(frozen=True)
class Fault:
    utc: datetime
    message: str
    cleared_utc: datetime | None  # when the run went on past it (None: not yet)


@dataclass(frozen=True)
class Waiting:
    utc: datetime  # since when
    text: str  # what the prompt asks, in words
    fault: bool  # a pause on a fault


@dataclass(frozen=True)
class StationView:
    state: State
    waiting: Waiting | None
    mount: int | None  # Soto Table 3's number of the mount on the plate (None: none yet)
    fault: Fault | None  # the latest fault
    last_heard: datetime | None
    interval_s: float | None  # the usual wall time between points
    silent_after_s: float  # how long a silence may last before the station is not heard from
    done_at: datetime | None  # wall clock (None: running with no estimate, or not running)
    next_remount_at: datetime | None  # wall clock

    @property
    def label(self) -> str:
        return LABELS[self.state]

    def waited_s(self, now: datetime) -> float | None:
        return None if self.waiting is None else max(0.0, (now - self.waiting.utc).total_seconds())

    def silent_s(self, now: datetime) -> float | None:
        return None if self.last_heard is None else max(0.0, (now - self.last_heard).total_seconds())


def replay(status: str | None, timeline: Iterable[Heard], now: datetime, silence: Silence = Silence(),
           eta_rig_s: float | None = None, remount_rig_s: float | None = None,
           last_heard: datetime | None = None) -> StationView:
    """The station's state from its current run: ``status`` as the runs table has it (None: the
    bench has no run yet), ``timeline`` what it journaled (`TIMELINE_KINDS` and its latest points),
    in the order journaled. ``eta_rig_s``/``remount_rig_s``: the run's estimates on the rig's clock,
    as of its latest point. ``last_heard``: when it last journaled anything at all (a move is heard
    too; default: the latest of ``timeline``)."""
    prompt: Heard | None = None
    fault: Fault | None = None
    mount: int | None = None
    points: list[Heard] = []
    heard: datetime | None = None
    for item in timeline:
        heard = item.utc if heard is None else max(heard, item.utc)
        data = item.data or {}
        if item.kind == "point":
            points.append(item)
            mount = mount_number(float(data["y_deg"]), float(data["u_deg"]))
            fault = _cleared(fault, item.utc)
        elif item.kind == "prompt":
            prompt = item
        elif item.kind == "answer" and STAYS_OPEN not in item.message:
            prompt = None
        elif item.kind == "fault":
            fault = Fault(item.utc, item.message, None)
        elif item.kind == "resume":
            fault = _cleared(fault, item.utc)
        elif item.kind == "status" and data.get("mount") is not None:
            mount = int(data["mount"])
    last_heard = last_heard or heard
    recent = points[-PACE_POINTS:]
    interval = _median(_gaps(recent))
    limit = silence.limit_s(interval)
    nothing = StationView(State.IDLE, None, mount, fault, last_heard, interval, limit, None, None)
    if status == COMPLETE:
        return replace(nothing, state=State.COMPLETE)
    if status != RUNNING:
        return nothing
    if prompt is not None:
        waiting = _waiting(prompt, fault)
        return replace(nothing, state=State.FAULT if waiting.fault else State.WAITING, waiting=waiting)
    if last_heard is not None and (now - last_heard).total_seconds() > limit:
        return replace(nothing, state=State.SILENT)
    return replace(nothing, state=State.RUNNING, done_at=on_the_wall(recent, eta_rig_s),
                   next_remount_at=on_the_wall(recent, remount_rig_s))


def on_the_wall(points: Sequence[Heard], rig_s: float | None) -> datetime | None:
    """When ``rig_s`` more seconds of the rig's clock, counted from the latest of ``points``, will
    have passed on the wall clock (None: no estimate, or fewer than two points to measure the rig's
    pace by)."""
    ratio = _clock_ratio(points[-PACE_POINTS:])
    if rig_s is None or ratio is None:
        return None
    return _after(points[-1].utc, rig_s * ratio)


def _cleared(fault: Fault | None, utc: datetime) -> Fault | None:
    if fault is None or fault.cleared_utc is not None:
        return fault
    return Fault(fault.utc, fault.message, utc)


def _waiting(prompt: Heard, fault: Fault | None) -> Waiting:
    """The open prompt; a pause with a fault not yet cleared is the fault's (a device's fault, a point
    that did not settle under the pause policy), any other is a person's (Ctrl-C, a remount)."""
    try:
        text = JournaledPrompt.read(prompt.message, prompt.data or {}).text()
    except ValueError:  # not a prompt labcal journaled (pydantic's ValidationError is a ValueError)
        text = prompt.message
    on_fault = prompt.message == "pause" and fault is not None and fault.cleared_utc is None
    return Waiting(prompt.utc, text, on_fault)


def _gaps(points: Sequence[Heard]) -> list[float]:
    return [(b.utc - a.utc).total_seconds() for a, b in zip(points, points[1:], strict=False)]


def _median(values: Sequence[float]) -> float | None:
    return statistics.median(values) if values else None


def _clock_ratio(points: Sequence[Heard]) -> float | None:
    """Wall seconds per rig second between consecutive points (their median: a remount's wait on a
    simulated rig's clock, or a pause, does not skew it); None before two points have measured it."""
    ratios = []
    for a, b in zip(points, points[1:], strict=False):
        ends = (a.data or {}).get("t_end"), (b.data or {}).get("t_end")
        if ends[0] is None or ends[1] is None:  # a point journaled without its rig time
            continue
        rig, wall = float(ends[1]) - float(ends[0]), (b.utc - a.utc).total_seconds()
        if rig > 0 and wall >= 0:
            ratios.append(wall / rig)
    return _median(ratios)


def _after(start: datetime, seconds: float) -> datetime:
    return start + timedelta(seconds=seconds)


def mount_angles(number: int | None) -> dict | None:
    """A mount's number and angles (Soto Table 3), as the overview states it."""
    if number is None:
        return None
    mount = MOUNTS[number - 1]
    return {"number": number, "y_deg": mount.y_deg, "u_deg": mount.u_deg}
