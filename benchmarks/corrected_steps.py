"""A corrected plan's certificates when the calibration device moved after its estimate: a step of ±4 u
in any one misalignment, or of 3 u in all six (u: each one's u in the plan's correction), N simulated
runs per case of the plan `labcal plan optimize --device SIMULATED` chooses for X = 6 × four-mount-64's
predicted U95 (where relying on the correction pays: the U95 of a reading in use is mostly the
instrument's noise, a corrected plan's misalignment row 2–4″), the device characterised in two sittings.

Per case: how many runs the run's check refused (the certificate not issued from the correction), the
least coverage of an issued certificate (the smaller of pitch's and roll's share of 200 new readings
in the envelope within the stated U95) and how many issued certificates cover under 90 % — the target
is none (0 of N). Also, no target: ±2 u (below what the check must see) and no step at all (its
refusals are false alarms).

--before: what the runs did before they checked: the plan the optimizer chose then for X = 1.5 ×
(one mount × 16 points, 4 samples, which sees none of e, f, k), its correction's u the history's own,
no check, the same steps in that u.

Usage: python benchmarks/corrected_steps.py [--runs N] [--before]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from simulated_runs import characterised_device, corrected_runs_under_a_step  # noqa: E402

from labcal.analysis.kinematics import MISALIGNMENT_NAMES  # noqa: E402
from labcal.cli import main as labcal  # noqa: E402
from labcal.config.plans import plan_correction  # noqa: E402


def corrected_plan(folder: Path) -> str:
    """The plan file `plan optimize --device SIMULATED` writes for X = 6 × four-mount-64's U95."""
    from labcal.analysis import optimize
    from labcal.app.planning import planning_bench
    from labcal.config.plans import load_plan

    db, out = folder / "lab.sqlite", folder / "fast.toml"
    characterised_device(db, (11, 12))
    bench, _, settings = planning_bench(None)
    fm64, _ = load_plan("four-mount-64")
    ref = optimize.evaluate(optimize.Candidate(tuple(fm64.mounts), tuple(fm64.points),
                                               settings.settle.samples), bench, None, 0.0)
    assert ref is not None
    import math

    with contextlib.redirect_stdout(io.StringIO()) as text:
        assert labcal(["plan", "optimize", "--target-attitude-u95-deg", repr(6.0 * math.degrees(ref.u95_rad)),
                       "--device", "SIMULATED", "--db", str(db), "--out", str(out), "--json"]) == 0
    doc = json.loads(text.getvalue())
    print(f"corrected plan: {len(doc['mounts'])} mounts × {doc['points']} points, {doc['samples']} samples, "
          f"{doc['rig_time_ratio']:.3f}× four-mount-64's rig time")
    return out.read_text(encoding="utf-8")


def one_mount_plan(text: str) -> str:
    """The plan the optimizer chose before the check (one mount × 16 D-optimal points, 4 samples), with
    the same correction, its u the history's own."""
    from labcal.analysis import optimize
    from labcal.analysis.plan import Plan
    from labcal.config.plans import correction_toml, plan_toml

    correction = plan_correction(text, "the plan")
    assert correction is not None and correction.u_history_arcsec is not None
    points = optimize.d_optimal_sequence([(0.0, 0.0)], optimize.candidate_articulations(), 16)
    plan = Plan(name="one-mount", mounts=[(0.0, 0.0)], points=[list(p) for p in points])
    before = correction.model_copy(update={"u_arcsec": correction.u_history_arcsec, "u_history_arcsec": None})
    return "# Run it with --samples 4\n" + plan_toml(plan) + "\n" + correction_toml(before)


def cases(text: str) -> list[tuple[str, dict[str, float], bool]]:
    """(label, step in arcsec, whether the target applies) for ±4 u in each misalignment and +3 u in
    all six; then ±2 u in each and no step."""
    correction = plan_correction(text, "the plan")
    assert correction is not None
    u = correction.u_arcsec
    found = [(f"{n} {sign * size:+d} u ({sign * size * u[n]:+.1f}″)", {n: sign * size * u[n]}, size == 4)
             for size in (4, 2) for n in MISALIGNMENT_NAMES for sign in (1, -1)]
    return [*found[:12], ("all +3 u", {n: 3 * u[n] for n in MISALIGNMENT_NAMES}, True), *found[12:],
            ("no step", {}, False)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--before", action="store_true", help="the one-mount plan, unchecked")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        text = corrected_plan(Path(tmp))
    if args.before:
        text = one_mount_plan(text)
        print("before: one mount × 16 points, 4 samples, the history's u, no check")
    wall = time.perf_counter()
    bad_total, targeted = 0, 0
    print(f"{'step':24s} {'refused':>9s} {'issued':>7s} {'least coverage':>15s} {'under 90 %':>11s}")
    for n, (label, step, target) in enumerate(cases(text)):
        results = corrected_runs_under_a_step(text, step, args.runs, 40000 + 1000 * n,
                                              checked=not args.before)
        refused = sum(r for r, _ in results)
        issued = [c for r, c in results if not r]
        bad = sum(c < 0.90 for c in issued)
        if target:
            bad_total, targeted = bad_total + bad, targeted + args.runs
        least = f"{100 * min(issued):.0f} %" if issued else "—"
        print(f"{label:24s} {refused:>5d}/{args.runs:<3d} {len(issued):>7d} {least:>15s} {bad:>11d}"
              + (" (target 0)" if target else ""))
    print(f"±4 u in one, 3 u in all: issued certificates under 90 % coverage: {bad_total} of {targeted} runs "
          f"(target 0); {time.perf_counter() - wall:.0f} s")


if __name__ == "__main__":
    main()
