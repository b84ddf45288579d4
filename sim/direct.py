"""Readings straight from a plan and a truth, without a sequencer (`labcal simulate`).

No dynamics: each reading is the settled output at the true gravity, plus white noise.
With zero noise and no index/wobble errors the readings are exact.
"""

from __future__ import annotations

import numpy as np

from labcal.analysis.kinematics import NO_MISALIGNMENT, IndexWobble, Misalignment, gravity
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.config.emulation import InstrumentTruth


def simulate_readings(
    plan: Plan, truth: InstrumentTruth, misalignment: Misalignment = NO_MISALIGNMENT,
    index_wobble: IndexWobble | None = None, noise_v: float = 0.0, seed: int = 0,
) -> Readings:
    rows = [(rep, y, u, p, r) for rep in range(1, plan.replicates + 1)
            for y, u in plan.mounts for p, r in plan.points]
    rep, y_deg, u_deg, pitch_deg, roll_deg = (np.array(c, dtype=float) for c in zip(*rows, strict=True))
    pitch, roll, y, u = (np.radians(a) for a in (pitch_deg, roll_deg, y_deg, u_deg))
    mis = misalignment
    if index_wobble is not None:
        mis = mis + index_wobble.misalignment(pitch, roll)
    volts = truth.static_volts(gravity(pitch, roll, y, u, mis))
    if noise_v > 0:
        volts = volts + np.random.default_rng([seed, 0xD1EC7]).normal(0.0, noise_v, volts.shape)
    return Readings(replicate=rep.astype(int), y_deg=y_deg, u_deg=u_deg,
                    pitch_deg=pitch_deg, roll_deg=roll_deg, volts=volts)
