"""Mount repeatability estimated from replicates: how far the instrument's seating on the plate
(its pitch, roll and yaw, Soto's e, f, k) scatters from one mounting to the next.

A replicated plan re-seats the instrument for every (replicate, mount) block, so each mounting
carries its own small rotation δ = (e, f, k). Taken against the point means over the replicates,
the readings of one mounting deviate by J·(δ_r − δ̄) + noise, where J = ∂V/∂(e, f, k) at that
mount's points; everything that repeats at a point (index errors, device misalignments, model
inadequacy) cancels in the deviation. Fitting δ_r − δ̄ per mounting and pooling their scatter over
the mounts is the marginal drift component of Tripp & Tcheng's replicated-calibration statistics
(reference/metrology_stats.md §2.5): s² = Σ‖δ_r − δ̄‖² / (3·(R − 1)·M), and
σ̂²_mount = max(0, s² − MS_E·tr((JᵀJ)⁻¹)/3), with MS_E the residual of the deviations after the
fitted rotations (what noise alone puts into the fitted δ).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.fit import point_keys
from labcal.analysis.kinematics import Misalignment, gravity
from labcal.analysis.readings import Readings

PLATE = ("e", "f", "k")  # the plate's yaw, roll and pitch about the instrument's axes (Soto Fig. 2)
COMPLEX_STEP = 1e-30


@dataclass(frozen=True)
class MountScatter:
    """σ of each of the plate's three angles per mounting (rad), with its degrees of freedom."""

    sd_rad: float
    dof: int
    mounts: int
    replicates: int


def _plate_jacobian(readings: Readings, rows: NDArray[np.intp], X: NDArray[np.float64]
                    ) -> NDArray[np.float64]:
    """∂vec(V)/∂(e, f, k) at the readings ``rows`` (3n × 3), exact by complex step."""
    p, r, y, u = (np.radians(a[rows]) for a in (readings.pitch_deg, readings.roll_deg, readings.y_deg,
                                                 readings.u_deg))
    columns = []
    for name in PLATE:
        g = gravity(p, r, y, u, Misalignment(**{name: 1j * COMPLEX_STEP}))
        columns.append((np.imag(g) / COMPLEX_STEP @ X[1:]).ravel())
    return np.column_stack(columns)


def mount_scatter(readings: Readings, X: NDArray[np.float64]) -> MountScatter | None:
    """The mount repeatability the replicates show (None: no mount was seated twice)."""
    replicates = np.unique(readings.replicate)
    if len(replicates) < 2:
        return None
    _, point = np.unique(point_keys(readings), axis=0, return_inverse=True)
    point = point.ravel()
    means = np.zeros((point.max() + 1, 3))
    np.add.at(means, point, readings.volts)
    means /= np.bincount(point)[:, None]
    deviation = readings.volts - means[point]
    mounts = np.round(np.column_stack([readings.y_deg, readings.u_deg]) % 360.0, 6)
    between, residual, trace, dof_between, dof_residual, n_mounts = 0.0, 0.0, 0.0, 0, 0, 0
    for mount in np.unique(mounts, axis=0):
        in_mount = np.all(mounts == mount, axis=1)
        seated = np.unique(readings.replicate[in_mount])
        if len(seated) < 2:
            continue
        n_mounts += 1
        for rep in seated:
            rows = np.flatnonzero(in_mount & (readings.replicate == rep))
            J = _plate_jacobian(readings, rows, X)
            d = deviation[rows].ravel()
            delta, *_ = np.linalg.lstsq(J, d, rcond=None)
            between += float(delta @ delta)
            residual += float(np.sum((d - J @ delta) ** 2))
            dof_residual += J.shape[0] - len(PLATE)
        # each mounting's deviations sum to zero over the replicates: R − 1 free rotations per mount
        dof_between += len(PLATE) * (len(seated) - 1)
        trace += (len(seated) - 1) * float(np.trace(np.linalg.inv(J.T @ J)))
        dof_residual -= J.shape[0] - len(PLATE)  # the point means: one mounting's worth per mount
    if n_mounts == 0 or dof_residual <= 0:
        return None
    ms_e = residual / dof_residual
    variance = max(0.0, (between - ms_e * trace) / dof_between)
    return MountScatter(float(np.sqrt(variance)), dof_between, n_mounts, len(replicates))
