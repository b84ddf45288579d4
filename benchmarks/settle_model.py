"""Model settling (`--settle model`) validated on sensors that do not match its model, and what it
saves in rig hours.

1. Validation. A simulated sensor built here from its own equations (`labcal.sim.tail_sensor`,
   not the rig simulator): a transient Δv = (0.5, −0.25, 0.1) V at motion end, in position 1 s
   later, σ = 20 µV per 0.2 s sample, N = 10, configured τ = 0.5 s. The cases: the model's own
   shape; τ off by −20 % and +20 % (the configured τ is wrong); a second pole, slow (3τ, weights
   from 1 % down to 1e-5: from obvious to buried in the noise; 10τ, 0.01 %) and fast (0.2τ,
   30 %); 1/f noise as large as the white noise. Model settling pools what it learns about the
   instrument over a run (`TailPool`), so each case is a few runs of many points on one sensor,
   settled by `dwell_model` with one pool per run and, point for point, by the conventional
   `dwell`; the error of each point against the sensor's settled value, in σ/√N. "seen": the runs
   whose pool detected a mismatch. A case passes when the points the model accepted have
   |bias| ≤ 1/3 (σ/(3√N), the issue's bound; the Monte Carlo SE is printed beside it), or when
   the model accepted none. With 1/f noise there is no fixed settled value to be biased from (the
   wander is zero-mean): the RMS error is what to compare.
2. Rig hours. Dry runs of four-mount-64 and the 481-point grid × 6 on the default simulated rig
   (steady lab), conventional and model settling, each against the independent physical bound of
   `settle_speed.py` (the conventional bound: the least a window that waits out the transient can
   cost), from the same moves.

Usage: python benchmarks/settle_model.py [--runs R] [--points P] [--only validate|hours]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from labcal.analysis.design import grid, make_plan
from labcal.analysis.kinematics import Mount
from labcal.config.emulation import RigConfig
from labcal.config.plans import load_plan, plan_toml
from labcal.config.settings import SettleSettings
from labcal.devices.station import mean_and_sd
from labcal.run.settle import TailPool, dwell, dwell_model
from labcal.sim.clock import VirtualClock
from labcal.sim.tail_sensor import TailSensor

sys.path.insert(0, str(Path(__file__).parent))
from settle_speed import point_bound, profile, run  # noqa: E402  (the independent bound, one copy)

TAU, SAMPLE_S, CLAMP_S = 0.5, 0.2, 1.0
STEP_V = np.array([0.5, -0.25, 0.1])
SETTINGS = SettleSettings(tau_s=TAU, noise_v=20e-6, samples=10, mode="model")
CASES = {
    "matched (one pole, τ as set)": ((1.0, TAU),),
    "τ −20 %": ((1.0, 0.8 * TAU),),
    "τ +20 %": ((1.0, 1.2 * TAU),),
    "2nd pole 3τ, 1 %": ((0.99, TAU), (0.01, 3 * TAU)),
    "2nd pole 3τ, 0.1 %": ((0.999, TAU), (1e-3, 3 * TAU)),
    "2nd pole 3τ, 0.03 %": ((0.9997, TAU), (3e-4, 3 * TAU)),
    "2nd pole 3τ, 0.01 %": ((0.9999, TAU), (1e-4, 3 * TAU)),
    "2nd pole 3τ, 0.006 %": ((0.99994, TAU), (6e-5, 3 * TAU)),
    "2nd pole 3τ, 0.003 %": ((0.99997, TAU), (3e-5, 3 * TAU)),
    "2nd pole 3τ, 0.001 %": ((0.99999, TAU), (1e-5, 3 * TAU)),
    "2nd pole 10τ, 0.01 %": ((0.9999, TAU), (1e-4, 10 * TAU)),
    "2nd pole 0.2τ, 30 %": ((0.7, TAU), (0.3, 0.2 * TAU)),
    "1/f noise = σ": ((1.0, TAU),),
}


def trials(poles, runs: int, points: int, seed: int, pink_v: float):
    """Errors (σ/√N) and settle times of ``runs`` runs of ``points`` points on one sensor each, by
    model settling (one pool per run, as the sequencer keeps it) and by waiting; which points the
    model accepted, and whether each run's pool saw a mismatch."""
    rng = np.random.default_rng(seed)
    target = SETTINGS.noise_v / math.sqrt(SETTINGS.samples)
    out = {"model": ([], [], []), "detect": ([], [], [])}
    detected = []
    for _ in range(runs):
        pool = TailPool(SETTINGS.tau_s, SETTINGS.noise_v)
        for _ in range(points):
            for mode in ("model", "detect"):
                clock = VirtualClock(CLAMP_S)  # the motion ended at 0
                settled = rng.normal(0.0, 1.0, 3)
                sensor = TailSensor(clock, settled, STEP_V, poles, SAMPLE_S, SETTINGS.noise_v, rng, pink_v)
                step = float(np.max(np.abs(STEP_V)))
                if mode == "model":
                    d = dwell_model(sensor, clock, step, SETTINGS, 0.0, SAMPLE_S, pool)
                else:
                    d = dwell(sensor, clock, step, SETTINGS, 0.0, SAMPLE_S)
                value = d.estimate[0] if d.estimate is not None else mean_and_sd(d.scan)[0]
                errors, times, accepted = out[mode]
                errors.append((value - settled) / target)
                times.append(d.settle_s)
                accepted.append(d.estimate is not None)
        detected.append(bool(pool.mismatch))
    result = {k: (np.array(e), np.array(t), np.array(a)) for k, (e, t, a) in out.items()}
    return result, np.array(detected)


def worst(errors: np.ndarray) -> tuple[float, float, float]:
    """(bias, its Monte Carlo SE, RMS error) on the channel with the largest |bias|."""
    if len(errors) == 0:
        return math.nan, math.nan, math.nan
    bias = errors.mean(axis=0)
    k = int(np.argmax(np.abs(bias)))
    return float(bias[k]), float(errors[:, k].std(ddof=1) / math.sqrt(len(errors))), \
        float(np.sqrt(np.mean(errors[:, k] ** 2)))


def validate(runs: int, points: int, seed: int) -> None:
    print(f"Validation: {runs} runs × {points} points per case, one sensor per run; errors in σ/√N; "
          "bound |bias| ≤ 1/3 on the points the model accepted; times from in position")
    print(f"{'case':28s} {'seen':>4s} {'accepted':>8s} {'model bias':>14s} {'rms':>5s} {'waiting bias':>14s} "
          f"{'rms':>5s} {'t model':>8s} {'(accepted)':>10s} {'t waiting':>9s}  verdict")
    for i, (name, poles) in enumerate(CASES.items()):
        pink = SETTINGS.noise_v if name.startswith("1/f") else 0.0
        r, detected = trials(poles, runs, points, seed + i, pink)
        err_m, t_m, acc = r["model"]
        err_c, t_c, _ = r["detect"]
        bm, sm, rm = worst(err_m[acc])
        bc, sc, rc = worst(err_c)
        if not acc.any():
            verdict = "ok: mismatch detected, waited" if detected.all() else "ok: never accepted, waited"
        elif pink:
            verdict = "ok: rms below waiting's" if rm <= rc else "RMS ABOVE WAITING'S"
        else:
            verdict = "ok: bias within bound" if abs(bm) <= 1 / 3 else "BIAS ABOVE σ/(3√N)"
        t_acc = f"{t_m[acc].mean():9.2f}s" if acc.any() else f"{'—':>10s}"
        model = f"{bm:+7.3f}±{sm:5.3f} {rm:5.2f}" if acc.any() else f"{'—':>13s} {'—':>5s}"  # none accepted
        print(f"{name:28s} {detected.sum():2d}/{runs:<1d} {acc.mean():8.0%} {model} "
              f"{bc:+7.3f}±{sc:5.3f} {rc:5.2f} {t_m.mean():7.2f}s {t_acc} {t_c.mean():8.2f}s  {verdict}")


def hours(seed: int) -> None:
    base = RigConfig()
    rig = base.model_copy(update={"lab_temp_swing_c": 0.0, "instrument": base.instrument.model_copy(
        update={"drift_v_per_h": [0.0, 0.0, 0.0]})})
    plans = [("four-mount-64", *load_plan("four-mount-64"))]
    tripp = make_plan("tripp-481", "", grid(-180, 180, 10, -180, 180, 30), four_mounts=False, replicates=6)
    plans.append(("481-point grid × 6", tripp, plan_toml(tripp)))
    for label, plan, text in plans:
        rows = {}
        for mode in ("detect", "model"):
            with tempfile.TemporaryDirectory() as tmp:
                result, points, settle, _ = run(plan, text, rig, seed, None, Path(tmp), mode)
            firsts = {min(p.seq for p in points if (p.replicate, p.y_deg, p.u_deg) == k)
                      for k in {(p.replicate, p.y_deg, p.u_deg) for p in points}}
            spent, bound, motion = 0.0, 0.0, 0.0
            where_model = np.zeros(3)  # spent, bound, motion over the points the model settled
            for prev, point in zip(points, points[1:], strict=False):
                if point.seq in firsts:
                    continue
                this = np.array([point.t_end - prev.t_end, point_bound(
                    (prev.pitch_deg, prev.roll_deg), (point.pitch_deg, point.roll_deg),
                    Mount(point.y_deg, point.u_deg), rig, settle), max(profile(
                        ((b - a + 180.0) % 360.0) - 180.0, rig.speed_dps, rig.accel_dps2, np.zeros(1))[0]
                        for a, b in ((prev.pitch_deg, point.pitch_deg), (prev.roll_deg, point.roll_deg)))])
                spent, bound, motion = spent + this[0], bound + this[1], motion + this[2]
                if (point.settle_verdict or "").startswith("settled (model"):
                    where_model += this
            fell_back = sum("waited" in (p.settle_verdict or "") for p in points)
            hours = (points[-1].t_end - points[0].t_start) / 3600
            rows[mode] = (result, spent, bound, motion, hours, fell_back, len(points), where_model)
        (rd, sd, bd, md, hd, _, _, _), (rm, sm, bm, mm, hm, fb, n, wm) = rows["detect"], rows["model"]
        z = np.abs(rm.fit.coefficients - rd.fit.coefficients) / rd.fit.stderr
        print(f"{label}: rig hours conventional {hd:.2f} h, model {hm:.2f} h (saved {hd - hm:.2f} h, "
              f"{1 - hm / hd:.0%}; remount allowances included)")
        print(f"  between remounts, against the independent conventional bound: conventional {sd / bd:.3f}×, "
              f"model {sm / bm:.3f}× per point (motion included, target ≤ 0.75×); the time after the "
              f"motion alone: conventional {(sd - md) / (bd - mm):.3f}×, model {(sm - mm) / (bm - mm):.3f}×")
        if wm[0] > 0:
            print(f"  on the {n - fb} points the model settled (where it is valid): model "
                  f"{wm[0] / wm[1]:.3f}× the bound (motion included), "
                  f"{(wm[0] - wm[2]) / (wm[1] - wm[2]):.3f}× after the motion")
        print(f"  model points that waited: {fb}/{n} (the pool vouches for the model after a hundred-odd "
              f"points); coefficients model vs conventional: "
              f"max {z.max():.2f} SE")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=3, help="runs per validation case")
    parser.add_argument("--points", type=int, default=600, help="points per run")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--only", choices=("validate", "hours"))
    args = parser.parse_args()
    if args.only != "hours":
        validate(args.runs, args.points, args.seed)
    if args.only != "validate":
        hours(args.seed)


if __name__ == "__main__":
    main()
