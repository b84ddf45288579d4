"""The calibration report: one self-contained HTML file and a PDF, built from a certificate.

The report shows what the certificate states and the evidence behind it: per sensor, residuals
against pitch and roll with 95 % confidence and prediction bands (as Tripp & Tcheng figs. 44–49),
the errors of pitch and roll inferred from every calibration reading, where the plan's points lie
on the gravity sphere, and the attitude uncertainty across the usage envelope. Tables are built
once and rendered three ways (HTML, PDF text, terminal), so every output says the same thing.
Plots use matplotlib's object API (no pyplot state, no display needed). Each figure is drawn once,
into an image that both the HTML and the PDF carry: drawing (text layout above all) is most of a
report's cost, and drawing each twice, as PNG and again as vectors, doubled it. matplotlib is
imported when the figures are drawn, not by a run that writes no report.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from labcal.analysis.attitude import sphere_least_squares
from labcal.analysis.device_fit import DeviceFit, preferred_fit
from labcal.analysis.fit import ROW_NAMES, SENSORS, Fit, fit_readings
from labcal.analysis.kinematics import NO_MISALIGNMENT, Misalignment, Mount, gravity
from labcal.analysis.models import Points
from labcal.config.files import write_atomic
from labcal.config.settings import CertificateSettings
from labcal.config.station import stated_angle_errors
from labcal.config.uncertainty import overdue_standards as overdue
from labcal.documents.administration import ItemGiven
from labcal.documents.certificate import (
    Certificate,
    format_result,
    format_uncertainty,
    read_certificate,
    write_certificate,
)
from labcal.documents.device_history import store_device_estimate
from labcal.documents.issuing import (
    build_certificate,
    changed_fields,
    envelope_grid,
    identification,
    kept_identification,
)
from labcal.documents.uncertainty import bench_section, type_b_inputs
from labcal.errors import LabcalError
from labcal.run.record import RunRecord, load_run

if TYPE_CHECKING:
    from matplotlib.figure import Figure

CERTIFICATE = "certificate.json"
SIMULATED_WORD = "SIMULATED"  # heads every page of a dry run's report (its notice says why)
REPORT_HTML = "report.html"
REPORT_PDF = "report.pdf"
UNITS = ("V", "V/g", "V/g", "V/g")
MOUNT_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red")
# Fixed margins: a layout engine would double the drawing time of every figure.
DODGE_DEG = 3.0
# Titles at a fixed height (just above the axes, where matplotlib puts them when nothing is drawn on
# top): placing them automatically measured every tick label of every panel, a quarter of drawing.
TITLE_Y = 1.0
WIDE = {"left": 0.08, "right": 0.98, "top": 0.84, "bottom": 0.13, "wspace": 0.25}


# --- tables: built once, rendered as HTML, PDF text and terminal ----------------------------------
@dataclass(frozen=True)
class Table:
    title: str
    header: list[str]
    rows: list[list[str]]
    caption: str = ""
    emphasis: set[tuple[int, int]] = field(default_factory=set)  # (row, column) cells that fail


def _g(x: float | None, spec: str = ".3g") -> str:
    return "—" if x is None else format(x, spec)


def identification_table(cert: Certificate) -> Table:
    env, plan, data = cert.environment, cert.plan, cert.data
    temperature = ("not recorded" if env.temperature_c_min is None else
                   f"{env.temperature_c_min:.2f} … {env.temperature_c_max:.2f} °C "
                   f"(mean {env.temperature_c_mean:.2f} °C)")
    rows = [
        ["certificate", cert.certificate_id],
        ["laboratory", cert.laboratory or "not stated"],
        ["instrument serial", cert.instrument.serial + (f" ({cert.instrument.description})"
                                                        if cert.instrument.description else "")],
        ["calibration device", cert.station.description + (" (simulated: a dry run, not a calibration "
                                                           "of a real instrument)" if cert.station.simulated
                                                           else "")],
        ["operator", cert.operator or "not recorded"],
        ["calibrated (UTC)", cert.calibrated_utc.isoformat()],
        ["issued (UTC)", cert.issued_utc.isoformat()],
        ["plan", f"{plan.name}: {len(plan.points)} points × {len(plan.mounts)} mount(s) × "
                 f"{plan.replicates} replicate(s); sha256 {plan.sha256[:16]}…"],
        ["readings", f"{data.n_points} points in {data.replicates} replicate(s); sha256 "
                     f"{data.readings_sha256[:16]}…"],
        ["temperature", temperature],
        ["software", f"labcal {cert.labcal_version}"],
    ]
    rows[0] = ["certificate", cert.number + (f", replacing {cert.replaces}" if cert.replaces else "")]
    a = cert.administration
    if a is not None:
        lab = ", ".join(p for p in (a.laboratory.name, a.laboratory.address) if p) or "not stated"
        rows[1] = ["laboratory", lab + (f"; accreditation {a.laboratory.accreditation_id}"
                                        if a.laboratory.accreditation_id else "")]
        item = " ".join(p for p in (a.item.manufacturer, a.item.model) if p)
        rows[2:2] = [["customer", a.customer or "not stated"],
                     ["item", f"{item or 'instrument'}, serial {a.item.serial}; received "
                              f"{a.item.received.isoformat() if a.item.received else 'date not recorded'}"]]
        rows += [["equipment", "; ".join(f"{e.role}: {e.description} ({e.reported()})"
                                         for e in a.equipment)],
                 ["traceability", "; ".join(f"{t.equipment} {t.identity}: certificate {t.certificate} "
                                            f"({t.issued_by}), due {t.due.isoformat()}"
                                            for t in a.traceability)
                  or "no reference standards recorded (station file [[traceability]])"],
                 ["ambient conditions", a.ambient]]
    rows.append(["approval", _status(cert)])
    return Table("Identification", ["item", "value"], rows)


def verdict_text(cert: Certificate) -> str:
    if cert.conformity is None:
        return "no statement of conformity: no tolerance was given"
    return "PASS" if cert.conformity.passed else "FAIL"


def conformity_table(cert: Certificate) -> Table:
    c = cert.conformity
    if c is None:
        return Table("Statement of conformity", ["verdict"], [[verdict_text(cert)]],
                     "Give --tolerance-deg (and optionally --bias-max-v) or a [certificate] section in the "
                     "station file.")
    rows = [[k.quantity, f"{format_uncertainty(k.value)} {k.unit}", f"{k.limit:g} {k.unit}",
             "pass" if k.passed else "FAIL"] for k in c.checks]
    emphasis = {(i, 3) for i, k in enumerate(c.checks) if not k.passed}
    return Table(f"Statement of conformity: {verdict_text(cert)}", ["quantity", "value", "limit", "result"],
                 rows, f"Decision rule: {c.decision_rule}", emphasis)


def attitude_table(cert: Certificate) -> Table:
    a = cert.attitude
    def where(at): return "—" if at is None else f"pitch {at[0]:g}°, roll {at[1]:g}°"
    def deg(u): return "undefined" if u is None else f"{format_uncertainty(u)}°"
    rows = [["pitch", deg(a.pitch_U95_max_deg), where(a.pitch_U95_max_at_deg), deg(a.pitch_U95_rms_deg)],
            ["roll", deg(a.roll_U95_max_deg), where(a.roll_U95_max_at_deg), deg(a.roll_U95_rms_deg)]]
    cf = a.closed_form
    if cf is not None:
        rows += [["pitch, closed form", deg(cf.pitch_U95_max_deg), where(cf.pitch_U95_max_at_deg),
                  deg(cf.pitch_U95_rms_deg)],
                 ["roll, closed form", deg(cf.roll_U95_max_deg), where(cf.roll_U95_max_at_deg),
                  deg(cf.roll_U95_rms_deg)]]
    (p0, p1), (r0, r1) = a.usage_pitch_deg, a.usage_roll_deg
    caption = (f"Over pitch {p0:g}…{p1:g}° × roll {r0:g}…{r1:g}° in {a.grid_step_deg:g}° steps "
               f"({a.grid_points} attitudes); "
               f"{a.method}; k = {a.k:.2f}.")
    if a.roll_undefined_points:
        caption += f" Roll is undefined at {a.roll_undefined_points} attitude(s) near pitch ±90°."
    if cf is not None:
        caption += f" {cf.statement}"
    return Table("Attitude uncertainty (95 %) over the usage envelope", ["angle", "largest U95", "at",
                                                                          "RMS of U95"], rows, caption)


def coefficients_with_expanded_uncertainty(cert: Certificate) -> Table:
    """The certified coefficients ± U95 (the terminal's fit table,
    `labcal.commands.console.coefficients_with_standard_errors`, states ± one standard error)."""
    X, U = cert.coefficients, cert.U
    e = cert.expanded_uncertainty
    unit = cert.output_unit
    units = UNITS if unit == "V" else (unit, *[f"{unit}/g"] * 3)
    rows = [[f"{name} ({unit})", *(format_result(X[i, j], U[i, j]) for j in range(3))]
            for i, (name, unit) in enumerate(zip(ROW_NAMES, units, strict=True))]
    rows.append([f"S_E ({unit})", *(format_uncertainty(s) for s in cert.fit.residual_standard_error)])
    rows.append(["k", *(f"{k:.2f}" for k in e.k)])
    rows.append(["ν_eff", *(str(n) for n in e.nu_eff)])
    rows.append(["basis of u", *cert.fit.uncertainty_basis])
    return Table("Coefficients X = [Bᵀ; S] with expanded uncertainty (y ± U)",
                 ["coefficient", *(f"sensor {s}" for s in SENSORS)], rows, e.statement)


def replication_table(cert: Certificate) -> Table:
    rep = cert.fit.replication
    header = ["sensor", "σ_prec (V)", "σ_bias (V)", "lack of fit F (df)", "F crit 95 %", "p",
              "offset drift F (p)", "sensitivity drift F (p)"]
    if rep is None:
        return Table("Replication and lack of fit (Tripp & Tcheng Table 2)", ["analysis"],
                     [["not available: one replicate"]], "Precision and bias cannot be separated and drift "
                     "cannot be tested without replicates.")
    rows, emphasis = [], set()
    for i, (sensor, r) in enumerate(rep.items()):
        lof = r["lack_of_fit"]

        def drift(name: str, col: int, r=r, i=i) -> str:
            t = r["drift"].get(name)
            if t is None:
                return "—"
            if t["significant"]:
                emphasis.add((i, col))
            return f"{t['F']:.3g} ({t['p_value']:.2g})"
        if lof["significant"]:
            emphasis.add((i, 3))
        rows.append([sensor, _g(r["sigma_prec"]), _g(r["sigma_bias"]), f"{lof['F']:.3g} {tuple(lof['df'])}",
                     f"{lof['critical_95']:.3g}", f"{lof['p_value']:.2g}", drift("offset", 6),
                     drift("sensitivity", 7)])
    first = next(iter(rep.values()))
    return Table("Replication and lack of fit (Tripp & Tcheng Table 2)", header, rows,
                 f"{first['distinct_points']} distinct points × {first['replicates']} replicates; "
                 "highlighted: significant at 5 %.", emphasis)


def audit_table(cert: Certificate) -> Table:
    a = cert.plan_audit
    rows = [[name, f"{m.bias_max:.2e}", f"{m.off_diagonal_max:.2e}", f"{m.diagonal_max:.2e}",
             "yes" if m.cancelled else "no"] for name, m in a.misalignments.items()]
    return Table("Plan audit: leakage of calibration-device misalignments (Soto §7)",
                 ["misalignment", "max |∂B| per rad", "max |∂S off-diag.| per rad", "max |∂S diag.| per rad",
                  "cancelled in B and off-diag. S"], rows,
                 f"First-order change of the coefficients of an ideal instrument (B = 0, S = I) per radian "
                 f"of each misalignment; zero below {a.zero_below:g}. Box figure of merit over the usage "
                 f"pitch range: V_R^½ = {a.figure_of_merit_usage_sqrt:.4f}.")


def _arcsec(x: float | None) -> str:
    """Arcseconds to three digits; rounding noise (what a plan cancels exactly) shows as 0."""
    return "—" if x is None else "0" if abs(x) < 1e-9 else f"{x:.3g}"


def budget_table(cert: Certificate) -> Table:
    """The GUM budget: one row per source, its contribution u_i to pitch and roll (arcsec) at the
    envelope's worst point and RMS over the envelope, then the totals (and the Monte Carlo check)."""
    b = cert.uncertainty_budget
    header = ["source", "type", "distribution", "u (own unit)", "c pitch (″/unit)", "pitch u_i worst (″)",
              "pitch u_i RMS (″)", "c roll (″/unit)", "roll u_i worst (″)", "roll u_i RMS (″)", "ν"]
    if b is None:
        return Table("Uncertainty budget", ["budget"], [["not in this certificate (issued before budgets)"]])
    rows = []
    for r in b.rows:
        name = r.source if r.added else f"{r.source} (not added)"
        rows.append([name, r.type, r.distribution, f"{r.standard_uncertainty:.3g} {r.unit}",
                     _arcsec(r.sensitivity_pitch), _arcsec(r.pitch_worst_arcsec), _arcsec(r.pitch_rms_arcsec),
                     _arcsec(r.sensitivity_roll), _arcsec(r.roll_worst_arcsec), _arcsec(r.roll_rms_arcsec),
                     "∞" if r.degrees_of_freedom is None else f"{r.degrees_of_freedom:.0f}"])
    for t in b.totals:
        rows.append([f"{t.angle}: combined u_c at pitch {t.worst_at_deg[0]:g}°, roll {t.worst_at_deg[1]:g}°",
                     "", "", "", "", f"{t.u_c_arcsec:.3g}", "", "", "", "",
                     "∞" if t.nu_eff is None else f"{t.nu_eff:.0f}"])
        rows.append([f"{t.angle}: U95 = k·u_c (k = {t.k:.2f}); RMS over the envelope {t.U95_rms_arcsec:.3g}″",
                     "", "", "", "", f"{t.U95_arcsec:.3g}", "", "", "", "", ""])
    for c in b.monte_carlo or []:
        rows.append([f"{c.angle}: Monte Carlo U95 ({c.trials} trials, JCGM 101)", "", "", "", "",
                     f"{c.monte_carlo_U95_arcsec:.3g}", "", "", "", "",
                     "agrees" if c.agree_within_5_percent else "differs > 5 %"])
    notes = " ".join(f"{r.source}: {r.note}." for r in b.rows if r.note)
    return Table("Uncertainty budget of inferred pitch and roll (GUM)", header, rows,
                 f"{b.statement} {notes} {b.method}")


def story_table(cert: Certificate) -> Table:
    """The journal's story: faults, retries, wrong mounts, pauses, resumes and the operator's answers."""
    s = cert.story
    title = "What happened during the run (from the journal)"
    if s is None:
        return Table(title, ["events"], [["not in this certificate (issued before the story was recorded)"]])
    rows = [[e.utc.replace("T", " ")[:23], "—" if e.station_time_s is None else f"{e.station_time_s:.1f}",
             e.kind, e.message] for e in s.events]
    emphasis = {(i, 2) for i, e in enumerate(s.events) if e.kind == "fault"}
    counts = ", ".join(f"{n} {kind}" for kind, n in s.counts.items()) or "no events"
    caption = f"{counts}." + (f" {s.omitted} later event(s) not listed; the journal keeps them."
                              if s.omitted else "")
    return Table(title, ["time (UTC)", "rig time (s)", "kind", "what"], rows or [["—", "—", "—", "nothing"]],
                 caption, emphasis)


def tables(cert: Certificate) -> list[Table]:
    return [identification_table(cert), conformity_table(cert), attitude_table(cert), budget_table(cert),
            coefficients_with_expanded_uncertainty(cert), replication_table(cert), audit_table(cert),
            story_table(cert)]


# --- figures ----------------------------------------------------------------------------------
def _mount_masks(record: RunRecord) -> list[tuple[Mount, np.ndarray]]:
    r = record.readings
    return [(m, (r.y_deg % 360 == m.y_deg % 360) & (r.u_deg % 360 == m.u_deg % 360))
            for m in record.plan.mount_list]


def volt_unit(v: float, unit: str = "V") -> tuple[float, str]:
    """The factor and unit a reading of size ``v`` (in the readings' ``unit``) reads best in: µV
    below 1 mV, mV below 1 V, else V; outputs in another unit (counts, m/s2) stay in it."""
    if unit not in ("V", "mV"):
        return 1.0, unit
    to_v = 1e-3 if unit == "mV" else 1.0
    a = abs(v) * to_v
    factor, shown = (1e6, "µV") if a < 1e-3 else (1e3, "mV") if a < 1.0 else (1.0, "V")
    return factor * to_v, shown


def in_volts(v: float, unit: str = "V") -> str:
    factor, shown = volt_unit(v, unit)
    return f"{v * factor:.3g} {shown}"


def certified_residuals(fit: Fit, device: DeviceFit | None) -> tuple[str, str, np.ndarray]:
    """The model the certificate states (its name, its equation) and every reading's residual (K×3,
    V) under it: the device model where the certificate is built on it (`fitted`), else the linear fit."""
    if device is not None:
        return ("device model", "V = B + g(p, r, y, u; a, b, d, e, f, k)ᵀS, Soto eq. 11, the calibration "
                "device's six misalignments fitted", device.residuals)
    extended = f" extended by {', '.join(fit.model.extensions)}" if fit.model.extensions else ""
    return f"linear model{extended}", "V = B + gᵀS on nominal gravity", fit.ls.residuals


def residual_heading(fit: Fit, device: DeviceFit | None, unit: str = "V") -> str:
    """The residual figure's heading: the model the certificate states and each sensor's residual RMS
    (``unit``: the readings' unit)."""
    name, equation, resid = certified_residuals(fit, device)
    rms = np.sqrt(np.mean(resid**2, axis=0))
    each = ", ".join(f"{s} {in_volts(float(v), unit)}" for s, v in zip(SENSORS, rms, strict=True))
    return (f"Residuals per sensor of the {name} ({equation}), with 95 % confidence and prediction bands; "
            f"residual RMS {each}")


def _bands(fit: Fit, device: DeviceFit | None, dense: np.ndarray, col: int) -> tuple[np.ndarray, np.ndarray]:
    """95 % prediction and confidence half-widths (n×3, V) of one reading along ``dense`` (pitch
    when ``col`` is 0, else roll) at the other angle 0°, top-forward mount, under the stated model:
    for the device model, first-order through its complete covariance, k = t₀.₉₇₅(ν)."""
    if device is None:
        at = Points.at(dense, 0.0, temp_c=fit.model.t_ref) if col == 0 else \
            Points.at(0.0, dense, temp_c=fit.model.t_ref)
        bands = fit.predict(at, 0.95)
        return bands["prediction"], bands["confidence"]
    from labcal.analysis.device_model import Geometry, jacobian

    zero = np.zeros_like(dense)
    where = Geometry.from_degrees(dense, zero, zero, zero) if col == 0 else \
        Geometry.from_degrees(zero, dense, zero, zero)
    _, jac = jacobian(device.theta, where)
    var_mean = np.einsum("ijp,pq,ijq->ij", jac, device.covariance, jac)
    k = device.k95
    return k * np.sqrt(var_mean + device.reading_sd()[None, :] ** 2), k * np.sqrt(var_mean)


def residual_figure(fit: Fit, record: RunRecord, device: DeviceFit | None = None) -> Figure:
    """Residuals of the model the certificate states against table pitch and roll, per sensor, with
    the 95 % bands of a reading taken at the other angle 0°, top-forward mount (Tripp & Tcheng figs.
    44, 47); each sensor in µV, mV or V by the size of what is drawn."""
    from matplotlib.figure import Figure

    r = record.readings
    name, equation, resid = certified_residuals(fit, device)
    fig = Figure(figsize=(11, 10))
    fig.subplots_adjust(left=0.08, right=0.98, top=0.90, bottom=0.06, hspace=0.42, wspace=0.22)
    axes = fig.subplots(3, 2, squeeze=False)
    rms = np.sqrt(np.mean(resid**2, axis=0))
    for col, (angle, label) in enumerate(((r.pitch_deg, "pitch α"), (r.roll_deg, "roll R"))):
        dense = np.linspace(angle.min(), angle.max(), 361)
        prediction, confidence = _bands(fit, device, dense, col)
        for j, sensor in enumerate(SENSORS):
            factor, unit = volt_unit(max(float(np.max(np.abs(resid[:, j]))), float(np.max(prediction[:, j]))),
                                     r.units)
            ax = axes[j, col]
            pred, conf = prediction[:, j] * factor, confidence[:, j] * factor
            ax.fill_between(dense, -pred, pred, color="0.85", label="95 % prediction band")
            ax.fill_between(dense, -conf, conf, color="0.65", label="95 % confidence band")
            for (mount, mask), colour in zip(_mount_masks(record), MOUNT_COLOURS, strict=False):
                ax.plot(angle[mask], resid[mask, j] * factor, "o", ms=4, color=colour, label=f"mount {mount}")
            ax.axhline(0.0, color="k", lw=0.6)
            ax.set_xlabel(f"table {label} (°)")
            ax.set_ylabel(f"residual v_{sensor} − v̂_{sensor} ({unit})")
            ax.set_title(f"sensor {sensor}: residuals against {label.split()[0]}; RMS "
                         f"{in_volts(float(rms[j]), r.units)}", y=TITLE_Y)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"Residuals of the {name} the certificate states ({equation});\nbands for one reading at "
                 "the other angle 0°, top-forward mount", fontsize=10)
    return fig


NO_ROLL = 1e-9  # |(g_y, g_z)| below which the nominal attitude is at a pole (pitch ±90°)


def inferred_attitude(cert: Certificate, record: RunRecord) -> dict[str, np.ndarray]:
    """Pitch and roll inferred from every calibration reading against the attitude the instrument
    had: the table angles mapped through the mount and, where the certificate is built on the device
    model, through the device's estimated misalignments (its coefficients are corrected for them, so
    the nominal attitude would show the device's own error), in degrees."""
    r = record.readings
    p, q, y, u = (np.radians(a) for a in (r.pitch_deg, r.roll_deg, r.y_deg, r.u_deg))
    device = NO_MISALIGNMENT if cert.device is None else Misalignment.from_degrees(
        **{name: m.value_arcsec / 3600.0 for name, m in cert.device.misalignments.items()})
    g = gravity(p, q, y, u, device)
    nominal_pitch = np.degrees(np.arcsin(np.clip(g[:, 0], -1, 1)))
    nominal_roll = np.degrees(np.arctan2(g[:, 1], g[:, 2]))
    att = sphere_least_squares(cert.calibration(), record.readings.volts)
    roll_error = (np.degrees(att.roll) - nominal_roll + 180.0) % 360.0 - 180.0
    # At pitch ±90° the attitude has no roll: the reading's roll (finite wherever the device's
    # misalignments tilt gravity off the pole) has nothing to be compared with
    nominal = gravity(p, q, y, u)
    roll_error[np.hypot(nominal[:, 1], nominal[:, 2]) < NO_ROLL] = np.nan
    return {"nominal_pitch": nominal_pitch, "nominal_roll": nominal_roll,
            "pitch_error": np.degrees(att.pitch) - nominal_pitch, "roll_error": roll_error,
            "U95_pitch": np.degrees(att.U_pitch), "U95_roll": np.degrees(att.U_roll)}


def attitude_error_figure(cert: Certificate, record: RunRecord) -> Figure:
    """Errors of inferred pitch and roll with their U95 (Tripp & Tcheng figs. 45–46, 48–49)."""
    from matplotlib.figure import Figure

    e = inferred_attitude(cert, record)
    fig = Figure(figsize=(11, 4.5))
    fig.subplots_adjust(**WIDE)
    axes = fig.subplots(1, 2)
    masks = _mount_masks(record)
    for ax, angle in zip(axes, ("pitch", "roll"), strict=True):
        defined = np.isfinite(e[f"{angle}_error"])
        for k, ((mount, mask), colour) in enumerate(zip(masks, MOUNT_COLOURS, strict=False)):
            m = mask & defined
            dodge = (k - (len(masks) - 1) / 2) * DODGE_DEG  # mounts side by side, not on top of each other
            ax.errorbar(e[f"nominal_{angle}"][m] + dodge, e[f"{angle}_error"][m], yerr=e[f"U95_{angle}"][m],
                        fmt="o", ms=4, capsize=2, color=colour, label=f"mount {mount}")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel(f"nominal {angle} of the instrument (°; mounts offset by {DODGE_DEG:g}° to stay apart)")
        ax.set_ylabel(f"inferred − nominal {angle} (°)")
        ax.ticklabel_format(axis="y", style="plain", useOffset=False)
        title = f"{angle} error, error bars U95"
        if not defined.all():
            title += f" ({int((~defined).sum())} points at pitch ±90° have no roll)"
        ax.set_title(title, fontsize=10, y=TITLE_Y)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Attitude inferred from each calibration reading (least squares on the sphere)")
    return fig


def sphere_figure(record: RunRecord) -> Figure:
    """Where the plan's points lie on the unit gravity sphere, in the instrument's axes, per mount."""
    import mpl_toolkits.mplot3d  # noqa: F401 - registers the 3-D projection
    from matplotlib.figure import Figure

    plan = record.plan
    g = plan.nominal_gravity().reshape(len(plan.mounts), len(plan.points), 3)
    fig = Figure(figsize=(7, 6.5))
    ax = fig.add_subplot(projection="3d")
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 37), np.linspace(0, np.pi, 19))
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.8", lw=0.4)
    markers = ("o", "s", "^", "D")
    for k, (mount, colour) in enumerate(zip(plan.mount_list, MOUNT_COLOURS, strict=False)):
        ax.scatter(*g[k].T, s=40 - 8 * k, marker=markers[k % 4], color=colour, depthshade=False,
                   label=f"mount {mount}")
    directions, counts = np.unique(np.round(g.reshape(-1, 3), 6), axis=0, return_counts=True)
    for d, n in zip(directions, counts * plan.replicates, strict=True):
        ax.text(*(1.18 * d), f"{n}", fontsize=8, ha="center")  # readings that share this direction
    ax.set_xlabel("g_x (g)")
    ax.set_ylabel("g_y (g)")
    ax.set_zlabel("g_z (g)")
    ax.set_box_aspect((1, 1, 1))
    ax.set_title(f"Plan {plan.name}: nominal gravity of every point in the instrument's axes\n"
                 "(numbers: readings in each direction, replicates included)", fontsize=10,
                 parse_math=False)  # a plan's name is drawn as written, never read as mathtext
    ax.legend(fontsize=7, loc="upper left")
    return fig


def envelope_figure(cert: Certificate) -> Figure:
    """U95 of inferred pitch and roll against pitch over the usage envelope (largest and RMS over roll)."""
    from matplotlib.figure import Figure

    a = cert.attitude
    settings = CertificateSettings(usage_pitch_deg=a.usage_pitch_deg, usage_roll_deg=a.usage_roll_deg,
                                   grid_step_deg=a.grid_step_deg)
    env = envelope_grid(cert.calibration(), settings)
    tolerance = next((c.limit for c in (cert.conformity.checks if cert.conformity else []) if c.unit == "°"),
                     None)
    fig = Figure(figsize=(11, 4.5))
    fig.subplots_adjust(**WIDE)
    axes = fig.subplots(1, 2)
    for ax, angle, values in zip(axes, ("pitch", "roll"), (env.u95_pitch_deg, env.u95_roll_deg), strict=True):
        defined = np.isfinite(values).any(axis=1)  # at pitch ±90° no roll exists
        largest, rms = np.full((2, len(env.pitch_deg)), np.nan)
        largest[defined] = np.nanmax(values[defined], axis=1)
        rms[defined] = np.sqrt(np.nanmean(values[defined] ** 2, axis=1))
        ax.plot(env.pitch_deg, largest, "-o", ms=3, label="largest over roll")
        ax.plot(env.pitch_deg, rms, "--", label="RMS over roll")
        if tolerance is not None:
            ax.axhline(tolerance, color="tab:red", lw=1, label=f"tolerance {tolerance:g}°")
        ax.set_xlabel("pitch of the instrument (°)")
        ax.set_ylabel(f"U95 of inferred {angle} (°)")
        ax.set_title(f"{angle}: 95 % expanded uncertainty", fontsize=10, y=TITLE_Y)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"Attitude uncertainty over the usage envelope (roll {a.usage_roll_deg[0]:g}…"
                 f"{a.usage_roll_deg[1]:g}°, one new reading)")
    return fig


def figures(cert: Certificate, record: RunRecord, fit: Fit, device: DeviceFit | None = None
            ) -> list[tuple[str, Figure]]:
    """``device``: the device model the certificate rests on (None: the linear fit); the residual
    figure shows that model's residuals, as the certificate states it."""
    return [
        (residual_heading(fit, device, record.readings.units), residual_figure(fit, record, device)),
        ("Errors of the attitude inferred from each calibration reading",
         attitude_error_figure(cert, record)),
        ("Attitude uncertainty over the usage envelope", envelope_figure(cert)),
        ("The plan's points on the gravity sphere", sphere_figure(record)),
    ]


# --- rendering --------------------------------------------------------------------------------
CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;max-width:1100px;margin:2em auto;color:#111;
line-height:1.4}
h1{font-size:1.5em;margin-bottom:0}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #bbb;padding:.25em .6em;text-align:right;font-variant-numeric:tabular-nums}
th:first-child,td:first-child{text-align:left}caption{caption-side:bottom;text-align:left;font-size:.85em;
color:#444;padding-top:.3em}td.fail{background:#fdd;font-weight:bold}
.verdict{font-size:1.3em;font-weight:bold;padding:.3em .6em;display:inline-block;border:2px solid}
.pass{color:#064;border-color:#064}.fail-v{color:#a00;border-color:#a00}.none{color:#555;border-color:#999}
img{max-width:100%}footer{margin-top:2em;font-size:.8em;color:#555;word-break:break-all}
@media print{h2{break-after:avoid}figure{break-inside:avoid}}
"""


def _html_table(t: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in t.header)
    fail = ' class="fail"'
    body = "".join(
        "<tr>" + "".join(f"<td{fail if (i, j) in t.emphasis else ''}>{html.escape(c)}</td>"
                         for j, c in enumerate(row)) + "</tr>"
        for i, row in enumerate(t.rows))
    caption = f"<caption>{html.escape(t.caption)}</caption>" if t.caption else ""
    return (f"<h2>{html.escape(t.title)}</h2><table>{caption}<thead><tr>{head}</tr></thead>"
            f"<tbody>{body}</tbody></table>")


FIGURE_DPI = 120  # one raster for the screen and for print (the HTML had 110)


@dataclass(frozen=True)
class DrawnFigure:
    """A figure drawn once: its PNG (RGB; the figure is opaque), for the HTML and the PDF alike."""

    title: str
    size_in: tuple[float, float]
    png: bytes


def draw(title: str, fig: Figure) -> DrawnFigure:
    """One Agg drawing of ``fig``; the PNG is encoded from the same pixels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image  # matplotlib's own image library; its imsave would write RGBA

    fig.set_dpi(FIGURE_DPI)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3]  # no alpha: the PDF takes an RGB PNG as it is
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="png", compress_level=1)  # encoding was a third of it
    return DrawnFigure(title, tuple(fig.get_size_inches()), buf.getvalue())


def _png(fig: DrawnFigure) -> str:
    return base64.b64encode(fig.png).decode("ascii")


def render_html(cert: Certificate, figs: list[DrawnFigure], extra: tuple[Table, ...] = ()) -> str:
    """One HTML file with inline CSS and inline PNG plots: it opens offline and can be mailed alone."""
    verdict = verdict_text(cert)
    css_class = "none" if cert.conformity is None else ("pass" if cert.conformity.passed else "fail-v")
    simulated = f"{SIMULATED_WORD} — " if cert.notice else ""
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{simulated}Calibration "
             f"certificate {html.escape(cert.certificate_id)}</title><style>{CSS}</style></head><body>",
             *([f"<p class=\"verdict fail-v\">{html.escape(cert.notice)}</p>"] if cert.notice else []),
             f"<h1>Calibration certificate and report</h1><p>{html.escape(cert.number)} · "
             f"instrument {html.escape(cert.instrument.serial)} · "
             f"<strong>{html.escape(_status(cert))}</strong></p>"
             f"<p class=\"verdict {css_class}\">{html.escape(verdict)}</p>"]
    parts += [_html_table(t) for t in (*tables(cert), *extra)]
    parts.append("<h2>Method</h2>" + "".join(f"<p>{html.escape(p)}</p>" for p in
                                             (cert.method, *cert.statements, *cert.fit.notes)))
    for fig in figs:
        title = fig.title
        parts.append(f"<h2>{html.escape(title)}</h2><figure><img alt=\"{html.escape(title)}\" "
                     f"src=\"data:image/png;base64,{_png(fig)}\"></figure>")
    parts.append(f"<footer>End of report {html.escape(cert.certificate_id)}. Certificate content sha256 "
                 f"{cert.digest.value} (certificate.json holds the full-precision values and covariances)."
                 "</footer></body></html>")
    return "\n".join(parts)


def _status(cert: Certificate) -> str:
    if cert.approval is None:
        return "DRAFT — not approved"
    a = cert.approval
    return f"approved by {a.by} ({a.role}) on {a.approved_utc:%Y-%m-%d}"


def overdue_standards(cert: Certificate) -> list[str]:
    """Each reference standard whose calibration was due before this calibration was made: said on
    the certificate's first page, not only in the budget (`labcal station check` says it by the same
    function, `labcal.config.uncertainty.overdue_standards`)."""
    if cert.administration is None:
        return []
    return overdue(cert.administration.traceability, cert.calibrated_utc.date())


def render_pdf(cert: Certificate, figs: list[DrawnFigure], extra: tuple[Table, ...] = ()) -> bytes:
    """The certificate typeset (`labcal.documents.typeset`): identification and verdict first, every
    table, the method and statements, the signature block, then one page per figure (its PNG, as
    drawn for the HTML); every page says "page X of Y" and, until it is approved, DRAFT."""
    from labcal.documents.typeset import CertificateDocument, render

    a = cert.approval
    signature = [("Approved by", f"{a.by} ({a.role})" if a else "not yet approved — DRAFT"),
                 ("Date", f"{a.approved_utc:%Y-%m-%d %H:%M} UTC" if a else "—"),
                 ("Electronic signature", f"{a.algorithm}, key {a.key_id[:16]}…" if a else "—"),
                 ("Certificate content", f"sha256 {cert.digest.value}")]
    return render(CertificateDocument(
        heading=f"{SIMULATED_WORD} — Calibration certificate" if cert.notice else "Calibration certificate",
        number=cert.number, status=_status(cert), draft=cert.draft,
        first_lines=[*([cert.notice] if cert.notice else []), verdict_text(cert)],
        alerts=overdue_standards(cert), tables=[*tables(cert), *extra],
        paragraphs=[cert.method, *cert.statements, *cert.fit.notes], figures=figs, signature=signature,
        title=f"Calibration certificate {cert.certificate_id}",
        subject=f"instrument {cert.instrument.serial}"))


def write_report(directory: Path, cert: Certificate, record: RunRecord, fit: Fit,
                 device: DeviceFit | None = None) -> tuple[Path, Path]:
    """``device``: the device model's fit, where the plan identifies it (its tables and residuals are
    appended: `labcal.documents.device_report`). Each figure is drawn once, for the HTML and the PDF."""
    figures_drawn = figures(cert, record, fit, device)
    extra: tuple[Table, ...] = ()
    if device is not None:
        from labcal.documents.device_report import device_rows, residuals_side_by_side

        extra = tuple(Table(*parts) for parts in device_rows(device))
        figures_drawn.append(("Residuals of the linear and of the device model",
                              residuals_side_by_side(device, record)))
    figs = [draw(title, fig) for title, fig in figures_drawn]
    html_path, pdf_path = directory / REPORT_HTML, directory / REPORT_PDF
    write_atomic(html_path, render_html(cert, figs, extra))  # whole or not at all: a kill never cuts a report
    write_atomic(pdf_path, render_pdf(cert, figs, extra))
    return html_path, pdf_path


# --- what a run leaves behind ------------------------------------------------------------------
@dataclass(frozen=True)
class RunOutputs:
    certificate: Certificate
    certificate_path: Path
    html_path: Path
    pdf_path: Path
    database: Path
    notes: tuple[str, ...] = ()  # what checking the run folder against the journal repaired
    dcc_path: Path | None = None
    compared_with: str | None = None  # the certificate this issue replaced in the run directory
    changes: tuple[str, ...] = ()  # its identification fields that differ, in words


def write_run_outputs(run_dir: str | Path, settings: CertificateSettings | None = None, *,
                      serial: str | None = None, operator: str | None = None,
                      db: str | Path | None = None, station: str | Path | None = None,
                      monte_carlo: int = 0, item: ItemGiven | None = None) -> RunOutputs:
    """Certificate, report and history entry of a finished run (called at the end of `labcal run`
    and by `labcal report`); ``db`` None means $LABCAL_DB or the lab file's database. The Type B
    inputs come from ``station`` (a station file), else the station the run was journaled with;
    ``monte_carlo`` trials check the budget by JCGM 101."""
    record = load_run(run_dir)
    fit, device, model_note = fitted(record)
    section = bench_section(record, station)
    inputs = type_b_inputs(section, record, device)
    revision, replaced = 1, None
    previous = _issued(record.directory / CERTIFICATE)
    if previous is not None and previous.approval is not None:
        # An approved certificate is never changed: what follows is a correction, a new revision
        # naming the one it replaces; the approved one stays beside it and in the history.
        revision, replaced = (previous.revision or 1) + 1, previous
        write_file(record.directory / f"certificate.rev{previous.revision or 1}.json", previous)
    elif previous is not None and (previous.revision or 1) > 1:
        # a revision's draft reported again is still that revision, replacing the same approved one
        revision, replaced = previous.revision or 1, replaced_by(record.directory, previous)
    item, serial, operator = kept_identification(previous, item or ItemGiven(), serial, operator)
    cert = build_certificate(record, fit, settings, serial=serial, operator=operator, inputs=inputs,
                             monte_carlo=monte_carlo, revision=revision,
                             replaces=None if replaced is None else replaced.number, section=section,
                             item=item, device=device, model_note=model_note, replaced=replaced)
    outputs = write_documents(cert, record, fit, device, db)
    if previous is None:
        return outputs
    return replace(outputs, compared_with=previous.number,
                   changes=tuple(changed_fields(identification(previous), identification(cert))))


def replaced_by(directory: Path, cert: Certificate) -> Certificate | None:
    """The approved certificate a revision replaces, as kept beside it in the run directory
    (``certificate.revN.json``); None for a first issue."""
    if not cert.replaces:
        return None
    path = directory / f"certificate.rev{(cert.revision or 1) - 1}.json"
    kept = read_certificate(path) if path.is_file() else None
    if kept is None or kept.number != cert.replaces:
        raise LabcalError(f"{path}: the certificate {cert.number} replaces ({cert.replaces}) is not kept "
                          "there")
    return kept


def fitted(record: RunRecord) -> tuple[Fit, DeviceFit | None, str]:
    """The linear fit, the device model where the points identify it, and the note saying which of
    them the run's fit.json holds: those `load_run` derived fit.json from, else fitted here."""
    if record.fit is not None:
        return record.fit, record.device, record.model_note
    fit = fit_readings(record.readings)
    return fit, *preferred_fit(record.readings, fit, stated_angle_errors(record.station_text))


def _issued(path: Path) -> Certificate | None:
    """The certificate already in the run directory, if one is there and reads back intact."""
    if not path.is_file():
        return None
    try:
        return read_certificate(path)
    except LabcalError:
        return None  # a damaged draft is replaced; an approved one would have read back


def write_file(path: Path, cert: Certificate) -> Path:
    """The one place a certificate document is written (atomic replace; see write_certificate)."""
    return write_certificate(path, cert)


def write_documents(cert: Certificate, record: RunRecord, fit: Fit, device: DeviceFit | None,
                    db: str | Path | None = None) -> RunOutputs:
    """Every file an issue (or an approval) writes: certificate, report, history entry — through one
    function, so that making them one transaction changes one place. ``device``: the device model
    the certificate rests on (`fitted`), None where the linear model is used."""
    from labcal.documents import history
    from labcal.documents.dcc import DCC_FILE, write_dcc

    dcc_path = write_dcc(record.directory / DCC_FILE, cert)  # validated first: a bad one stops it all
    html_path, pdf_path = write_report(record.directory, cert, record, fit, device)
    # The history entry and the certificate file go together: the entry is committed first and the
    # file is the entry's document, so a kill between them leaves a history entry without its file
    # (`outputs_in_place` sees it; resume or report writes it again), never a certificate that
    # history does not know.
    database = history.store(cert, db)
    if device is not None:
        store_device_estimate(record, device, db)
    cert_path = write_file(record.directory / CERTIFICATE, cert)
    return RunOutputs(cert, cert_path, html_path, pdf_path, database, notes=record.notes, dcc_path=dcc_path)


def outputs_in_place(run_dir: str | Path, db: str | Path | None = None) -> bool:
    """Whether a complete run's certificate, its report and its history entry are all there and
    are of the run's current readings (after a kill during `labcal report` one may be missing)."""
    from labcal.documents import history
    from labcal.documents.dcc import DCC_FILE

    run_dir = Path(run_dir)
    if not all((run_dir / name).is_file() for name in (CERTIFICATE, DCC_FILE, REPORT_HTML, REPORT_PDF)):
        return False
    try:
        cert = read_certificate(run_dir / CERTIFICATE)
        record = load_run(run_dir)
    except LabcalError:
        return False
    return (cert.data.readings_sha256 == record.readings_sha256
            and history.stored_digest(cert.certificate_id, db) == cert.digest.value)
