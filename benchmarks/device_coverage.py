"""Coverage of the device model's U when the tables wobble.

Usage: python benchmarks/device_coverage.py [--trials 1000] [--index 1] [--wobble 2] [--noise 5e-6]
                                            [--replicates 1 3] [--stated]

Each trial is a new simulated rig (`labcal.sim.direct`, the path `labcal simulate` takes): the default
rig's misalignments, index and wobble errors drawn afresh (a new seed: new harmonics and phases) with
the given amplitudes, white noise, four-mount-64 repeated --replicates times. The device model is fitted
and each of a, b, d, e, f, k and each of the twelve coefficients is checked against the truth:
|estimate − truth| ≤ U = k·u. Coverage per misalignment and pooled over the coefficients, with the
binomial standard error √(p(1−p)/N) of a 95 % interval's coverage beside it. With --stated the fit is
told the tables' stated index and wobble (the amplitudes, as ± half-widths); without it, not.
"""

from __future__ import annotations

import argparse

import numpy as np

from labcal.analysis.device_fit import AngleErrors, fit_device
from labcal.analysis.device_model import PARAMETER_NAMES
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble
from labcal.analysis.plan import Plan
from labcal.config.emulation import DeviceTruth, default_instrument
from labcal.config.plans import load_plan
from labcal.sim.direct import simulate_readings


def coverage(trials: int, index: float, wobble: float, noise: float, replicates: int, stated: bool,
             first_seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per parameter (18: a…k, then the twelve coefficients): the fraction of trials whose U covers
    the truth, the ratio of the mean stated u to the empirical RMS error, and the fraction of
    consecutive trials whose estimates differ by more than √(U₁² + U₂²) (the device history's flag)."""
    base, _ = load_plan("four-mount-64")
    plan = Plan(**{**base.model_dump(), "replicates": replicates})
    truth = default_instrument()
    mis = DeviceTruth().misalignment()
    true_mis = np.array([getattr(mis, n) for n in MISALIGNMENT_NAMES])
    errors = AngleErrors(pitch_index=index * ARCSEC, pitch_wobble=wobble * ARCSEC,
                         roll_index=index * ARCSEC, roll_wobble=wobble * ARCSEC) if stated else None
    hits, err, u, U = [], [], [], []
    true = np.concatenate([true_mis, truth.X.ravel()])
    for seed in range(first_seed, first_seed + trials):
        readings = simulate_readings(plan, truth, mis, IndexWobble(index, wobble, seed), noise, seed)
        fit = fit_device(readings, angle_errors=errors)
        e = fit.theta - true
        hits.append(np.abs(e) <= fit.k95 * fit.stderr)
        err.append(e)
        u.append(fit.stderr)
        U.append(fit.k95 * fit.stderr)
    err_a, U_a = np.array(err), np.array(U)
    flags = np.abs(np.diff(err_a, axis=0)) > np.sqrt(U_a[1:] ** 2 + U_a[:-1] ** 2)
    return (np.mean(hits, axis=0), np.mean(u, axis=0) / np.sqrt(np.mean(np.square(err_a), axis=0)),
            flags.mean(axis=0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--index", type=float, default=1.0)
    parser.add_argument("--wobble", type=float, default=2.0)
    parser.add_argument("--noise", type=float, default=5e-6)
    parser.add_argument("--replicates", type=int, nargs="+", default=[1, 3])
    parser.add_argument("--stated", action="store_true")
    args = parser.parse_args()
    se = np.sqrt(0.95 * 0.05 / args.trials)
    print(f"{args.trials} trials, index ±{args.index}″, wobble ±{args.wobble}″, "
          f"noise {args.noise * 1e6:g} µV, stated to the fit: {args.stated}; "
          f"binomial SE of a 95 % coverage {se:.3f}")
    for reps in args.replicates:
        cov, ratio, flags = coverage(args.trials, args.index, args.wobble, args.noise, reps, args.stated)
        cells = "  ".join(f"{n} {c:.3f}" for n, c in zip(MISALIGNMENT_NAMES, cov, strict=False))
        print(f"replicates {reps}: coverage {cells}; coefficients pooled {cov[6:].mean():.3f}, lowest "
              f"{PARAMETER_NAMES[6 + int(np.argmin(cov[6:]))]} {cov[6:].min():.3f}")
        print(f"{'':14}mean u / RMS error: " + "  ".join(
            f"{n} {q:.2f}" for n, q in zip(PARAMETER_NAMES, ratio, strict=True)))
        print(f"{'':14}pairs of consecutive trials flagged: " + "  ".join(
            f"{n} {q:.3f}" for n, q in zip(MISALIGNMENT_NAMES, flags, strict=False)))


if __name__ == "__main__":
    main()
