"""`labcal attitude` end to end against a vectorised numpy pipeline of the same maths and I/O.

The pipeline is written here from the papers, importing nothing of labcal: it reads the fit's JSON
and the voltages (np.loadtxt), computes both estimators (closed form, Soto App. B and eqs. 5–7;
weighted least squares on the sphere, Tripp eqs. 99–104, with the same Σ_v, the same roll-exists
rule and labcal's Gauss–Newton step count) and writes the same columns with np.savetxt. Before
timing, both outputs are compared on the benchmark's file: the pipeline is only a baseline if it
computes the same numbers (to 2e-8 relative; both print nine significant digits). Both run
as processes, interleaved; the median of the pairwise ratios is printed, with rows per second and
peak memory of `--json`. Target: labcal ≤ 1.0× the pipeline's time.

Usage: python benchmarks/attitude_pipeline.py [--rows 100000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from processes import ENV, measure

LABCAL = str(Path(sys.executable).with_name("labcal"))

PIPELINE = r"""
import json, sys
from statistics import NormalDist
import numpy as np
doc = json.load(open(sys.argv[1], encoding="utf-8"))
X, C = np.array(doc["coefficients"]), np.array(doc["covariance"])[:, :4, :4]
sd2 = np.array(doc["reading_sd"]) ** 2
nus = np.array(doc["uncertainty_dof"], dtype=float)
z = NormalDist().inv_cdf(0.975)

def k95(u2, parts):  # Welch-Satterthwaite over the sensors' Type A parts (GUM G.2b), nu_eff truncated
    # (G.4.1 note 1); t quantile by Cornish-Fisher, Abramowitz & Stegun 26.7.5
    with np.errstate(divide="ignore", invalid="ignore"):
        nu = np.floor(np.maximum(u2**2 / sum(p**2 / n for p, n in zip(parts, nus)), 1.0) + 1e-9)
    return (z + (z**3 + z) / 4 / nu + (5 * z**5 + 16 * z**3 + 3 * z) / 96 / nu**2
            + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384 / nu**3
            + (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160 / nu**4)
B, S = X[0], X[1:]
Si = np.linalg.inv(S)
v = np.loadtxt(sys.argv[2], delimiter=",", skiprows=1, ndmin=2)

def var_v(g):  # per sensor: [1 g] C_j [1 g]^T + one reading's variance (Tripp eq. 104's Sigma_v)
    f = np.column_stack([np.ones(len(g)), g])
    return np.einsum("na,jab,nb->nj", f, C, f) + sd2

def unit(p, r):
    sp, cp, sr, cr = np.sin(p), np.cos(p), np.sin(r), np.cos(r)
    return (np.column_stack([sp, cp * sr, cp * cr]), np.column_stack([cp, -sp * sr, -sp * cr]),
            np.column_stack([0 * p, cp * cr, -cp * sr]))

g = (v - B) @ Si  # Soto App. B
gx = np.clip(g[:, 0], -1, 1)
p0, r0 = np.arcsin(gx), np.arctan2(g[:, 1], g[:, 2])
w = var_v(g)
h2 = g[:, 1] ** 2 + g[:, 2] ** 2
with np.errstate(divide="ignore", invalid="ignore"):
    jp = np.outer(1 / np.sqrt(np.maximum(1 - gx**2, 1e-300)), Si[:, 0])  # d pitch / dv
    jr = (g[:, 2:3] * Si[:, 1] - g[:, 1:2] * Si[:, 2]) / h2[:, None]  # d roll / dv
up, ur = np.sqrt((jp**2 * w).sum(1)), np.sqrt((jr**2 * w).sum(1))
cf_k = [k95(up**2, list((jp**2 * w).T)), k95(ur**2, list((jr**2 * w).T))]
vg = w @ Si**2
free = np.sqrt(h2) > 3 * np.sqrt((vg[:, 1] + vg[:, 2]) / 2)  # roll exists: |g_h| above 3 u
cf = [p0, np.where(free, r0, np.nan), np.where(free & (np.abs(g[:, 0]) < 1), up, np.nan),
      np.where(free, ur, np.nan)]
p, r = p0.copy(), r0.copy()  # Tripp eqs. 99-104: Gauss-Newton over (pitch, roll), weights 1/Sigma_v
for it in range(5):
    gg, dp, dr = unit(p, r)
    W = 1 / var_v(gg)
    fp, fr, e = dp @ S, dr @ S, v - B - gg @ S
    a, b, c = (W * fp * fp).sum(1), (W * fp * fr).sum(1), (W * fr * fr).sum(1)
    det = a * c - b * b
    if it == 4:
        break
    ep, er = (W * fp * e).sum(1), (W * fr * e).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = p + np.where(free, (c * ep - b * er) / det, ep / a)
        r = r + np.where(free, (a * er - b * ep) / det, 0)
with np.errstate(divide="ignore", invalid="ignore"):
    ls = [np.arctan2(np.sin(p), np.cos(p)), np.where(free, np.arctan2(np.sin(r), np.cos(r)), np.nan),
          np.sqrt(np.where(free, c / det, 1 / a)), np.where(free, np.sqrt(a / det), np.nan)]
    # A = (F W F^T)^-1 F W: each sensor's share of the variance, for the coverage factor
    ap = np.where(free[:, None], (c[:, None] * W * fp - b[:, None] * W * fr) / det[:, None],
                  W * fp / a[:, None])
    ar = (a[:, None] * W * fr - b[:, None] * W * fp) / det[:, None]
    ls_k = [k95(ls[2]**2, list((ap**2 / W).T)), np.where(free, k95(ls[3]**2, list((ar**2 / W).T)), np.nan)]
cols = []
for est, (kp, kr) in ((cf, cf_k), (ls, ls_k)):
    d = [np.degrees(x) for x in est]
    cols += [*d, kp * d[2], kr * d[3], np.where(np.isfinite(d[2]), kp, np.nan),
             np.where(np.isfinite(d[3]), kr, np.nan)]
names = [f"{m}{c}" for m in ("cf_", "ls_") for c in ("pitch_deg", "roll_deg", "u_pitch_deg", "u_roll_deg",
                                                      "U95_pitch_deg", "U95_roll_deg", "k_pitch", "k_roll")]
np.savetxt(sys.stdout, np.column_stack([np.arange(1, len(v) + 1), *cols]), delimiter=",",
           fmt=["%d"] + ["%.9g"] * 16, comments="", header="row," + ",".join(names))
"""


def agree(labcal: list[str], pipeline: list[str]) -> None:
    """Both outputs hold the same numbers, column by column (labcal leaves an undefined value empty,
    np.savetxt writes nan), or the pipeline is no baseline."""
    tables = [np.genfromtxt(io.StringIO(subprocess.run(argv, check=True, capture_output=True, text=True,
                                                       env=ENV).stdout), delimiter=",", names=True)
              for argv in (labcal, pipeline)]
    if tables[0].dtype.names != tables[1].dtype.names or len(tables[0]) != len(tables[1]):
        raise SystemExit("the pipeline's columns or rows differ from labcal's")
    a, b = tables
    worst = max(float(np.nanmax(np.abs(a[n] - b[n]) / np.maximum(np.abs(a[n]), 1e-300), initial=0.0))
                for n in a.dtype.names)
    undefined = [n for n in tables[0].dtype.names
                 if not np.array_equal(np.isnan(tables[0][n]), np.isnan(tables[1][n]))]
    if worst > 2e-8 or undefined:  # nine significant digits: the last may round either way
        raise SystemExit(f"the pipeline disagrees with labcal: {worst:.2g} relative, undefined "
                         f"differently in {undefined or 'no column'}")
    print(f"labcal and the pipeline agree on all {len(tables[0])} rows to {worst:.1g} relative")


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
        labcal = [LABCAL, "attitude", "--cert", str(fit), "--csv", str(volts)]
        pipeline = [sys.executable, "-c", PIPELINE, str(fit), str(volts)]
        measure(labcal), measure(pipeline)  # warm-up: labcal's bytecode, the file cache
        csv_pairs, json_runs = [], []
        for _ in range(args.repeat):
            csv_pairs.append((measure(labcal), measure(pipeline)))
            json_runs.append(measure([*labcal, "--json"]))
        agree(labcal, pipeline)  # last: its tables would count in every later child's peak memory
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
