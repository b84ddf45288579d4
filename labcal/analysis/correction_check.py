"""Whether a run that corrects for the calibration device's misalignments can still see them move, and
whether they did.

A plan that relies on a device correction fits the instrument with the misalignments a…k held at an
earlier estimate. Its readings still carry information about a change δ of the misalignments since
then: linearised at θ₀ = [correction; X̂], the device model (Soto eq. 11 with the six misalignments
free, `labcal.analysis.device_model`) gives the weighted readings' Jacobian J = [J_m | J_c]. With the
coefficients profiled out (P = I − J_c J_c⁺), the misalignments' information is F = J̃_mᵀJ̃_m with
J̃_m = P·J_m, and the change is estimated by δ̂ = F⁺·J̃_mᵀ r (r: the corrected fit's weighted
residuals; one Gauss–Newton step of the device model from the correction). A misalignment whose
column lies in the span of the coefficients' (a confounded one, `device_model.identifiability`) has no
information at all: a change of it moves nothing the run sees.

Under "no change", δ̂_m scatters by the run's own share (the readings' noise, F⁺; and the tables'
stated index and wobble errors through the same least squares, `device_fit.angle_error_shapes`) and by
the correction's own error (its history's u_h): s_m² = v_m + u_h,m². Each observable misalignment is
tested two-sided at α/n (Bonferroni over the n observable ones: the family-wise false-alarm rate is at
most α), so a change Δ is detected with power Φ(Δ/s − c) + Φ(−Δ/s − c), c = z(1 − α/2n). The change
detected with 95 % power is Δ₉₅ = (c + z₀.₉₅)·s (the far tail dropped: conservative).

The budget's u of a corrected misalignment is then max(u_h, Δ₉₅/3): the run's check detects a change
of 3 u with power ≥ 95 %, so a change it lets pass is covered by the budget; a plan that sees a
misalignment poorly pays for it in its U95, and one that cannot see it at all (u infinite) cannot rely
on the correction. The plan optimizer prices this against rig time like every other row.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.device_fit import AngleErrors, PointMeans, angle_error_shapes
from labcal.analysis.device_model import N_MIS, Geometry, jacobian
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES
from labcal.lazy import lazy

if TYPE_CHECKING:
    from scipy import stats
else:
    stats = lazy("scipy.stats")  # start-up without scipy, numpy

FALSE_ALARM = 0.01  # family-wise, over the observable misalignments of one run
POWER = 0.95  # for a change of CHANGE_IN_U × u
CHANGE_IN_U = 3.0
# singular value of the column-scaled profiled Jacobian, relative to the largest, that counts as 0
RANK_TOLERANCE = 1e-8


def _z(p: float) -> float:
    return float(stats.norm.ppf(p))


@dataclass(frozen=True)
class Sensitivity:
    """What a run at these points sees of a change of each misalignment (radians): the standard deviation
    of its estimate from the run alone (noise and tables; inf where it is not observable), and the
    operator that turns the weighted residuals into the estimate."""

    run_sd: NDArray[np.float64]  # (6,)
    gain: NDArray[np.float64]  # (6, 3G): δ̂ = gain @ weighted residuals (rows of unobservable ones: 0)

    @property
    def observable(self) -> tuple[str, ...]:
        return tuple(n for n, s in zip(MISALIGNMENT_NAMES, self.run_sd, strict=True) if np.isfinite(s))

    @property
    def critical(self) -> float:
        """The two-sided critical |z| of each test (Bonferroni over the observable ones)."""
        return _z(1.0 - FALSE_ALARM / (2 * max(len(self.observable), 1)))

    def null_sd(self, u_history: NDArray[np.float64]) -> NDArray[np.float64]:
        """s_m: how δ̂_m scatters when nothing moved (the run's share and the correction's own u)."""
        return np.asarray(np.sqrt(self.run_sd**2 + np.asarray(u_history) ** 2), dtype=float)

    def power(self, change: NDArray[np.float64], u_history: NDArray[np.float64]) -> NDArray[np.float64]:
        """Probability that a change of each misalignment by ``change`` (rad, one at a time) is detected."""
        shift = np.abs(np.asarray(change, dtype=float)) / self.null_sd(u_history)
        c = self.critical
        p = stats.norm.cdf(shift - c) + stats.norm.cdf(-shift - c)
        return np.asarray(np.where(np.isfinite(self.run_sd), p, 0.0), dtype=float)

    def detectable(self, u_history: NDArray[np.float64]) -> NDArray[np.float64]:
        """Δ₉₅ per misalignment (rad): the change detected with probability ≥ `POWER`; inf where unseen."""
        return np.asarray((self.critical + _z(POWER)) * self.null_sd(u_history), dtype=float)

    def budget_u(self, u_history: NDArray[np.float64]) -> NDArray[np.float64]:
        """The u the budget carries for each corrected misalignment: max(u_h, Δ₉₅/3)."""
        return np.asarray(np.maximum(np.asarray(u_history, dtype=float),
                                     self.detectable(u_history) / CHANGE_IN_U), dtype=float)


def _profiled(jac: NDArray[np.float64]) -> NDArray[np.float64]:
    """J̃_m = P·J_m: the misalignment columns with the coefficients' span projected out (P = I − QQᵀ)."""
    q, _ = np.linalg.qr(jac[:, N_MIS:])
    jm = jac[:, :N_MIS]
    return np.asarray(jm - q @ (q.T @ jm), dtype=float)


def sensitivity(where: Geometry, X: NDArray[np.float64], sensor_sd: NDArray[np.float64],
                correction_rad: NDArray[np.float64], angle_errors: AngleErrors | None = None,
                root_counts: NDArray[np.float64] | None = None) -> Sensitivity:
    """`Sensitivity` of readings at ``where`` (one row per distinct point, ``root_counts`` √ of each one's
    number of readings; default one each) of an instrument ``X`` (4×3) whose point means scatter by
    ``sensor_sd`` (3,) per reading, on a device at ``correction_rad`` (6,); the tables' stated angle
    errors add to the run's share as in `device_fit.angle_error_covariance`."""
    counts = np.ones(len(where.pitch)) if root_counts is None else np.asarray(root_counts, dtype=float)
    theta = np.concatenate([np.asarray(correction_rad, dtype=float), np.asarray(X, dtype=float).ravel()])
    _, jac = jacobian(theta, where)
    w = counts[:, None] / np.asarray(sensor_sd, dtype=float)[None, :]
    design = (jac * w[:, :, None]).reshape(-1, jac.shape[2])
    jt = _profiled(design)
    scale = np.linalg.norm(design[:, :N_MIS], axis=0)
    scale[scale == 0] = 1.0
    u_, sv, vt = np.linalg.svd(jt / scale, full_matrices=False)
    keep = sv > RANK_TOLERANCE * sv[0]
    # F⁺ in the scaled coordinates, restricted to the observable subspace
    f_pinv = (vt[keep].T / sv[keep] ** 2) @ vt[keep] / np.outer(scale, scale)
    gain = f_pinv @ jt.T  # (6, 3G)
    projector = vt[keep].T @ vt[keep]  # onto the observable subspace (scaled coordinates)
    seen = np.abs(np.diag(projector) - 1.0) < 1e-6
    cov = f_pinv.copy()  # the readings' noise: F⁺ F F⁺ = F⁺
    if angle_errors:
        for table, names, half in angle_errors.inputs():
            if half <= 0:
                continue
            shapes = angle_error_shapes(where.pitch if table == "pitch" else where.roll)
            for name in names:
                dv = jac[:, :, MISALIGNMENT_NAMES.index(name)] * w  # weighted δV per unit angle error
                for basis, share in shapes:
                    effect = gain @ (dv[:, :, None] * basis[:, None, :]).reshape(-1, basis.shape[1])
                    cov += (share * half**2 / 3.0) * (effect @ effect.T)
    run_sd = np.where(seen, np.sqrt(np.maximum(np.diag(cov), 0.0)), np.inf)
    gain[~seen] = 0.0
    return Sensitivity(np.asarray(run_sd, dtype=float), np.asarray(gain, dtype=float))


@dataclass(frozen=True)
class Change:
    """One misalignment's estimated change since the correction's estimate, judged by the run's check."""

    name: str
    change_rad: float
    null_sd_rad: float
    u_rad: float  # the correction's u (the budget's), the unit the change is stated in
    critical: float

    @property
    def z(self) -> float:
        return self.change_rad / self.null_sd_rad

    @property
    def detected(self) -> bool:
        return abs(self.z) > self.critical

    def describe(self, since: str) -> str:
        moved = self.change_rad / ARCSEC
        return (f"the calibration device's misalignment {self.name} has moved by {moved:+.1f}″ "
                f"({abs(self.change_rad) / self.u_rad:.1f} u) since {since}")

    def to_json(self) -> dict[str, float | str | bool]:
        return {"misalignment": self.name, "change_arcsec": self.change_rad / ARCSEC,
                "null_sd_arcsec": self.null_sd_rad / ARCSEC, "u_arcsec": self.u_rad / ARCSEC, "z": self.z,
                "critical_z": self.critical, "detected": self.detected}


def check(data: PointMeans, residuals: NDArray[np.float64], X: NDArray[np.float64],
          sensor_sd: NDArray[np.float64], correction_rad: NDArray[np.float64], u_history: NDArray[np.float64],
          u_budget: NDArray[np.float64], angle_errors: AngleErrors | None = None) -> list[Change]:
    """Each observable misalignment's change since the correction, estimated from a corrected run's
    readings (``data``: their point means; ``residuals``: every reading's residual (K×3) of the fit with
    the misalignments held at ``correction_rad``, coefficients ``X``) by one Gauss–Newton step of the
    device model from the correction, and judged against s_m (`Sensitivity.null_sd`)."""
    sens = sensitivity(data.where, X, sensor_sd, correction_rad, angle_errors, data.root_counts)
    counts = data.root_counts**2
    means = np.zeros((len(counts), 3))
    np.add.at(means, data.groups, np.asarray(residuals, dtype=float))
    means /= counts[:, None]
    weighted = means * data.root_counts[:, None] / np.asarray(sensor_sd, dtype=float)[None, :]
    delta = sens.gain @ weighted.ravel()  # residual = reading − model ≈ J·δ
    null = sens.null_sd(u_history)
    return [Change(n, float(delta[i]), float(null[i]), float(u_budget[i]), sens.critical)
            for i, n in enumerate(MISALIGNMENT_NAMES) if n in sens.observable]
