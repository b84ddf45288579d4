"""The device model: fit time on a day-long calibration, recovered misalignments, coverage.

Usage: python benchmarks/device_model.py [--trials 1000] [--repeat 5]

1. Fit time of `fit_device` on 6 replicates × 481 points × 4 mounts (11 544 readings; target < 0.5 s),
   against the linear fit of the same readings as the baseline, with their ratio (median of --repeat).
2. Recovered misalignments ± U (95 %) on a four-mount-64 dry run and on the 481-point four-mount grid
   (6 replicates), simulated with the default rig's misalignments, ±2″ index and wobble errors and
   20 µV noise, beside the truth.
3. Monte Carlo coverage of the 95 % intervals of every parameter and the ratio of the mean standard
   error to the empirical standard deviation (four-mount-64, 60″ rig, 20 µV noise).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from labcal.analysis.design import grid, make_plan
from labcal.analysis.device_fit import fit_device
from labcal.analysis.device_model import PARAMETER_NAMES
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble, Misalignment
from labcal.analysis.readings import Readings
from labcal.config.emulation import DeviceTruth, default_instrument
from labcal.config.plans import load_plan
from labcal.sim.direct import simulate_readings


def grid_481():
    """481 (pitch, roll) points: pitch −90..90 step 15 (13) × roll 0..350 step 10 (36) = 468, plus 13 more
    rolls at pitch 0 (every 5° offset) — 481 in all."""
    points = grid(-90, 90, 15, 0, 350, 10)
    points += [(0.0, float(r)) for r in range(5, 130, 10)]
    return make_plan("grid-481", "481 points × 4 mounts", points, four_mounts=True, replicates=6)


def median_time(call, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def recovered(name: str, readings: Readings, truth: Misalignment) -> None:
    fit = fit_device(readings)
    doc = fit.to_json()["misalignments"]
    print(f"\n{name}: {len(readings)} readings, rank {fit.ident.rank}, condition {fit.ident.condition:.3g}")
    print(f"{'':3}{'truth (″)':>11}{'estimate (″)':>14}{'U95 (″)':>9}{'|err|/U':>9}")
    for n in MISALIGNMENT_NAMES:
        t = float(getattr(truth, n)) / ARCSEC
        print(f"{n:3}{t:11.2f}{doc[n]['value_arcsec']:14.2f}{doc[n]['U_arcsec']:9.2f}"
              f"{abs(doc[n]['value_arcsec'] - t) / doc[n]['U_arcsec']:9.2f}")
    pairs = zip(fit.linear.ls.residual_se, fit.residual_se, strict=True)
    print("residual SE linear → device (µV):", ", ".join(f"{a * 1e6:.1f} → {b * 1e6:.1f}" for a, b in pairs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    truth = default_instrument()
    device = DeviceTruth()
    mis = device.misalignment()
    wobble = IndexWobble(device.index_arcsec, device.wobble_arcsec, seed=1)

    big = grid_481()
    readings = simulate_readings(big, truth, mis, wobble, 20e-6, seed=1)
    t_device = median_time(lambda: fit_device(readings), args.repeat)
    t_linear = median_time(lambda: fit_readings(readings), args.repeat)
    print(f"fit time, {len(readings)} readings (6 × 481 × 4): device {t_device:.3f} s, linear "
          f"{t_linear:.3f} s, ratio {t_device / t_linear:.1f}")

    recovered("four-mount-64", simulate_readings(load_plan("four-mount-64")[0], truth, mis, wobble, 20e-6, 1),
              mis)
    recovered("grid 481 × 4 mounts × 6 replicates", readings, mis)

    rig60 = Misalignment(*(np.array([60, -60, 60, 60, -60, 60]) * ARCSEC))
    base = simulate_readings(load_plan("four-mount-64")[0], truth, rig60)
    rng = np.random.default_rng(2020)
    est, se, k = [], [], []
    for _ in range(args.trials):
        r = base.volts + rng.normal(0, 20e-6, base.volts.shape)
        fit = fit_device(Readings(base.replicate, base.y_deg, base.u_deg, base.pitch_deg, base.roll_deg, r))
        est.append(fit.theta)
        se.append(fit.stderr)
        k.append(fit.k95)
    est_a, se_a = np.array(est), np.array(se)
    true = np.concatenate([[getattr(rig60, n) for n in MISALIGNMENT_NAMES], truth.X.ravel()])
    covered = np.abs(est_a - true) <= np.array(k)[:, None] * se_a
    ratio = se_a.mean(axis=0) / est_a.std(axis=0, ddof=1)
    print(f"\nMonte Carlo, {args.trials} trials (four-mount-64, 60″ rig, 20 µV):")
    print(f"{'parameter':10}{'coverage':>10}{'mean SE/SD':>12}")
    for n, c, q in zip(PARAMETER_NAMES, covered.mean(axis=0), ratio, strict=True):
        print(f"{n:10}{c:10.3f}{q:12.3f}")
    print(f"{'pooled':10}{covered.mean():10.3f}")


if __name__ == "__main__":
    main()
