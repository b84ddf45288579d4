"""A run's residual plot, drawn from the points in the lab database.

The server may not reach the run's folder (another station's disk), but the lab database holds every
reading. A complete run's plot shows the residuals of the model its certificate rests on, rebuilt
from the lab's own copy of the run (`labcal.run.lab_certificates.lab_record`) and fitted as the
report fits it (`labcal.documents.report.fitted`): the device model where the plan identifies it
(Soto eq. 11, the device's six misalignments fitted), else the linear fit. The linear fit's residuals
next to a device-model certificate hold the device's misalignments, forty times the certificate's
scatter, and read as a bad calibration. A run not complete yet is plotted under the linear fit
(`labcal.analysis.fit.fit_readings`) of the readings so far. Per sensor against pitch and roll; the
heading names the model.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.engine import Connection

from labcal.analysis.readings import Readings
from labcal.errors import LabcalError
from labcal.run.schema import points, runs

SENSORS = ("x", "y", "z")


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


CACHED = 64  # plots (about 100 kB each) and residuals kept
_CACHE: OrderedDict[tuple, Any] = OrderedDict()  # plots (PNG bytes) and residuals, by `_state`
_CACHE_LOCK = threading.Lock()
_DRAWING = threading.Lock()  # one plot drawn at a time: the others wait, then find theirs drawn


def _state(conn: Connection, run_id: int) -> tuple:
    """What a run's residuals depend on: the database, the run, its status, its number of measured
    points and its last one."""
    count, last = conn.execute(select(func.count(), func.max(points.c.seq))
                               .where(points.c.run_id == run_id, points.c.status == "ok")).one()
    status = conn.execute(select(runs.c.status).where(runs.c.id == run_id)).scalar()
    return conn.engine.url.render_as_string(hide_password=True), run_id, status, count, last


def residual_png(conn: Connection, run_id: int) -> bytes | None:
    """PNG of the run's residuals (None: too few readings to fit), drawn once per state of the run —
    its status, its number of measured points and its last one — however many ask for it at once: a plot
    costs a fit and a Matplotlib figure (~0.4 s of CPU), and 40 requests for it took 18 s."""
    key = ("png", *_state(conn, run_id))
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


@dataclass(frozen=True)
class CertifiedResiduals:
    """Every reading's residual under the model a run's certificate rests on."""

    model: str  # "device model", "linear model", …
    equation: str
    residuals: Any  # K×3 array, in the readings' unit
    pitch_deg: Any
    roll_deg: Any
    unit: str


def certified_residuals(conn: Connection, run_id: int) -> CertifiedResiduals | None:
    """The residuals of the model the run's certificate rests on, from the lab database's own copy of
    the run (None: no such run, not complete, or its readings cannot be fitted); fitted once per
    state of the run (a device model's fit costs about a second), kept like the plots."""
    key = ("residuals", *_state(conn, run_id))
    with _CACHE_LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
    found = _certified(conn, run_id)
    with _CACHE_LOCK:
        _CACHE[key] = found
        while len(_CACHE) > CACHED:
            _CACHE.popitem(last=False)
    return found


def _certified(conn: Connection, run_id: int) -> CertifiedResiduals | None:
    # the report's and the record's modules (scipy, pydantic) load when a page first asks
    from labcal.documents.report import fitted
    from labcal.documents.report_figures import certified_residuals as stated
    from labcal.run.lab_certificates import lab_record

    run_dir = conn.execute(select(runs.c.run_dir).where(runs.c.id == run_id)).scalar()
    if run_dir is None:
        return None
    try:
        record = lab_record(conn, run_id, Path(run_dir))
        fit, device, _ = fitted(record)
    except (LabcalError, ValueError):
        return None
    model, equation, residuals = stated(fit, device)
    r = record.readings
    return CertifiedResiduals(model, equation, np.asarray(residuals)[:, :3], r.pitch_deg, r.roll_deg, r.units)


def _shown(conn: Connection, run_id: int) -> tuple[CertifiedResiduals, str] | None:
    """What the plot shows and its heading: the certificate's model for a complete run, else the
    linear fit of the readings so far."""
    from labcal.analysis.fit import fit_readings

    certified = certified_residuals(conn, run_id)
    if certified is not None:
        return certified, f"Run {run_id}: residuals of the {certified.model} its certificate rests on"
    found = readings(conn, run_id)
    if found is None:
        return None
    try:
        fit = fit_readings(found)
    except LabcalError:
        return None
    linear = CertifiedResiduals("linear model", "V = B + gᵀS", fit.ls.residuals[:, :3], found.pitch_deg,
                                found.roll_deg, found.units)
    return linear, (f"Run {run_id}: residuals of the linear fit (V = B + gᵀS) to the {len(found)} "
                    "readings so far")


def _draw(conn: Connection, run_id: int) -> bytes | None:
    from labcal.documents.report_figures import volt_unit

    shown = _shown(conn, run_id)
    if shown is None:
        return None
    found, heading = shown
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 6.5), dpi=100, layout="constrained")
    axes = fig.subplots(3, 2, sharex="col")
    residuals = np.asarray(found.residuals, dtype=float)
    rms = np.sqrt(np.mean(residuals**2, axis=0))
    for j, sensor in enumerate(SENSORS):
        factor, unit = volt_unit(float(np.max(np.abs(residuals[:, j]))), found.unit)
        for k, (angle, label) in enumerate(((found.pitch_deg, "pitch (°)"), (found.roll_deg, "roll (°)"))):
            ax = axes[j, k]
            ax.axhline(0.0, color="#888", lw=0.8)
            ax.plot(angle, residuals[:, j] * factor, "o", ms=3, color="#1f5f99")
            ax.set_ylabel(f"{sensor}: residual ({unit})" if k == 0 else "")
            ax.grid(True, lw=0.3)
            if j == 2:
                ax.set_xlabel(label)
        axes[j, 1].set_title(f"RMS {rms[j] * factor:.3g} {unit}", fontsize=9, loc="right")
    fig.suptitle(heading, fontsize=10)
    out = io.BytesIO()
    fig.savefig(out, format="png")
    return out.getvalue()
