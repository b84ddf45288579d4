"""Does the certificate's attitude U95 cover new readings of the instrument in use, and does its
lack-of-fit test see what the model misses? Each figure beside its target.

Usage: python benchmarks/attitude_coverage.py [--trials 300] [--readings 5] [--lof-trials 500 60]

Coverage (`labcal.sim.coverage`): calibrations of four-mount-64 (single and replicated ×3) on the
simulated bench — per-sample noise over windows of 10, the tables' ±2″ index errors and wobble drawn
afresh, the device's misalignments, 1″ of seating scatter at each mounting, the bias drift over 30 s a
point — each fitted and budgeted as its certificate is, then new readings of the true instrument at
random attitudes of the envelope, each the mean of 10 samples. Target: 95 ± 2 % inside the stated
U95, RMS(error/U95) 0.45–0.6. "residual rows" is the budget certificates had before (the fit's
residual for one new reading and for the coefficients' Type A), "in use" the budget now. The
binomial standard error is given with the calibrations as the sample (the readings of one share its
coefficients' error).

Lack of fit: the fraction of calibrations flagged on the clean bench (target ≤ 1 %) and with each
effect the model or the station leaves out (target ≥ 80 %), with the drift test's fraction beside it.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # many small matrices: threads only contend

import numpy as np  # noqa: E402

from labcal.analysis.plan import Plan  # noqa: E402
from labcal.config.plans import load_plan  # noqa: E402
from labcal.sim.coverage import EFFECTS, Bench, coverage, flagged, with_effect  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=300, help="calibrations per coverage figure")
    parser.add_argument("--readings", type=int, default=5, help="new readings per calibration")
    parser.add_argument("--lof-trials", type=int, nargs=2, default=[500, 60], metavar=("CLEAN", "EFFECT"))
    args = parser.parse_args()
    base, _ = load_plan("four-mount-64")
    se = np.sqrt(0.95 * 0.05 / args.trials)
    print(f"coverage of the stated U95 (target 0.95 ± 0.02; binomial SE over {args.trials} calibrations "
          f"≤ {se:.3f}) and RMS(error/U95) (target 0.45–0.6)")
    for replicates in (1, 3):
        plan = Plan(**{**base.model_dump(), "replicates": replicates})
        trials = args.trials if replicates == 1 else max(args.trials // 3, 1)
        for label, windows in (("residual rows (before)", False), ("in use (now)", True)):
            c = coverage(plan, Bench(), trials, args.readings, first_seed=1000, windows=windows)
            print(f"  four-mount-64 ×{replicates}, {label:22} pitch {c.covered[0]:.3f}, "
                  f"roll {c.covered[1]:.3f}; "
                  f"RMS pitch {c.rms_ratio[0]:.3f}, roll {c.rms_ratio[1]:.3f}; median U95 "
                  f"{c.U95_median_arcsec[0]:.2f}″, {c.U95_median_arcsec[1]:.2f}″ ({c.readings} readings)")
    clean, effect_trials = args.lof_trials
    rate, drift = flagged(base, with_effect("clean"), clean, first_seed=7000)
    print(f"lack of fit, four-mount-64 single pass: clean bench flagged {rate:.1%} (target ≤ 1 %), "
          f"drift test {drift:.1%} ({clean} calibrations)")
    for effect in EFFECTS:
        rate, drift = flagged(base, with_effect(effect), effect_trials, first_seed=9000)
        print(f"  {effect:24} flagged {rate:.0%} (target ≥ 80 %), drift test {drift:.0%} "
              f"({effect_trials} calibrations)")


if __name__ == "__main__":
    main()
