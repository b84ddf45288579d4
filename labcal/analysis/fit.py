"""Fitting the instrument model V = B + gᵀS (Soto eqs. 13–21) with honest statistics.

Every model is a regressor set (`labcal.analysis.models`) solved by the one QR core. Uncertainties
use the residual standard error, or — when replicates show significant lack of fit — the
lack-of-fit mean square, because point biases repeat in every replicate and replication
cannot average them away (metrology_stats.md §2.6).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.distributions import f_isf, f_sf, t_quantile
from labcal.analysis.models import BASE_NAMES, EXTENSIONS, Model, Points
from labcal.analysis.readings import Readings, angle_key
from labcal.analysis.regression import LeastSquares, least_squares, least_squares_of_means
from labcal.analysis.replication import (
    ALPHA,
    NUMERIC_RESOLUTION,
    Replication,
    analyse,
    analyse_points,
    analyse_with_covariates,
    noise_free,
)
from labcal.errors import LabcalError

SENSORS = ("x", "y", "z")
ROW_NAMES = BASE_NAMES


NOISE_FREE = "noise-free readings"  # how the note on readings that fit to rounding begins


def readings_points(readings: Readings, rows: NDArray[np.intp] | None = None) -> Points:
    """Where every reading was taken, or the readings ``rows`` only."""
    if rows is None:
        return Points(readings.pitch_deg, readings.roll_deg, readings.y_deg, readings.u_deg, readings.temp_c)
    return Points(readings.pitch_deg[rows], readings.roll_deg[rows], readings.y_deg[rows],
                  readings.u_deg[rows], None if readings.temp_c is None else readings.temp_c[rows])


def point_keys(readings: Readings) -> NDArray[np.float64]:
    """Identity of each calibration point: mount and table angles modulo 360°."""
    return angle_key(np.column_stack([readings.y_deg, readings.u_deg, readings.pitch_deg, readings.roll_deg]))


@dataclass(frozen=True)
class Fit:
    """Coefficients of every sensor (columns) with the statistics a certificate needs."""

    model: Model
    names: tuple[str, ...]
    ls: LeastSquares
    replication: Replication | None = None
    notes: tuple[str, ...] = field(default=())
    sensors: tuple[str, ...] = SENSORS  # the columns: a package's sensors (Tripp & Tcheng §6)

    # --- coefficients and their uncertainty -------------------------------------------------
    @property
    def coefficients(self) -> NDArray[np.float64]:
        """Soto's X = [Bᵀ; S] (4×3); extension coefficients are in `ls.coef[4:]`."""
        return self.ls.coef[: len(BASE_NAMES)]

    def noise_free(self, readings: Readings) -> NDArray[np.bool_]:
        """Per sensor: the readings fit to floating-point rounding (a simulation without noise)."""
        volts = readings.volts
        if volts.shape[1] != len(self.ls.residual_se):  # a package's readings with every output: its own
            volts = volts[:, [SENSORS.index(s) for s in self.sensors]]
        return noise_free(self.ls.residual_se, np.max(np.abs(volts), axis=0))

    @property
    def bias_significant(self) -> NDArray[np.bool_]:
        if self.replication is None:
            return np.zeros(self.ls.coef.shape[1], dtype=bool)
        return self.replication.lack_of_fit.significant

    @property
    def variance(self) -> NDArray[np.float64]:
        """Per sensor: the variance that scales (FᵀF)⁻¹ into the coefficient covariance."""
        if self.replication is None:
            return self.ls.residual_se**2
        return np.where(self.bias_significant, self.replication.lack_of_fit_ms, self.ls.residual_se**2)

    @property
    def variance_dof(self) -> NDArray[np.int_]:
        dof = np.full(self.ls.coef.shape[1], self.ls.dof)
        if self.replication is not None:
            dof = np.where(self.bias_significant, self.replication.lack_of_fit.df_num, dof)
        return dof

    @property
    def variance_basis(self) -> list[str]:
        return ["lack-of-fit mean square" if b else "residual standard error" for b in self.bias_significant]

    def covariance(self, sensor: int) -> NDArray[np.float64]:
        """Covariance of every coefficient of one sensor (L×L, in `names` order)."""
        return float(self.variance[sensor]) * self.ls.cov_unscaled

    @property
    def stderr(self) -> NDArray[np.float64]:
        return np.sqrt(np.diag(self.ls.cov_unscaled))[:, None] * np.sqrt(self.variance)[None, :]

    # --- the output at new points (Tripp eqs. 52, 72, 73) -------------------------------------
    def new_measurement_variance(self) -> NDArray[np.float64]:
        """Variance of one new reading like the calibration's: σ_prec² + σ_bias², or S_E²."""
        if self.replication is None:
            return self.ls.residual_se**2
        return self.replication.sigma_prec**2 + self.replication.sigma_bias**2

    def predict(self, points: Points, level: float = 0.95) -> dict[str, NDArray[np.float64]]:
        """Predicted output (n×3) with confidence and prediction half-widths at ``level``."""
        _, f = self.model.design(points)
        q = np.einsum("ij,jk,ik->i", f, self.ls.cov_unscaled, f)  # fᵀ R⁻¹ f
        t = t_quantile(0.5 + level / 2, self.variance_dof)
        var_mean = q[:, None] * self.variance[None, :]
        return {
            "volts": f @ self.ls.coef,
            "confidence": t * np.sqrt(var_mean),
            "prediction": t * np.sqrt(var_mean + self.new_measurement_variance()[None, :]),
            "std_normalised": np.sqrt(q),
        }

    def to_json(self) -> dict[str, Any]:
        """The linear fit JSON contract of docs/design.md §5, plus the statistics behind it."""
        n_base = len(BASE_NAMES)
        doc = {
            "model": "linear",
            "coefficients": self.coefficients.tolist(),
            "standard_errors": self.stderr[:n_base].tolist(),
            "residual_standard_error": self.ls.residual_se.tolist(),
            "degrees_of_freedom": self.ls.dof,
            "n_points": self.ls.n_obs,
            "parameters": list(self.names),
            "covariance": [self.covariance(j).tolist() for j in range(len(self.sensors))],
            "uncertainty_basis": self.variance_basis,
            "reading_sd": np.sqrt(self.new_measurement_variance()).tolist(),
            "uncertainty_dof": self.variance_dof.tolist(),
            "layout": {
                "rows": ["B", "S row g_x", "S row g_y", "S row g_z"],
                "columns": [f"sensor {s}" for s in self.sensors],
                "units": "V (bias), V/g (sensitivity)",
            },
        }
        if self.model.extensions:
            doc["extensions"] = {
                "names": list(self.names[n_base:]), "t_ref_c": self.model.t_ref,
                "coefficients": self.ls.coef[n_base:].tolist(),
                "standard_errors": self.stderr[n_base:].tolist(),
            }
        if self.replication is not None:
            doc["replication"] = {s: self.replication.to_json(j) for j, s in enumerate(self.sensors)}
        if self.notes:
            doc["notes"] = list(self.notes)
        return doc


def reference_temperature(readings: Readings) -> float:
    """Where temperature terms are centred: the run's mean temperature (20 °C when none was read)."""
    return float(np.mean(readings.temp_c)) if readings.temp_c is not None else 20.0


def fit_readings(readings: Readings, model: Model | None = None) -> Fit:
    """Least squares on the nominal gravity, with replicated analysis when there are replicates.

    Where every regressor is a function of the calibration point (no temperature term) the fit is
    made on the point means weighted by their counts: the same normal equations (Σ c·f fᵀ = FᵀF,
    Σ c·f v̄ = FᵀV), so the same coefficients and covariance, with a design row per point instead of
    per reading; the residuals are still every reading's.

    A package of fewer than three sensors (Tripp & Tcheng §6.1–6.5) has NaN outputs in the columns of
    the sensors it lacks: each present sensor is fitted alone (v = b + s·g, Tripp eq. 8 in labcal's
    linear form), which is what the multivariate fit does column by column anyway."""
    model = model or Model(t_ref=reference_temperature(readings))
    sensors = present_sensors(readings.volts)
    if len(sensors) < len(SENSORS):
        columns = [SENSORS.index(s) for s in sensors]
        return _fit(replace(readings, volts=readings.volts[:, columns]), model, sensors)
    return _fit(readings, model, SENSORS)


def present_sensors(volts: NDArray[np.float64]) -> tuple[str, ...]:
    """The sensors whose outputs were read: a column all NaN is a sensor the package does not have;
    a column NaN in some rows only is refused (a reading lost, not a sensor absent)."""
    absent = np.all(np.isnan(volts), axis=0)
    if np.any(np.isnan(volts[:, ~absent])):
        raise LabcalError("some readings lack an output their other readings have: every reading of a "
                          "sensor the package has needs its output")
    if absent.all():
        raise LabcalError("no sensor's output was read")
    return tuple(s for s, a in zip(SENSORS, absent, strict=True) if not a)


def _fit(readings: Readings, model: Model, sensors: tuple[str, ...]) -> Fit:
    """`fit_readings` of the columns of ``sensors``."""
    points = readings.points if model.per_point else None
    where = readings_points(readings, None if points is None else points.first)
    weight = None if points is None else np.sqrt(points.counts)[:, None]
    names, design = model.design(where)
    notes: list[str] = []
    weighted = design if weight is None else design * weight
    aliased = tuple(n for i, n in enumerate(names) if i not in _estimable(weighted, len(BASE_NAMES)))
    if aliased:  # e.g. sin 2α and sin 2R vanish on a 0/90/180/270° grid: fit what the plan determines
        model = replace(model, dropped=model.dropped + aliased)
        names, design = model.design(where)
        notes.append(f"term(s) {', '.join(aliased)} left out: this plan cannot estimate them (they vanish "
                     "on its points or repeat the other regressors)")
    replicated = readings.cells.n_replicates > 1
    replication = None
    if points is not None:
        ls = least_squares_of_means(design, readings.point_means, points.counts, readings.volts,
                                    points.groups)
        if replicated:
            replication = analyse_points(design, readings.cells)
    else:
        ls = least_squares(design, readings.volts)
        groups = readings.points.groups
        if replicated:
            per_point = np.all(np.isclose(design, design[readings.points.first][groups], rtol=0, atol=1e-12),
                               axis=0)
            if per_point.all():
                replication = analyse(design, readings.volts, groups, readings.replicate)
            else:  # temperature terms: corrected within points first (Tripp Table 2 footnote b)
                replication = analyse_with_covariates(design, readings.volts, groups, readings.replicate,
                                                      per_point)
    fit = Fit(model, names, ls, replication)
    exact = fit.noise_free(readings)
    if np.any(exact):
        which = ", ".join(s for s, e in zip(sensors, exact, strict=True) if e)
        notes.append(f"{NOISE_FREE} for sensor(s) {which}: the model fits them to floating-point "
                     f"rounding (residual standard error ≤ {NUMERIC_RESOLUTION:g} of the largest reading), "
                     "as a simulation without noise does; their uncertainties are at that rounding, and the "
                     "gross-error, lack-of-fit and drift tests, which compare against noise, are not made")
    if np.any(fit.bias_significant):
        which = ", ".join(s for s, b in zip(sensors, fit.bias_significant, strict=True) if b)
        notes.append(f"significant lack of fit (bias) for sensor(s) {which} at {ALPHA:.0%}: their "
                     "coefficient uncertainties are scaled by the lack-of-fit mean square")
    return Fit(model, names, ls, replication, tuple(notes), sensors)


@dataclass(frozen=True)
class ExtensionTest:
    """Is an extra regressor set warranted? Extra-sum-of-squares F test against the base model.

    Terms the plan cannot separate from the base model (aliased) are left out and named.
    """

    name: str
    reason: str | None  # why it could not be tested, else None
    f: NDArray[np.float64] | None = None
    df: tuple[int, int] | None = None
    aliased: tuple[str, ...] = ()

    @property
    def p_value(self) -> NDArray[np.float64] | None:
        if self.f is None or self.df is None:
            return None
        return f_sf(self.f, *self.df)

    def to_json(self) -> dict[str, Any]:
        if self.reason or self.f is None or self.df is None:
            return {"tested": False, "reason": self.reason or "no F statistic was computed"}
        p_value = f_sf(self.f, *self.df)
        return {"tested": True, "F": self.f.tolist(), "df": list(self.df), "p_value": p_value.tolist(),
                "critical_95": float(f_isf(ALPHA, *self.df)),
                "warranted": (p_value < ALPHA).tolist(), "aliased_terms": list(self.aliased)}


def _estimable(design: NDArray[np.float64], n_base: int) -> NDArray[np.int_]:
    """Columns beyond the base that add rank, in order (aliased ones are dropped)."""
    keep = list(range(n_base))
    for col in range(n_base, design.shape[1]):
        trial = design[:, keep + [col]]
        scale = np.linalg.norm(trial, axis=0)
        # a base column may be all zero (every reading at one attitude with g_x = 0): it adds no
        # rank and divides by nothing; the base fit then says its design is singular in one line
        if scale[-1] > 1e-12 * scale.max() and \
                np.linalg.matrix_rank(trial / np.where(scale > 0, scale, 1.0), tol=1e-9) == len(keep) + 1:
            keep.append(col)
    return np.array(keep)


def extension_tests(readings: Readings) -> list[ExtensionTest]:
    """F test of each model extension added alone to the base model."""
    t_ref = reference_temperature(readings)
    points = readings_points(readings)
    _, base_design = Model().design(points)
    n_base = base_design.shape[1]
    sse_base = np.sum(least_squares(base_design, readings.volts).residuals ** 2, axis=0)
    results = []
    for name in EXTENSIONS:
        try:
            names, design = Model((name,), t_ref).design(points)
        except LabcalError as exc:
            results.append(ExtensionTest(name, str(exc)))
            continue
        keep = _estimable(design, n_base)
        aliased = tuple(n for i, n in enumerate(names) if i >= n_base and i not in keep)
        q, dof = len(keep) - n_base, len(readings) - len(keep)
        if q == 0:
            results.append(ExtensionTest(name, "not estimable with this plan: its terms are aliased with "
                                               "the base model"))
            continue
        if dof <= 0:
            results.append(ExtensionTest(name, "no degrees of freedom left to test it"))
            continue
        sse_full = np.sum(least_squares(design[:, keep], readings.volts).residuals ** 2, axis=0)
        f = ((sse_base - sse_full) / q) / (sse_full / dof)
        results.append(ExtensionTest(name, None, f, (q, dof), aliased))
    return results
