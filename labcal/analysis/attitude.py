"""Pitch and roll from the three voltages, with uncertainty (Soto eqs. 5–7, App. B; Tripp eqs. 99–104).

Two estimators, both vectorised over rows:
- closed form: g = (v − B)S⁻¹ (batch form of Soto App. B), α = asin g_x, R = atan2(g_y, g_z);
- weighted least squares on the unit sphere: minimise (v − f(z)) Σ_v⁻¹ (v − f(z))ᵀ over
  z = (α, R), f(z) = B + g(z)ᵀS, by Gauss–Newton from the closed form.
Σ_v holds, per sensor, the calibration's Type A output variance fᵀ C f plus the variance of one
new reading: it sets the estimator's weights (eq. 104 is its covariance when that is all there is).
The uncertainty every output states — `labcal attitude`, the certificate's envelope and budget, the
report and the DCC — is `combined_uncertainty`: the estimator's sensitivity A = ∂z/∂v applied to the
*complete* covariance of the coefficients and of one new reading (Type A, Type B and their
correlations across the three channels), held as independent parts each with its degrees of
freedom, ν_eff by Welch–Satterthwaite and k = t₀.₉₇₅(ν_eff) per attitude and angle. A fit alone has
Type A parts only, and then the sphere estimator's u is eq. 104 exactly. At α = ±90° gravity lies
along x and the roll angle does not exist; such rows report roll as NaN with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.distributions import t_quantile, welch_satterthwaite
from labcal.errors import LabcalError

# Local gravity where an instrument is used may differ from where it was calibrated: by latitude
# and height, a few 1e-4 between labs of one region. The attitude is a direction, so that is no
# error of it; readings within this of the calibration's |g| are valid (`labcal attitude`).
LOCAL_GRAVITY_TOLERANCE = 5e-4
LOCAL_GRAVITY_U = LOCAL_GRAVITY_TOLERANCE / np.sqrt(3.0)  # rectangular over ±tolerance (GUM 4.3.7)
N_COEFFICIENTS = 12  # vec(X), row-major: X[i, j] at 3i + j
N_ERRORS = N_COEFFICIENTS + 3  # then one new reading's three outputs
ROLL_SIGNIFICANCE = 3.0  # the horizontal part of g must exceed this many standard uncertainties
GN_ITERATIONS = 4  # the closed form starts within ~1e-4 rad; Gauss–Newton converges quadratically


@dataclass(frozen=True)
class CovariancePart:
    """One independent group of inputs that share one variance estimate (so one number of degrees of
    freedom): the covariance (15×15) of the errors it causes in [vec(X) row-major; one new reading's
    three outputs]. Off-diagonal terms carry correlations, across coefficients and across channels
    (a gain common to the three channels of a scanning DMM)."""

    matrix: NDArray[np.float64]  # (15, 15)
    dof: float  # np.inf: a Type B input of known distribution
    label: str = ""


def type_a_parts(covariance: NDArray[np.float64], reading_sd: NDArray[np.float64],
                 dofs: NDArray[np.float64]) -> tuple[CovariancePart, ...]:
    """The Type A parts of a fit: per sensor, its coefficients' covariance and one new reading's
    variance, which share that sensor's residual variance estimate and its degrees of freedom."""
    parts = []
    for j in range(3):
        m = np.zeros((N_ERRORS, N_ERRORS))
        idx = np.arange(4) * 3 + j
        m[np.ix_(idx, idx)] = covariance[j]
        m[N_COEFFICIENTS + j, N_COEFFICIENTS + j] = reading_sd[j] ** 2
        parts.append(CovariancePart(m, float(dofs[j]), f"Type A, sensor {'xyz'[j]}"))
    return tuple(parts)


@dataclass(frozen=True)
class Calibration:
    """What attitude needs from a fit or certificate: X (4×3), per-sensor 4×4 Type A covariance of
    (B, s_x, s_y, s_z) and the standard deviation of one new reading (the estimator's weights), the
    degrees of freedom, and the complete covariance as independent parts (empty: the Type A one)."""

    X: NDArray[np.float64]
    covariance: NDArray[np.float64]  # (3, 4, 4)
    reading_sd: NDArray[np.float64]  # (3,)
    dof: int
    parts: tuple[CovariancePart, ...] = ()

    @property
    def s_inv(self) -> NDArray[np.float64]:
        defect = sensitivity_defect(self.X)
        if defect:  # every reader checks first, naming its file; this is the last word, not a traceback
            raise LabcalError(defect)
        # numpy's stubs type inv() as floating[Any]; the inverse of a float64 matrix is float64
        return cast("NDArray[np.float64]", np.linalg.inv(self.X[1:]))

    @property
    def uncertainty_parts(self) -> tuple[CovariancePart, ...]:
        """The complete covariance's parts: as given, or the Type A ones of the fit."""
        return self.parts or type_a_parts(self.covariance, self.reading_sd, np.full(3, float(self.dof)))


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
    per_sensor = dofs if dofs.size == 3 else np.full(3, float(dof))
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(cov)) and np.all(np.isfinite(sd))):
        raise LabcalError(f"{path}: coefficients or uncertainties contain NaN or infinity")
    if np.max(np.abs(X)) > MAX_COEFFICIENT or np.max(np.abs(cov)) > MAX_COEFFICIENT**2 \
            or np.max(np.abs(sd)) > MAX_COEFFICIENT:
        raise LabcalError(f"{path}: field coefficients (or their uncertainties) exceeds {MAX_COEFFICIENT:g} "
                          "V in magnitude; not an instrument's calibration")
    if sensitivity_defect(X):
        raise LabcalError(f"{path}: the sensitivity matrix S is singular; it cannot turn voltages into g")
    return Calibration(X, cov, sd, dof, type_a_parts(cov, sd, per_sensor))


@dataclass(frozen=True)
class Uncertainty:
    """Per row and angle (n×2: pitch, roll): combined standard uncertainty (rad), ν_eff and k."""

    u: NDArray[np.float64]
    nu_eff: NDArray[np.float64]
    k: NDArray[np.float64]

    @property
    def U(self) -> NDArray[np.float64]:
        return np.asarray(self.k * self.u, dtype=float)


# f_i f_k for f = [1, g]: the ten distinct products, and which one each (i, k) is
_PAIRS = tuple((i, k) for i in range(4) for k in range(i, 4))
_MONOMIAL = {pair: m for m, pair in enumerate(_PAIRS)} | {(k, i): m for m, (i, k) in enumerate(_PAIRS)}


def _output_covariance_weights(matrix: NDArray[np.float64]) -> NDArray[np.float64]:
    """W (10 × 9) with Cov(δv_j, δv_l) = Σ_m f-monomial_m · W[m, 3j + l] for one part, where a reading
    in use errs by δv = −f·δX + δr (f = [1, g]): Σ_ik f_i f_k C(X_ij, X_kl) − Σ_i f_i [C(X_ij, r_l) +
    C(r_j, X_il)] + C(r_j, r_l)."""
    cx = matrix[:N_COEFFICIENTS, :N_COEFFICIENTS].reshape(4, 3, 4, 3)
    cxr = matrix[:N_COEFFICIENTS, N_COEFFICIENTS:].reshape(4, 3, 3)  # C(X_ij, r_l)
    crr = matrix[N_COEFFICIENTS:, N_COEFFICIENTS:]
    w = np.zeros((len(_PAIRS), 3, 3))
    for i in range(4):
        for k in range(4):
            w[_MONOMIAL[(i, k)]] += cx[i, :, k, :]
        w[_MONOMIAL[(0, i)]] -= cxr[i] + cxr[i].T
    w[_MONOMIAL[(0, 0)]] += crr
    return w.reshape(len(_PAIRS), 9)


def output_covariance(parts: tuple[CovariancePart, ...], f: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per row and part (n × P × 9, [j, l] row-major) the covariance of one reading's error in use,
    Σ_v = G Σ_part Gᵀ with G = [−f ⊗ I, I]: one (n × 10)·(10 × 9P) product of f's monomials for every
    part at once."""
    monomials = np.empty((len(f), len(_PAIRS)))
    for m, (i, k) in enumerate(_PAIRS):
        np.multiply(f[:, i], f[:, k], out=monomials[:, m])
    weights = np.concatenate([_output_covariance_weights(p.matrix) for p in parts], axis=1) if parts \
        else np.zeros((len(_PAIRS), 0))
    return (monomials @ weights).reshape(len(f), len(parts), 9)


def part_variances(parts: tuple[CovariancePart, ...], A: NDArray[np.float64], f: NDArray[np.float64],
                   sigma: NDArray[np.float64] | None = None) -> list[NDArray[np.float64]]:
    """Each part's variance of pitch and roll (n×2) for estimator sensitivity A (n×2×3) at f:
    A Σ_v Aᵀ (``sigma``: `output_covariance` of the parts at f, where already computed)."""
    if sigma is None:
        sigma = output_covariance(parts, f)
    outer = (A[:, :, :, None] * A[:, :, None, :]).reshape(len(f), 2, 9)  # A_aj A_al
    variances = np.matmul(outer, np.swapaxes(sigma, 1, 2))  # (n, 2, P): a batched product, not einsum
    return [variances[:, :, q] for q in range(len(parts))]


def combined_uncertainty(parts: tuple[CovariancePart, ...], A: NDArray[np.float64],
                         f: NDArray[np.float64], sigma: NDArray[np.float64] | None = None,
                         known: NDArray[np.float64] | None = None) -> Uncertainty:
    """THE attitude uncertainty: u_c² = Σ_parts H Σ_part Hᵀ, ν_eff by Welch–Satterthwaite over the
    parts (GUM G.4.1), k = t₀.₉₇₅(ν_eff). Every output that states a pitch or roll U95 comes here.
    ``known``: a further variance of pitch and roll (n×2) from an input whose distribution is stated,
    not estimated (infinite degrees of freedom): the prior on local |g| of `sphere_least_squares`."""
    with np.errstate(invalid="ignore"):
        variances = part_variances(parts, A, f, sigma)
        dofs = [p.dof for p in parts]
        if known is not None:
            variances, dofs = [*variances, known], [*dofs, np.inf]
        total = np.sum(variances, axis=0) if variances else np.zeros((len(A), 2))
        u = np.sqrt(np.clip(total, 0.0, None))
        nu = welch_satterthwaite(u, [(v, dof) for v, dof in zip(variances, dofs, strict=True)])
    return Uncertainty(u, nu, coverage_factor(nu, u))


def coverage_factor(nu: NDArray[np.float64], u: NDArray[np.float64]) -> NDArray[np.float64]:
    """k = t₀.₉₇₅ at ν_eff truncated to the integer below (GUM G.4.1 note 1), once per distinct value
    (a hundred thousand rows share a handful); NaN where u is undefined."""
    whole = np.where(np.isfinite(nu) & (nu < MAX_DOF), np.floor(np.maximum(nu, 1.0) + 1e-9), np.inf)
    values, inverse = np.unique(whole, return_inverse=True)
    k = np.asarray(t_quantile(0.975, values), dtype=float)[inverse].reshape(nu.shape)
    return np.where(np.isfinite(u), k, np.nan)


@dataclass(frozen=True)
class Attitude:
    """Per row: pitch and roll (rad), their combined standard uncertainties and 95 % coverage
    factors (k = t₀.₉₇₅(ν_eff) per row and angle)."""

    pitch: NDArray[np.float64]
    roll: NDArray[np.float64]  # NaN where undefined
    u_pitch: NDArray[np.float64]
    u_roll: NDArray[np.float64]
    k_pitch: NDArray[np.float64]
    k_roll: NDArray[np.float64]

    @property
    def roll_defined(self) -> NDArray[np.float64]:
        return np.isfinite(self.roll)

    @property
    def U_pitch(self) -> NDArray[np.float64]:
        return np.asarray(self.k_pitch * self.u_pitch, dtype=float)

    @property
    def U_roll(self) -> NDArray[np.float64]:
        return np.asarray(self.k_roll * self.u_roll, dtype=float)


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


def regressors_of(g: NDArray[np.float64]) -> NDArray[np.float64]:
    """f = [1, g] per row (n×4): what multiplies X in V = B + gᵀS."""
    return np.concatenate([np.ones((len(g), 1)), g], axis=1)


def sphere_sensitivity(F: NDArray[np.float64], w: NDArray[np.float64], free_roll: NDArray[Any],
                       gravity_u: float = 0.0, magnitude: NDArray[np.float64] | None = None
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """How the sphere estimator's pitch and roll move with the outputs, A = (F W Fᵀ + P)⁻¹ F W
    (n×2×3), F (n×2×3) the rows ∂f/∂pitch, ∂f/∂roll and W the weights (n×3); where roll is not free
    only pitch is estimated and roll's row is NaN.

    With ``gravity_u`` > 0 the estimator also estimates |g| = m (``magnitude``: ∂f/∂m, n×3) with the
    prior m = 1 ± gravity_u (P = 1/gravity_u² on m): local gravity where the instrument is used is not
    the calibration's, and the direction is what is wanted. Then the second value is the variance of
    pitch and roll that the prior itself brings (n×2): δz = −P·N⁻¹e_m·δm₀, so P·(N⁻¹)[:2, m]²; else
    None. `labcal attitude` and the certificate's budget both come here: one estimator, one U95."""
    held = ~np.asarray(free_roll, dtype=bool)
    free_m = gravity_u > 0 and magnitude is not None
    rows = np.concatenate([F, magnitude[:, None, :]], axis=1) if free_m and magnitude is not None else F
    weighted = rows * w[:, None, :]
    weighted[held, 1] = 0.0
    M = np.einsum("nai,nbi->nab", weighted, rows)
    M[held, 1, :] = 0.0
    M[held, :, 1] = 0.0
    M[held, 1, 1] = 1.0
    if free_m:
        M[:, 2, 2] += 1.0 / gravity_u**2
    A = np.stack([_solve(M, weighted[:, :, j]) for j in range(3)], axis=2)[:, :2]
    A[held, 1] = np.nan
    if not free_m:
        return A, None
    column = _solve(M, np.tile(np.eye(3)[2], (len(M), 1)))[:, :2]  # (N⁻¹)[:2, m]
    known = column**2 / gravity_u**2
    known[held, 1] = np.nan
    return A, known


def closed_form(cal: Calibration, volts: NDArray[np.float64]) -> Attitude:
    """Soto eqs. 5–7 with first-order uncertainty through the same Σ_v as the sphere solution.

    Pitch is the elevation of g, atan2(g_x, √(g_y² + g_z²)): Soto's asin g_x where |g| = 1, and the
    same direction wherever local gravity differs from the calibration's (asin of an unnormalised
    g_x was 0.012° off at 45° and 1.05° at 89.9° for |g| = 1 + 2e-4, and clipped beyond the pole)."""
    volts = np.atleast_2d(np.asarray(volts, float))
    g = (volts - cal.X[0]) @ cal.s_inv  # batch form of Soto App. B
    h2 = g[:, 1] ** 2 + g[:, 2] ** 2
    h, n2 = np.sqrt(h2), h2 + g[:, 0] ** 2
    pitch, roll = np.arctan2(g[:, 0], h), np.arctan2(g[:, 1], g[:, 2])
    # dz/dv = (dz/dg)(dg/dv), dg/dv = S⁻¹ (row-vector convention: dg = dv·S⁻¹)
    with np.errstate(divide="ignore", invalid="ignore"):
        dp_dg = np.stack([h, -g[:, 0] * g[:, 1] / h, -g[:, 0] * g[:, 2] / h], axis=1) / n2[:, None]
        dr_dg = np.stack([np.zeros(len(g)), g[:, 2] / h2, -g[:, 1] / h2], axis=1)
    A = np.stack([dp_dg @ cal.s_inv.T, dr_dg @ cal.s_inv.T], axis=1)
    f = regressors_of(g)
    sigma = output_covariance(cal.uncertainty_parts, f)
    unc = combined_uncertainty(cal.uncertainty_parts, A, f, sigma)
    sigma_v = sigma.sum(axis=1)[:, [0, 4, 8]]  # the complete Σ_v's diagonal
    u_p, u_r = unc.u[:, 0], unc.u[:, 1]
    roll, u_r = _undefined_roll(cal, g, sigma_v, roll, u_r)
    # Where roll is undefined g lies along x within noise: the elevation's slope turns with the
    # unknown direction of the small horizontal part, so the closed form's linear uncertainty means
    # nothing there (asin's read 1e148°) and is stated as undefined (NaN); the sphere estimator's
    # stays defined.
    u_p = np.where(~np.isfinite(roll), np.nan, u_p)
    return Attitude(pitch, roll, u_p, u_r, np.where(np.isfinite(u_p), unc.k[:, 0], np.nan),
                    np.where(np.isfinite(u_r), unc.k[:, 1], np.nan))


def _undefined_roll(
    cal: Calibration, g: NDArray[np.float64], sigma_v: NDArray[np.float64], roll: NDArray[np.float64],
    u_roll: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """NaN roll where the horizontal part of g is not distinguishable from zero (pitch ±90°)."""
    var_g = sigma_v @ cal.s_inv**2  # diagonal of Σ_g = S⁻ᵀ Σ_v S⁻¹ (Σ_v diagonal)
    u_h = np.sqrt(0.5 * (var_g[:, 1] + var_g[:, 2]))
    undefined = np.hypot(g[:, 1], g[:, 2]) <= ROLL_SIGNIFICANCE * u_h
    return np.where(undefined, np.nan, roll), np.where(undefined, np.nan, u_roll)


def sphere_least_squares(cal: Calibration, volts: NDArray[np.float64], gravity_u: float = 0.0) -> Attitude:
    """Tripp eqs. 99–104: weighted least squares over (α, R) on the unit sphere.

    ``gravity_u``: the standard uncertainty of local |g| relative to the calibration's (0: the same
    gravity, Tripp's estimator exactly). Three sensors see one direction and one magnitude; the
    magnitude is what the sphere adds to the closed form, and it is worth only what |g| is known to.
    So |g| = m is estimated with the attitude, m a priori 1 ± ``gravity_u``: where local gravity
    differs from the calibration's (a few 1e-4 between labs) the estimate follows the direction
    instead of being pulled by the anisotropic weights (0.0012° at 45° for |g| off by 2e-4 with a
    10 µV instrument), and its covariance carries that uncertainty.
    """
    volts = np.atleast_2d(np.asarray(volts, float))
    start = closed_form(cal, volts)
    # Where roll is undefined it is held, not estimated, but at the direction the small horizontal
    # part of g has: held at 0° instead, pitch absorbed the whole horizontal part as an error.
    g_raw = (volts - cal.X[0]) @ cal.s_inv
    pitch, roll = start.pitch.copy(), np.where(start.roll_defined, start.roll,
                                               np.arctan2(g_raw[:, 1], g_raw[:, 2]))
    free_roll: NDArray[np.bool_] = np.isfinite(start.roll)
    held = ~free_roll
    free_m = gravity_u > 0
    prior = 1.0 / gravity_u**2 if free_m else 0.0
    m = np.ones(len(volts))
    S = cal.X[1:]

    def normal_equations(pitch: NDArray[np.float64], roll: NDArray[np.float64], m: NDArray[np.float64]
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """N = Jᵀ W J (+ the prior on m) and Jᵀ W r − prior·(m − 1), per row; a held parameter's
        row and column are the identity's, so its step is 0."""
        g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
        w = 1.0 / output_variance(cal, g)
        resid = volts - cal.X[0] - m[:, None] * (g @ S)
        jac = np.stack([m[:, None] * (dg_dp @ S), m[:, None] * (dg_dr @ S), g @ S], axis=1)  # n × 3 × 3
        jac[held, 1] = 0.0
        if not free_m:
            jac[:, 2] = 0.0
        normal = np.einsum("nak,nk,nbk->nab", jac, w, jac)
        rhs = np.einsum("nak,nk,nk->na", jac, w, resid)
        normal[:, 2, 2] += prior if free_m else 1.0
        rhs[:, 2] -= prior * (m - 1.0)
        normal[held, 1, 1] = 1.0
        return normal, rhs

    with np.errstate(all="ignore"):  # a row of 1e308 V is flagged by the gravity check, not here
        for _ in range(GN_ITERATIONS):
            normal, rhs = normal_equations(pitch, roll, m)
            step = _solve(normal, rhs)
            pitch, roll, m = pitch + step[:, 0], roll + step[:, 1], m + step[:, 2]
        g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
        w = 1.0 / output_variance(cal, g)
        A, known = sphere_sensitivity(np.stack([m[:, None] * (dg_dp @ S), m[:, None] * (dg_dr @ S)], axis=1),
                                      w, free_roll, gravity_u, g @ S)
        unc = combined_uncertainty(cal.uncertainty_parts, A, regressors_of(g), known=known)
    # pitch beyond ±90° is the same direction seen with roll turned by 180°: fold it back, so that
    # both estimators state one attitude (at the pole they disagreed in roll by 180°)
    pitch = np.arctan2(np.sin(pitch), np.cos(pitch))
    over = np.abs(pitch) > np.pi / 2
    pitch = np.where(over, np.sign(pitch) * np.pi - pitch, pitch)
    roll = np.where(over, roll + np.pi, roll)
    roll = np.arctan2(np.sin(roll), np.cos(roll))
    roll, u_r = np.where(free_roll, roll, np.nan), np.where(free_roll, unc.u[:, 1], np.nan)
    return Attitude(pitch, roll, unc.u[:, 0], u_r, unc.k[:, 0], np.where(free_roll, unc.k[:, 1], np.nan))


def _solve(normal: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each row's 3×3 system; a singular one (a reading of no direction) steps by NaN, not an error."""
    ok = np.all(np.isfinite(normal), axis=(1, 2)) & (np.abs(np.linalg.det(np.where(
        np.isfinite(normal), normal, 0.0))) > 0)
    out = np.full(rhs.shape, np.nan)
    if ok.any():
        out[ok] = np.linalg.solve(normal[ok], rhs[ok][..., None])[..., 0]
    return out
