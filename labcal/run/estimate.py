"""How long a plan takes on a rig, without moving anything (`labcal run --dry-run`, the ETA).

Per point: both tables' trapezoidal moves (the longer one) and the clamp, the part of the dead
time the clamp does not overlap (the transient the move leaves, labcal.run.settle), and one window
of samples; per mounting: the operator's remount allowance, the mount check and the return to its
attitude after the mount's last point. The settle test
usually accepts the first window, so this is also close to what a run with settle detection takes.

On a station reached through its links, each point also waits for the exchanges the sequencer makes
while nothing moves and the DMM does not integrate (`LinkTiming`, counted from the sequencer and the
drivers as they do them): the commands that start both moves (the moves run from their answers), the
status polls that find the tables in position and their positions read back (hidden in the dead time
when it is longer), the DMM's trigger, its readings' transfer and its error check around the window,
both tables' status and position after it; at each mount, the DMM's configuration read back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import Mount
from labcal.analysis.plan import Plan
from labcal.config.settings import SequencerSettings
from labcal.run.motion import move_time, transient_at_stop
from labcal.run.mounting import CHECK_ATTITUDE
from labcal.run.sequencer import LOAD_POSITION, Forecast, Step, schedule
from labcal.run.settle import dead_time


@dataclass(frozen=True)
class LinkTiming:
    """What the station's links add, in the rig's seconds (`labcal.bench.setup.link_timing` prices
    them from the station file: baud rates, frame sizes, the protocols' silent intervals and the
    exchanges' latency). Zero everywhere: a simulated rig, which exchanges no bytes."""

    table_s: float = 0.0  # one table exchange, request out to reply in (the two tables' mean)
    start_exchanges: int = 0  # both tables', to start a move: each one's position read, its move command
    # (+ the SMC100's TE after it)
    poll_s: float = 0.0  # the tables' status polling interval while they move
    dmm_s: float = 0.0  # one DMM query, out and back
    fetch_per_sample_s: float = 0.0  # one sample's readings over the DMM's line (FETC?'s reply)
    verify_exchanges: int = 0  # the DMM's configuration read back at each mount

    def starting_s(self) -> float:
        """Both tables' start commands: the moves' profiles run from the second one's answer."""
        return self.start_exchanges * self.table_s

    def finding_s(self) -> float:
        """From the end of the motion to both positions read back: half a polling cycle (status,
        then `poll_s`) until a status reply says in position, its position read, and half the time
        the other table's status and position still to read (it was waited for second)."""
        return (self.poll_s + self.table_s) / 2 + self.table_s + self.table_s

    def window_s(self, samples: int) -> float:
        """Around each window: TRIG:COUN and INIT written (half a query each), *OPC? answered at the
        end of the scan, FETC? (its readings at the line's rate), SYST:ERR?; then both tables'
        status and position."""
        return 4 * self.dmm_s + samples * self.fetch_per_sample_s + 4 * self.table_s


@dataclass(frozen=True)
class Timing:
    """The rig's pace: table motion, clamp, one DMM sample, one remount by the operator, and the
    station's links."""

    clamp_s: float
    sample_s: float
    remount_s: float
    link: LinkTiming = LinkTiming()
    temperature: bool = True  # the station reads the instrument's temperature: a thermal gate waits


@dataclass(frozen=True)
class Estimate:
    per_step_s: dict[int, float]
    moves_s: float
    settling_s: float
    averaging_s: float
    mounting_s: float
    prompt_s: dict[int, float] = field(default_factory=dict)  # a mount's first step: its start to the prompt
    mount_s: dict[int, float] = field(default_factory=dict)  # … to the end of the mount (check included)
    thermal_s: float = 0.0  # the thermal gate's least wait, within mounting_s

    @property
    def total_s(self) -> float:
        return self.moves_s + self.settling_s + self.averaging_s + self.mounting_s

    def forecast(self) -> Forecast:
        """What a run's statuses compute the next remount and the ETA from."""
        return Forecast(self.per_step_s, self.prompt_s, self.mount_s)


def estimate(plan: Plan, settings: SequencerSettings, timing: Timing,
             steps: list[Step] | None = None) -> Estimate:
    """``steps``: the run's schedule, if already made."""
    s, link = settings.settle, timing.link
    window_s = s.samples * timing.sample_s + link.window_s(s.samples)
    found = timing.clamp_s + link.finding_s()  # from a motion's end: clamped, in position, read back

    def travel(a: NDArray, b: NDArray) -> float:
        """The move with its start commands, its clamp and the polls that find it in position."""
        return float(move_time(a, b, settings.speed_dps, settings.accel_dps2)) + link.starting_s() + found

    def move_and_settle(a: NDArray, b: NDArray, mount: Mount) -> tuple[float, float]:
        """`travel`, and the dead time (from the motion's end) that its clamp and polls do not overlap."""
        if s.fixed_dwell_s is not None:
            return travel(a, b), s.fixed_dwell_s
        lag = float(transient_at_stop(a, b, mount, settings.speed_dps, settings.accel_dps2, s.tau_s,
                                      math.radians(s.off_axis_arcsec / 3600)))
        dead = float(dead_time(lag * s.sensitivity_v_per_g, s, timing.sample_s))
        return travel(a, b), max(0.0, dead - found)

    per_step, prompt, mount_s, moves, settling, mounting, thermal = {}, {}, {}, 0.0, 0.0, 0.0, 0.0
    where: NDArray[np.float64] = np.array(LOAD_POSITION, dtype=float)
    steps = schedule(plan, settings) if steps is None else steps
    for i, step in enumerate(steps):
        t_mount = 0.0
        if step.block_start and i and settings.check_mount:  # the last mount's return to its check
            t_mount += sum(move_and_settle(where, np.array(CHECK_ATTITUDE), steps[i - 1].mount)) + window_s
            where = np.array(CHECK_ATTITUDE)
        if step.block_start:
            prompt[step.seq] = t_mount + travel(where, np.array(LOAD_POSITION))  # the tables still then
            t_mount = prompt[step.seq] + timing.remount_s + link.verify_exchanges * link.dmm_s
            if settings.thermal_gate is not None and timing.temperature:  # its least wait: hold_s
                t_mount += settings.thermal_gate.hold_s
                thermal += settings.thermal_gate.hold_s
            if settings.check_mount:
                t_mount += sum(move_and_settle(np.array(LOAD_POSITION), np.array(CHECK_ATTITUDE),
                                               step.mount)) + window_s
                where = np.array(CHECK_ATTITUDE)
            else:
                where = np.array(LOAD_POSITION)
            mount_s[step.seq] = t_mount
        target = np.array([step.pitch_deg, step.roll_deg])
        t_move, t_settle = move_and_settle(where, target, step.mount)
        per_step[step.seq] = float(t_mount + t_move + t_settle + window_s)
        moves, settling, mounting = moves + t_move, settling + t_settle, mounting + float(t_mount)
        where = target
    if steps and settings.check_mount:  # the last mount's return to its check attitude
        closing = sum(move_and_settle(where, np.array(CHECK_ATTITUDE), steps[-1].mount)) + window_s
        per_step[steps[-1].seq] += closing
        mounting += closing
    return Estimate(per_step, moves, settling, window_s * len(steps), mounting, prompt, mount_s, thermal)
