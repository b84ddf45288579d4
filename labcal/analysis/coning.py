"""Tripp & Tcheng's per-sensor model v = b + S·(u·g) as a change of variables of the linear fit.

Column j of S is sensor j's sensitivity vector s = S·u; the coning angle Ω is its angle from
the nominal axis and the azimuth A the direction of the tilt (unit vectors of docs/design.md §3,
Tripp eqs. 2, 4, 5). The covariance follows through the Jacobian of that map. No iterative
solver is needed, and near Ω = 0 the azimuth is undefined and reported as such.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.attitude import MAX_COEFFICIENT  # the bound on a calibration read from a file
from labcal.analysis.distributions import f_isf, noncentral_f2_cdf, t_quantile
from labcal.analysis.fit import SENSORS, Fit
from labcal.errors import LabcalError

# For each sensor: index of the main component m of s, and the signed components (t1, t2) with
# sin Ω cos A = t1/S and sin Ω sin A = t2/S, read off the unit vectors u_x, u_y, u_z.
_AXES = {
    "x": (0, (1, -1.0), (2, -1.0)),
    "y": (1, (2, +1.0), (0, -1.0)),
    "z": (2, (0, -1.0), (1, +1.0)),
}
AZIMUTH_SIGNIFICANCE = 3.0  # Ω must exceed this many standard errors for A to mean anything
OMEGA_NEAR_ZERO = (f"Ω is within {AZIMUTH_SIGNIFICANCE:g} standard errors of 0, where Ω ± k·u is no valid "
                   "interval: Ω ≥ 0 is the length of a 2-D vector, and at a true Ω of 0 the delta-method "
                   "interval ±1.96·u covers it 85 % of the time, not 95 % (by Monte Carlo); "
                   "its 95 % interval is the one from the distribution of that length (omega_interval_95)")
LEVEL = 0.95
RICE_UP_TO = 30.0  # |τ|/σ beyond which the length is normal to 1e-3 and Ω ± t·u is the interval


def omega_interval(tan_omega: ArrayLike, sigma: ArrayLike, dof: float, level: float = LEVEL
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The ``level`` confidence interval of Ω (rad) from tan Ω̂ = |τ̂| and σ, the standard uncertainty
    of each component of the tilt vector τ = (t1, t2)/m (its larger principal one: conservative when
    the two differ), estimated on ``dof`` degrees of freedom.

    Ω ≥ 0 is the length of a 2-D vector, so Ω̂ ± k·u is no interval near 0 (85 % at Ω = 0). Instead
    the central Neyman construction on the length's own distribution: (|τ̂|/σ̂)²/2 is noncentral
    F(2, ν, λ = |τ|²/σ²) (the Rice distribution with σ estimated), and its CDF falls as λ grows, so
    the limits are the λ at which the observed value is the upper and the lower (1 − level)/2 point,
    the lower one 0 where even λ = 0 does not reach it. Coverage is ``level`` where the lower limit
    is above 0 and more at the boundary (1 − (1 − level)/2 at Ω = 0). Below the null median of the
    statistic, the central upper limit shrinks to nothing (an observed Ω̂ ≈ 0 is unlikely under every
    λ); there the upper limit is the one at the null median: a longer interval, so coverage only
    grows, and "Ω < U" reads as it should."""
    dof = min(float(dof), 1e7)  # σ known: F(2, ∞) is χ²₂/2, which 1e7 degrees of freedom reach
    r, s = (np.asarray(v, dtype=float) for v in np.broadcast_arrays(tan_omega, sigma))
    x = np.where(s > 0, r / np.where(s > 0, s, 1.0), np.inf)
    tail = (1 - level) / 2
    lower, upper = np.empty_like(x), np.empty_like(x)
    far = ~(x <= RICE_UP_TO)  # also a zero σ (a noise-free fit)
    k = float(t_quantile(1 - tail, dof))
    lower[far], upper[far] = np.maximum(x[far] - k, 0.0), x[far] + k
    near = ~far
    if near.any():
        f = x[near] ** 2 / 2
        f_up = np.maximum(f, float(f_isf(0.5, 2, dof)))  # at least the null median (docstring)
        upper[near] = _solve(lambda nu: noncentral_f2_cdf(f_up, nu**2, dof), tail, np.zeros_like(f),
                             np.sqrt(2 * f_up) + 4 * k + 4)

        def cdf(nu: NDArray[np.float64]) -> NDArray[np.float64]:
            return noncentral_f2_cdf(f, nu**2, dof)

        reaches = cdf(np.zeros_like(f)) > 1 - tail
        lower_near = np.zeros_like(f)
        if reaches.any():
            lower_near[reaches] = _solve(lambda nu: noncentral_f2_cdf(f[reaches], nu**2, dof), 1 - tail,
                                         np.zeros(int(reaches.sum())), x[near][reaches])
        lower[near] = lower_near
    return np.arctan(lower * s), np.arctan(upper * s)


def _solve(cdf: Callable[[NDArray[np.float64]], NDArray[np.float64]], target: float,
           low: NDArray[np.float64], high: NDArray[np.float64], steps: int = 48) -> NDArray[np.float64]:
    """ν with cdf(ν) = target for a cdf falling in ν, by bisection within [low, high] (the bracket's
    top is widened until the cdf there is below the target)."""
    for _ in range(20):
        above = cdf(high) > target
        if not above.any():
            break
        high = np.where(above, 2 * high + 1, high)
    for _ in range(steps):
        mid = (low + high) / 2
        falls = cdf(mid) > target
        low, high = np.where(falls, mid, low), np.where(falls, high, mid)
    return (low + high) / 2


@dataclass(frozen=True)
class ConingSensor:
    name: str
    values: NDArray[np.float64]  # b (V), S (V/g), Ω (rad), A (rad)
    covariance: NDArray[np.float64]  # 4×4, same order
    azimuth_defined: bool
    omega_interval: tuple[float, float] = (float("nan"), float("nan"))  # 95 %, rad (`omega_interval`)

    def to_json(self) -> dict[str, Any]:
        se = np.sqrt(np.diag(self.covariance))
        sd = np.where(se > 0, se, 1.0)
        corr = self.covariance / np.outer(sd, sd)
        b, s, omega, azimuth = self.values
        doc = {
            "b": b, "S": s, "omega_deg": np.degrees(omega),
            "azimuth_deg": np.degrees(azimuth) if self.azimuth_defined else None,
            "standard_errors": {"b": se[0], "S": se[1], "omega_deg": np.degrees(se[2]),
                                "azimuth_deg": np.degrees(se[3]) if self.azimuth_defined else None},
            "correlation": {"order": ["b", "S", "omega", "azimuth"], "matrix": corr.tolist()},
            "omega_interval_95_deg": [float(np.degrees(v)) for v in self.omega_interval],
        }
        if not self.azimuth_defined:
            doc["azimuth_note"] = (f"Ω is within {AZIMUTH_SIGNIFICANCE:g} standard errors of 0: the sensor "
                                   "axis is not measurably tilted, so its azimuth A is undefined")
            doc["correlation"] = {"order": ["b", "S", "omega"], "matrix": corr[:3, :3].tolist()}
            doc["omega_note"] = OMEGA_NEAR_ZERO
        doc["omega_interval_reliable"] = self.azimuth_defined
        return {k: (float(v) if isinstance(v, np.floating) else v) for k, v in doc.items()}


def tilt(column: NDArray[np.float64], cov: NDArray[np.float64], sensor: str) -> tuple[float, float]:
    """tan Ω̂ = |τ̂| of the tilt vector τ = (t1, t2)/m of one sensor's column (B, s_x, s_y, s_z
    covariance ``cov``), and the larger principal standard uncertainty of τ's components."""
    main, (i1, sign1), (i2, sign2) = _AXES[sensor]
    m = column[main]
    signs = np.diag([sign1, sign2])
    cov_t = signs @ cov[np.ix_([1 + i1, 1 + i2], [1 + i1, 1 + i2])] @ signs / m**2
    rho = float(np.hypot(sign1 * column[i1], sign2 * column[i2]))
    return rho / abs(float(m)), float(np.sqrt(max(np.linalg.eigvalsh(cov_t)[-1], 0.0)))


def coning_from_column(bias: float, column: NDArray[np.float64], cov: NDArray[np.float64],
                       sensor: str, dof: float = np.inf) -> ConingSensor:
    """(b, S, Ω, A) and covariance from one sensor's (B, s_x, s_y, s_z) and their 4×4 covariance
    (estimated on ``dof`` degrees of freedom), and Ω's 95 % interval."""
    main, (i1, sign1), (i2, sign2) = _AXES[sensor]
    m, t1, t2 = column[main], sign1 * column[i1], sign2 * column[i2]
    s = float(np.linalg.norm(column))
    rho = float(np.hypot(t1, t2))
    omega, azimuth = np.arctan2(rho, m), np.arctan2(t2, t1)
    # Jacobian d(b, S, Ω, A)/d(B, s_x, s_y, s_z), built in (m, t1, t2) then mapped to columns.
    jac = np.zeros((4, 4))
    jac[0, 0] = 1.0
    jac[1, 1:] = column / s
    d_omega = np.array([-rho, m * t1 / rho, m * t2 / rho]) / s**2 if rho > 0 else np.array([0.0, 1, 0]) / s
    d_azimuth = np.array([0.0, -t2, t1]) / rho**2 if rho > 0 else np.zeros(3)
    for k, (index, sign) in enumerate(((main, 1.0), (i1, sign1), (i2, sign2))):
        jac[2, 1 + index] = d_omega[k] * sign
        jac[3, 1 + index] = d_azimuth[k] * sign
    cov_out = jac @ cov @ jac.T
    defined = rho > 0 and omega > AZIMUTH_SIGNIFICANCE * np.sqrt(cov_out[2, 2])
    low, high = omega_interval(*tilt(column, cov, sensor), dof)
    return ConingSensor(sensor, np.array([bias, s, omega, azimuth]), cov_out, bool(defined),
                        (float(low), float(high)))


def coning(fit: Fit) -> list[ConingSensor]:
    """The coning parameters of every sensor from a fit (its first four coefficients per sensor)."""
    X = fit.coefficients
    largest = float(np.max(np.abs(X))) if np.all(np.isfinite(X)) else float("inf")
    if largest > MAX_COEFFICIENT:  # the angles' Jacobian squares them: keep it far from overflow
        raise LabcalError(f"the fitted coefficients reach {largest:.3g} V (or V/g), beyond any "
                          f"instrument (bound {MAX_COEFFICIENT:g}); the readings' voltages are not an "
                          "accelerometer's: check the readings file")
    return [coning_from_column(X[0, j], X[1:, j], fit.covariance(j)[:4, :4], name, float(fit.variance_dof[j]))
            for j, name in enumerate(SENSORS)]


def coning_json(fit: Fit) -> dict[str, Any]:
    doc = fit.to_json()
    doc["model"] = "coning"
    doc["sensors"] = {c.name: c.to_json() for c in coning(fit)}
    return doc
