"""A run's residuals and their plot, from the points in the lab database.

The server may not reach the run's folder (another station's disk), but the lab database holds every
reading. A run with a certificate shows the residuals of the model that certificate states, with
the values it states: each reading of the lab's own copy of the run
(`labcal.store.lab_certificates.lab_record`) less ``B + gᵀS``, with the certificate's B and S and the
gravity its model gives — through the device's misalignments where it rests on the device model
(Soto eq. 11, the six misalignments its device section states) or on a device correction (the
correction's values), nominal gravity otherwise (Soto eq. 4). Nothing is fitted again: the residuals
are the certificate's, in a few milliseconds. A certificate whose model holds more than that (the
temperature or harmonic terms, a two-axis package) is refitted as the report fits it
(`labcal.documents.report.fitted`).

The linear fit's residuals next to a device-model certificate hold the device's misalignments, forty
times the certificate's scatter, and read as a bad calibration. A run without a certificate (still
running, or not issued) is plotted under the linear fit (`labcal.analysis.fit.fit_readings`) of the
readings so far, and its heading says so.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import NO_MISALIGNMENT, Misalignment, gravity
from labcal.analysis.readings import Readings
from labcal.documents.certificate import Certificate
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.journal import readings_of
from labcal.store.lab_certificates import lab_record
from labcal.store.lab_points import ok_points, points_state, run_status_and_folder

if TYPE_CHECKING:
    import matplotlib
    from matplotlib import figure

    from labcal.documents import report, report_figures
    from labcal.store.handles import Connection
else:
    # matplotlib only where a page draws the plot or a certificate is refitted as the report fits
    # it: `labcal runs` and the overview list runs without it
    matplotlib = lazy("matplotlib")
    figure = lazy("matplotlib.figure")
    report_figures = lazy("labcal.documents.report_figures")
    report = lazy("labcal.documents.report")


def readings(conn: Connection, run_id: int) -> Readings | None:
    """The run's measured points as Readings, as `labcal.store.journal.Journal.readings` gives them."""
    good = ok_points(conn, run_id)
    return readings_of(good, f"run {run_id}") if good else None


CACHED = 64  # plots (about 100 kB each) and residuals kept
_CACHE: OrderedDict[tuple, Any] = OrderedDict()  # plots (PNG bytes) and residuals, by `_state`
_CACHE_LOCK = threading.Lock()
_DRAWING = threading.Lock()  # one plot drawn at a time: the others wait, then find theirs drawn


def _state(conn: Connection, run_id: int, cert: Certificate | None) -> tuple:
    """What a run's residuals depend on: the database, the run, its status, its number of measured
    points and its last one, and the certificate they are judged by."""
    status, _ = run_status_and_folder(conn, run_id)
    digest = None if cert is None else cert.digest.value
    return (*points_state(conn, run_id), status, digest)


def _cached(key: tuple, make: Any) -> Any:
    with _CACHE_LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
    found = make()
    with _CACHE_LOCK:
        _CACHE[key] = found
        while len(_CACHE) > CACHED:
            _CACHE.popitem(last=False)
    return found


def residual_png(conn: Connection, run_id: int, cert: Certificate | None) -> bytes | None:
    """PNG of the run's residuals under ``cert``'s model (None: the linear fit of the readings so far;
    None returned: too few readings to fit), drawn once per `_state` however many ask for it at
    once: a plot costs a Matplotlib figure (~0.4 s of CPU), and 40 requests for it took 18 s."""
    key = ("png", *_state(conn, run_id, cert))
    with _DRAWING:
        return _cached(key, lambda: _draw(conn, run_id, cert))


@dataclass(frozen=True)
class CertifiedResiduals:
    """Every reading's residual under the model a run's certificate states."""

    model: str  # "device model", "linear model", …
    equation: str
    residuals: Any  # K × sensors array, in the readings' unit
    pitch_deg: Any
    roll_deg: Any
    unit: str
    sensors: tuple[str, ...] = ("x", "y", "z")  # the columns: a package's sensors (Tripp & Tcheng §6)


def certified_residuals(conn: Connection, run_id: int, cert: Certificate) -> CertifiedResiduals | None:
    """The residuals of the model ``cert`` states, with its values, of the lab database's own copy of
    run ``run_id`` (None: not complete, or its readings cannot be read)."""
    return _cached(("residuals", *_state(conn, run_id, cert)), lambda: _certified(conn, run_id, cert))


def _gravity_misalignment(cert: Certificate) -> tuple[Misalignment, str, str] | None:
    """The misalignments the certificate's gravity goes through, its model's name and equation; None
    where its model holds more than B and S on that gravity."""
    if cert.fit.extensions is not None or cert.package is not None:
        return None
    if cert.device is not None:
        values = {n: m.value_arcsec for n, m in cert.device.misalignments.items()}
        return (Misalignment.from_degrees(**{n: v / 3600.0 for n, v in values.items()}), "device model",
                "V = B + g(p, r, y, u; a, b, d, e, f, k)ᵀS, Soto eq. 11, the certificate's misalignments")
    if cert.device_correction is not None:
        values = cert.device_correction.value_arcsec
        return (Misalignment.from_degrees(**{n: v / 3600.0 for n, v in values.items()}),
                "linear model on the device correction's gravity",
                "V = B + g(p, r, y, u; the correction's a…k)ᵀS, Soto eq. 11")
    return NO_MISALIGNMENT, "linear model", "V = B + gᵀS on nominal gravity, Soto eq. 4"


def _certified(conn: Connection, run_id: int, cert: Certificate) -> CertifiedResiduals | None:
    _, run_dir = run_status_and_folder(conn, run_id)
    if run_dir is None:
        return None
    try:
        record = lab_record(conn, run_id, Path(run_dir))
    except (LabcalError, ValueError):
        return None
    r = record.readings
    stated = _gravity_misalignment(cert)
    if stated is None:  # more than B and S: refitted as the report fits it
        try:
            fit, device, _ = report.fitted(record)
        except LabcalError:
            return None
        model, equation, residuals = report_figures.certified_residuals(fit, device)
        return CertifiedResiduals(model, equation, np.asarray(residuals)[:, :len(fit.sensors)], r.pitch_deg,
                                  r.roll_deg, r.units, fit.sensors)
    mis, model, equation = stated
    pitch, roll, y, u = (np.radians(a) for a in (r.pitch_deg, r.roll_deg, r.y_deg, r.u_deg))
    g = gravity(pitch, roll, y, u, mis)
    X = cert.coefficients
    return CertifiedResiduals(model, equation, r.volts[:, :3] - X[0] - g @ X[1:], r.pitch_deg, r.roll_deg,
                              r.units)


def _shown(conn: Connection, run_id: int, cert: Certificate | None) -> tuple[CertifiedResiduals, str] | None:
    """What the plot shows and its heading: the certificate's model, else the linear fit of the
    readings so far."""
    certified = None if cert is None else certified_residuals(conn, run_id, cert)
    if certified is not None:
        return certified, (f"Run {run_id}: residuals of the {certified.model} its certificate states "
                           f"({cert.number if cert else ''})")
    found = readings(conn, run_id)
    if found is None:
        return None
    try:
        fit = fit_readings(found)
    except LabcalError:
        return None
    linear = CertifiedResiduals("linear model", "V = B + gᵀS", fit.ls.residuals[:, :len(fit.sensors)],
                                found.pitch_deg, found.roll_deg, found.units, fit.sensors)
    return linear, (f"Run {run_id}: residuals of the linear fit (V = B + gᵀS) to the {len(found)} "
                    "readings so far (no certificate yet)")


def _draw(conn: Connection, run_id: int, cert: Certificate | None) -> bytes | None:
    shown = _shown(conn, run_id, cert)
    if shown is None:
        return None
    found, heading = shown
    matplotlib.use("Agg")
    fig = figure.Figure(figsize=(9, 6.5 * (len(found.sensors) + 0.5) / 3.5), dpi=100, layout="constrained")
    axes = fig.subplots(len(found.sensors), 2, sharex="col", squeeze=False)
    residuals = np.asarray(found.residuals, dtype=float)
    rms = np.sqrt(np.mean(residuals**2, axis=0))
    for j, sensor in enumerate(found.sensors):
        factor, unit = report_figures.volt_unit(float(np.max(np.abs(residuals[:, j]))), found.unit)
        for k, (angle, label) in enumerate(((found.pitch_deg, "pitch (°)"), (found.roll_deg, "roll (°)"))):
            ax = axes[j, k]
            ax.axhline(0.0, color="#888", lw=0.8)
            ax.plot(angle, residuals[:, j] * factor, "o", ms=3, color="#1f5f99")
            ax.set_ylabel(f"{sensor}: residual ({unit})" if k == 0 else "")
            ax.grid(True, lw=0.3)
            if j == len(found.sensors) - 1:
                ax.set_xlabel(label)
        axes[j, 1].set_title(f"RMS {rms[j] * factor:.3g} {unit}", fontsize=9, loc="right")
    fig.suptitle(heading, fontsize=10)
    out = io.BytesIO()
    fig.savefig(out, format="png")
    return out.getvalue()
