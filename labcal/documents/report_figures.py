"""The report's figures, drawn with matplotlib's object API (no pyplot state, no display needed):
per sensor, residuals against pitch and roll with 95 % confidence and prediction bands (as Tripp &
Tcheng figs. 44–49), the errors of pitch and roll inferred from every calibration reading, where the
plan's points lie on the gravity sphere, and the attitude uncertainty across the usage envelope.

Each figure is drawn once, into an image that both the HTML and the PDF carry: drawing (text layout
above all) is most of a report's cost, and drawing each twice, as PNG and again as vectors, doubled
it. matplotlib is imported when the figures are drawn, not by a run that writes no report.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from PIL import Image

from labcal.analysis.attitude import sphere_least_squares
from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.device_model import Geometry, jacobian
from labcal.analysis.fit import SENSORS, Fit
from labcal.analysis.kinematics import NO_MISALIGNMENT, Misalignment, Mount, gravity
from labcal.analysis.models import Points
from labcal.config.settings import CertificateSettings
from labcal.documents.certificate import Certificate
from labcal.documents.issuing import envelope_grid
from labcal.documents.package import region_parts
from labcal.lazy import lazy
from labcal.store.record import RunRecord

if TYPE_CHECKING:
    from matplotlib import figure
    from matplotlib.figure import Figure
else:
    figure = lazy("matplotlib.figure")  # start-up without matplotlib, numpy

MOUNT_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red")
# Fixed margins: a layout engine would double the drawing time of every figure.
DODGE_DEG = 3.0
# Titles at a fixed height (just above the axes, where matplotlib puts them when nothing is drawn on
# top): placing them automatically measured every tick label of every panel, a quarter of drawing.
TITLE_Y = 1.0
WIDE = {"left": 0.08, "right": 0.98, "top": 0.84, "bottom": 0.13, "wspace": 0.25}


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
    each = ", ".join(f"{s} {in_volts(float(v), unit)}" for s, v in zip(fit.sensors, rms, strict=True))
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
    r = record.readings
    name, equation, resid = certified_residuals(fit, device)
    sensors = fit.sensors if device is None else SENSORS  # a package's: the sensors it has
    fig = figure.Figure(figsize=(11, 10 * (len(sensors) + 0.6) / 3.6))
    fig.subplots_adjust(left=0.08, right=0.98, top=0.90, bottom=0.06, hspace=0.42, wspace=0.22)
    # the angle's ticks once, under each column
    axes = fig.subplots(len(sensors), 2, squeeze=False, sharex="col")
    rms = np.sqrt(np.mean(resid**2, axis=0))
    for col, (angle, label) in enumerate(((r.pitch_deg, "pitch α"), (r.roll_deg, "roll R"))):
        dense = np.linspace(angle.min(), angle.max(), 361)
        prediction, confidence = _bands(fit, device, dense, col)
        for j, sensor in enumerate(sensors):
            factor, unit = volt_unit(max(float(np.max(np.abs(resid[:, j]))), float(np.max(prediction[:, j]))),
                                     r.units)
            ax = axes[j, col]
            pred, conf = prediction[:, j] * factor, confidence[:, j] * factor
            ax.fill_between(dense, -pred, pred, color="0.85", label="95 % prediction band")
            ax.fill_between(dense, -conf, conf, color="0.65", label="95 % confidence band")
            for (mount, mask), colour in zip(_mount_masks(record), MOUNT_COLOURS, strict=False):
                ax.plot(angle[mask], resid[mask, j] * factor, "o", ms=4, color=colour, label=f"mount {mount}")
            ax.axhline(0.0, color="k", lw=0.6)
            if j == len(sensors) - 1:
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
    model or a plan's device correction, through the device's misalignments (its coefficients are
    corrected for them, so the nominal attitude would show the device's own error), in degrees."""
    r = record.readings
    p, q, y, u = (np.radians(a) for a in (r.pitch_deg, r.roll_deg, r.y_deg, r.u_deg))
    device = NO_MISALIGNMENT
    if cert.device is not None:
        device = Misalignment.from_degrees(
            **{name: m.value_arcsec / 3600.0 for name, m in cert.device.misalignments.items()})
    elif cert.device_correction is not None:  # a plan's device correction: the fit's gravity had it too
        device = Misalignment.from_degrees(
            **{name: v / 3600.0 for name, v in cert.device_correction.value_arcsec.items()})
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
    e = inferred_attitude(cert, record)
    fig = figure.Figure(figsize=(11, 4.5))
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
    plan = record.plan
    g = plan.nominal_gravity().reshape(len(plan.mounts), len(plan.points), 3)
    fig = figure.Figure(figsize=(7, 6.5))
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
    a = cert.attitude
    settings = CertificateSettings(usage_pitch_deg=a.usage_pitch_deg, usage_roll_deg=a.usage_roll_deg,
                                   grid_step_deg=a.grid_step_deg)
    env = envelope_grid(cert.calibration(), settings)
    tolerance = next((c.limit for c in (cert.conformity.checks if cert.conformity else []) if c.unit == "°"),
                     None)
    fig = figure.Figure(figsize=(11, 4.5))
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


def package_envelope_figure(cert: Certificate, fit: Fit) -> Figure:
    """A package's inferred angles' U95 against pitch over the region its section states (largest
    and RMS over roll), from the same parts as its budget (Tripp & Tcheng eqs. 78, 81, 90, 96)."""
    section = cert.package
    assert section is not None
    parts = region_parts(fit, section)
    pitch_deg = np.degrees(parts.alpha[:, 0])
    angles = {"pitch": parts.pitch} | ({} if parts.roll_sd is None else {"roll": parts.roll_sd})
    fig = figure.Figure(figsize=(5.5 * len(angles), 4.5))
    fig.subplots_adjust(**WIDE)
    axes = np.atleast_1d(fig.subplots(1, len(angles)))
    for ax, (angle, by_source) in zip(axes, angles.items(), strict=True):
        u95 = section.k * np.degrees(np.sqrt(sum(p**2 for p in by_source.values())))
        ax.plot(pitch_deg, u95.max(axis=1), "-o", ms=3, label="largest over roll")
        ax.plot(pitch_deg, np.sqrt(np.mean(u95**2, axis=1)), "--", label="RMS over roll")
        if section.u95_limit_deg is not None:
            ax.axhline(section.u95_limit_deg, color="tab:red", lw=1,
                       label=f"limit {section.u95_limit_deg:g}°")
        ax.set_xlabel("pitch of the package (°)")
        ax.set_ylabel(f"U95 of inferred {angle} (°)")
        ax.set_title(f"{angle}: 95 % expanded uncertainty", fontsize=10, y=TITLE_Y)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    low, high = np.degrees(parts.roll[0, [0, -1]])
    fig.suptitle(f"{section.package}: attitude uncertainty over roll {low:g}…{high:g}° ({section.equations})")
    return fig


def figures(cert: Certificate, record: RunRecord, fit: Fit, device: DeviceFit | None = None
            ) -> list[tuple[str, Figure]]:
    """``device``: the device model the certificate rests on (None: the linear fit); the residual
    figure shows that model's residuals, as the certificate states it. A package's certificate
    shows its own envelope: its angles are not the three-axis estimator's."""
    if cert.package is not None:
        return [(residual_heading(fit, device, record.readings.units), residual_figure(fit, record, device)),
                ("Attitude uncertainty over the region the package section states",
                 package_envelope_figure(cert, fit)),
                ("The plan's points on the gravity sphere", sphere_figure(record))]
    return [
        (residual_heading(fit, device, record.readings.units), residual_figure(fit, record, device)),
        ("Errors of the attitude inferred from each calibration reading",
         attitude_error_figure(cert, record)),
        ("Attitude uncertainty over the usage envelope", envelope_figure(cert)),
        ("The plan's points on the gravity sphere", sphere_figure(record)),
    ]


FIGURE_DPI = 120  # one raster for the screen and for print (the HTML had 110)


@dataclass(frozen=True)
class DrawnFigure:
    """A figure drawn once: its PNG (RGB; the figure is opaque), for the HTML and the PDF alike."""

    title: str
    size_in: tuple[float, float]
    png: bytes


def draw(title: str, fig: Figure) -> DrawnFigure:
    """One Agg drawing of ``fig``; the PNG is encoded from the same pixels."""
    fig.set_dpi(FIGURE_DPI)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3]  # no alpha: the PDF takes an RGB PNG as it is
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="png", compress_level=1)  # encoding was a third of it
    return DrawnFigure(title, tuple(fig.get_size_inches()), buf.getvalue())
