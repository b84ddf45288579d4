"""Executes a plan on a station: move, wait in position, settle, measure, report, repeat.

The sequencer never knows whether a real rig or the simulator answers. Before anything moves,
every angle of the run is checked against the tables' limits. Axes never move while a prompt is
open. The sequencer does not call its audiences: it publishes typed events (`labcal.run.events`)
and the journal, their first and durable subscriber, commits each point in one transaction before
the next move; the console, the lab database sync and a notifier subscribe besides. It still
reads the journal (where the tables were last sent, the points so far). The first Ctrl-C pauses
after the current point; the second stops the tables at once.
"""

from __future__ import annotations

import logging
import math
from contextlib import nullcontext
from dataclasses import dataclass, field, replace

import numpy as np

from labcal.analysis.kinematics import Mount
from labcal.analysis.plan import Plan
from labcal.config.settings import SequencerSettings
from labcal.config.snapshot import output_units, parse_snapshot
from labcal.devices.station import RotaryAxis, Station, StopFailed, TableState, mean_and_sd
from labcal.devices.winding import MOVE_EVENT, last_move, locate, plan_windings
from labcal.errors import LabcalError
from labcal.run import settle_pool
from labcal.run.checks import Verdict, check_readings, closure
from labcal.run.events import (
    Answer,
    Discarded,
    EventBus,
    Fault,
    Note,
    Paused,
    PointMeasured,
    Prompt,
    Resumed,
    RunEvent,
    Status,
    Stopped,
    mount_number,
)
from labcal.run.interrupts import Interrupts
from labcal.run.motion import Move, move_time, transient_after, transient_at_stop
from labcal.run.mounting import CHECK_ATTITUDE, distinguishes, identify
from labcal.run.operator import GATE_KEY, Operator, OperatorDeclined, Terminal
from labcal.run.ordering import order_points
from labcal.run.settle import Dwell, TailPool, dead_time, dwell, dwell_model
from labcal.store.journal import Journal, PointRecord

THERMAL_SAMPLES = 4  # DMM samples averaged per temperature read of the thermal gate
Winding = tuple[float, float]  # each table's accumulated rotation from home, degrees (pitch, roll)

LOAD_POSITION = (0.0, 0.0)  # tables level while the operator remounts
log = logging.getLogger(__name__)


class PolicyAbort(LabcalError):
    """A point did not settle and the policy says abort (not a device fault to pause on)."""


class TableFault(LabcalError):
    """A table reported a fault around a measurement window: the run stops the tables and pauses."""


class StationMiswired(LabcalError):
    """The mount check reads the tables exchanged, a table reversed or the DMM's channels out of order
    (`labcal.run.mounting`): the run stops the tables and pauses before any point of the mount."""


class ReadingsRefused(LabcalError):
    """The run's readings fail the checks of their fit after the points named were measured again:
    the run ends "failed", every reading kept, with no certificate."""


MOUNT_ATTEMPTS = 3
MEASURE_AGAIN = 2  # windows of one point a table's state may discard before the run pauses on it



def finite(values) -> list[float | None]:
    """Values for an event's JSON: a package's absent sensors (NaN) and an unknown rate (infinity) as
    null, which every JSON reader takes (``NaN`` and ``Infinity`` are not JSON)."""
    return [float(v) if math.isfinite(float(v)) else None for v in values]


@dataclass(frozen=True)
class Step:
    seq: int
    replicate: int
    mount: Mount
    pitch_deg: float
    roll_deg: float
    block_start: bool  # first point of a (replicate, mount) block: the instrument is (re)seated first


def schedule(plan: Plan, settings: SequencerSettings) -> list[Step]:
    """Every point of the run in order. Replicates alternate the mount order (…, 3, 4 | 4, 3, …) so
    that consecutive replicates meet on the same orientation; the instrument is still re-seated
    there, so that each replicate holds its own mountings and replicates stay independent. Even
    replicates walk a mount's shortest tour backwards: every point is then reached from the other
    side, so the transient a move leaves in the window (at most σ/√N, but with the sign of the move)
    cancels between replicates to first order instead of adding up in the coefficients."""
    steps: list[Step] = []
    orders: dict[tuple[int, Mount], list[int]] = {}
    for rep in range(1, plan.replicates + 1):
        mounts = plan.mount_list if rep % 2 else plan.mount_list[::-1]
        for mount in mounts:
            key = (rep if settings.order in ("sweep", "random") else 0, mount)
            if key not in orders:  # the shortest tour of a mount is the same in every replicate
                orders[key] = order_points(plan.points, settings.order, replicate=rep, seed=settings.seed,
                                           start=LOAD_POSITION, speed=settings.speed_dps,
                                           accel=settings.accel_dps2, settle_s=settle_cost(mount, settings))
            order = orders[key] if rep % 2 or settings.order != "shortest" else orders[key][::-1]
            for k, i in enumerate(order):
                pitch, roll = plan.points[i]
                steps.append(Step(len(steps), rep, mount, pitch, roll, block_start=k == 0))
    return steps


def settle_cost(mount: Mount, settings: SequencerSettings):
    """The dead time after a move from attitude(s) a to b on ``mount``: what the shortest tour
    weighs besides the move itself (the window's own fading is left out: it shortens every dead
    time alike)."""
    s = settings.settle

    def cost(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        lag = transient_at_stop(a, b, mount, settings.speed_dps, settings.accel_dps2, s.tau_s,
                                math.radians(s.off_axis_arcsec / 3600))
        return np.asarray(dead_time(lag * s.sensitivity_v_per_g, s))
    return cost


@dataclass(frozen=True)
class Forecast:
    """The plan's estimate of each step on the rig's clock (`labcal.run.estimate.Estimate.forecast`):
    what a Status's live figures come from. For a mount's first step, ``prompt_s`` is the rig time
    from the step's start to its remount prompt (the move to the load position), ``mount_s`` to the
    end of the mounting (the operator's allowance and the mount check)."""

    per_step_s: dict[int, float]
    prompt_s: dict[int, float]
    mount_s: dict[int, float]

    def ahead(self, todo: list[Step]) -> list[tuple[float | None, float]]:
        """For each i, before ``todo[i]`` is measured (i = len(todo): after the last): the rig time
        until the next remount prompt (None: none is left) and the rig time of the rest. The first
        step of a segment prompts too (a resumed run confirms the mount). Computed once per run,
        from the end, so that a day-long run's statuses cost nothing."""
        figures: list[tuple[float | None, float]] = [(None, 0.0)]
        next_prompt: float | None = None
        rest = 0.0
        for i in range(len(todo) - 1, -1, -1):
            step = todo[i]
            took = self.per_step_s.get(step.seq, 0.0)
            if step.block_start or i == 0:
                next_prompt = self.prompt_s.get(step.seq, 0.0)
            elif next_prompt is not None:
                next_prompt += took
            rest += took
            figures.append((next_prompt, rest))
        return figures[::-1]

    def after_mount(self, step: Step, after: tuple[float | None, float]) -> tuple[float | None, float]:
        """The figures once ``step``'s mounting is done, from ``after`` (`ahead`'s after the step):
        its point is still to measure."""
        left = self.per_step_s.get(step.seq, 0.0) - self.mount_s.get(step.seq, 0.0)
        remount, rest = after
        return (None if remount is None else remount + left), rest + left


@dataclass
class RunOutcome:
    points_recorded: int
    points_failed: int
    station_time_s: float


def unvouched(before: tuple[TableState, ...], after: tuple[TableState, ...]) -> tuple[str | None, bool]:
    """Why a window measured between the ``before`` and ``after`` states cannot be kept (None if it
    can), and whether a table reported a fault (the run pauses) rather than being off or moving (the
    point is measured again). A fault anywhere outranks the rest."""
    found: list[tuple[bool, str]] = []
    for when, states in (("before", before), ("after", after)):
        for state in states:
            if problem := state.problem():
                found.append((state.fault is not None, f"{when} the measurement window, {problem}"))
    if not found:
        return None, False
    faulted, why = max(found, key=lambda item: item[0])
    return why, faulted


def _read(value: float) -> float | None:
    """A channel's mean or SD for the journal: None (NULL) for a sensor the package does not have,
    whose channel the voltmeter leaves NaN."""
    return None if math.isnan(value) else float(value)


def raw_samples(result: Dwell) -> np.ndarray:
    """The window's samples, one row each: the three voltages and the temperature (NaN if none)."""
    scan = result.scan
    return np.column_stack([scan.volts, scan.temp_c if scan.temp_c is not None
                            else np.full(len(scan.volts), np.nan)])


def check_limits(station: Station, steps: list[Step], check_mount: bool = True) -> dict[int, Winding]:
    """Every angle the run will visit, against each table's limits and cable wrap, before anything
    moves; returns each step's winding, planned for the whole run (`labcal.devices.winding`)."""
    angles = {
        station.pitch: [s.pitch_deg for s in steps] + [LOAD_POSITION[0], CHECK_ATTITUDE[0]],
        station.roll: [s.roll_deg for s in steps] + [LOAD_POSITION[1], CHECK_ATTITUDE[1]],
    }
    for axis, values in angles.items():
        check = getattr(axis, "check_angle", None)
        if check is None:
            continue
        for angle in sorted(set(values)):
            try:
                check(angle)
            except LabcalError as exc:
                raise LabcalError(f"plan refused before any motion: {axis.name} {exc}") from None
    return planned_windings(station, steps, check_mount)


def planned_windings(station: Station, steps: list[Step], check_mount: bool = True) -> dict[int, Winding]:
    """Each step's winding in the uninterrupted run: every move (a mount's load position and check
    attitude included) to the equivalent nearest where the tables are, from home. A resumed run
    goes to the same windings, so it makes the same moves as the uninterrupted one."""
    targets: list[tuple[float, float]] = []
    index: dict[int, int] = {}
    for step in steps:
        if step.block_start:
            targets += [LOAD_POSITION, CHECK_ATTITUDE] if check_mount else [LOAD_POSITION]
        index[step.seq] = len(targets)
        targets.append((step.pitch_deg, step.roll_deg))
    windings = plan_windings(targets, (station.pitch.reach, station.roll.reach))
    return {seq: windings[i] for seq, i in index.items()}


def move_both(station: Station, pitch: float, roll: float, settings: SequencerSettings,
              critical=nullcontext, travel: tuple[float, float] | None = None) -> tuple[float, float]:
    """Start both tables (inside ``critical()``: a command is never cut in half), each turning by
    its ``travel`` (the way round its cable wrap chose; None: the shortest), wait for both, and
    verify the read-back positions."""
    start_both(station, pitch, roll, critical, travel)
    return wait_both(station, pitch, roll, settings)


def start_both(station: Station, pitch: float, roll: float, critical=nullcontext,
               travel: tuple[float, float] | None = None) -> None:
    """Command both moves (`move_both`'s first half); each table starts as its command is
    answered, which takes the link's round trips: not the instant the first command was sent."""
    turn_pitch, turn_roll = travel or (None, None)
    with critical():
        station.pitch.move_to(pitch, travel_deg=turn_pitch)
        station.roll.move_to(roll, travel_deg=turn_roll)


def wait_both(station: Station, pitch: float, roll: float,
              settings: SequencerSettings) -> tuple[float, float]:
    """Wait for both tables and verify their read-back positions (`move_both`'s second half)."""
    return (_in_position(station.pitch, pitch, settings.move_timeout_s, settings.position_tolerance_deg),
            _in_position(station.roll, roll, settings.move_timeout_s, settings.position_tolerance_deg))


def _in_position(axis, target: float, timeout: float, tolerance: float) -> float:
    position = axis.wait_in_position(timeout)
    error = (position - target + 180.0) % 360.0 - 180.0
    if abs(error) > tolerance:
        raise LabcalError(
            f"{axis.name} table reads {position:.4f}° after a move to {target:g}° "
            f"(tolerance {tolerance:g}°); check the table and its clamp"
        )
    return position


@dataclass
class Sequencer:
    plan: Plan
    station: Station
    operator: Operator
    journal: Journal
    run_id: int
    settings: SequencerSettings
    events: EventBus = field(default_factory=EventBus)  # the journal subscribed first (`labcal.run.runner`)
    terminal: Terminal = field(default_factory=Terminal)
    interrupts: Interrupts = field(default_factory=Interrupts)
    offset_s: float = 0.0  # rig time since the run began when this segment starts (0 unless resumed)
    forecast: Forecast | None = None  # the plan's estimates, for the statuses' live figures
    _t0: float = 0.0
    moving: tuple[str, ...] = ()  # tables whose last stop failed: they may still be moving
    _at: Winding | None = None  # where the last move went (accumulated from home); None: unknown, locate it
    _windings: dict[int, Winding] = field(default_factory=dict)  # each step's, planned for the run
    _last_move: tuple[tuple[float, float], tuple[float, float], float] = ((0.0, 0.0), (0.0, 0.0), 0.0)
    _moves: list[Move] = field(default_factory=list)  # since the last window: what the transient is
    _sample_s: float = 0.0  # the voltmeter's time per sample, once measured
    _tail: TailPool | None = None  # model settling: the instrument's tail, pooled over its runs' points
    _pool_key: settle_pool.PoolKey | None = None  # where to keep _tail when the segment ends
    _prior_key: settle_pool.PoolKey | None = None  # where to add this segment's records for other instruments
    _mount: int | None = None  # the mount on the plate (its number), once confirmed
    _points_done: int = 0  # points of the run in the journal (ok and failed)
    _points_total: int = 0
    _ahead: list[tuple[float | None, float]] = field(default_factory=list)  # `Forecast.ahead` of the todo
    _next: int = 0  # the index in the todo of the next step to measure
    _todo: list[Step] = field(default_factory=list)
    _home: tuple[RotaryAxis, ...] = ()  # tables to home before the next action (agreed at a pause)
    _mounted: Mount | None = None  # the mount on the plate, once confirmed
    _provisional: object = None  # `run`'s provisional(): an X from the points so far, for a mount check

    # --- motion ----------------------------------------------------------------------------------
    def move(self, pitch: float, roll: float, winding: Winding | None = None) -> tuple[float, float]:
        """Move both tables to ``winding`` (each table's accumulated rotation from home; by default
        the equivalents of the angles nearest where they are, within their reach), journaling the
        move before it starts, and remember where from and when the motion ended: the tables' own
        profile from the move's start, or the in-position time if that came first. A table a turn
        or more from its winding gets there by way of the midpoint: no leg is a turn or more."""
        start = self._at
        if start is None:
            start = self.locate()
            if self._moves:  # a stop caught the last move part way: it ended where the tables are
                self._moves[-1] = (self._moves[-1][0], start, self._moves[-1][2])
        if winding is None:
            found = [axis.reach.nearest(angle, here) for axis, angle, here
                     in ((self.station.pitch, pitch, start[0]), (self.station.roll, roll, start[1]))]
            if found[0] is None or found[1] is None:  # the plan was checked: only a stray angle gets here
                raise LabcalError(f"pitch {pitch:g}°, roll {roll:g}° is beyond the tables' cable wrap or "
                                  "limits")
            winding = (found[0], found[1])
        self._at = None
        legs = [winding]
        if max(abs(winding[0] - start[0]), abs(winding[1] - start[1])) >= 360.0 - 1e-6:
            legs.insert(0, ((start[0] + winding[0]) / 2, (start[1] + winding[1]) / 2))
        clock = self.station.clock
        for leg in legs:
            self.note(MOVE_EVENT, f"pitch {start[0]:g}° → {leg[0]:g}°, roll {start[1]:g}° → {leg[1]:g}° "
                       "(accumulated from home)", pitch=[start[0], leg[0]], roll=[start[1], leg[1]])
            start_both(self.station, leg[0] % 360.0, leg[1] % 360.0, self.interrupts.critical,
                       (leg[0] - start[0], leg[1] - start[1]))
            # both tables are moving by now (on a slow link, or an emulated one whose clock runs
            # fast, the commands' round trips are a good part of a second): their profiles, and the
            # transient's dead time, run from here, else the first window meets the transient
            t_start = clock.now()
            read = wait_both(self.station, leg[0] % 360.0, leg[1] % 360.0, self.settings)
            travel = float(move_time(np.array(start), np.array(leg), self.settings.speed_dps,
                                     self.settings.accel_dps2, unwrapped=True))
            self._last_move = (start, leg, min(t_start + travel, clock.now()))
            self._moves.append((start, leg, t_start))
            start = leg
        self._at = winding
        return read

    def locate(self) -> Winding:
        """Where the tables are, in accumulated degrees from home: as a device that counts turns says
        (homing it unwound its cables), else its position read back placed on the last move the
        journal has (`labcal.devices.winding.locate`)."""
        last = last_move(self.journal.events(self.run_id))
        found = []
        for i, axis in enumerate((self.station.pitch, self.station.roll)):
            counted = axis.winding()
            found.append(counted if counted is not None else
                         locate(axis.position(), last and last[i], axis.reach))
        return found[0], found[1]

    def measure(self, mount: Mount, key: str) -> Dwell:
        """Settle after the last move and take the window. The dead time is sized by the transient
        the tables' moves since the last window left (from where each really began: after a resume
        the move to the load position too, if the output had no time to settle since), not by the
        last move's alone; once the window is taken, the output is settled to its criterion."""
        s, (_, _, motion_end) = self.settings.settle, self._last_move
        lag_g = transient_after(self._moves, mount, self.settings.speed_dps, self.settings.accel_dps2,
                                s.tau_s, off_axis_rad=math.radians(s.off_axis_arcsec / 3600))
        self._moves = []
        self.station.at_point(key)
        with self.interrupts.critical():
            if s.mode == "model" and s.fixed_dwell_s is None:
                self._tail = self._tail or self._start_pool()
                result = dwell_model(self.station.dmm, self.station.clock, lag_g * s.sensitivity_v_per_g, s,
                                     motion_end, self._sample_s, self._tail)
            else:
                result = dwell(self.station.dmm, self.station.clock, lag_g * s.sensitivity_v_per_g, s,
                               motion_end, self._sample_s)
        self._sample_s = result.sample_s
        return result

    def _start_pool(self) -> TailPool:
        """Model settling's pool, with the step records of the instrument's earlier runs on this
        station where the lab database has them (`labcal.run.settle_pool`), and where the station
        says so its type's or station's records as a prior; the journal says which."""
        s, row = self.settings.settle, self.journal.run(self.run_id)
        key = settle_pool.pool_key(row, s)
        if key is None:
            return TailPool(s.tau_s, s.noise_v)
        state, note, keep = settle_pool.load(self.journal.db, key)
        self._pool_key = key if keep else None
        prior, prior_key = None, settle_pool.prior_key(row, s)
        if prior_key is not None:
            whose = (f"the {s.instrument_type} instruments" if s.prior == "type" else "every instrument")
            prior, prior_note, keep_prior = settle_pool.load_prior(self.journal.db, prior_key, whose)
            self._prior_key = prior_key if keep_prior else None
            note += f"; {prior_note}"
        pool = TailPool(s.tau_s, s.noise_v, state, prior, s.prior_records)
        if pool.lent:
            note += f", counted as {pool.lent:.0f} records"
        self.note("settle_pool", note, pool_key=key.key, records=state.records if state else 0,
                  prior_records=pool.lent)
        return pool

    def _keep_pool(self) -> None:
        """Keep the pool for the instrument's next run (or this one's resume). A database that
        refuses it costs the next run its head start, never this run's points: warned, not raised."""
        if self._tail is None:
            return
        try:
            with self.journal.refusals():
                if self._pool_key is not None:
                    settle_pool.save(self.journal.db, self._pool_key, self._tail)
                if self._prior_key is not None:
                    settle_pool.add_to_prior(self.journal.db, self._prior_key, self._tail)
        except LabcalError as exc:  # a JournalError among them
            log.warning("model settling's pool was not kept for the next run: %s", exc)

    # --- what the run reports ----------------------------------------------------------------
    def rig_time(self) -> float:
        """Rig seconds since the run began (the journal's station_time)."""
        return self.station.clock.now() - self._t0

    def publish(self, event: RunEvent) -> None:
        """To every subscriber; the journal's write inside the critical section (no stop cuts it)."""
        self.events.publish(event, self.interrupts.critical)

    def note(self, name: str, message: str, **data) -> None:
        """Anything else the journal keeps, under its own kind (``name``)."""
        self.publish(Note(run_id=self.run_id, rig_time_s=self.rig_time(), name=name, message=message,
                          data=data or None))

    def status(self, at: str, status: str = "running", reason: str | None = None,
               rig_time_s: float | None = None, waiting_s: float = 0.0, mounting: bool = False) -> None:
        """Where the run stands, before the next step (`Forecast.ahead`); ``at``: what occasioned it.
        At the end (``status`` not running) no remount is ahead, whatever the forecast said.
        ``rig_time_s``: when, if not now. ``waiting_s``: the least wait still ahead before the next
        step (the thermal gate's), added to the forecast; ``mounting``: said within a mount, whose
        prompt is past (as at "mount")."""
        remount, eta = self._ahead[self._next] if self._ahead else (None, None)
        if (at == "mount" or mounting) and self.forecast is not None:  # its prompt is past
            remount, eta = self.forecast.after_mount(self._todo[self._next], self._ahead[self._next + 1])
        if waiting_s:
            remount = None if remount is None else remount + waiting_s
            eta = None if eta is None else eta + waiting_s
        if status != "running":
            remount = None
        when = self.rig_time() if rig_time_s is None else rig_time_s
        self.publish(Status(run_id=self.run_id, rig_time_s=when,
                            status=status, reason=reason, at=at,  # type: ignore[arg-type]
                            points_done=self._points_done,
                            points_total=self._points_total, mount=self._mount,
                            next_remount_in_s=remount, eta_s=eta))

    # --- the operator ----------------------------------------------------------------------------
    def ask(self, prompt: Prompt, question, *args) -> object:
        """A prompt, with the tables still, and every answer to it published."""
        self.publish(prompt)
        what = prompt.what

        def answer(reply: str, meaning: str, outcome: str) -> None:
            self.publish(Answer(run_id=self.run_id, rig_time_s=self.rig_time(), what=what, reply=reply,
                                meaning=meaning, outcome=outcome))  # type: ignore[arg-type]

        self.operator.heard = lambda reply, meaning: answer(reply, meaning, "open")  # "n": as they come
        try:
            with self.terminal.pause(), self.interrupts.prompting():
                reply = question(*args)
        except OperatorDeclined as exc:
            answer("declined", str(exc), "declined")
            raise
        finally:
            self.operator.heard = None
        text = str(reply) if reply is not None else "confirmed"
        answer(text, text, "answered")
        return reply

    def prompt(self, what: str, message: str, args: tuple, mount: Mount | None = None,
               step: int | None = None, n_steps: int | None = None, note: str = "", why: str = "",
               may_be_moving: tuple[str, ...] = ()) -> Prompt:
        return Prompt(run_id=self.run_id, rig_time_s=self.rig_time(), what=what,  # type: ignore[arg-type]
                      mount=None if mount is None else mount_number(mount.y_deg, mount.u_deg), step=step,
                      n_steps=n_steps, message=message, where="" if mount is None else str(mount), note=note,
                      why=why, may_be_moving=may_be_moving, args=tuple(str(a) for a in args))

    def mount(self, mount: Mount, step: int, n_steps: int, why: str,
              provisional: np.ndarray | None) -> None:
        """Move to the load position, have the operator mount, and verify the mount from gravity. The
        check's reading is journaled with the mount's note: a return to it later (`verify`) shows
        whether the rig is still where it was."""
        note = why
        for _ in range(MOUNT_ATTEMPTS):
            self.move(*LOAD_POSITION)
            asked = f"mount {step} of {n_steps}: put the instrument on the {mount.describe()} ({mount})"
            prompt = self.prompt("mount", asked + (f"; {note}" if note else ""), (mount, step, n_steps, note),
                                 mount, step, n_steps, note=note)
            self.ask(prompt, self.operator.confirm_mount, mount, step, n_steps, note)
            self.station.remounted(mount)
            verify = getattr(self.station.dmm, "verify", None)  # a DMM with a declared configuration
            if verify is not None:
                verify("at the mount")
            self.wait_thermal(mounting=True)
            if not self.settings.check_mount:
                return
            self.move(*CHECK_ATTITUDE)
            check = self.measure(mount, f"check:{mount}")
            volts = (check.estimate or mean_and_sd(check.scan))[0]
            seen, wiring = identify(volts, provisional, mount)
            if wiring.faults:  # no remount mends it: the station's file or cables must change
                raise StationMiswired(f"the mount check on {mount} (pitch {CHECK_ATTITUDE[0]:g}°, roll "
                                      f"{CHECK_ATTITUDE[1]:g}°): {'; '.join(wiring.faults)}")
            if seen == mount:
                said = (f"mount verified: {mount}" if distinguishes(volts) else
                        f"mount verified as far as a single sensor tells: its x direction ({mount})")
                if np.isnan(volts).any():  # `identify` judges a package by its signs, as wired
                    said += ("; wiring taken as stated (exchanged or reversed tables and exchanged "
                             "channels are told apart by three sensors only)")
                self.note("mount", said,
                          mount=[mount.y_deg, mount.u_deg], check_deg=list(CHECK_ATTITUDE),
                          volts=finite(volts), samples=len(check.scan.volts))
                return
            note = f"the instrument reads as if on the {seen.describe()}; please correct it"
            if seen.u_deg == mount.u_deg:  # turned 180° about z: both tables reversed read so too
                note += " (if it is mounted as asked, both tables turn the wrong way)"
            self.publish(Fault(run_id=self.run_id, rig_time_s=self.rig_time(),
                               message=f"wrong mount: expected {mount}, reads as {seen}"))
        raise OperatorDeclined(f"the instrument was not mounted as {mount.describe()} after "
                               f"{MOUNT_ATTEMPTS} attempts")

    def wait_thermal(self, mounting: bool = False, on_demand: bool = False) -> float:
        """The thermal gate (`ThermalGate`): read the instrument's temperature every ``poll_s`` until
        the least-squares slope of the reads over the last ``hold_s`` is within the limit (at least
        ``hold_s`` of reads: the rate must be seen to stay low), or ``max_wait_s`` has passed. The
        wait is journaled as it begins and ends; at each read the status says the least wait left
        (so the ETA counts it), and a Ctrl-C pauses it as it pauses a point (a second stops at
        once). ``mounting``: before a mount's points, ``on_demand``: asked for by the operator
        during the run. Returns the seconds waited."""
        gate = self.settings.thermal_gate
        asked = " (asked for during the run)" if on_demand else ""
        if gate is None:
            if on_demand:
                self.note("thermal", "thermal gate asked for, but the run has none ([instrument] "
                          "thermal_gate, --thermal-gate)", on_demand=True)
            return 0.0
        clock, dmm = self.station.clock, self.station.dmm
        if not dmm.measures_temperature:
            self.note("thermal", f"thermal gate{asked} skipped: the station reads no instrument temperature",
                      on_demand=on_demand)
            return 0.0
        self.note("thermal", f"thermal gate{asked}: waiting until the temperature settles "
                  f"({gate.describe()})", on_demand=on_demand, waiting=True)
        t0 = clock.now()
        times: list[float] = []
        temps: list[float] = []
        rate = math.inf
        while True:
            scan = dmm.read(THERMAL_SAMPLES)
            assert scan.temp_c is not None
            times.append(clock.now() - t0)
            temps.append(float(np.mean(scan.temp_c)))
            spanning = [i for i, t in enumerate(times) if times[-1] - t >= gate.hold_s - 1e-9]
            if spanning:  # the reads since the last one at least hold_s ago
                first = spanning[-1]
                rate = 60 * float(np.polyfit(times[first:], temps[first:], 1)[0])
                if abs(rate) <= gate.rate_c_per_min:
                    break
            if times[-1] >= gate.max_wait_s:
                break
            left = max(gate.hold_s - times[-1], gate.poll_s)  # the least wait left: the hold, or a poll
            self.status("thermal", waiting_s=min(left, gate.max_wait_s - times[-1]), mounting=mounting)
            if self.interrupts.pause_requested:
                self.pause("Ctrl-C during the thermal gate's wait")
            clock.sleep(gate.poll_s)
        waited = clock.now() - t0
        settled = abs(rate) <= gate.rate_c_per_min
        self.note("thermal", (f"thermal gate{asked}: waited {waited:.0f} s; the temperature " +
                              (f"settled ({gate.describe()})" if settled else
                               f"had not settled ({gate.describe()}) after the gate's {gate.max_wait_s:g} s; "
                               "going on")) + f" at {temps[-1]:.3f} °C, {rate:+.3g} °C/min",
                  waited_s=waited, temp_c=temps[-1], rate_c_per_min=finite([rate])[0], settled=settled,
                  on_demand=on_demand)
        return waited

    def pause(self, why: str, home: tuple[RotaryAxis, ...] = ()) -> None:
        """Ask the operator to resume or abort. ``home``: tables that lost their reference; the
        prompt says that resuming homes them, and they are homed before the run goes on."""
        if home:
            which = " and ".join(axis.name for axis in home) + (" tables" if len(home) > 1 else " table")
            its, it, moves = ("their", "them", "they move") if len(home) > 1 else ("its", "it", "it moves")
            why += (f"; the {which} lost {its} reference: resuming homes {it} first ({moves} to the home "
                    "switch), then the run goes on")
        self.publish(Paused(run_id=self.run_id, rig_time_s=self.rig_time(), why=why,
                            may_be_moving=self.moving))
        try:
            tables = (f"; the stop did not reach the {', '.join(self.moving)} table(s)" if self.moving
                      else "; the tables are still")
            choice = self.ask(self.prompt("pause", f"paused ({why}){tables}", (why, self.moving), why=why,
                                          may_be_moving=self.moving),
                              self.operator.after_pause, why, self.moving)
        except OperatorDeclined as exc:  # nobody answered (an unattended run): the pause's cause ended it
            raise OperatorDeclined(f"{why}; paused, and {exc}") from None
        if choice == "abort":
            raise OperatorDeclined(f"operator aborted the run after a pause ({why})")
        self.interrupts.resumed()
        self.moving = ()  # the operator has seen to the tables
        self._home = home
        self.publish(Resumed(run_id=self.run_id, rig_time_s=self.rig_time(),
                             why="operator resumed after the pause"))
        self.status("resume")

    # --- the run ---------------------------------------------------------------------------------
    def run(self, steps: list[Step], committed: set[int], provisional=lambda: None) -> RunOutcome:
        """Measure every step not yet committed. ``provisional()`` returns an X from the points so
        far (or None) for the mount check."""
        self._windings = check_limits(self.station, steps, self.settings.check_mount)
        self._t0 = self.station.clock.now() - self.offset_s  # one clock per run, across resumes
        todo = [s for s in steps if s.seq not in committed]
        blocks = [s for s in steps if s.block_start]
        self._points_done, self._points_total = len(steps) - len(todo), len(steps)
        self._ahead = self.forecast.ahead(todo) if self.forecast is not None else []
        self._todo = todo
        mounted: Mount | None = None
        failed = 0
        self._next = 0
        self._provisional = provisional
        self.status("start")
        try:
            for k, step in enumerate(todo):
                self._next = k
                if step.block_start or mounted is None:
                    if not step.block_start:
                        why = "confirm the mount to resume the run"
                    elif mounted == step.mount:
                        why = "re-seat it for an independent replicate"
                    else:
                        why = ""
                    index = sum(1 for b in blocks if b.seq <= step.seq)
                    self.until_done(self.mount, step.mount, index, len(blocks), why, provisional())
                    mounted = self._mounted = step.mount
                    self._mount = mount_number(step.mount.y_deg, step.mount.u_deg)
                    self.status("mount")
                failed += self.until_done(self.point, step)
                self._next = k + 1
                self.status("point")  # before the return below: its forecast counts that return
                if k + 1 == len(todo) or todo[k + 1].block_start:
                    self.close_block(step.mount)
                if self.interrupts.pause_requested:
                    self.pause("Ctrl-C")
                if GATE_KEY in self.terminal.typed().lower() and k + 1 < len(todo) \
                        and not todo[k + 1].block_start:  # a mount's own gate comes before its points
                    self.wait_thermal(on_demand=True)
            self.verify(steps)
        except BaseException as exc:
            self.stop_tables(exc)
            raise
        finally:
            self._keep_pool()
        recorded = len(self.journal.points(self.run_id, status="ok"))
        return RunOutcome(recorded, failed, self.station.clock.now() - self._t0)  # since the run began

    # --- the readings judged -------------------------------------------------------------------
    def judge(self) -> tuple[Verdict | None, list[PointRecord]]:
        """The checks of the run's good points (`labcal.run.checks`), and those points in the
        readings' order; None where they cannot be fitted yet (the run's end says so)."""
        row = self.journal.run(self.run_id)
        points = self.journal.points(self.run_id, status="ok")
        try:
            station = parse_snapshot(row.station_text)
            readings = replace(self.journal.readings(self.run_id), units=output_units(station))
            return check_readings(readings, row.plan_text, station, self.settings.settle), points
        except LabcalError:
            return None, points

    def verify(self, steps: list[Step]) -> None:
        """Judge the run's readings as `labcal fit` judges a readings file, before the run can end
        complete. The points a check names are measured once more (`remeasure`), each new reading in
        the place of the one it re-measures; readings that still fail end the run with no certificate
        (`ReadingsRefused`), every reading kept. A resumed run that re-measured already does not again."""
        verdict, points = self.judge()
        if verdict is None or verdict.passed:
            if verdict is not None:
                self.note("checks", "the readings pass the checks of their fit"
                          + (f"; {verdict.note}" if verdict.note else " and the declared noise"))
            return
        named = [steps[points[r - 1].seq] for r in verdict.rows if points[r - 1].seq < len(steps)]
        again = any(p.seq >= len(steps) for p in self.journal.points(self.run_id))
        why = verdict.summary()
        self.publish(Fault(run_id=self.run_id, rig_time_s=self.rig_time(),
                           message=f"the readings fail the checks of their fit: {why}"))
        listed = ", ".join(str(s.seq) for s in named)
        if not named or again:
            raise ReadingsRefused(f"issued no certificate: the readings fail the checks of their fit"
                                  f"{f' (point(s) {listed})' if listed else ''}: {why}")
        self.note("checks", f"measuring point(s) {listed} again: {why}", points=[s.seq for s in named])
        self.remeasure(named, len(steps), listed)
        verdict, points = self.judge()
        if verdict is None or verdict.passed:
            self.note("checks", f"the readings pass the checks of their fit once point(s) {listed} were "
                      "measured again")
            return
        still = ", ".join(str(points[r - 1].seq) for r in verdict.rows)
        still = f" (point(s) {still})" if still else ""
        raise ReadingsRefused(f"issued no certificate: point(s) {listed} failed the checks of their fit, and "
                              f"measured again the readings still fail them{still}: {verdict.summary()}")

    def checked(self) -> dict[Mount, tuple[list[float], int]]:
        """The last mount check's reading of each mount, as the journal has it (mean volts, samples)."""
        found = {}
        for event in self.journal.events(self.run_id):
            data = event.values
            if event.kind in ("mount", "closure") and "volts" in data:
                found[Mount(*data["mount"])] = (data["volts"], int(data["samples"]))
        return found

    def check_again(self, mount: Mount) -> tuple[list[float], int]:
        """Measure the mount's check attitude again, journaled as a closure: the mean volts, samples."""
        self.move(*CHECK_ATTITUDE)
        result = self.measure(mount, f"closure:{mount}")
        scan = result.scan  # the settled reading, as a point's: model settling's estimate where it made one
        volts = [float(v) for v in (result.estimate or mean_and_sd(scan))[0]]
        self.note("closure", f"the check attitude on {mount} measured again",
                  mount=[mount.y_deg, mount.u_deg], volts=finite(volts), samples=len(scan.volts))
        return volts, len(scan.volts)

    def close_block(self, mount: Mount) -> None:
        """After a mount's last point, return to its check attitude: the reading must be what its mount
        check gave (`labcal.run.checks.closure`). A table, clamp or coupling that slipped during the
        mount moves it by |S|·slip, and the drives cannot see it (their position sensors are on the
        motors); the readings since are at another attitude than the plan's, and the run ends with
        no certificate, every reading kept."""
        before = self.checked().get(mount) if self.settings.check_mount else None
        if before is None:
            return
        now = self.until_done(self.check_again, mount)
        moved = closure(before, now, self.settings.settle,
                        parse_snapshot(self.journal.run(self.run_id).station_text), remounted=False)
        if moved:
            pitch, roll = CHECK_ATTITUDE
            why = (f"the rig is not where it was when {mount} was checked: back at its check attitude (pitch "
                   f"{pitch:g}°, roll {roll:g}°) {moved}; a table, its clamp or its coupling slipped?")
            self.publish(Fault(run_id=self.run_id, rig_time_s=self.rig_time(), message=why))
            raise ReadingsRefused(f"issued no certificate: {why}")

    def remeasure(self, named: list[Step], first_seq: int, listed: str) -> None:
        """Measure each of ``named`` once more as a new point (seq from ``first_seq``), in the mount on
        the plate first; a new reading that settled supersedes the one it re-measures.

        Only a fault that has passed can be measured away: a table or coupling that slipped and stays
        slipped makes the new readings agree with the later ones and not with the earlier, whichever
        the checks named. So each mount's check attitude is measured again first (after a remount:
        by its mount check) and compared with its reading when the mount was checked
        (`labcal.run.checks.closure`); a rig that is not where it was refuses the run. Without a
        mount check nothing tells the two apart: the run is refused."""
        refused = f"issued no certificate: point(s) {listed} fail the checks of their fit"
        if not self.settings.check_mount:
            raise ReadingsRefused(f"{refused}, and without the mount check (--no-mount-check) measuring them "
                                  "again cannot show that the rig is still where it was")
        before = self.checked()
        mounts = list(dict.fromkeys([s.mount for s in named if s.mount == self._mounted] +
                                    [s.mount for s in named]))
        self._points_total += len(named)
        seq = first_seq
        for i, mount in enumerate(mounts):
            remounted = mount != self._mounted
            if remounted:
                self.until_done(self.mount, mount, i + 1, len(mounts), "re-seat it to measure points again",
                                self._provisional() if callable(self._provisional) else None)
                self._mounted, self._mount = mount, mount_number(mount.y_deg, mount.u_deg)
            else:
                self.until_done(self.check_again, mount)
            if mount not in before:
                raise ReadingsRefused(f"{refused}, and {mount} has no mount check to return to")
            moved = closure(before[mount], self.checked()[mount], self.settings.settle,
                            parse_snapshot(self.journal.run(self.run_id).station_text), remounted)
            if moved:
                pitch, roll = CHECK_ATTITUDE
                raise ReadingsRefused(f"{refused}, and the rig is not where it was: at the check attitude "
                                      f"(pitch {pitch:g}°, roll {roll:g}°) on {mount}, {moved}; a table, "
                                      "its clamp or its coupling slipped?")
            for old in (s for s in named if s.mount == mount):
                new = Step(seq, old.replicate, old.mount, old.pitch_deg, old.roll_deg, block_start=False)
                seq += 1
                if not self.until_done(self.point, new):  # it settled: it takes the old one's place
                    with self.interrupts.critical():  # the chained event first: it vouches for the mark
                        self.note("remeasured", f"point {old.seq} measured again as point {new.seq}",
                                  seq=old.seq, by=new.seq)
                        self.journal.supersede(self.run_id, old.seq)

    def stop_tables(self, cause: BaseException) -> None:
        """Stop both tables, uninterrupted, and journal whether the stop reached them. A failed
        stop is said loudly at once and noted on ``cause`` (the news that ended the run, which it
        does not replace); `moving` remembers it for the pause prompt."""
        why = str(cause) or type(cause).__name__
        self._at = None  # wherever the tables stopped, the next move reads it first
        with self.interrupts.stopping():
            try:
                self.station.stop()
            except StopFailed as failed:
                self.moving = failed.tables
                log.warning("STOP FAILED after %s: %s", why, failed)
                cause.add_note(f"STOP FAILED: {failed}")
                self.publish(Stopped(run_id=self.run_id, rig_time_s=self.rig_time(), cause=why,
                                     failed=str(failed), may_be_moving=failed.tables))
                return
            self.moving = ()
            log.info("both tables stopped after %s", why)
            self.publish(Stopped(run_id=self.run_id, rig_time_s=self.rig_time(), cause=why))

    def discard(self, step: Step, attempt: int, result: Dwell, why: str, faulted: bool) -> None:
        """Journal a window the tables did not vouch for, with its readings (nothing taken is lost)."""
        mean, sd = result.estimate or mean_and_sd(result.scan)
        self.publish(Discarded(
            run_id=self.run_id, rig_time_s=self.rig_time(), seq=step.seq, attempt=attempt, reason=why,
            faulted=faulted, volts=(float(mean[0]), float(mean[1]), float(mean[2])),
            sd=(float(sd[0]), float(sd[1]), float(sd[2])),
            samples=tuple(tuple(None if np.isnan(v) else float(v) for v in row)
                          for row in raw_samples(result))))

    def discard_refused(self, step: Step, attempt: int, fault: LabcalError) -> None:
        """Journal the readings of a scan the voltmeter refused (a driver's fault that carries them as
        ``readings``, samples × channels: an overload), as a discarded window before the run pauses."""
        readings = getattr(fault, "readings", None)
        if readings is None:
            return
        rows = np.atleast_2d(np.asarray(readings, dtype=float))
        volts = rows[:, :3]
        self.publish(Discarded(
            run_id=self.run_id, rig_time_s=self.rig_time(), seq=step.seq, attempt=attempt, reason=str(fault),
            faulted=True, volts=tuple(float(v) for v in volts.mean(axis=0)),  # type: ignore[arg-type]
            sd=tuple(float(v) for v in volts.std(axis=0, ddof=1 if len(volts) > 1 else 0)),  # type: ignore[arg-type]
            samples=tuple(tuple(None if np.isnan(v) else float(v) for v in row) for row in rows)))

    def until_done(self, action, *args):
        """Do ``action(*args)``; on a device fault stop the tables, say what happened and pause: the
        operator fixes the cause and resumes (the action is done again) or aborts (resumable later)."""
        while True:
            try:
                self.home_lost()
                return action(*args)
            except PolicyAbort:
                raise
            except LabcalError as fault:
                self.stop_tables(fault)
                self.publish(Fault(run_id=self.run_id, rig_time_s=self.rig_time(), message=str(fault)))
                self.pause(f"fault: {fault}", self.lost_reference())

    def lost_reference(self) -> tuple[RotaryAxis, ...]:
        """The tables, stopped, whose controllers say they lost their reference (a power cycle); a
        table that cannot be read is left to the fault's own words."""
        if self.moving:
            return ()
        lost = []
        for axis in (self.station.pitch, self.station.roll):
            try:
                if axis.state().needs_homing:
                    lost.append(axis)
            except LabcalError:
                continue
        return tuple(lost)

    def home_lost(self) -> None:
        """Home the tables the operator agreed to home at the pause, before anything else moves."""
        home, self._home = self._home, ()
        for axis in home:
            self.note("home", f"homing the {axis.name} table, which had lost its reference")
            self._at = None  # homing moves it: the next move reads where it is
            axis.prepare()

    def window_opens(self) -> None:
        """Both tables note their fault memory: `tables` after the window then reports a fault
        raised and cleared inside it (a status read before and after cannot see one)."""
        self.station.pitch.window_opens()
        self.station.roll.window_opens()

    def tables(self) -> tuple[TableState, TableState]:
        """Both tables' status and position, read now."""
        return self.station.pitch.state(), self.station.roll.state()

    def point(self, step: Step) -> int:
        """Measure one step (retrying once if it does not settle) and commit it; 1 if it failed.
        Each window is kept only if both tables vouch for it, before and after: healthy, still, and
        on their commanded positions within the station's tolerance. Before the first window that
        is what the move has just verified (its last status and position reads); before a second
        window, and after every window, their states are read. A window they do not vouch for is
        journaled as discarded, with why, and the point is moved to and measured again; one during
        which a table reported a fault pauses the run instead (`TableFault`)."""
        for _ in range(MEASURE_AGAIN + 1):
            pitch_read, roll_read = self.move(step.pitch_deg, step.roll_deg, self._windings.get(step.seq))
            for attempt in (1, 2):
                t_start = self.station.clock.now() - self._t0
                before = () if attempt == 1 else self.tables()  # () : verified by the move
                self.window_opens()
                try:
                    result = self.measure(step.mount, f"{step.seq}:{attempt}")
                except LabcalError as fault:  # a scan refused with its readings (an overload): kept
                    self.discard_refused(step, attempt, fault)
                    raise
                why, faulted = unvouched(before, self.tables())
                if why or result.verdict.settled:
                    break
                if attempt == 1:  # the window the settle test refused is kept with its samples
                    self.discard(step, attempt, result, f"did not settle: {result.verdict.reason}", False)
                    self.note("retry",
                               f"point {step.seq} did not settle ({result.verdict.reason}); retrying")
            if why is None:
                break
            self.discard(step, attempt, result, why, faulted)
            if faulted:
                raise TableFault(f"point {step.seq}'s readings discarded: {why}")
        else:
            raise LabcalError(f"point {step.seq} measured {MEASURE_AGAIN + 1} times, every window discarded "
                              f"(last: {why}); check the table, its clamp and coupling")
        ok = result.verdict.settled
        mean, sd = result.estimate or mean_and_sd(result.scan)
        scan = result.scan
        temp = None if scan.temp_c is None else float(np.mean(scan.temp_c))
        raw = raw_samples(result)
        record = PointRecord(
            seq=step.seq, replicate=step.replicate, y_deg=step.mount.y_deg, u_deg=step.mount.u_deg,
            pitch_deg=step.pitch_deg, roll_deg=step.roll_deg, pitch_read=pitch_read, roll_read=roll_read,
            attempt=attempt, status="ok" if ok else "failed", t_start=t_start,
            t_end=self.station.clock.now() - self._t0, n_samples=len(scan.volts),
            vx=_read(mean[0]), vy=_read(mean[1]), vz=_read(mean[2]),
            sd_vx=_read(sd[0]), sd_vy=_read(sd[1]), sd_vz=_read(sd[2]), temp_c=temp,
            settle_s=result.settle_s, settle_verdict=result.verdict.reason,
        )
        self._points_done += 1
        self.publish(PointMeasured(
            run_id=self.run_id, rig_time_s=record.t_end, seq=step.seq, replicate=step.replicate,
            mount=mount_number(step.mount.y_deg, step.mount.u_deg), pitch_deg=step.pitch_deg,
            roll_deg=step.roll_deg, volts=(float(mean[0]), float(mean[1]), float(mean[2])),
            settle_s=result.settle_s, ok=ok,
            points_done=self._points_done, points_total=self._points_total, record=record, samples=raw))
        if ok:
            return 0
        policy = self.settings.on_failure
        self.publish(Fault(run_id=self.run_id, rig_time_s=self.rig_time(),
                           message=f"point {step.seq} failed: {result.verdict.reason}", policy=policy))
        if policy == "abort":
            raise PolicyAbort(f"point {step.seq} (pitch {step.pitch_deg:g}°, roll {step.roll_deg:g}°) did "
                              f"not settle: {result.verdict.reason}; run stopped (on_failure = abort)")
        if self.settings.on_failure == "pause":
            self.pause(f"point {step.seq} did not settle")
        return 1
