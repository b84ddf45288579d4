"""Tripp & Tcheng's per-sensor model v = b + S·(u·g) as a change of variables of the linear fit.

Column j of S is sensor j's sensitivity vector s = S·u; the coning angle Ω is its angle from
the nominal axis and the azimuth A the direction of the tilt (unit vectors of DESIGN.md §3,
Tripp eqs. 2, 4, 5). The covariance follows through the Jacobian of that map. No iterative
solver is needed, and near Ω = 0 the azimuth is undefined and reported as such.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.attitude import MAX_COEFFICIENT  # the bound on a calibration read from a file
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
                   "interval ±1.96·u covers it 85 % of the time, not 95 % (tests/test_fit_options.py); "
                   "read it as 'Ω not distinguishable from 0'")


@dataclass(frozen=True)
class ConingSensor:
    name: str
    values: NDArray[np.float64]  # b (V), S (V/g), Ω (rad), A (rad)
    covariance: NDArray[np.float64]  # 4×4, same order
    azimuth_defined: bool

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
        }
        if not self.azimuth_defined:
            doc["azimuth_note"] = (f"Ω is within {AZIMUTH_SIGNIFICANCE:g} standard errors of 0: the sensor "
                                   "axis is not measurably tilted, so its azimuth A is undefined")
            doc["correlation"] = {"order": ["b", "S", "omega"], "matrix": corr[:3, :3].tolist()}
            doc["omega_note"] = OMEGA_NEAR_ZERO
        doc["omega_interval_reliable"] = self.azimuth_defined
        return {k: (float(v) if isinstance(v, np.floating) else v) for k, v in doc.items()}


def coning_from_column(bias: float, column: NDArray[np.float64], cov: NDArray[np.float64],
                       sensor: str) -> ConingSensor:
    """(b, S, Ω, A) and covariance from one sensor's (B, s_x, s_y, s_z) and their 4×4 covariance."""
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
    return ConingSensor(sensor, np.array([bias, s, omega, azimuth]), cov_out, bool(defined))


def coning(fit: Fit) -> list[ConingSensor]:
    """The coning parameters of every sensor from a fit (its first four coefficients per sensor)."""
    X = fit.coefficients
    largest = float(np.max(np.abs(X))) if np.all(np.isfinite(X)) else float("inf")
    if largest > MAX_COEFFICIENT:  # the angles' Jacobian squares them: keep it far from overflow
        raise LabcalError(f"the fitted coefficients reach {largest:.3g} V (or V/g), beyond any "
                          f"instrument (bound {MAX_COEFFICIENT:g}); the readings' voltages are not an "
                          "accelerometer's: check the readings file")
    return [coning_from_column(X[0, j], X[1:, j], fit.covariance(j)[:4, :4], name)
            for j, name in enumerate(SENSORS)]


def coning_json(fit: Fit) -> dict[str, Any]:
    doc = fit.to_json()
    doc["model"] = "coning"
    doc["sensors"] = {c.name: c.to_json() for c in coning(fit)}
    return doc
