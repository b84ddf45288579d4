"""Readings straight from a plan and a truth, without a sequencer (`labcal simulate`).

No dynamics: each reading is the settled output at the true gravity, plus white noise.
With zero noise and no index/wobble errors the readings are exact.

`BenchEffects` adds what the simulated rig (`labcal.sim.rig`) does at the bench and the plain path
leaves out — each point a window of samples with the instrument's per-sample noise (so the readings
carry their windows' scatter, as the journal's do), the plate seated anew at every mounting, the
instrument's bias drift over the run's time — and one effect no rig applies yet: a quadratic
nonlinearity of each sensor along its input axis (K₂·a², the accelerometer model's second-order term),
so that Monte Carlo can check both what the certificate states and what its lack-of-fit test sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labcal.analysis.kinematics import ARCSEC, NO_MISALIGNMENT, IndexWobble, Misalignment, gravity
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.config.emulation import InstrumentTruth


@dataclass(frozen=True)
class BenchEffects:
    """Effects of a calibration at the bench beyond the plain path's (zero: absent)."""

    samples: int = 0  # > 0: each point a window of this many samples, noise per sample (the rig's noise_v)
    mount_repeat_arcsec: float = 0.0  # σ of the plate's e, f, k at each mounting (replicate × mount)
    point_s: float = 0.0  # rig time per point: the instrument's drift_v_per_h accrues over the run
    quadratic_v_per_g2: tuple[float, float, float] = (0.0, 0.0, 0.0)  # K₂ of each sensor, V/g²


def simulate_readings(
    plan: Plan, truth: InstrumentTruth, misalignment: Misalignment = NO_MISALIGNMENT,
    index_wobble: IndexWobble | None = None, noise_v: float = 0.0, seed: int = 0,
    effects: BenchEffects | None = None,
) -> Readings:
    """The plan's readings of ``truth`` on a device with ``misalignment`` and the tables'
    ``index_wobble``; ``noise_v``: white noise of one reading, or of one sample where ``effects``
    asks for windows of samples."""
    rows = [(rep, y, u, p, r) for rep in range(1, plan.replicates + 1)
            for y, u in plan.mounts for p, r in plan.points]
    rep, y_deg, u_deg, pitch_deg, roll_deg = (np.array(c, dtype=float) for c in zip(*rows, strict=True))
    pitch, roll, y, u = (np.radians(a) for a in (pitch_deg, roll_deg, y_deg, u_deg))
    mis = misalignment
    if index_wobble is not None:
        mis = mis + index_wobble.misalignment(pitch, roll)
    if effects is None:
        volts = truth.static_volts(gravity(pitch, roll, y, u, mis))
        if noise_v > 0:
            volts = volts + np.random.default_rng([seed, 0xD1EC7]).normal(0.0, noise_v, volts.shape)
        return Readings(replicate=rep.astype(int), y_deg=y_deg, u_deg=u_deg,
                        pitch_deg=pitch_deg, roll_deg=roll_deg, volts=volts)
    return _with_effects(rep, y_deg, u_deg, pitch_deg, roll_deg, truth, mis, noise_v, seed, effects)


def _with_effects(rep: np.ndarray, y_deg: np.ndarray, u_deg: np.ndarray, pitch_deg: np.ndarray,
                  roll_deg: np.ndarray, truth: InstrumentTruth, mis: Misalignment, noise_v: float, seed: int,
                  effects: BenchEffects) -> Readings:
    rng = np.random.default_rng([seed, 0xBE7C4])
    pitch, roll, y, u = (np.radians(a) for a in (pitch_deg, roll_deg, y_deg, u_deg))
    if effects.mount_repeat_arcsec > 0:  # one seating per mounting, in the plan's order
        _, mounting = np.unique(np.column_stack([rep, y_deg, u_deg]), axis=0, return_inverse=True)
        seat = rng.normal(0.0, effects.mount_repeat_arcsec * ARCSEC, (int(mounting.max()) + 1, 3))
        e, f, k = seat[np.ravel(mounting)].T
        mis = mis + Misalignment(e=e, f=f, k=k)
    g = gravity(pitch, roll, y, u, mis)
    volts = truth.static_volts(g, np.arange(len(rep)) * effects.point_s)
    axes = np.asarray(truth.S) / np.linalg.norm(truth.S, axis=0)  # each sensor's input axis (columns)
    volts = volts + np.asarray(effects.quadratic_v_per_g2) * (g @ axes) ** 2
    n = max(effects.samples, 1)
    samples = volts[:, None, :] + rng.normal(0.0, noise_v, (len(rep), n, 3))
    sd = samples.std(axis=1, ddof=1) if n > 1 else np.zeros_like(volts)
    return Readings(replicate=rep.astype(int), y_deg=y_deg, u_deg=u_deg, pitch_deg=pitch_deg,
                    roll_deg=roll_deg, volts=samples.mean(axis=1), window_sd=sd,
                    window_n=np.full(len(rep), float(n)) if n > 1 else None)
