"""Wall time of the main job and of start-up, against floors built here, measured side by side.

- `labcal run --sim --yes` (certificate and report included), and with --no-report, against a
  floor job: a script doing the same dry run with numpy and sqlite — the plan's 64 points, ten
  samples each from the nominal gravity through a known X plus noise, one WAL transaction per
  point with its raw samples, readings.csv, a QR least-squares fit and fit.json. Target ≤ 2×.
- `labcal --help` and `labcal plan list` against `python -c pass`. Target ≤ 3×.

Commands run as separate processes, interleaved (A B A B …); the ratio printed is the median of
the pairwise ratios, so a machine that slows down in between affects both sides alike.

Usage: python benchmarks/run_sim_wall_time.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LABCAL = str(Path(sys.executable).with_name("labcal"))
PLAN = Path(__file__).resolve().parent.parent / "sequences" / "four-mount-64.toml"

FLOOR = r"""
import json, sqlite3, sys, tomllib
import numpy as np
plan = tomllib.loads(open(sys.argv[1], encoding="utf-8").read())
out = sys.argv[2]
db = sqlite3.connect(out + "/floor.sqlite", isolation_level=None)
db.execute("PRAGMA journal_mode=WAL")
db.execute("PRAGMA synchronous=NORMAL")
db.execute("CREATE TABLE points (seq INTEGER PRIMARY KEY, y REAL, u REAL, p REAL, r REAL, "
           "vx REAL, vy REAL, vz REAL, samples BLOB)")
rng = np.random.default_rng(0)
x_true = np.vstack([[0.0123, -0.0081, 0.0047], 5.0 * np.eye(3)])
rows = []
for y, u in plan["mounts"]:
    for p, r in plan["points"]:
        pr, rr, yr, ur = np.radians([p, r, y, u])
        a0, a1, a2 = np.sin(pr), np.cos(pr) * np.sin(rr), np.cos(pr) * np.cos(rr)
        b1 = a0 * np.sin(yr) + a1 * np.cos(yr)
        g = np.array([a0 * np.cos(yr) - a1 * np.sin(yr), b1 * np.cos(ur) + a2 * np.sin(ur),
                      a2 * np.cos(ur) - b1 * np.sin(ur)])
        samples = x_true[0] + g @ x_true[1:] + rng.normal(0, 2e-5, (10, 3))
        v = samples.mean(axis=0)
        db.execute("BEGIN")
        db.execute("INSERT INTO points VALUES (?,?,?,?,?,?,?,?,?)",
                   (len(rows), y, u, p, r, *v.tolist(), samples.tobytes()))
        db.execute("COMMIT")
        rows.append([1, y, u, p, r, *v, *g])
data = np.array(rows)
np.savetxt(out + "/readings.csv", data[:, :8], delimiter=",", comments="",
           header="replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz")
f = np.column_stack([np.ones(len(data)), data[:, 8:11]])
q, r = np.linalg.qr(f)
x = np.linalg.solve(r, q.T @ data[:, 5:8])
resid = data[:, 5:8] - f @ x
se = np.sqrt((resid ** 2).sum(axis=0) / (len(data) - 4))
json.dump({"coefficients": x.tolist(), "residual_standard_error": se.tolist()}, open(out + "/fit.json", "w"))
"""


def wall(argv: list[str]) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        argv = [a.replace("{tmp}", tmp) for a in argv]
        t0 = time.perf_counter()
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return time.perf_counter() - t0


def side_by_side(label: str, a: list[str], b: list[str], repeat: int, target: float) -> None:
    pairs = [(wall(a), wall(b)) for _ in range(repeat)]
    ratio = statistics.median(x / y for x, y in pairs)
    print(f"{label}: {statistics.median(x for x, _ in pairs):.3f} s vs "
          f"{statistics.median(y for _, y in pairs):.3f} s = {ratio:.2f}× (target ≤ {target:g}×)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    run = [LABCAL, "run", "--sim", "--yes", "--out", "{tmp}/run", "--db", "{tmp}/lab.sqlite"]
    floor = [sys.executable, "-c", FLOOR, str(PLAN), "{tmp}"]
    wall(run)  # warm the file cache
    side_by_side("labcal run --sim --yes / floor job", run, floor, args.repeat, 2)
    side_by_side("labcal run --sim --yes --no-report / floor job", [*run, "--no-report"], floor,
                 args.repeat, 2)
    nothing = [sys.executable, "-c", "pass"]
    side_by_side("labcal --help / python -c pass", [LABCAL, "--help"], nothing, args.repeat * 2, 3)
    side_by_side("labcal plan list / python -c pass", [LABCAL, "plan", "list"], nothing, args.repeat * 2, 3)


if __name__ == "__main__":
    main()
