"""The one linear least-squares core every model uses (docs/design.md §3).

Solved by a thin QR factorisation, never the normal equations: the normal equations
square the design's condition number, which costs digits a calibration cannot spare.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from labcal.errors import LabcalError

RANK_TOLERANCE = 1e-10  # smallest singular value of the column-scaled design, relative to the largest
ZERO_COLUMN = 1e-12  # a column this much smaller than the largest is zero to rounding


@dataclass(frozen=True)
class LeastSquares:
    """Fit of Y (K×m) = F (K×L) · coef (L×m) + e, one column of Y per sensor."""

    coef: NDArray[np.float64]  # (L, m)
    cov_unscaled: NDArray[np.float64]  # (L, L) = (FᵀF)⁻¹, shared by every column
    residuals: NDArray[np.float64]  # (K, m)

    @property
    def n_obs(self) -> int:
        return int(self.residuals.shape[0])

    @property
    def dof(self) -> int:
        return self.n_obs - int(self.coef.shape[0])

    @cached_property
    def residual_se(self) -> NDArray[np.float64]:
        """S_E = √(eᵀe / (K − L)) per column (Tripp eq. 34); NaN when no degree of freedom is left."""
        if self.dof == 0:
            return np.full(self.coef.shape[1], np.nan)
        se: NDArray[np.float64] = np.sqrt(np.sum(self.residuals**2, axis=0) / self.dof)
        return se

    @property
    def stderr(self) -> NDArray[np.float64]:
        """Standard error of every coefficient, (L, m)."""
        return np.sqrt(np.diag(self.cov_unscaled))[:, None] * self.residual_se[None, :]

    def covariance(self, column: int) -> NDArray[np.float64]:
        """Coefficient covariance S_E² (FᵀF)⁻¹ of one column (one sensor)."""
        return float(self.residual_se[column]) ** 2 * self.cov_unscaled


def least_squares(design: NDArray[np.float64], observations: NDArray[np.float64]) -> LeastSquares:
    """Solve the least-squares problem by QR; refuse a design that cannot determine every coefficient."""
    design = np.asarray(design, dtype=float)
    observations = np.asarray(observations, dtype=float)
    if observations.ndim == 1:
        observations = observations[:, None]
    n_obs, n_coef = design.shape
    if n_obs < n_coef:
        raise _too_few(n_obs, n_coef)
    scale = np.linalg.norm(design, axis=0)
    # A column of rounding noise (sin 180° ≈ 1e-16) is zero; scaling must not blow it up to unit norm.
    null_column = scale <= ZERO_COLUMN * scale.max()
    scale[null_column] = 1.0
    q, r = np.linalg.qr(design / scale)
    singular = np.linalg.svd(r, compute_uv=False)
    if np.any(null_column) or singular[-1] <= RANK_TOLERANCE * singular[0]:
        raise _singular(n_coef)
    # R is upper triangular: LU with partial pivoting never swaps a row and is back substitution
    # (the same numbers as a triangular solve, without importing scipy.linalg for it)
    r_inv = np.linalg.solve(r, np.eye(n_coef)) / scale[:, None]
    coef = r_inv @ (q.T @ observations)
    residuals = observations - design @ coef
    return LeastSquares(coef=coef, cov_unscaled=r_inv @ r_inv.T, residuals=residuals)


def least_squares_of_means(point_design: NDArray[np.float64], means: NDArray[np.float64],
                           counts: NDArray[np.float64], observations: NDArray[np.float64],
                           groups: NDArray[np.intp]) -> LeastSquares:
    """The fit of every observation (K×m) when its design row is its group's (``point_design``, G×L):
    QR of the group means weighted by √count gives the same normal equations (FᵀF = Σ c·f fᵀ,
    FᵀY = Σ c·f ȳ), so the same coefficients and (FᵀF)⁻¹, at G rows instead of K; the residuals
    are every observation's, and the degrees of freedom K − L."""
    n_coef = point_design.shape[1]
    if len(observations) < n_coef:
        raise _too_few(len(observations), n_coef)
    if len(point_design) < n_coef:  # enough readings, too few distinct points
        raise _singular(n_coef)
    weight = np.sqrt(counts)[:, None]
    ls = least_squares(point_design * weight, means * weight)
    fitted = point_design @ ls.coef
    residuals = observations - np.take(fitted, groups, axis=0)  # take: 7× faster than fitted[groups]
    return LeastSquares(coef=ls.coef, cov_unscaled=ls.cov_unscaled, residuals=residuals)


def _too_few(n_obs: int, n_coef: int) -> LabcalError:
    return LabcalError(f"{n_obs} points cannot determine {n_coef} coefficients per sensor; "
                       "add points or mounts to the plan")


def _singular(n_coef: int) -> LabcalError:
    return LabcalError(f"the points do not determine all {n_coef} coefficients (the design is singular); "
                       "spread the points over more pitch and roll angles")
