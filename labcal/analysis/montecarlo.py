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

from labcal.analysis.attitude import LOCAL_GRAVITY_TOLERANCE, LOCAL_GRAVITY_U, _gravity_and_derivatives
from labcal.analysis.budget import (
    LOCAL_GRAVITY,
    Calibration,
    Component,
    Source,
    estimator_weights,
    regressors,
)

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


def estimate(X: NDArray[np.float64], volts: NDArray[np.float64], w: NDArray[np.float64],
             gravity_u: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pitch and roll (rad) from readings (N×3) with per-trial coefficients (N×4×3): the closed form,
    then Gauss–Newton with the fixed weights ``w`` (3,) — on the unit sphere, or with ``gravity_u`` >
    0 over pitch, roll and |g| = m with the prior m = 1 ± gravity_u, as `labcal attitude` estimates
    (`labcal.analysis.attitude.sphere_least_squares`)."""
    B, S = X[:, 0], X[:, 1:]
    g = np.linalg.solve(np.swapaxes(S, 1, 2), (volts - B)[..., None])[..., 0]
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    pitch, roll = np.arcsin(np.clip(g[:, 0], -1, 1)), np.arctan2(g[:, 1], g[:, 2])
    m = np.ones(len(volts))
    prior = 1.0 / gravity_u**2 if gravity_u > 0 else 0.0
    for _ in range(GN_ITERATIONS):
        g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
        gS = np.einsum("ni,nij->nj", g, S)
        resid = volts - B - m[:, None] * gS
        J = np.stack([m[:, None] * np.einsum("ni,nij->nj", dg_dp, S),
                      m[:, None] * np.einsum("ni,nij->nj", dg_dr, S), gS], axis=1)  # n × (p, r, m) × 3
        N = np.einsum("nai,i,nbi->nab", J, w, J)
        rhs = np.einsum("nai,i,ni->na", J, w, resid)
        if prior:
            N[:, 2, 2] += prior
            rhs[:, 2] -= prior * (m - 1.0)
        else:  # |g| = 1: m is not estimated
            N[:, 2, :], N[:, :, 2], rhs[:, 2] = 0.0, 0.0, 0.0
            N[:, 2, 2] = 1.0
        step = np.linalg.solve(N, rhs[..., None])[..., 0]
        pitch, roll, m = pitch + step[:, 0], roll + step[:, 1], m + step[:, 2]
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
    g_S = f[0, 1:] @ cal.X[1:]  # the outputs' part that scales with |g|
    with_gravity = any(s.name == LOCAL_GRAVITY and s.added for s in rows)
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
        volts = v_true[None] + dv.T
        if with_gravity:  # local gravity in use: anywhere within the prior's ± tolerance
            volts += rng.uniform(-LOCAL_GRAVITY_TOLERANCE, LOCAL_GRAVITY_TOLERANCE, (n, 1)) * g_S
        p, r = estimate(X, volts, w, LOCAL_GRAVITY_U)
        errors.append(np.column_stack([p - pitch, (r - roll + np.pi) % (2 * np.pi) - np.pi]))
    err = np.concatenate(errors)
    low, high = np.quantile(err, [0.025, 0.975], axis=0)
    half = (high - low) / 2
    return MonteCarlo(pitch, roll, trials, (float(half[0]), float(half[1])), err)
