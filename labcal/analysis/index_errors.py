"""Per-angle index errors of the two tables, estimated beside the device model.

A table that stops at an angle errs the same way every time it returns there: the pitch table's
index error at pitch pᵢ adds to the pitch misalignment a at every point at pᵢ (prot(p)·prot(a) is
a rotation by p + a), the roll table's at rⱼ to the plate roll f (rrot(r)·rrot(f)). So the
extension is one extra parameter per visited angle of each table, zero-mean per table (the mean is
a and f themselves), written in an orthonormal basis of zero-sum vectors. Contrasts the plan cannot
separate from the device model (a roll error at pitch ±90° is a rotation about gravity) are left
out, column by column, as the linear model's extensions are (`labcal.analysis.fit`). The extension
is accepted only when its extra-sum-of-squares F test against the device model says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.device_fit import DeviceFit, NestedTest, PointMeans
from labcal.analysis.device_model import N_MIS, N_PARAMETERS, jacobian
from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import _estimable
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, Misalignment
from labcal.analysis.readings import Readings
from labcal.analysis.regression import least_squares
from labcal.analysis.replication import ALPHA

A, F = MISALIGNMENT_NAMES.index("a"), MISALIGNMENT_NAMES.index("f")
ITERATIONS = 8  # Gauss–Newton from the device fit; index errors are arcseconds, the problem nearly linear
CONVERGED = 1e-12  # largest step (rad, or relative coefficient) at which the iteration stops


def zero_sum_basis(n: int) -> NDArray[np.float64]:
    """n × (n − 1) orthonormal columns orthogonal to (1, …, 1)."""
    q, _ = np.linalg.qr(np.column_stack([np.ones(n), np.eye(n)[:, : max(n - 1, 0)]]))
    basis: NDArray[np.float64] = q[:, 1:n]
    return basis


def _visited(angle_rad: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Distinct table angles (degrees, 0..360) and each point's index among them."""
    key = np.round(np.degrees(angle_rad) % 360.0, 9) % 360.0
    angles, index = np.unique(key, return_inverse=True)
    return angles, index.ravel()


@dataclass(frozen=True)
class TableErrors:
    angles_deg: NDArray[np.float64]
    value_rad: NDArray[np.float64]
    u_rad: NDArray[np.float64]
    kept: int  # contrasts estimated
    possible: int  # visited angles − 1

    def to_json(self, k: float) -> dict[str, Any]:
        return {"angles": [{"angle_deg": float(a), "value_arcsec": float(v / ARCSEC),
                            "u_arcsec": float(u / ARCSEC), "U_arcsec": float(k * u / ARCSEC)}
                           for a, v, u in zip(self.angles_deg, self.value_rad, self.u_rad, strict=True)],
                "contrasts_estimated": self.kept, "contrasts_possible": self.possible}


@dataclass(frozen=True)
class IndexErrors:
    pitch: TableErrors
    roll: TableErrors
    misalignment_rad: NDArray[np.float64]  # a…k re-estimated with the index errors
    misalignment_u_rad: NDArray[np.float64]
    test: NestedTest
    k95: float

    @property
    def accepted(self) -> bool:
        return self.test.p_value < ALPHA

    def to_json(self) -> dict[str, Any]:
        return {"accepted": self.accepted, "test": self.test.to_json(),
                "pitch_table": self.pitch.to_json(self.k95), "roll_table": self.roll.to_json(self.k95),
                "misalignments": {n: {"value_arcsec": float(v / ARCSEC), "u_arcsec": float(u / ARCSEC),
                                      "U_arcsec": float(self.k95 * u / ARCSEC)}
                                  for n, v, u in zip(MISALIGNMENT_NAMES, self.misalignment_rad,
                                                     self.misalignment_u_rad, strict=True)},
                "note": "index errors are zero-mean over the angles each table visited; their mean is in a "
                        "(pitch table) and f (roll table)"}


def fit_index_errors(readings: Readings, device: DeviceFit) -> IndexErrors | None:
    """The device model plus per-angle index errors, from the device fit; None when the plan leaves
    no index-error contrast identifiable."""
    data = PointMeans.of(readings)
    sd = device.sensor_sd
    pitch_angles, pi = _visited(data.where.pitch)
    roll_angles, ri = _visited(data.where.roll)
    bases = (zero_sum_basis(len(pitch_angles)), zero_sum_basis(len(roll_angles)))
    n_p = bases[0].shape[1]
    weight = data.root_counts[:, None] / sd[None, :]

    def system(theta: NDArray[np.float64], eta: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        dp, dr = (bases[0] @ eta[:n_p])[pi], (bases[1] @ eta[n_p:])[ri]
        model, jac = jacobian(theta, data.where, Misalignment(a=dp, f=dr))
        extra = np.concatenate([jac[:, :, A, None] * bases[0][pi][:, None, :],
                                jac[:, :, F, None] * bases[1][ri][:, None, :]], axis=2)
        design = np.concatenate([jac, extra], axis=2) * weight[:, :, None]
        return model, ((model - data.means) * weight).ravel(), design.reshape(-1, design.shape[2])

    theta, eta = device.theta.copy(), np.zeros(n_p + bases[1].shape[1])
    _, _, design = system(theta, eta)
    keep = _estimable(design, N_PARAMETERS)
    if len(keep) == N_PARAMETERS:
        return None
    kept_eta = keep[N_PARAMETERS:] - N_PARAMETERS
    for _ in range(ITERATIONS):
        _, resid, design = system(theta, eta)
        step = least_squares(design[:, keep], -resid)
        delta = step.coef[:, 0]
        theta += delta[:N_PARAMETERS]
        eta[kept_eta] += delta[N_PARAMETERS:]
        size = np.maximum(1.0, np.abs(np.concatenate([theta, eta[kept_eta]])))
        if np.max(np.abs(delta) / size) < CONVERGED:
            break
    model, resid, design = system(theta, eta)
    cov_unscaled = least_squares(design[:, keep], -resid).cov_unscaled
    n, q = len(readings), len(keep) - N_PARAMETERS
    dof = 3 * n - N_PARAMETERS - q
    weighted_sse = float(np.sum(((readings.volts - model[data.groups]) / sd) ** 2))
    cov = weighted_sse / dof * cov_unscaled
    extra_sse = float(np.sum((device.residuals / sd) ** 2)) - weighted_sse
    if device.linear.replication is not None:  # weights 1/σ_prec²: the pure-error mean square is 1
        test = NestedTest(max(extra_sse, 0.0) / q, (q, device.test.df[1]), "pure error (replicate scatter)")
    else:
        test = NestedTest(max(extra_sse, 0.0) / q / (weighted_sse / dof), (q, dof), "extended model residual")
    tables = []
    for angles, basis, start, stop in ((pitch_angles, bases[0], 0, n_p),
                                       (roll_angles, bases[1], n_p, len(eta))):
        cols = np.array([i for i, c in enumerate(kept_eta) if start <= c < stop], dtype=int)
        b = basis[:, kept_eta[cols] - start]
        c_eta = cov[np.ix_(N_PARAMETERS + cols, N_PARAMETERS + cols)]
        u = np.sqrt(np.einsum("ij,jk,ik->i", b, c_eta, b))
        tables.append(TableErrors(angles, b @ eta[kept_eta[cols]], u, len(cols), basis.shape[1]))
    return IndexErrors(tables[0], tables[1], theta[:N_MIS], np.sqrt(np.diag(cov)[:N_MIS]), test,
                       float(t_quantile(0.975, dof)))
