"""Pitch and roll from the three voltages, with uncertainty (Soto eqs. 5–7, App. B; Tripp eqs. 99–104).

Two estimators, both vectorised over rows:
- closed form: g = (v − B)S⁻¹ (batch form of Soto App. B), α = asin g_x, R = atan2(g_y, g_z);
- weighted least squares on the unit sphere: minimise (v − f(z)) Σ_v⁻¹ (v − f(z))ᵀ over
  z = (α, R), f(z) = B + g(z)ᵀS, by Gauss–Newton from the closed form.
Σ_v holds, per sensor, the calibration's output variance fᵀ C f plus the variance of one new
reading; the attitude covariance follows by eq. 104. At α = ±90° gravity lies along x and the
roll angle does not exist; such rows report roll as NaN with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.distributions import t_quantile
from labcal.errors import LabcalError

ROLL_SIGNIFICANCE = 3.0  # the horizontal part of g must exceed this many standard uncertainties
GN_ITERATIONS = 4  # the closed form starts within ~1e-4 rad; Gauss–Newton converges quadratically


@dataclass(frozen=True)
class Calibration:
    """What attitude needs from a fit or certificate: X (4×3), per-sensor 4×4 covariance of
    (B, s_x, s_y, s_z), the standard deviation of one new reading, and degrees of freedom."""

    X: NDArray[np.float64]
    covariance: NDArray[np.float64]  # (3, 4, 4)
    reading_sd: NDArray[np.float64]  # (3,)
    dof: int

    @property
    def s_inv(self) -> NDArray[np.float64]:
        defect = sensitivity_defect(self.X)
        if defect:  # every reader checks first, naming its file; this is the last word, not a traceback
            raise LabcalError(defect)
        # numpy's stubs type inv() as floating[Any]; the inverse of a float64 matrix is float64
        return cast("NDArray[np.float64]", np.linalg.inv(self.X[1:]))


SINGULAR_CONDITION = 1e8  # an accelerometer triad's S is near orthogonal (condition ~1); 1e8 is no triad


def sensitivity_defect(X: NDArray[np.float64]) -> str | None:
    """Why the sensitivity matrix S (rows 1–3 of X) cannot turn voltages into g, or None.

    S is singular when the voltages do not follow gravity in three independent directions:
    identical voltages on every row (a dead or disconnected meter), a constant channel, or two
    inputs wired to one sensor. Judged by S's condition number, which no unit or gain changes."""
    S = np.asarray(X, float)[1:]
    if not np.all(np.isfinite(S)):
        return "the sensitivity matrix S is not finite; it cannot turn voltages into g"
    singular_values = np.linalg.svd(S, compute_uv=False)
    if not singular_values[-1] > singular_values[0] / SINGULAR_CONDITION:
        return ("the sensitivity matrix S is singular (the voltages do not follow gravity in three "
                "independent directions: a constant channel, identical readings, or two channels on one "
                "sensor); check the wiring and the columns vx, vy, vz")
    return None


MAX_COEFFICIENT = 1e6  # V and V/g: a million volts is no accelerometer's bias or sensitivity
MAX_DOF = 1e9  # degrees of freedom of any fit a lab makes; beyond this t is the normal quantile anyway


def calibration_from_json(doc: dict[str, Any], path: str | Path) -> Calibration:
    """The attitude calibration from a fit JSON document (``path`` names it in messages)."""
    try:
        X = np.array(doc["coefficients"], dtype=float)
        cov = np.array(doc["covariance"], dtype=float)
        sd = np.array(doc.get("reading_sd", doc["residual_standard_error"]), dtype=float)
        dofs = np.array(doc.get("uncertainty_dof", [doc["degrees_of_freedom"]]), dtype=float)
    except KeyError as exc:
        raise LabcalError(f"{path}: not a labcal fit or certificate (no field {exc})") from None
    except (TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise LabcalError(f"{path}: not a labcal fit or certificate ({exc})") from None
    if dofs.ndim != 1 or dofs.size == 0 or not np.all((dofs >= 1) & (dofs <= MAX_DOF)) \
            or not np.all(dofs == np.round(dofs)):
        raise LabcalError(f"{path}: field uncertainty_dof (or degrees_of_freedom) must be whole numbers "
                          f"from 1 to {MAX_DOF:.0e}")
    dof = int(dofs.min())
    if X.shape != (4, 3) or cov.ndim != 3 or cov.shape[0] != 3 or cov.shape[1] < 4 or sd.shape != (3,):
        raise LabcalError(f"{path}: coefficients must be 4×3, covariance 3 matrices of at least 4×4, "
                          "and 3 reading standard deviations")
    cov = cov[:, :4, :4]  # extension terms do not enter the attitude
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(cov)) and np.all(np.isfinite(sd))):
        raise LabcalError(f"{path}: coefficients or uncertainties contain NaN or infinity")
    if np.max(np.abs(X)) > MAX_COEFFICIENT or np.max(np.abs(cov)) > MAX_COEFFICIENT**2 \
            or np.max(np.abs(sd)) > MAX_COEFFICIENT:
        raise LabcalError(f"{path}: field coefficients (or their uncertainties) exceeds {MAX_COEFFICIENT:g} "
                          "V in magnitude; not an instrument's calibration")
    if sensitivity_defect(X):
        raise LabcalError(f"{path}: the sensitivity matrix S is singular; it cannot turn voltages into g")
    return Calibration(X, cov, sd, dof)


@dataclass(frozen=True)
class Attitude:
    """Per row: pitch and roll (rad), their standard uncertainties, and the 95 % coverage factor."""

    pitch: NDArray[np.float64]
    roll: NDArray[np.float64]  # NaN where undefined
    u_pitch: NDArray[np.float64]
    u_roll: NDArray[np.float64]
    k95: float

    @property
    def roll_defined(self) -> NDArray[np.float64]:
        return np.isfinite(self.roll)


def _gravity_and_derivatives(
    pitch: NDArray[np.float64], roll: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    sp, cp, sr, cr = np.sin(pitch), np.cos(pitch), np.sin(roll), np.cos(roll)
    g = np.stack([sp, cp * sr, cp * cr], axis=-1)
    dg_dp = np.stack([cp, -sp * sr, -sp * cr], axis=-1)
    dg_dr = np.stack([np.zeros_like(sp), cp * cr, -cp * sr], axis=-1)
    return g, dg_dp, dg_dr


def output_variance(cal: Calibration, g: NDArray[np.float64]) -> NDArray[np.float64]:
    """Σ_v diagonal per row (n×3): calibration variance fᵀ C_j f plus one reading's variance.

    With f = [1, g] the quadratic form is C₀₀ + 2·C₀g·g + Σ_ab C_ab g_a g_b: one small matrix
    product and the six distinct products g_a g_b, not a 4×4 form per row and sensor."""
    c = cal.covariance
    pairs = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    terms = np.empty((len(g), 9))  # g_a, then g_a g_b: one (n×9)·(9×3) product for all three sensors
    terms[:, :3] = g
    for t, (a, b) in enumerate(pairs, start=3):
        np.multiply(g[:, a], g[:, b], out=terms[:, t])
    weights = np.vstack([2.0 * c[:, 0, 1:].T,
                         [c[:, 1 + a, 1 + b] + (c[:, 1 + b, 1 + a] if a != b else 0.0) for a, b in pairs]])
    out: NDArray[np.float64] = terms @ weights
    out += c[:, 0, 0] + cal.reading_sd**2
    return out


def _k95(cal: Calibration) -> float:
    return float(t_quantile(0.975, cal.dof)) if cal.dof > 0 else float("inf")


def closed_form(cal: Calibration, volts: NDArray[np.float64]) -> Attitude:
    """Soto eqs. 5–7 with first-order uncertainty through the same Σ_v as the sphere solution."""
    volts = np.atleast_2d(np.asarray(volts, float))
    g = (volts - cal.X[0]) @ cal.s_inv  # batch form of Soto App. B
    gx = np.clip(g[:, 0], -1.0, 1.0)
    h2 = g[:, 1] ** 2 + g[:, 2] ** 2
    pitch, roll = np.arcsin(gx), np.arctan2(g[:, 1], g[:, 2])
    # dz/dv = (dz/dg)(dg/dv), dg/dv = S⁻¹ (row-vector convention: dg = dv·S⁻¹)
    dp_dg = np.zeros_like(g)
    dp_dg[:, 0] = 1.0 / np.sqrt(np.maximum(1.0 - gx**2, 1e-300))
    with np.errstate(divide="ignore", invalid="ignore"):
        dr_dg = np.stack([np.zeros(len(g)), g[:, 2] / h2, -g[:, 1] / h2], axis=1)
    sigma_v = output_variance(cal, g)
    dp_dv, dr_dv = dp_dg @ cal.s_inv.T, dr_dg @ cal.s_inv.T
    u_p = np.sqrt(np.sum(dp_dv**2 * sigma_v, axis=1))
    u_r = np.sqrt(np.sum(dr_dv**2 * sigma_v, axis=1))
    roll, u_r = _undefined_roll(cal, g, sigma_v, roll, u_r)
    # Where roll is undefined |g_x| is within noise of 1, and where |g_x| ≥ 1 it was clipped: asin's
    # slope is unbounded there, so the closed form's linear uncertainty is meaningless (it read
    # 1e148°) and is stated as undefined (NaN); the sphere estimator's stays defined.
    u_p = np.where(~np.isfinite(roll) | (np.abs(g[:, 0]) >= 1.0), np.nan, u_p)
    return Attitude(pitch, roll, u_p, u_r, _k95(cal))


def _undefined_roll(
    cal: Calibration, g: NDArray[np.float64], sigma_v: NDArray[np.float64], roll: NDArray[np.float64],
    u_roll: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """NaN roll where the horizontal part of g is not distinguishable from zero (pitch ±90°)."""
    var_g = sigma_v @ cal.s_inv**2  # diagonal of Σ_g = S⁻ᵀ Σ_v S⁻¹ (Σ_v diagonal)
    u_h = np.sqrt(0.5 * (var_g[:, 1] + var_g[:, 2]))
    undefined = np.hypot(g[:, 1], g[:, 2]) <= ROLL_SIGNIFICANCE * u_h
    return np.where(undefined, np.nan, roll), np.where(undefined, np.nan, u_roll)


def sphere_least_squares(cal: Calibration, volts: NDArray[np.float64]) -> Attitude:
    """Tripp eqs. 99–104: weighted least squares over (α, R) on the unit sphere."""
    volts = np.atleast_2d(np.asarray(volts, float))
    start = closed_form(cal, volts)
    # Where roll is undefined it is held, not estimated, but at the direction the small horizontal
    # part of g has: held at 0° instead, pitch absorbed the whole horizontal part as an error.
    g_raw = (volts - cal.X[0]) @ cal.s_inv
    pitch, roll = start.pitch.copy(), np.where(start.roll_defined, start.roll,
                                               np.arctan2(g_raw[:, 1], g_raw[:, 2]))
    free_roll = start.roll_defined
    S = cal.X[1:]
    for _ in range(GN_ITERATIONS):
        g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
        w = 1.0 / output_variance(cal, g)
        resid = volts - cal.X[0] - g @ S
        fp, fr = dg_dp @ S, dg_dr @ S  # rows of F_z
        a = np.sum(w * fp * fp, axis=1)
        b = np.sum(w * fp * fr, axis=1)
        c = np.sum(w * fr * fr, axis=1)
        rp, rr = np.sum(w * fp * resid, axis=1), np.sum(w * fr * resid, axis=1)
        det = a * c - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            step_p = np.where(free_roll, (c * rp - b * rr) / det, rp / a)
            step_r = np.where(free_roll, (a * rr - b * rp) / det, 0.0)
        pitch, roll = pitch + step_p, roll + step_r
    g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
    w = 1.0 / output_variance(cal, g)
    fp, fr = dg_dp @ S, dg_dr @ S
    a, b, c = (np.sum(w * x * y, axis=1) for x, y in ((fp, fp), (fp, fr), (fr, fr)))
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):  # Σ_z = (F W Fᵀ)⁻¹ with W = Σ_v⁻¹
        u_p = np.sqrt(np.where(free_roll, c / det, 1.0 / a))
        u_r = np.sqrt(a / det)
    pitch = np.arctan2(np.sin(pitch), np.cos(pitch))
    roll = np.arctan2(np.sin(roll), np.cos(roll))
    roll, u_r = np.where(free_roll, roll, np.nan), np.where(free_roll, u_r, np.nan)
    return Attitude(pitch, roll, u_p, u_r, _k95(cal))
