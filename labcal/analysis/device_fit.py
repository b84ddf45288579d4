"""Estimating the calibration device with the instrument: the device model of
`labcal.analysis.device_model` fitted by nonlinear least squares, started from the linear fit.

The solver is scipy's Levenberg–Marquardt (MINPACK) on the analytic Jacobian; its answer is
polished, and its covariance taken, by one Gauss–Newton step through the one QR core
(`labcal.analysis.regression`), so the linearised problem is solved exactly as every other model
is. Readings of the three sensors are weighted by each sensor's noise: the replicate scatter (pure
error) when there are replicates, else the device model's own per-sensor residual standard error
from a first pass. The covariance is s²·(JᵀWJ)⁻¹ with s² the weighted residual mean square on
3K − 18 degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.device_model import (
    N_MIS,
    N_PARAMETERS,
    PARAMETER_NAMES,
    SENSORS,
    Geometry,
    Identifiability,
    identifiability,
    jacobian,
    predict,
    split,
)
from labcal.analysis.distributions import f_isf, f_sf, t_quantile
from labcal.analysis.fit import Fit, fit_readings
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, gravity
from labcal.analysis.readings import Readings
from labcal.analysis.regression import least_squares
from labcal.analysis.replication import ALPHA, Replication, analyse_points
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from scipy import optimize
else:
    optimize = lazy("scipy.optimize")  # about 0.2 s: a command that reads a stored fit fits nothing

MAX_EVALUATIONS = 200  # Levenberg–Marquardt from the linear fit needs about ten
SMALL_ANGLE_LIMIT_DEG = 2.0  # Soto's grouped misalignments are small rotations; beyond, the model is wrong
# Relative fall of the cost, or step relative to θ, at which LM stops: a cost within 1e-10 of its
# minimum puts θ within √(1e-10·χ²) ≈ 1e-3 standard errors of it for thousands of residuals, and the
# Gauss–Newton step after LM converges quadratically from there.
SOLVER_TOLERANCE = 1e-10
NOISE_FLOOR = 1e-12  # relative to the sensitivity: a noise-free reading's residual SE is rounding


@dataclass(frozen=True)
class NestedTest:
    """Extra-sum-of-squares F test of the six misalignments against the linear model (weighted,
    pooled over the sensors); against pure error when there are replicates."""

    f: float
    df: tuple[int, int]
    against: str

    @property
    def p_value(self) -> float:
        return float(f_sf(self.f, *self.df))

    def to_json(self) -> dict[str, Any]:
        return {"F": self.f, "df": list(self.df), "p_value": self.p_value,
                "critical_95": float(f_isf(ALPHA, *self.df)), "warranted": self.p_value < ALPHA,
                "denominator": self.against}


@dataclass(frozen=True)
class Intrinsic:
    """Mount-independent properties of the instrument: each sensor's sensitivity |s_j| (column norm
    of S) and the angle between each pair of sensitive axes (from SᵀS), with standard uncertainties."""

    sensitivity: NDArray[np.float64]  # (3,) V/g
    u_sensitivity: NDArray[np.float64]
    angles_deg: dict[str, float]  # "xy", "xz", "yz"
    u_angles_arcsec: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {
            "sensitivity_v_per_g": {s: {"value": float(v), "u": float(u)}
                                    for s, v, u in zip(SENSORS, self.sensitivity, self.u_sensitivity,
                                                       strict=True)},
            "inter_axis_angle_deg": {p: {"value_deg": self.angles_deg[p],
                                         "deviation_from_90_arcsec": (self.angles_deg[p] - 90.0) * 3600,
                                         "u_arcsec": self.u_angles_arcsec[p]} for p in self.angles_deg},
        }


def intrinsic(X: NDArray[np.float64], cov_s: NDArray[np.float64]) -> Intrinsic:
    """From S = X[1:] and the covariance of S.ravel() (9×9): first-order propagation."""
    S = X[1:]
    norms = np.linalg.norm(S, axis=0)
    values, grads = [], []
    for j in range(3):
        g = np.zeros((3, 3))
        g[:, j] = S[:, j] / norms[j]
        values.append(norms[j])
        grads.append(g.ravel())
    angles, u_angles = {}, {}
    for i, j in ((0, 1), (0, 2), (1, 2)):
        c = float(S[:, i] @ S[:, j] / (norms[i] * norms[j]))
        theta = float(np.arccos(np.clip(c, -1, 1)))
        g = np.zeros((3, 3))
        g[:, i] = -(S[:, j] / (norms[i] * norms[j]) - c * S[:, i] / norms[i] ** 2) / np.sin(theta)
        g[:, j] = -(S[:, i] / (norms[i] * norms[j]) - c * S[:, j] / norms[j] ** 2) / np.sin(theta)
        pair = SENSORS[i] + SENSORS[j]
        angles[pair] = float(np.degrees(theta))
        u_angles[pair] = float(np.sqrt(g.ravel() @ cov_s @ g.ravel()) / ARCSEC)
    grad = np.array(grads)
    u_sens = np.sqrt(np.einsum("ij,jk,ik->i", grad, cov_s, grad))
    return Intrinsic(np.array(values), u_sens, angles, u_angles)


@dataclass(frozen=True)
class AngleErrors:
    """The tables' stated per-point angle errors (± half-widths in rad, rectangular, GUM 4.3.7): each
    table's index accuracy and wobble. A table errs the same way every time it returns to an angle,
    so the error is a function of the table angle, shared by every mount and replicate there (shapes:
    `angle_error_shapes`) — not noise that replicates average away, and not something the residuals
    of one run can tell from the misalignments it partly aliases into."""

    pitch_index: float = 0.0
    pitch_wobble: float = 0.0
    roll_index: float = 0.0
    roll_wobble: float = 0.0

    def inputs(self) -> tuple[tuple[str, tuple[str, ...], float], ...]:
        """(table, misalignments it turns, half-width): Soto Table 1's a2 (pitch index), d1 and f1
        (pitch wobble), f3 (roll index), e1 and k1 (roll wobble), as the simulator and the budget
        model them."""
        return (("pitch", ("a",), self.pitch_index), ("pitch", ("d", "f"), self.pitch_wobble),
                ("roll", ("f",), self.roll_index), ("roll", ("e", "k"), self.roll_wobble))

    def __bool__(self) -> bool:
        return any(half > 0 for _, _, half in self.inputs())

    def to_json(self) -> dict[str, float]:
        return {f"{name}_arcsec": getattr(self, name) / ARCSEC
                for name in ("pitch_index", "pitch_wobble", "roll_index", "roll_wobble")}


SMOOTH_HARMONICS = 3  # eccentricity, ellipticity, trefoil: the low harmonics a bearing or gear gives


def angle_error_shapes(angle_rad: NDArray[np.float64]) -> tuple[tuple[NDArray[np.float64], float], ...]:
    """How a table's error over its angles is modelled, as (basis K × m, variance of each column
    relative to the stated u²). The stated half-width says how large the error is, not how it varies
    with the angle, so two shapes each get the whole u²: a rough table, one independent error per
    distinct angle (gear teeth, high harmonics), and a smooth one, harmonics 1–3 of the angle with
    random amplitudes (u²/3 each). The errors of nearby angles of a smooth table do not average out as
    independent ones do: with one shape alone, a Monte Carlo on smooth tables covered a and d in 76 %
    of trials on a 20-point plan. The sum of the two covariances bounds the variance of anything
    computed from the fit under either shape, and exceeds the larger by at most a factor 2 (√2 in u)."""
    degrees = np.round(np.mod(np.degrees(angle_rad), 360.0), 6) % 360.0
    _, groups = np.unique(degrees, return_inverse=True)
    groups = np.asarray(groups, dtype=np.intp).ravel()
    member = np.zeros((len(groups), int(groups.max()) + 1 if len(groups) else 0))
    member[np.arange(len(groups)), groups] = 1.0
    h = np.arange(1, SMOOTH_HARMONICS + 1)
    angle = np.radians(degrees)[:, None] * h[None, :]
    smooth = np.concatenate([np.cos(angle), np.sin(angle)], axis=1)
    return (member, 1.0), (smooth, 1.0 / SMOOTH_HARMONICS)


@dataclass(frozen=True)
class DeviceFit:
    """θ = [a…k; B; S] with its covariance and the statistics that judge it. ``covariance`` is the
    complete one: the readings' noise (s²·(JᵀWJ)⁻¹) plus ``angle_covariance``, what the tables' stated
    index and wobble errors do to θ through the same least squares."""

    theta: NDArray[np.float64]  # (18,)
    covariance: NDArray[np.float64]  # (18, 18)
    residuals: NDArray[np.float64]  # (K, 3) volts
    sensor_sd: NDArray[np.float64]  # (3,) the noise each sensor was weighted by
    dof: int  # 3K − 18
    ident: Identifiability
    linear: Fit
    test: NestedTest
    replication: Replication | None  # the device model's lack of fit, misalignments fixed at the estimate
    evaluations: int
    notes: tuple[str, ...] = field(default=())
    angle_errors: AngleErrors | None = None
    angle_covariance: NDArray[np.float64] | None = None  # (18, 18); None: no angle errors stated

    @property
    def noise_covariance(self) -> NDArray[np.float64]:
        """The readings' share of the covariance (Type A), without the tables' angle errors."""
        if self.angle_covariance is None:
            return self.covariance
        return np.asarray(self.covariance - self.angle_covariance, dtype=float)

    @property
    def coefficients(self) -> NDArray[np.float64]:
        """X = [Bᵀ; S] (4×3) in the linear fit's layout."""
        return split(self.theta)[1]

    @property
    def stderr(self) -> NDArray[np.float64]:
        return np.sqrt(np.diag(self.covariance))

    @property
    def misalignment_rad(self) -> NDArray[np.float64]:
        return self.theta[:N_MIS]

    @property
    def misalignment_u_rad(self) -> NDArray[np.float64]:
        return self.stderr[:N_MIS]

    @property
    def k95(self) -> float:
        return float(t_quantile(0.975, self.dof))

    @property
    def residual_se(self) -> NDArray[np.float64]:
        """Per sensor; each sensor carries a third of the 18 parameters."""
        n = len(self.residuals)
        se: NDArray[np.float64] = np.sqrt(np.sum(self.residuals**2, axis=0) / (n - N_PARAMETERS / 3))
        return se

    def sensor_covariance(self, sensor: int) -> NDArray[np.float64]:
        """Marginal covariance of (B_j, S[:, j]) — the 4×4 a linear fit gives per sensor — with the
        misalignments' uncertainty propagated into it."""
        idx = N_MIS + np.arange(4) * 3 + sensor
        return self.covariance[np.ix_(idx, idx)]

    @property
    def correlation(self) -> NDArray[np.float64]:
        sd = np.where(self.stderr > 0, self.stderr, 1.0)
        corr: NDArray[np.float64] = self.covariance / np.outer(sd, sd)
        return corr

    def intrinsic(self) -> Intrinsic:
        idx = N_MIS + 3 + np.arange(9)
        return intrinsic(self.coefficients, self.covariance[np.ix_(idx, idx)])

    def reading_projection(self, readings: Readings) -> NDArray[np.float64]:
        """∂θ̂/∂V (18 × K × 3), linearised at θ̂: how the estimate moves with each reading's three
        outputs, the misalignments re-estimated with the coefficients (a reading enters its point's
        mean with weight 1/count, the mean's residual with √count/σ_j)."""
        data = PointMeans.of(readings)
        _, jac = jacobian(self.theta, data.where)
        w = data.root_counts[:, None] / self.sensor_sd[None, :]
        design = (jac * w[:, :, None]).reshape(-1, N_PARAMETERS)
        gain = np.linalg.pinv(design.T @ design) @ design.T  # (18, 3G)
        per_mean = gain.reshape(N_PARAMETERS, len(w), 3) * w[None]
        counts = data.root_counts**2
        return np.asarray(per_mean[:, data.groups, :] / counts[data.groups][None, :, None], dtype=float)

    def reading_sd(self) -> NDArray[np.float64]:
        """One new reading's standard deviation: σ_prec² + σ_bias² after the device model, or S_E."""
        if self.replication is None:
            return self.residual_se
        sd: NDArray[np.float64] = np.sqrt(self.replication.sigma_prec**2 + self.replication.sigma_bias**2)
        return sd

    def to_json(self) -> dict[str, Any]:
        """The device fit JSON contract: the linear layout for `coefficients`, plus the
        misalignments in arcseconds, the full correlation, identifiability and the tests."""
        k = self.k95
        se = self.stderr
        X_se = se[N_MIS:].reshape(4, 3)
        doc: dict[str, Any] = {
            "model": "device",
            "misalignments": {n: {"value_arcsec": float(v / ARCSEC), "u_arcsec": float(u / ARCSEC),
                                  "U_arcsec": float(k * u / ARCSEC)}
                              for n, v, u in zip(MISALIGNMENT_NAMES, self.misalignment_rad,
                                                 self.misalignment_u_rad, strict=True)},
            "coefficients": self.coefficients.tolist(),
            "standard_errors": X_se.tolist(),
            "coverage_factor_95": k,
            "residual_standard_error": self.residual_se.tolist(),
            "residual_standard_error_linear": self.linear.ls.residual_se.tolist(),
            "sensor_weights_sd": self.sensor_sd.tolist(),
            "degrees_of_freedom": self.dof,
            "n_points": len(self.residuals),
            "covariance": [self.sensor_covariance(j).tolist() for j in range(3)],
            "reading_sd": self.reading_sd().tolist(),
            "uncertainty_dof": [self.dof] * 3,
            "parameters": list(PARAMETER_NAMES),
            "correlation": self.correlation.tolist(),
            "identifiability": self.ident.to_json(),
            "intrinsic": self.intrinsic().to_json(),
            "misalignment_test": self.test.to_json(),
            "evaluations": self.evaluations,
            "layout": {"rows": ["B", "S row g_x", "S row g_y", "S row g_z"],
                       "columns": ["sensor x", "sensor y", "sensor z"],
                       "units": "V (bias), V/g (sensitivity); misalignments in arcseconds"},
        }
        if self.linear.replication is not None and self.replication is not None:
            doc["replication"] = {
                s: {"sigma_bias_linear": float(self.linear.replication.sigma_bias[j]),
                    "sigma_bias_device": float(self.replication.sigma_bias[j]),
                    "sigma_prec": float(self.replication.sigma_prec[j]),
                    "lack_of_fit_linear": self.linear.replication.lack_of_fit.to_json(j),
                    "lack_of_fit_device": self.replication.lack_of_fit.to_json(j)}
                for j, s in enumerate(SENSORS)}
        if self.angle_errors is not None:
            doc["angle_errors_stated"] = self.angle_errors.to_json()
        if self.notes:
            doc["notes"] = list(self.notes)
        return doc


@dataclass(frozen=True)
class PointMeans:
    """The readings as the mean of each distinct point, weighted by √(its count): the same least-squares
    solution as every reading (the sum of squares splits into this plus the replicates' own scatter,
    which no parameter moves), at a sixth of the work for six replicates."""

    where: Geometry  # one row per distinct point
    means: NDArray[np.float64]  # (G, 3)
    root_counts: NDArray[np.float64]  # (G,)
    groups: NDArray[np.intp]  # (K,) distinct point of every reading

    @classmethod
    def of(cls, readings: Readings) -> PointMeans:
        points = readings.points
        first = points.first
        where = Geometry.from_degrees(readings.pitch_deg[first], readings.roll_deg[first],
                                      readings.y_deg[first], readings.u_deg[first])
        return cls(where, readings.point_means, np.sqrt(points.counts), points.groups)

    def residuals(self, theta: NDArray[np.float64], volts: NDArray[np.float64]) -> NDArray[np.float64]:
        """Every reading's residual (K×3) under θ: the model predicted once per point, then gathered."""
        return volts - np.take(predict(theta, self.where), self.groups, axis=0)

    def weighted(self, theta: NDArray[np.float64],
                 sd: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Weighted residuals (model − mean) and their Jacobian, rows flattened."""
        model, jac = jacobian(theta, self.where)
        w = self.root_counts[:, None] / sd[None, :]
        return ((model - self.means) * w).ravel(), (jac * w[:, :, None]).reshape(-1, N_PARAMETERS)


def _solve(theta0: NDArray[np.float64], data: PointMeans,
           sd: NDArray[np.float64]) -> tuple[NDArray[np.float64], int]:
    """Levenberg–Marquardt (scipy.optimize.least_squares, MINPACK's lmder) on the weighted residuals
    with the analytic Jacobian, scaled by its column norms. Refuses to return a fit that did not
    converge."""
    last: dict[bytes, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}

    def weighted(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        key = theta.tobytes()  # MINPACK asks for the Jacobian where it has just asked for the residuals
        if key not in last:
            last.clear()
            last[key] = data.weighted(theta, sd)
        return last[key]

    result = optimize.least_squares(lambda t: weighted(t)[0], theta0, jac=lambda t: weighted(t)[1],
                                    method="lm", x_scale="jac", xtol=SOLVER_TOLERANCE, ftol=SOLVER_TOLERANCE,
                                    gtol=SOLVER_TOLERANCE, max_nfev=MAX_EVALUATIONS)
    if result.status <= 0:
        cost = 2 * float(result.cost)
        raise LabcalError(f"the device model did not converge in {MAX_EVALUATIONS} evaluations (its cost "
                          f"was still falling at {cost:.6g}); the readings may not come from this plan's "
                          "geometry, or the misalignments are not small: fit with {0} linear", "model")
    return np.asarray(result.x, dtype=float), int(result.nfev)


Arrays = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def angle_error_covariance(theta: NDArray[np.float64], data: PointMeans, sd: NDArray[np.float64],
                           cov_unscaled: NDArray[np.float64], errors: AngleErrors) -> NDArray[np.float64]:
    """Cov(θ̂) from the tables' angle errors, linearised: an error δ of misalignment m at a table angle
    moves the reading of every point at that angle by ∂V/∂m·δ (the model's own Jacobian column, the
    same δ in all three channels' g), and θ̂ by (JᵀWJ)⁻¹JᵀW of that; u² = half-width²/3 (rectangular)
    in each of the two shapes of `angle_error_shapes`. Summed over inputs: G·Σ·Gᵀ.

    Added to s²·(JᵀWJ)⁻¹, not instead of a part of it: the angle errors also widen the residuals, so s²
    holds some of them again, but taking their expected share out of s² leaves the noise as the small
    difference of two large numbers (wobble of 2″ moves a 5 V output by 50 µV, the noise is 5 µV), which
    in a Monte Carlo covered the coefficients in 31 % of trials; kept, the coefficients' U is about three
    times their scatter, as it was before the angle errors were propagated."""
    _, jac = jacobian(theta, data.where)  # (G, 3, 18)
    w = data.root_counts[:, None] / sd[None, :]
    gain = cov_unscaled @ (jac * w[:, :, None]).reshape(-1, N_PARAMETERS).T  # (18, 3G)
    out = np.zeros((N_PARAMETERS, N_PARAMETERS))
    for table, names, half in errors.inputs():
        if half <= 0:
            continue
        shapes = angle_error_shapes(data.where.pitch if table == "pitch" else data.where.roll)
        for name in names:
            dv = jac[:, :, MISALIGNMENT_NAMES.index(name)] * w  # (G, 3) weighted δV per unit error
            for basis, share in shapes:
                effect = gain @ (dv[:, :, None] * basis[:, None, :]).reshape(-1, basis.shape[1])
                out += (share * half**2 / 3.0) * (effect @ effect.T)
    return out


def _gauss_newton(theta: NDArray[np.float64], data: PointMeans, volts: NDArray[np.float64],
                  sd: NDArray[np.float64]) -> Arrays:
    """One step through the QR core: θ polished, (JᵀWJ)⁻¹, and the residuals of every reading (K×3)."""
    resid, design = data.weighted(theta, sd)
    step = least_squares(design, -resid)
    theta = theta + step.coef[:, 0]
    return theta, step.cov_unscaled, data.residuals(theta, volts)


def fit_device(readings: Readings, linear: Fit | None = None, angle_errors: AngleErrors | None = None
               ) -> DeviceFit:
    """The device model by nonlinear least squares from the linear fit; LabcalError (one line) when the
    readings cannot identify it, the solver does not converge, or the misalignments are not small.
    ``angle_errors``: the tables' stated index and wobble, propagated into the covariance."""
    data = PointMeans.of(readings)
    ident = identifiability(data.where)
    problem = ident.problem()
    if problem:
        raise LabcalError(f"the device model cannot be fitted to these readings: {problem}")
    linear = linear or fit_readings(readings)
    volts = readings.volts
    n = len(volts)
    theta0 = np.concatenate([np.zeros(N_MIS), linear.coefficients.ravel()])
    floor = NOISE_FLOOR * float(np.max(np.abs(linear.coefficients[1:])))
    if linear.replication is not None:  # a priori: pure error does not depend on the model
        sd = np.maximum(linear.replication.sigma_prec, floor)
        theta, evaluations = _solve(theta0, data, sd)
    else:  # first pass unweighted, then each sensor by its own residual scatter
        theta, evaluations = _solve(theta0, data, np.ones(3))
        resid = data.residuals(theta, volts)
        sd = np.maximum(np.sqrt(np.sum(resid**2, axis=0) / (n - N_PARAMETERS / 3)), floor)
        # The weighted optimum lies within the noise of the unweighted one: Gauss–Newton converges
        # from there in a step, quadratically; the step below polishes it again.
        theta, _, _ = _gauss_newton(theta, data, volts, sd)
    theta, cov_unscaled, resid = _gauss_newton(theta, data, volts, sd)
    worst = float(np.max(np.abs(np.degrees(theta[:N_MIS]))))
    if worst > SMALL_ANGLE_LIMIT_DEG:
        name = MISALIGNMENT_NAMES[int(np.argmax(np.abs(theta[:N_MIS])))]
        raise LabcalError(f"the device model's misalignment {name} came out at {worst:.3g}°, beyond its "
                          f"small-angle validity ({SMALL_ANGLE_LIMIT_DEG:g}°); check the mounts and angles "
                          "in the readings, or fit with {0} linear", "model")
    dof = 3 * n - N_PARAMETERS
    weighted_sse = float(np.sum((resid / sd) ** 2))
    scale = weighted_sse / dof if dof > 0 else float("nan")
    test = _nested_test(linear, sd, weighted_sse, dof)
    replication = None
    if linear.replication is not None:
        mis, _ = split(theta)
        where = data.where  # the true gravity is a function of the point: one design row per point
        g = gravity(where.pitch, where.roll, where.y, where.u, mis)
        replication = analyse_points(np.column_stack([np.ones(len(g)), g]), readings.cells)
    verdict = "warrants" if test.p_value < ALPHA else "does not warrant"
    notes = [f"the F test of the six misalignments against the linear model {verdict} them "
             f"(F = {test.f:.3g}, df {test.df}, p = {test.p_value:.2g})"]
    if replication is not None:
        notes.append("lack of fit after the device model is computed with the misalignments fixed at their "
                     "estimates (its degrees of freedom do not deduct them)")
    covariance = scale * cov_unscaled
    angle_cov = None
    if angle_errors:
        angle_cov = angle_error_covariance(theta, data, sd, cov_unscaled, angle_errors)
        covariance = covariance + angle_cov
        notes.append("the tables' stated index and wobble errors (one per table angle) are propagated into "
                     "the covariance: " + ", ".join(f"{k.removesuffix('_arcsec').replace('_', ' ')} "
                                                    f"±{v:g}″" for k, v in angle_errors.to_json().items()))
    return DeviceFit(theta, covariance, resid, sd, dof, ident, linear, test, replication,
                     evaluations, tuple(notes), angle_errors if angle_errors else None, angle_cov)


LINEAR_HINT = "--model linear for Soto's linear fit"  # the technician's, not the certificate's


def default_model(readings: Readings) -> tuple[str, str]:
    """Which model a calibration's readings deserve — the device model where the points identify all
    six misalignments, else the linear one — and the one line that says so (and why). The line is
    also the certificate's statement, so it names no command-line option (`LINEAR_HINT` is said
    where a technician reads it)."""
    absent = np.asarray(np.isnan(readings.volts).all(axis=0))
    if absent.any():  # a package of fewer sensors (Tripp & Tcheng §6): no gravity vector to see δ in
        present = ", ".join(s for s, gone in zip(SENSORS, absent, strict=True) if not gone)
        return "linear", (f"linear model of the {present} sensor(s) the package has, each v = b + s·g "
                          "(Tripp & Tcheng eq. 8): the device model needs three sensors' gravity")
    ident = identifiability(PointMeans.of(readings).where)
    problem = ident.problem()
    if problem is None:
        return "device", ("device model: the plan identifies all six calibration-device misalignments "
                          f"(rank {ident.rank}, condition {ident.condition:.3g})")
    return "linear", f"linear model: this plan cannot identify the device misalignments ({problem})"


def preferred_fit(readings: Readings, linear: Fit, angle_errors: AngleErrors | None = None
                  ) -> tuple[DeviceFit | None, str]:
    """The device fit where `default_model` picks it and it succeeds, with the line saying which model
    the results are; a device fit that fails (no convergence, > 2°) falls back to the linear one.
    ``angle_errors``: the tables' stated index and wobble (`fit_device`)."""
    model, note = default_model(readings)
    if model == "linear":
        return None, note
    try:
        return fit_device(readings, linear, angle_errors), note
    except LabcalError as exc:
        return None, f"linear model: the device model failed ({exc})"


def _nested_test(linear: Fit, sd: NDArray[np.float64], weighted_sse_device: float, dof: int) -> NestedTest:
    weighted_sse_linear = float(np.sum(np.sum(linear.ls.residuals**2, axis=0) / sd**2))
    extra = (weighted_sse_linear - weighted_sse_device) / N_MIS
    if linear.replication is not None:  # weights are 1/σ_prec²: the pooled pure-error mean square is 1
        df_pe = int(np.sum(np.broadcast_to(linear.replication.lack_of_fit.df_den, (3,))))
        return NestedTest(max(extra, 0.0), (N_MIS, df_pe), "pure error (replicate scatter)")
    return NestedTest(max(extra, 0.0) / (weighted_sse_device / dof), (N_MIS, dof), "device model residual")
