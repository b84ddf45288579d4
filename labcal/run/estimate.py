"""How long a plan takes on a rig, without moving anything (`labcal run --dry-run`, the ETA).

Per point: both tables' trapezoidal moves (the longer one) and the clamp, the part of the dead
time the clamp does not overlap (the transient the move leaves, labcal.run.settle), and one window
of samples; per mounting: the operator's remount
allowance and the mount check. The settle test usually accepts the first window, so this is also
close to what a run with settle detection takes.
"""

from __future__ import annotations

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
class Timing:
    """The rig's pace: table motion, clamp, one DMM sample, one remount by the operator."""

    clamp_s: float
    sample_s: float
    remount_s: float


@dataclass(frozen=True)
class Estimate:
    per_step_s: dict[int, float]
    moves_s: float
    settling_s: float
    averaging_s: float
    mounting_s: float
    prompt_s: dict[int, float] = field(default_factory=dict)  # a mount's first step: its start to the prompt
    mount_s: dict[int, float] = field(default_factory=dict)  # … to the end of the mount (check included)

    @property
    def total_s(self) -> float:
        return self.moves_s + self.settling_s + self.averaging_s + self.mounting_s

    def forecast(self) -> Forecast:
        """What a run's statuses compute the next remount and the ETA from."""
        return Forecast(self.per_step_s, self.prompt_s, self.mount_s)


def estimate(plan: Plan, settings: SequencerSettings, timing: Timing,
             steps: list[Step] | None = None) -> Estimate:
    """``steps``: the run's schedule, if already made."""
    s = settings.settle
    window_s = s.samples * timing.sample_s

    def move_and_settle(a: NDArray, b: NDArray, mount: Mount) -> tuple[float, float]:
        """The move with its clamp, and the dead time the clamp does not overlap."""
        move = float(move_time(a, b, settings.speed_dps, settings.accel_dps2))
        if s.fixed_dwell_s is not None:
            return move + timing.clamp_s, s.fixed_dwell_s
        lag = float(transient_at_stop(a, b, mount, settings.speed_dps, settings.accel_dps2, s.tau_s))
        dead = float(dead_time(lag * s.sensitivity_v_per_g, s, timing.sample_s))
        return move + timing.clamp_s, max(0.0, dead - timing.clamp_s)

    per_step, prompt, mount_s, moves, settling, mounting = {}, {}, {}, 0.0, 0.0, 0.0
    where: NDArray[np.float64] = np.array(LOAD_POSITION, dtype=float)
    steps = schedule(plan, settings) if steps is None else steps
    for step in steps:
        t_mount = 0.0
        if step.block_start:
            to_load = move_time(where, np.array(LOAD_POSITION), settings.speed_dps, settings.accel_dps2)
            prompt[step.seq] = float(to_load) + timing.clamp_s  # the move to the load position, clamped
            t_mount = float(to_load) + timing.remount_s + timing.clamp_s
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
    return Estimate(per_step, moves, settling, window_s * len(steps), mounting, prompt, mount_s)
