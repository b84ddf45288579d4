"""The device model in a run's documents: the calibration device's misalignments with U,
the instrument's intrinsic parameters, and the residuals of the linear and the device model side by
side. Kept apart from the certificate's own tables so that the certificate can change without it:
`labcal.documents.report` appends these where a run's plan identifies the device.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.fit import SENSORS
from labcal.lazy import lazy
from labcal.store.record import RunRecord

if TYPE_CHECKING:  # matplotlib only where a figure is drawn: a run stores device.json without it
    from matplotlib import figure
    from matplotlib.figure import Figure
else:
    figure = lazy("matplotlib.figure")  # start-up without matplotlib, numpy

TITLE_Y = 1.0  # titles at a fixed height, as the report's figures have them (labcal.documents.report_figures)

DEVICE_JSON = "device.json"


def device_document(fit: DeviceFit, device_id: str) -> dict[str, Any]:
    """What the run says about the calibration device and the instrument's intrinsic parameters."""
    doc = fit.to_json()
    return {"device_id": device_id, "misalignments": doc["misalignments"],
            "coverage_factor_95": doc["coverage_factor_95"], "degrees_of_freedom": doc["degrees_of_freedom"],
            "intrinsic": doc["intrinsic"], "identifiability": doc["identifiability"],
            "misalignment_test": doc["misalignment_test"],
            "residual_standard_error": {"linear": doc["residual_standard_error_linear"],
                                        "device": doc["residual_standard_error"]},
            "coefficients_device_model": doc["coefficients"],
            "standard_errors_device_model": doc["standard_errors"]}


def device_rows(fit: DeviceFit) -> list[tuple[str, list[str], list[list[str]], str]]:
    """(title, header, rows, caption) of the device's tables, for any renderer."""
    doc = fit.to_json()
    k = doc["coverage_factor_95"]
    mis = [[n, f"{m['value_arcsec']:+.2f}", f"{m['u_arcsec']:.2f}", f"{m['U_arcsec']:.2f}"]
           for n, m in doc["misalignments"].items()]
    test = doc["misalignment_test"]
    se = zip(SENSORS, doc["residual_standard_error_linear"], doc["residual_standard_error"], strict=True)
    mis_caption = (f"Estimated with the instrument (device model, Soto eq. 11); U = k·u with k = {k:.3g} "
                   f"({doc['degrees_of_freedom']} df). F test of the six against the linear model: "
                   f"F = {test['F']:.3g}, df {tuple(test['df'])}, p = {test['p_value']:.2g}. Residual "
                   "standard error linear → device (V): "
                   + ", ".join(f"{s} {a:.3g} → {b:.3g}" for s, a, b in se))
    intrinsic = doc["intrinsic"]
    rows = [[f"|s_{s}| (V/g)", f"{v['value']:.9f}", f"{v['u']:.2g}"]
            for s, v in intrinsic["sensitivity_v_per_g"].items()]
    rows += [[f"angle {p} − 90° (″)", f"{v['deviation_from_90_arcsec']:+.2f}", f"{v['u_arcsec']:.2g}"]
             for p, v in intrinsic["inter_axis_angle_deg"].items()]
    return [("Calibration-device misalignments", ["misalignment", "value (″)", "u (″)", "U (″)"], mis,
             mis_caption),
            ("Intrinsic parameters of the instrument (independent of the mount)", ["parameter", "value", "u"],
             rows, "Sensitivity: column norm of S; inter-axis angle: from SᵀS; first-order uncertainties "
                   "from the device model's covariance.")]


def residuals_side_by_side(fit: DeviceFit, record: RunRecord) -> Figure:
    """Residuals against pitch and roll, linear model beside device model, per sensor (µV)."""
    r = record.readings
    fig = figure.Figure(figsize=(11, 10))
    fig.subplots_adjust(left=0.08, right=0.98, top=0.92, bottom=0.06, hspace=0.42, wspace=0.25)
    axes = fig.subplots(3, 4, squeeze=False, sharex="col", sharey="row")  # ticks once per column and row
    models = (("linear", fit.linear.ls.residuals), ("device", fit.residuals))
    for j, sensor in enumerate(SENSORS):
        for col, ((name, resid), (angle, label)) in enumerate(
                (m, a) for a in ((r.pitch_deg, "pitch"), (r.roll_deg, "roll")) for m in models):
            ax = axes[j, col]
            ax.plot(angle, resid[:, j] * 1e6, "o", ms=3)
            ax.axhline(0.0, color="k", lw=0.6)
            ax.set_title(f"{sensor}: {name} model vs {label}", fontsize=9, y=TITLE_Y)
            if j == len(SENSORS) - 1:
                ax.set_xlabel(f"table {label} (°)")
            ax.grid(alpha=0.3)
        axes[j, 0].set_ylabel(f"residual v_{sensor} (µV)")
        lim = np.max(np.abs(fit.linear.ls.residuals[:, j])) * 1.1e6
        axes[j, 0].set_ylim(-lim, lim)  # the row's
    fig.suptitle("Residuals of the linear model and of the device model (same scale per sensor)")
    return fig
