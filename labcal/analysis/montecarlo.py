"""The same budget propagated by Monte Carlo (JCGM 101): a check on the linear budget's U95.

Each trial draws every elementary input of the budget from its own distribution — rectangular
inputs uniformly, Type A inputs from Student's t at their degrees of freedom (JCGM 101 6.4.9: the
coefficients of one sensor share one χ² draw, a multivariate t), normal ones normally — builds the
coefficients the fit would have produced and the reading the instrument would give, and infers
the attitude with the weighted least-squares estimator on the sphere exactly, not linearised. The
95 % coverage interval is the probabilistically symmetric one (JCGM 101 7.7); its half-width is
compared with the linear k·u_c.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.attitude import _gravity_and_derivatives
from labcal.analysis.budget import Calibration, Component, Source, estimator_weights, regressors

GN_ITERATIONS = 6
CHUNK = 4000  # trials per batch: bounds memory for plans with many elementary inputs


def _draw(c: Component, n: int, rng: np.random.Generator, chi: dict[str, NDArray[np.float64]]
          ) -> NDArray[np.float64]:
    """The component's elementary inputs in units of u (m×n); components naming one estimate share
    its χ² draw (``chi``, filled as they come), as one sensor's coefficients and new reading do."""
    m = c.jac_x.shape[1]
    if c.distribution == "rectangular":
        e = rng.uniform(-np.sqrt(3.0), np.sqrt(3.0), size=(m, n))
    else:
        e = rng.standard_normal((m, n))
        if c.distribution == "t" and np.isfinite(c.dof):
            # t_ν with scale u (JCGM 101 6.4.9.7): wider than u by √(ν/(ν−2)), as k = t(ν) is in GUM
            key = c.estimate or str(id(c))
            if key not in chi:
                chi[key] = np.sqrt(c.dof / rng.chisquare(c.dof, size=n))
            e *= chi[key][None, :]
    return e


def estimate(X: NDArray[np.float64], volts: NDArray[np.float64], w: NDArray[np.float64]
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pitch and roll (rad) from readings (N×3) with per-trial coefficients (N×4×3): the closed form,
    then Gauss–Newton on the unit sphere with the fixed weights ``w`` (3,)."""
    B, S = X[:, 0], X[:, 1:]
    g = np.linalg.solve(np.swapaxes(S, 1, 2), (volts - B)[..., None])[..., 0]
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    pitch, roll = np.arcsin(np.clip(g[:, 0], -1, 1)), np.arctan2(g[:, 1], g[:, 2])
    for _ in range(GN_ITERATIONS):
        g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
        resid = volts - B - np.einsum("ni,nij->nj", g, S)
        fp, fr = np.einsum("ni,nij->nj", dg_dp, S), np.einsum("ni,nij->nj", dg_dr, S)
        a, b, c = (np.sum(w * x * y, axis=1) for x, y in ((fp, fp), (fp, fr), (fr, fr)))
        rp, rr = np.sum(w * fp * resid, axis=1), np.sum(w * fr * resid, axis=1)
        det = a * c - b * b
        pitch, roll = pitch + (c * rp - b * rr) / det, roll + (a * rr - b * rp) / det
    return pitch, roll


@dataclass(frozen=True)
class MonteCarlo:
    """The 95 % half-widths (rad) of the pitch and roll errors at one attitude, and the errors."""

    pitch: float
    roll: float
    trials: int
    half_width: tuple[float, float]
    errors: NDArray[np.float64]  # (trials, 2)


def monte_carlo(cal: Calibration, rows: list[Source], pitch: float, roll: float, trials: int,
                seed: int = 0) -> MonteCarlo:
    """JCGM 101 propagation of the added sources to the attitude (radians) at one attitude."""
    rng = np.random.default_rng(seed)
    f = regressors(np.array([pitch]), np.array([roll]))
    w = estimator_weights(cal, f)[0]
    v_true = (f @ cal.X)[0]
    errors = []
    for start in range(0, trials, CHUNK):
        n = min(CHUNK, trials - start)
        dX = np.zeros((12, n))
        dv = np.zeros((3, n))
        chi: dict[str, NDArray[np.float64]] = {}
        for source in rows:
            if not source.added:
                continue
            for c in source.components:
                e = _draw(c, n, rng, chi) * c.u
                dX += c.jac_x @ e
                dv += c.jac_v @ e
        X = cal.X[None] + dX.T.reshape(n, 4, 3)
        p, r = estimate(X, v_true[None] + dv.T, w)
        errors.append(np.column_stack([p - pitch, (r - roll + np.pi) % (2 * np.pi) - np.pi]))
    err = np.concatenate(errors)
    low, high = np.quantile(err, [0.025, 0.975], axis=0)
    half = (high - low) / 2
    return MonteCarlo(pitch, roll, trials, (float(half[0]), float(half[1])), err)
