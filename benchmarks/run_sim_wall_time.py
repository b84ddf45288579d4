"""Wall time of the main job and of start-up, against floors built here, measured side by side.

The targets:
- `labcal run --sim --yes` (certificate, report and DCC included) against the documents floor: the
  floor job below plus the documents the run issues, made with scipy, matplotlib, reportlab and lxml
  directly — scipy's t quantile and a `scipy.optimize.least_squares` fit of the model; five figures
  of the report's kinds (6, 2, 2, 3-D and 12 panels) each drawn once with Agg at the report's 120
  dpi, their PNGs in an HTML file with the readings table; a PDF typeset by reportlab's platypus
  (three pages of tables in a proportional font, then the five images); and a DCC of the same
  schema built as text, parsed and validated by lxml against the test suite's copy of PTB's schema,
  compiled in the process. Target ≤ 1.1×.
- `labcal run --sim --yes --no-report` against the floor job: the same dry run with numpy and sqlite
  — the plan's 64 points, ten samples each from the nominal gravity through a known X plus noise, one
  WAL transaction per point with its raw samples, readings.csv, a QR least-squares fit and fit.json —
  importing first what the run must import (numpy, scipy.optimize for the device model's least
  squares, scipy.special for the settling test's and the coverage factor's quantiles). Target ≤ 3×.
  The bare floor job (numpy and sqlite only) is printed beside it, without a target.
- `labcal --help` and `labcal plan list` against `python -c pass`. Target ≤ 3×.

Commands run as separate processes, interleaved (A B A B …); the ratio printed is the median of
the pairwise ratios, so a machine that slows down in between affects both sides alike. Every process
runs with its bytecode cached, as an installed labcal has it (`processes.py`; a warm-up run writes
it): compiling labcal's imported source in every process costs `labcal --help` about 20 ms.

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

from processes import ENV

LABCAL = str(Path(sys.executable).with_name("labcal"))
ROOT = Path(__file__).resolve().parent.parent
PLAN = ROOT / "sequences" / "four-mount-64.toml"
DCC_SCHEMA = ROOT / "tests" / "data" / "dcc" / "dcc.xsd"  # not the copy labcal ships

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


# what `labcal run --sim --no-report` must import besides numpy: least squares and the quantiles
FLOOR_SCIPY = "import scipy.optimize, scipy.special\n" + FLOOR

FLOOR_DOCUMENTS = FLOOR + r"""
# --- the documents, with the public libraries directly ------------------------------------------
import base64, html, io, os
from pathlib import Path
from lxml import etree
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import getSampleStyleSheet
from reportlab.platypus import Image as PdfImage, PageBreak, Paragraph, SimpleDocTemplate, Table
from scipy import optimize, stats
from PIL import Image
import mpl_toolkits.mplot3d  # the 3-D projection

t95 = stats.t.ppf(0.975, len(data) - 4)  # the coverage factor of each coefficient
fitted = optimize.least_squares(lambda b: (f @ b.reshape(4, 3) - data[:, 5:8]).ravel(), np.zeros(12))
assert np.allclose(fitted.x.reshape(4, 3), x, atol=1e-9)
pitch, roll, mount = data[:, 3], data[:, 4], (data[:, 1] // 180 + 2 * (data[:, 2] // 180)).astype(int)
figs = []
fig = Figure(figsize=(11, 10))  # residuals with bands, per sensor, against pitch and roll
for k, ax in enumerate(fig.subplots(3, 2).ravel()):
    angle = pitch if k % 2 == 0 else roll
    dense = np.linspace(angle.min(), angle.max(), 361)
    ax.fill_between(dense, -3 * se[k // 2] * 1e6, 3 * se[k // 2] * 1e6, color="0.85", label="prediction")
    ax.fill_between(dense, -se[k // 2] * 1e6, se[k // 2] * 1e6, color="0.65", label="confidence")
    for m in range(4):
        ax.plot(angle[mount == m], resid[mount == m, k // 2] * 1e6, "o", ms=4, label=f"mount {m}")
    ax.axhline(0, color="k", lw=0.6)
    ax.set(xlabel="table angle (°)", ylabel="residual (µV)", title=f"sensor {k // 2}: residuals")
    ax.grid(alpha=0.3)
    if k == 0:
        ax.legend(fontsize=7)
fig.suptitle("Calibration residuals")
figs.append(fig)
for title in ("attitude errors", "uncertainty over the envelope"):  # two panels each
    fig = Figure(figsize=(11, 4.5))
    for k, ax in enumerate(fig.subplots(1, 2)):
        for m in range(4):
            if title == "attitude errors":
                ax.errorbar(pitch[mount == m] + m, resid[mount == m, k], yerr=se[k], fmt="o", ms=4, capsize=2)
            else:
                grid = np.arange(-90, 91, 5.0)
                ax.plot(grid, np.abs(np.sin(np.radians(grid + m))), "-o")
        ax.axhline(0, color="k", lw=0.6)
        ax.set(xlabel="pitch (°)", ylabel="error (°)", title=title)
        ax.grid(alpha=0.3)
        ax.legend([f"mount {m}" for m in range(4)], fontsize=7)
    figs.append(fig)
fig = Figure(figsize=(7, 6.5))  # the points on the gravity sphere
ax = fig.add_subplot(projection="3d")
u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 37), np.linspace(0, np.pi, 19))
ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.8", lw=0.4)
for m in range(4):
    ax.scatter(*data[mount == m, 8:11].T, s=40, depthshade=False, label=f"mount {m}")
for d in np.unique(np.round(data[:, 8:11], 6), axis=0):
    ax.text(*(1.18 * d), "4", fontsize=8)
ax.set(xlabel="g_x", ylabel="g_y", zlabel="g_z", title="the plan's points")
ax.legend(fontsize=7)
figs.append(fig)
fig = Figure(figsize=(11, 10))  # a second model's residuals, 3 × 4 panels
for k, ax in enumerate(fig.subplots(3, 4).ravel()):
    ax.plot(pitch if k % 2 == 0 else roll, resid[:, k // 4] * 1e6, "o", ms=3)
    ax.axhline(0, color="k", lw=0.6)
    ax.set(xlabel="table angle (°)", title=f"panel {k}")
    ax.grid(alpha=0.3)
figs.append(fig)

pngs = []
for fig in figs:  # each drawn once; its PNG goes into the HTML page and into the PDF
    fig.set_dpi(120)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="png")
    pngs.append(buf.getvalue())
lines = [" ".join(f"{x:+.9e}" for x in row[:8]) for row in data] + [str(c) for c in x.ravel()]
lines = (lines * 3)[:180]  # three pages of text, as the report's tables take
styles = getSampleStyleSheet()
story = [Paragraph("Calibration certificate (floor)", styles["Title"])]
for start in range(0, len(lines), 60):
    story += [Table([line.split()[:8] or [line] for line in lines[start:start + 60]], repeatRows=0,
                    style=[("FONTSIZE", (0, 0), (-1, -1), 8)]), PageBreak()]
for png in pngs:
    story.append(PdfImage(io.BytesIO(png), width=170 * 2.83, height=140 * 2.83, kind="proportional"))
SimpleDocTemplate(out + "/report.pdf", pagesize=A4).build(story)
rows = "".join(f"<tr>{''.join(f'<td>{html.escape(c)}</td>' for c in line.split())}</tr>" for line in lines)
images = "".join(f'<img src="data:image/png;base64,{base64.b64encode(p).decode()}">' for p in pngs)
page = f"<!DOCTYPE html><html><body><table>{rows}</table>{images}</body></html>"
Path(out + "/report.html").write_text(page, encoding="utf-8")

D, S = "https://ptb.de/dcc", "https://ptb.de/si"
def real(label, value, unit):
    return (f"<si:real><si:label>{label}</si:label><si:value>{value!r}</si:value><si:unit>{unit}</si:unit>"
            "<si:expandedUnc><si:uncertainty>1e-06</si:uncertainty><si:coverageFactor>2.0</si:coverageFactor>"
            "<si:coverageProbability>0.95</si:coverageProbability></si:expandedUnc></si:real>")
def text(tag, words):
    return f"<dcc:{tag}><dcc:content>{words}</dcc:content></dcc:{tag}>"
results = "".join(
    f"<dcc:result>{text('name', f'sensor {j}')}<dcc:data><dcc:quantity><si:list><si:realList>"
    + "".join(real(f"X{i}{j}", float(x[i, j]), "\\volt") for i in range(4))
    + "<si:ellipsoidalRegion><si:covarianceMatrix>"
    + "".join("<si:column>" + "<si:covariance><si:value>1e-12</si:value><si:unit>\\volt\\tothe{2}</si:unit>"
              "</si:covariance>" * 4 + "</si:column>" for _ in range(4))
    + "</si:covarianceMatrix><si:coverageFactor>2.0</si:coverageFactor>"
      "<si:coverageProbability>0.95</si:coverageProbability></si:ellipsoidalRegion>"
    + "</si:realList></si:list></dcc:quantity></dcc:data></dcc:result>" for j in range(3))
dcc = (f'<?xml version="1.0" encoding="utf-8"?><dcc:digitalCalibrationCertificate xmlns:dcc="{D}" '
       f'xmlns:si="{S}" schemaVersion="3.2.0"><dcc:administrativeData><dcc:dccSoftware><dcc:software>'
       f"{text('name', 'floor')}<dcc:release>1</dcc:release></dcc:software></dcc:dccSoftware><dcc:coreData>"
       "<dcc:countryCodeISO3166_1>ZZ</dcc:countryCodeISO3166_1><dcc:usedLangCodeISO639_1>en"
       "</dcc:usedLangCodeISO639_1><dcc:mandatoryLangCodeISO639_1>en</dcc:mandatoryLangCodeISO639_1>"
       "<dcc:uniqueIdentifier>floor</dcc:uniqueIdentifier><dcc:beginPerformanceDate>2026-01-01"
       "</dcc:beginPerformanceDate><dcc:endPerformanceDate>2026-01-01</dcc:endPerformanceDate>"
       "<dcc:performanceLocation>laboratory</dcc:performanceLocation></dcc:coreData><dcc:items><dcc:item>"
       f"{text('name', 'instrument')}<dcc:manufacturer>{text('name', 'maker')}</dcc:manufacturer>"
       "<dcc:identifications><dcc:identification><dcc:issuer>manufacturer</dcc:issuer><dcc:value>S1"
       f"</dcc:value>{text('name', 'serial')}</dcc:identification></dcc:identifications></dcc:item>"
       f"</dcc:items><dcc:calibrationLaboratory><dcc:contact>{text('name', 'lab')}<dcc:location>"
       f"{text('further', 'here')}</dcc:location></dcc:contact></dcc:calibrationLaboratory><dcc:respPersons>"
       f"<dcc:respPerson><dcc:person>{text('name', 'nobody')}</dcc:person></dcc:respPerson></dcc:respPersons>"
       f"<dcc:customer>{text('name', 'customer')}<dcc:location>{text('further', 'there')}</dcc:location>"
       f"</dcc:customer></dcc:administrativeData><dcc:measurementResults><dcc:measurementResult>"
       f"{text('name', 'coefficients')}<dcc:results>{results}</dcc:results></dcc:measurementResult>"
       "</dcc:measurementResults></dcc:digitalCalibrationCertificate>")
schema = etree.XMLSchema(etree.parse(sys.argv[3], etree.XMLParser(no_network=True)))
schema.assertValid(etree.fromstring(dcc.encode()))
Path(out + "/certificate.dcc.xml").write_text(dcc, encoding="utf-8")
"""




def wall(argv: list[str]) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        argv = [a.replace("{tmp}", tmp) for a in argv]
        t0 = time.perf_counter()
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
        return time.perf_counter() - t0


def side_by_side(label: str, a: list[str], b: list[str], repeat: int, target: float) -> None:
    wall(a), wall(b)  # warm-up: the file cache and the bytecode
    pairs = [(wall(a), wall(b)) for _ in range(repeat)]
    show(label, pairs, target)


def show(label: str, pairs: list[tuple[float, float]], target: float | None) -> None:
    ratio = statistics.median(x / y for x, y in pairs)
    print(f"{label}: {statistics.median(x for x, _ in pairs):.3f} s vs "
          f"{statistics.median(y for _, y in pairs):.3f} s = {ratio:.2f}×"
          + ("" if target is None else f" (target ≤ {target:g}×)"))


def main_job(repeat: int) -> None:
    """The run, the run without documents and both floors, interleaved in every round."""
    run = [LABCAL, "run", "--sim", "--yes", "--out", "{tmp}/run", "--db", "{tmp}/lab.sqlite"]
    floor = [sys.executable, "-c", FLOOR, str(PLAN), "{tmp}"]
    floor_scipy = [sys.executable, "-c", FLOOR_SCIPY, str(PLAN), "{tmp}"]
    documents = [sys.executable, "-c", FLOOR_DOCUMENTS, str(PLAN), "{tmp}", str(DCC_SCHEMA)]
    # labcal's command line collects the youngest objects every 50 000 new ones, not CPython's 700
    # (labcal.cli.GC_THRESHOLDS), and freezes every object before the interpreter's exit, whose last
    # collection then has nothing to walk (labcal.cli.script); the same written here, so that the
    # floor can be given them too
    tuned = [sys.executable, "-c", "import gc; gc.set_threshold(50_000, 20, 10)\n" + FLOOR_DOCUMENTS
             + "\ngc.freeze()\n", str(PLAN), "{tmp}", str(DCC_SCHEMA)]
    for warm in (run, floor, floor_scipy, documents, tuned, [*run, "--no-report"]):  # cache, bytecode
        wall(warm)
    rounds = [(wall(run), wall(floor), wall(documents), wall([*run, "--no-report"]), wall(floor_scipy),
               wall(tuned)) for _ in range(repeat)]
    show("labcal run --sim --yes / documents floor", [(r[0], r[2]) for r in rounds], 1.1)
    show("labcal run --sim --yes / documents floor with labcal's collector settings",
         [(r[0], r[5]) for r in rounds], None)
    show("labcal run --sim --yes --no-report / floor job with scipy", [(r[3], r[4]) for r in rounds], 3)
    show("labcal run --sim --yes --no-report / bare floor job", [(r[3], r[1]) for r in rounds], None)
    show("documents floor / floor job", [(r[2], r[1]) for r in rounds], None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    main_job(args.repeat)
    nothing = [sys.executable, "-c", "pass"]
    side_by_side("labcal --help / python -c pass", [LABCAL, "--help"], nothing, args.repeat * 2, 3)
    side_by_side("labcal plan list / python -c pass", [LABCAL, "plan", "list"], nothing, args.repeat * 2, 3)


if __name__ == "__main__":
    main()
