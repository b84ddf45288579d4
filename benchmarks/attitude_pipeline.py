"""`labcal attitude` end to end against a vectorised numpy pipeline of the same maths and I/O.

The pipeline reads the voltages with np.loadtxt, runs labcal's two estimators (closed form and
least squares on the sphere, `labcal.analysis.attitude`: the maths is the same by construction,
what is compared is everything around it) and writes the same columns with np.savetxt. Both run
as processes, interleaved; the median of the pairwise ratios is printed, with rows per second and
peak memory of `--json`. Target: labcal ≤ 1.0× the pipeline's time.

Usage: python benchmarks/attitude_pipeline.py [--rows 100000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

LABCAL = str(Path(sys.executable).with_name("labcal"))

PIPELINE = r"""
import sys
import numpy as np
from labcal.analysis import attitude
from labcal.documents.certificate import load_calibration
cal = load_calibration(sys.argv[1])
volts = np.loadtxt(sys.argv[2], delimiter=",", skiprows=1, ndmin=2)
columns = []
for method in (attitude.closed_form, attitude.sphere_least_squares):
    a = method(cal, volts)
    deg = np.degrees
    columns += [deg(a.pitch), deg(a.roll), deg(a.u_pitch), deg(a.u_roll), a.k95 * deg(a.u_pitch),
                a.k95 * deg(a.u_roll)]
table = np.column_stack([np.arange(1, len(volts) + 1), *columns])
names = [f"{p}{c}" for p in ("cf_", "ls_") for c in ("pitch_deg", "roll_deg", "u_pitch_deg", "u_roll_deg",
                                                      "U95_pitch_deg", "U95_roll_deg")]
np.savetxt(sys.stdout, table, delimiter=",", fmt=["%d"] + ["%.9g"] * 12, comments="",
           header="row," + ",".join(names))
"""


def measure(argv: list[str]) -> tuple[float, float]:
    """Wall seconds and peak resident MiB of one process (output discarded)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    if status != 0:
        raise SystemExit(f"{argv[:3]} failed: {proc.stderr.read().decode()[-500:]}")
    return time.perf_counter() - t0, usage.ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        readings, fit = Path(tmp) / "r.csv", Path(tmp) / "fit.json"
        subprocess.run([LABCAL, "simulate", "--noise", "2e-5", "--out", str(readings)], check=True,
                       capture_output=True)
        fit.write_text(subprocess.run([LABCAL, "fit", str(readings), "--json"], check=True,
                                      capture_output=True, text=True).stdout)
        x = np.array(json.loads(fit.read_text())["coefficients"])
        rng = np.random.default_rng(1)
        p, r = rng.uniform(-1.5, 1.5, args.rows), rng.uniform(-np.pi, np.pi, args.rows)
        g = np.column_stack([np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])
        volts = Path(tmp) / "v.csv"
        np.savetxt(volts, x[0] + g @ x[1:], delimiter=",", header="vx,vy,vz", comments="", fmt="%.10g")
        csv_pairs, json_runs = [], []
        for _ in range(args.repeat):
            csv_pairs.append((measure([LABCAL, "attitude", "--cert", str(fit), "--csv", str(volts)]),
                              measure([sys.executable, "-c", PIPELINE, str(fit), str(volts)])))
            json_runs.append(measure([LABCAL, "attitude", "--cert", str(fit), "--csv", str(volts), "--json"]))
    a = statistics.median(x[0][0] for x in csv_pairs)
    b = statistics.median(x[1][0] for x in csv_pairs)
    ratio = statistics.median(x[0][0] / x[1][0] for x in csv_pairs)
    print(f"{args.rows} rows: labcal attitude {a:.2f} s ({args.rows / a:,.0f} rows/s), numpy pipeline "
          f"{b:.2f} s ({args.rows / b:,.0f} rows/s): {ratio:.2f}× (target ≤ 1.0×)")
    print(f"--json: {statistics.median(r[0] for r in json_runs):.2f} s, peak "
          f"{statistics.median(r[1] for r in json_runs):.0f} MiB (CSV: "
          f"{statistics.median(x[0][1] for x in csv_pairs):.0f} MiB, pipeline "
          f"{statistics.median(x[1][1] for x in csv_pairs):.0f} MiB)")


if __name__ == "__main__":
    main()
