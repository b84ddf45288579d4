"""Settle detection against a fixed 30 s dwell and against the physical lower bound.

Simulated (rig) seconds per point for four-mount-64, one replicate, on the default simulated
rig. The lower bound for a point is its move (both tables, then the clamp) + the dead time
τ·ln(Δv/(σ/√N)) for the transient to fall below the noise of the mean + the N samples the noise
target needs. Points right after a (re)mount are left out: their time is the operator's.
Also prints each run's coefficient error against the truth in units of its standard error.

Usage: python benchmarks/settle_speed.py [--seed N]
"""

from __future__ import annotations

import argparse
import io
import tempfile
from pathlib import Path

import numpy as np
from rich.console import Console

from labcal.analysis.kinematics import gravity
from labcal.bench.setup import sim_station
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.run.journal import Journal
from labcal.run.operator import AutoOperator
from labcal.run.ordering import move_time
from labcal.run.runner import calibrate
from labcal.run.sequencer import schedule
from labcal.run.settle import dead_time


def run(seed: int, fixed_dwell: float | None, tmp: Path):
    plan, text = load_plan("four-mount-64")
    setup = sim_station(None, seed)
    settle = setup.settle.model_copy(update={"fixed_dwell_s": fixed_dwell})
    settings = SequencerSettings(settle=settle)
    with Journal(tmp / "j.sqlite") as journal:
        result = calibrate(plan, text, setup.station, setup.text, AutoOperator(Console(file=io.StringIO())),
                           settings, tmp, journal)
        points = journal.points(result.run_id)
    steps = schedule(plan, settings)
    per_point, bound = [], []
    sample_s = setup.timing.sample_s
    for prev, step, point, prev_point in zip(steps, steps[1:], points[1:], points, strict=False):
        if step.block_start:
            continue
        per_point.append(point.t_end - prev_point.t_end)
        g0 = gravity(*np.radians([prev.pitch_deg, prev.roll_deg]), *prev.mount.radians)
        g1 = gravity(*np.radians([step.pitch_deg, step.roll_deg]), *step.mount.radians)
        a, b = np.array([prev.pitch_deg, prev.roll_deg]), np.array([step.pitch_deg, step.roll_deg])
        move = float(move_time(a, b, settings.speed_dps, settings.accel_dps2)) + setup.timing.clamp_s
        step_v = float(np.max(np.abs(g1 - g0))) * settle.sensitivity_v_per_g
        bound.append(move + dead_time(step_v, settle) + settle.samples * sample_s)
    truth = np.array(setup.metadata["simulated_truth"]["coefficients"])
    z = np.abs(result.fit.coefficients - truth) / result.fit.stderr
    return np.mean(per_point), np.mean(bound), z, result.fit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b:
        detect, bound, z_detect, fit_detect = run(args.seed, None, Path(a))
        fixed, _, z_fixed, fit_fixed = run(args.seed, 30.0, Path(b))
    print("rig seconds per point (points after a remount excluded):")
    print(f"  lower bound      {bound:6.2f} s")
    print(f"  settle detection {detect:6.2f} s  ({detect / bound:.2f}× the bound; target ≤ 1.3×)")
    print(f"  fixed 30 s dwell {fixed:6.2f} s  ({fixed / bound:.2f}× the bound; "
          f"{fixed / detect:.2f}× settle detection)")
    print("coefficient error against the truth, max over the 12, in standard errors:")
    print(f"  settle detection {z_detect.max():.2f}   fixed dwell {z_fixed.max():.2f}")
    worse = (np.abs(fit_detect.coefficients - fit_fixed.coefficients) - fit_fixed.stderr).max()
    print(f"  settle detection worse than fixed dwell by more than one SE anywhere: {worse > 0}")


if __name__ == "__main__":
    main()
