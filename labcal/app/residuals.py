"""A finished run's residual plot, drawn from the points in the lab database.

The server may not reach the run's folder (another station's disk), but the lab database holds every
reading: the plot is the linear fit's residuals (`labcal.analysis.fit.fit_readings`, the fit
`labcal fit` and the certificate start from), per sensor against pitch and against roll, in µV. It
is the run's data as journaled, not the certificate's statement (that is the report's, in the run's
folder), and its heading says so.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.engine import Connection

from labcal.analysis.readings import Readings
from labcal.errors import LabcalError
from labcal.run.schema import points


def readings(conn: Connection, run_id: int) -> Readings | None:
    """The run's measured points as Readings, as `labcal.run.journal.Journal.readings` gives them."""
    rows = conn.execute(select(points.c.replicate, points.c.y_deg, points.c.u_deg, points.c.pitch_deg,
                               points.c.roll_deg, points.c.vx, points.c.vy, points.c.vz, points.c.temp_c)
                        .where(points.c.run_id == run_id, points.c.status == "ok")
                        .order_by(points.c.seq)).all()
    if not rows:
        return None
    a = np.array([r[:8] for r in rows], dtype=float)
    temps = [r[8] for r in rows]
    return Readings(replicate=a[:, 0].astype(int), y_deg=a[:, 1], u_deg=a[:, 2], pitch_deg=a[:, 3],
                    roll_deg=a[:, 4], volts=a[:, 5:8],
                    temp_c=None if any(t is None for t in temps) else np.array(temps, dtype=float))


CACHED = 64  # plots kept (about 100 kB each)
_CACHE: OrderedDict[tuple, bytes | None] = OrderedDict()
_CACHE_LOCK = threading.Lock()
_DRAWING = threading.Lock()  # one plot drawn at a time: the others wait, then find theirs drawn


def residual_png(conn: Connection, run_id: int) -> bytes | None:
    """PNG of the linear fit's residuals (None: too few readings to fit), drawn once per state of the
    run — its number of measured points and its last one — however many ask for it at once: a plot
    costs a fit and a Matplotlib figure (~0.4 s of CPU), and 40 requests for it took 18 s."""
    count, last = conn.execute(select(func.count(), func.max(points.c.seq))
                               .where(points.c.run_id == run_id, points.c.status == "ok")).one()
    key = (conn.engine.url.render_as_string(hide_password=True), run_id, count, last)
    with _CACHE_LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
    with _DRAWING:
        with _CACHE_LOCK:
            if key in _CACHE:
                return _CACHE[key]
        png = _draw(conn, run_id)
        with _CACHE_LOCK:
            _CACHE[key] = png
            while len(_CACHE) > CACHED:
                _CACHE.popitem(last=False)
    return png


def _draw(conn: Connection, run_id: int) -> bytes | None:
    from labcal.analysis.fit import fit_readings

    found = readings(conn, run_id)
    if found is None:
        return None
    try:
        fit = fit_readings(found)
    except LabcalError:
        return None
    residuals = fit.ls.residuals[:, :3] * 1e6  # µV, one column per sensor the package has
    sensors = fit.sensors
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 6.5 * (len(sensors) + 0.5) / 3.5), dpi=100, layout="constrained")
    axes = fig.subplots(len(sensors), 2, sharex="col", squeeze=False)
    rms = np.sqrt(np.mean(residuals**2, axis=0))
    for j, sensor in enumerate(sensors):
        for k, (angle, label) in enumerate(((found.pitch_deg, "pitch (°)"), (found.roll_deg, "roll (°)"))):
            ax = axes[j, k]
            ax.axhline(0.0, color="#888", lw=0.8)
            ax.plot(angle, residuals[:, j], "o", ms=3, color="#1f5f99")
            ax.set_ylabel(f"{sensor}: residual (µV)" if k == 0 else "")
            ax.grid(True, lw=0.3)
            if j == len(sensors) - 1:
                ax.set_xlabel(label)
        shown = f"{rms[j] / 1000:.3g} mV" if rms[j] >= 1000 else f"{rms[j]:.3g} µV"
        axes[j, 1].set_title(f"RMS {shown}", fontsize=9, loc="right")
    fig.suptitle(f"Run {run_id}: residuals of the linear fit (V = B + gᵀS) to the {len(found)} readings "
                 "in the lab database", fontsize=10)
    out = io.BytesIO()
    fig.savefig(out, format="png")
    return out.getvalue()
