"""How long a plan takes on a rig, without moving anything (`labcal run --dry-run`, the ETA).

Per point: both tables' trapezoidal moves (the longer one) and the clamp, the dead time the step
in gravity needs (labcal.run.settle), and one window of samples; per mounting: the operator's remount
allowance and the mount check. The settle test usually accepts the first window, so this is also
close to what a run with settle detection takes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import mount_gravity
from labcal.analysis.plan import Plan
from labcal.config.settings import SequencerSettings
from labcal.run.mounting import CHECK_ATTITUDE
from labcal.run.ordering import move_time
from labcal.run.sequencer import LOAD_POSITION, Step, schedule
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

    @property
    def total_s(self) -> float:
        return self.moves_s + self.settling_s + self.averaging_s + self.mounting_s


def estimate(plan: Plan, settings: SequencerSettings, timing: Timing) -> Estimate:
    s = settings.settle
    window_s = s.samples * timing.sample_s
    per_step, moves, settling, mounting = {}, 0.0, 0.0, 0.0
    where: NDArray[np.float64] = np.array(LOAD_POSITION, dtype=float)
    g_last: NDArray[np.float64] | None = None
    steps: list[Step] = schedule(plan, settings)
    for step in steps:
        t_mount = 0.0
        if step.block_start:
            to_load = move_time(where, np.array(LOAD_POSITION), settings.speed_dps, settings.accel_dps2)
            t_mount = float(to_load) + timing.remount_s + timing.clamp_s
            if settings.check_mount:
                t_mount += float(move_time(np.array(LOAD_POSITION), np.array(CHECK_ATTITUDE),
                                           settings.speed_dps, settings.accel_dps2)) + timing.clamp_s
                t_mount += dead_time(2 * s.sensitivity_v_per_g, s) + window_s
                where = np.array(CHECK_ATTITUDE)
            else:
                where = np.array(LOAD_POSITION)
            g_last = None
        target = np.array([step.pitch_deg, step.roll_deg])
        t_move = float(move_time(where, target, settings.speed_dps, settings.accel_dps2)) + timing.clamp_s
        g = mount_gravity(step.pitch_deg, step.roll_deg, step.mount)
        step_g = 2.0 if g_last is None else float(np.max(np.abs(g - g_last)))
        t_settle = (s.fixed_dwell_s if s.fixed_dwell_s is not None
                    else dead_time(step_g * s.sensitivity_v_per_g, s))
        per_step[step.seq] = float(t_mount + t_move + t_settle + window_s)
        moves, settling, mounting = moves + t_move, settling + t_settle, mounting + float(t_mount)
        where, g_last = target, g
    return Estimate(per_step, moves, settling, window_s * len(steps), mounting)
