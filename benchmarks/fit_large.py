"""`labcal fit` on a million readings against a bare numpy process doing the least the same job can:
np.loadtxt of the file and a QR least-squares fit of [1 gᵀ] on the nominal gravity.

Both run as separate processes (`processes.py`: labcal's bytecode cached, as installed), after
one warm-up each, then interleaved (A B A B …); each one's wall time and peak resident memory
are taken, and the medians of the pairwise ratios printed. Targets: time
≤ 1.5×, memory ≤ 1.2×.

Usage: python benchmarks/fit_large.py [--rows 1000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
from processes import measure

LABCAL = str(Path(sys.executable).with_name("labcal"))

BARE = """
import sys
import numpy as np
data = np.loadtxt(sys.argv[1], delimiter=",", skiprows=1, usecols=range(8))
p, r, y, u = np.radians(data[:, 1:5]).T[[2, 3, 0, 1]]
g = np.column_stack([np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])
g[:, 0], g[:, 1] = g[:, 0] * np.cos(y) - g[:, 1] * np.sin(y), g[:, 0] * np.sin(y) + g[:, 1] * np.cos(y)
g[:, 1], g[:, 2] = g[:, 1] * np.cos(u) + g[:, 2] * np.sin(u), g[:, 2] * np.cos(u) - g[:, 1] * np.sin(u)
f = np.column_stack([np.ones(len(g)), g])
q, rr = np.linalg.qr(f)
x = np.linalg.solve(rr, q.T @ data[:, 5:8])
print(x)
"""


def write_readings(path: Path, rows: int) -> None:
    """Readings of a four-mount grid, replicated to ``rows`` rows, noisy volts (written by numpy)."""
    rng = np.random.default_rng(1)
    pitch, roll = np.meshgrid(np.arange(-180, 180, 10), np.arange(-180, 180, 30))
    points = np.column_stack([pitch.ravel(), roll.ravel()])
    mounts = np.array([[0, 0], [180, 0], [0, 180], [180, 180]])
    per_rep = len(points) * len(mounts)
    n_rep = -(-rows // per_rep)
    rep = np.repeat(np.arange(1, n_rep + 1), per_rep)[:rows]
    mount = np.tile(np.repeat(mounts, len(points), axis=0), (n_rep, 1))[:rows]
    pr = np.tile(np.tile(points, (len(mounts), 1)), (n_rep, 1))[:rows]
    p, r = np.radians(pr).T
    g = np.column_stack([np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])
    g[:, :2] *= np.where(mount[:, :1] == 180, -1, 1)  # y = 180: x and y reversed
    g[:, 1:] *= np.where(mount[:, 1:2] == 180, -1, 1)  # u = 180: y and z reversed
    volts = 0.01 + g @ (5 * np.eye(3)) + rng.normal(0, 2e-5, (rows, 3))
    table = np.column_stack([rep, mount, pr, volts])
    np.savetxt(path, table, delimiter=",", fmt=["%d", "%d", "%d", "%d", "%d", "%.9f", "%.9f", "%.9f"],
               header="replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz", comments="")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "readings.csv"
        write_readings(path, args.rows)
        argv_labcal, argv_bare = [LABCAL, "fit", str(path), "--json"], [sys.executable, "-c", BARE, str(path)]
        measure(argv_labcal), measure(argv_bare)  # warm-up: labcal's bytecode, the file cache
        labcal, bare = [], []
        for _ in range(args.repeat):
            labcal.append(measure(argv_labcal))
            bare.append(measure(argv_bare))
    for name, runs in (("labcal fit", labcal), ("bare numpy", bare)):
        print(f"{name:11s} wall {statistics.median(r[0] for r in runs):6.2f} s   "
              f"peak {statistics.median(r[1] for r in runs):6.0f} MiB")
    time_ratio = statistics.median(a[0] / b[0] for a, b in zip(labcal, bare, strict=True))
    mem_ratio = statistics.median(a[1] / b[1] for a, b in zip(labcal, bare, strict=True))
    print(f"{args.rows} readings: labcal fit / bare numpy = {time_ratio:.2f}× in time (target ≤ 1.5×), "
          f"{mem_ratio:.2f}× in peak memory (target ≤ 1.2×)")


if __name__ == "__main__":
    main()
