"""Settle detection against an independent physical lower bound, and against a long fixed wait.

For each plan (four-mount-64; Tripp's 481-point grid × 6 replicates) a dry run on the default
simulated rig (lab temperature steady, so that only settling tells runs apart) with settle
detection, and one with a fixed 30 s dwell (the long-wait reference). Rig seconds per point are
taken from the journal; points right after a (re)mount are left out (their time is the
operator's).

The lower bound is built here, from the rig's physics, without labcal's timing code (no
`labcal.run.motion`, `labcal.run.settle`, `labcal.run.ordering`, `labcal.sim.tables`): for each
move the sequencer actually made,

- both tables follow their own trapezoidal profile (written out below), starting together;
- the instrument's output follows nominal gravity through a first-order lag of time constant τ,
  integrated numerically along that motion (step τ/200, exact for a piecewise-constant input),
  starting settled;
- the window of N samples (one sample per DMM integration) starts at the first instant, on a
  1 ms grid, at which the tables are clamped (motion end + clamp) and the transient's bias on
  the *window mean* is at most ℓ·σ/√N on every sensor (σ/√N: the noise of the point's mean; ℓ:
  the ``leftover`` the run was told, 0.1 by default), with the transient of gravity off the tables'
  axes by the ``off_axis_arcsec`` the run was told added (the tables' own lag times it).

bound = motion + (window start − motion end) + N·sample time. Also printed: the largest
coefficient difference between the settle-detection run and the long wait, in the long wait's
standard errors, and each run's retries. Both runs draw each point's noise from the seed and the
point's identity (`SimRig.at_point`), so the difference is the settling bias plus the new noise of
the windows that slid on; the same pair of runs on a noise-free instrument (the sequencer told the
usual noise, so it waits as long) gives the settling bias alone, printed in the fit's SE and in the
far smaller SE white noise alone would give (the fit's SE is dominated by the index and wobble
errors' lack of fit: a bias can hide under it).

Usage: python benchmarks/settle_speed.py [--seed N] [--only 64|481]
"""

from __future__ import annotations

import argparse
import io
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from labcal.analysis.design import grid, make_plan
from labcal.analysis.kinematics import Mount, gravity
from labcal.config.emulation import RigConfig
from labcal.config.plans import load_plan, plan_toml
from labcal.config.settings import SequencerSettings
from labcal.run.operator import AutoOperator
from labcal.run.runner import calibrate
from labcal.sim.clock import VirtualClock
from labcal.sim.rig import SimRig
from labcal.store.journal import Journal

DT_FRACTION = 200  # lag integration step: τ / 200
GRID_S = 1e-3  # window start resolution


def profile(distance: float, speed: float, accel: float, t: np.ndarray) -> tuple[float, np.ndarray]:
    """This benchmark's own trapezoid: (duration, signed travel at times t) from rest to rest."""
    d = abs(distance)
    if d == 0:
        return 0.0, np.zeros_like(t)
    v = min(speed, (d * accel) ** 0.5)  # peak speed: triangular if full speed is never reached
    ramp = v / accel
    total = 2 * ramp + (d - v * ramp) / v
    t = np.clip(t, 0.0, total)
    up = np.minimum(t, ramp)
    travel = 0.5 * accel * up**2 + v * np.clip(t - ramp, 0.0, total - 2 * ramp)
    down = np.clip(t - (total - ramp), 0.0, ramp)
    travel += v * down - 0.5 * accel * down**2
    return total, np.sign(distance) * travel


def point_bound(a: tuple[float, float], b: tuple[float, float], mount, rig: RigConfig, settle) -> float:
    """Seconds from one window's end to the next one's, at the least, for the move a → b."""
    tau, sample_s = rig.instrument.tau_s, rig.nplc / rig.line_hz
    travel = [((bb - aa + 180.0) % 360.0) - 180.0 for aa, bb in zip(a, b, strict=True)]
    durations = [profile(d, rig.speed_dps, rig.accel_dps2, np.zeros(1))[0] for d in travel]
    motion = max(durations)
    dt = tau / DT_FRACTION
    n = max(1, int(np.ceil(motion / dt)))
    mids = (np.arange(n) + 0.5) * motion / n
    pitch = a[0] + profile(travel[0], rig.speed_dps, rig.accel_dps2, mids)[1]
    roll = a[1] + profile(travel[1], rig.speed_dps, rig.accel_dps2, mids)[1]
    y, u = np.radians([mount.y_deg, mount.u_deg])
    g_in = gravity(np.radians(pitch), np.radians(roll), y, u)
    g_end = gravity(np.radians(b[0]), np.radians(b[1]), y, u)
    x = gravity(np.radians(a[0]), np.radians(a[1]), y, u)  # settled at the start
    fade = np.exp(-(motion / n) / tau)
    # x ← g + (x − g)·fade over each step (exact for an input held over it), summed in one go
    x = x * fade**n + (1 - fade) * (fade ** np.arange(n - 1, -1, -1)) @ g_in
    left = np.abs(x - g_end) * settle.sensitivity_v_per_g  # V, per sensor, at motion end
    # gravity off the tables' axes by the allowance the run was told turns on a cone of that
    # half-angle: the tables' own lag (rad) times it, on every sensor
    angles_in = np.radians(np.column_stack([pitch, roll]))
    angle_lag = np.radians(a) * fade**n + (1 - fade) * (fade ** np.arange(n - 1, -1, -1)) @ angles_in
    left = left + (np.radians(settle.off_axis_arcsec / 3600) * np.max(np.abs(angle_lag - np.radians(
        np.asarray(a) + np.asarray(travel)))) * settle.sensitivity_v_per_g)
    target = settle.leftover * settle.noise_v / np.sqrt(settle.samples)  # the criterion the run was told
    sample_times = (np.arange(settle.samples) + 0.5) * sample_s
    # candidate window starts after motion end, from the clamp on (no sample counts before it)
    starts = rig.clamp_s + GRID_S * np.arange(int(20 * tau / GRID_S) + 1)
    # the transient fades as e^(−t/τ) once the tables stand still: its mean over the window
    bias = left[None, :] * np.exp(-starts[:, None] / tau) * np.mean(np.exp(-sample_times / tau))
    ok = np.all(bias <= target, axis=1)
    start = starts[np.argmax(ok)] if ok.any() else np.inf
    return motion + start + settle.samples * sample_s


def run(plan, text, rig: RigConfig, seed: int, fixed_dwell: float | None, tmp: Path, mode: str = "detect",
        quiet: bool = False):
    """A dry run; ``quiet``: the simulated instrument has no noise, the sequencer is told it has its
    usual noise (so it waits exactly as long): the run then differs from the long wait only by the
    transient left in each window."""
    inst = rig.instrument
    sim = SimRig(rig.model_copy(update={"instrument": inst.model_copy(update={"noise_v": 0.0})})
                 if quiet else rig, seed=seed, clock=VirtualClock())
    settle = SequencerSettings().settle.model_copy(update={
        "tau_s": inst.tau_s, "noise_v": inst.noise_v, "fixed_dwell_s": fixed_dwell, "mode": mode,
        "sensitivity_v_per_g": float(np.max(np.abs(inst.S)))})
    settings = SequencerSettings(settle=settle, speed_dps=rig.speed_dps, accel_dps2=rig.accel_dps2)
    wall = time.perf_counter()
    with Journal(tmp / "j.sqlite") as journal:
        result = calibrate(plan, text, sim.station(), "benchmark rig",
                           AutoOperator(Console(file=io.StringIO())), settings, tmp, journal)
        points = journal.points(result.run_id)
    return result, points, settle, time.perf_counter() - wall


def compare(label: str, plan, text, rig: RigConfig, seed: int) -> None:
    with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b:
        detect, points, settle, wall = run(plan, text, rig, seed, None, Path(a))
        fixed, fixed_points, _, _ = run(plan, text, rig, seed, 30.0, Path(b))
    per_point, bound = [], []
    blocks = {(p.replicate, p.y_deg, p.u_deg) for p in points}
    first_of_block = {min(p.seq for p in points if (p.replicate, p.y_deg, p.u_deg) == k) for k in blocks}
    for prev, point in zip(points, points[1:], strict=False):
        if point.seq in first_of_block:
            continue
        per_point.append(point.t_end - prev.t_end)
        bound.append(point_bound((prev.pitch_deg, prev.roll_deg), (point.pitch_deg, point.roll_deg),
                                 Mount(point.y_deg, point.u_deg), rig, settle))
    z = np.abs(detect.fit.coefficients - fixed.fit.coefficients) / fixed.fit.stderr
    with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b, \
            np.errstate(divide="ignore", invalid="ignore"):  # no noise: replicates agree exactly
        quiet_shift = (run(plan, text, rig, seed, None, Path(a), quiet=True)[0].fit.coefficients
                       - run(plan, text, rig, seed, 30.0, Path(b), quiet=True)[0].fit.coefficients)
    # the coefficients' SE were the points' only error their white noise (σ/√N per point)
    noise_se = (np.sqrt(np.diag(fixed.fit.ls.cov_unscaled))[:len(quiet_shift), None]
                * settle.noise_v / np.sqrt(settle.samples))
    retries = sum(p.attempt > 1 for p in points)
    half_window = settle.samples // 2 * rig.nplc / rig.line_hz
    slid = sum(t - b > 0.9 * half_window for t, b in zip(per_point, bound, strict=True))
    fixed_retries = sum(p.attempt > 1 for p in fixed_points)
    rig_h = (points[-1].t_end - points[0].t_start) / 3600
    print(f"{label}: {len(points)} points, dry run {wall:.1f} s wall")
    fixed_per_point = [q.t_end - p.t_end for p, q in zip(fixed_points, fixed_points[1:], strict=False)
                       if q.seq not in first_of_block]
    print(f"  rig seconds per point (after a remount excluded): bound {np.mean(bound):.3f} s, "
          f"settle detection {np.mean(per_point):.3f} s, fixed 30 s dwell {np.mean(fixed_per_point):.3f} s")
    print(f"  settle detection / independent bound = {np.sum(per_point) / np.sum(bound):.3f}×"
          "  (target ≤ 1.03×)")
    print(f"  rig hours, whole run with settle detection: {rig_h:.2f} h "
          f"(fixed dwell: {(fixed_points[-1].t_end - fixed_points[0].t_start) / 3600:.2f} h)")
    print(f"  coefficients vs the long wait: max {z.max():.3f} SE (target ≤ 0.1); "
          f"retries: settle detection {retries}, long wait {fixed_retries}; windows slid on (new "
          f"samples, so new noise) {slid}; "
          f"failed points {sum(p.status != 'ok' for p in points)}")
    print(f"  the settling bias alone (noise-free instrument, same waits): max "
          f"{np.max(np.abs(quiet_shift) / fixed.fit.stderr):.3f} SE of the fit, "
          f"{np.max(np.abs(quiet_shift) / noise_se):.2f} of the SE white noise alone would give (the fit's "
          f"SE is {np.median(fixed.fit.stderr / noise_se):.0f}× that: index and wobble errors)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--only", choices=("64", "481"))
    args = parser.parse_args()
    base = RigConfig()  # steady lab, no drift: only settling tells the two runs apart
    rig = base.model_copy(update={"lab_temp_swing_c": 0.0, "instrument": base.instrument.model_copy(
        update={"drift_v_per_h": [0.0, 0.0, 0.0]})})
    if args.only != "481":
        plan, text = load_plan("four-mount-64")
        compare("four-mount-64", plan, text, rig, args.seed)
    if args.only != "64":
        plan = make_plan("tripp-481", "", grid(-180, 180, 10, -180, 180, 30), four_mounts=False, replicates=6)
        compare("481-point grid × 6", plan, plan_toml(plan), rig, args.seed)


if __name__ == "__main__":
    main()
