"""The lack-of-fit and drift tests (`labcal.analysis.lack_of_fit`): checked against ordinary least
squares computed here with numpy, and by simulated data whose errors are known."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.analysis.lack_of_fit import lack_of_fit


def _linear_design(k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """K points on the sphere and the linear model's Jacobian (K × 3 × 12): [1, g] per output."""
    g = rng.normal(size=(k, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    F = np.column_stack([np.ones(k), g])
    jac = np.zeros((k, 3, 12))
    for c in range(3):
        jac[:, c, 4 * c:4 * c + 4] = F
    return F, jac


def test_without_bench_errors_the_statistic_is_the_residual_sum_of_squares_over_the_noise():
    """With no bench error stated, Q is Σ_c RSS_c / σ_c² of the per-output least squares (3K − 12
    degrees of freedom): numpy's lstsq, not the module's projection."""
    rng = np.random.default_rng(1)
    F, jac = _linear_design(40, rng)
    sigma = np.array([1e-5, 2e-5, 3e-5])
    volts = F @ rng.normal(size=(4, 3)) + rng.normal(size=(40, 3)) * sigma
    coef = np.linalg.lstsq(F, volts, rcond=None)[0]
    residuals = volts - F @ coef
    rss = np.sum(residuals**2, axis=0)
    result = lack_of_fit(residuals, jac, np.tile(sigma**2, (40, 1)), {}, 500.0)
    assert result.dof[0] == 3 * 40 - 12
    assert result.statistic == pytest.approx(np.sum(rss / sigma**2) / (3 * 40 - 12), rel=1e-9)
    assert 0.01 < result.p_value  # the data are the model's: no lack of fit (this seed: p ≈ 0.6)


def test_bench_errors_larger_than_stated_are_found_and_as_stated_are_not():
    """A bench error per point (K columns, one per point, on output x) stated at u; the data carry it
    at u (not flagged) or at 3u (flagged, its score ratio near 9)."""
    rng = np.random.default_rng(2)
    k, sigma, u = 60, 1e-5, 3e-5
    F, jac = _linear_design(k, rng)
    bench = np.zeros((k, 3, k))
    bench[np.arange(k), 0, np.arange(k)] = u
    ratios = {}
    for scale in (1.0, 3.0):
        volts = F @ np.eye(4, 3) + rng.normal(size=(k, 3)) * sigma
        volts[:, 0] += scale * u * rng.normal(size=k)
        residuals = volts - F @ np.linalg.lstsq(F, volts, rcond=None)[0]
        result = lack_of_fit(residuals, jac, np.full((k, 3), sigma**2), {"tables": bench}, 1000.0)
        ratios[scale] = result.bench[0].ratio
        assert result.significant == (scale == 3.0), (scale, result)
    assert 0.5 < ratios[1.0] < 2.0 and 5.0 < ratios[3.0] < 15.0


def test_a_trend_over_the_run_is_a_drift_and_noise_is_not():
    rng = np.random.default_rng(3)
    k, sigma = 64, 1e-5
    F, jac = _linear_design(k, rng)
    for slope, drifting in ((0.0, False), (20 * sigma, True)):
        volts = F @ np.eye(4, 3) + rng.normal(size=(k, 3)) * sigma
        volts[:, 1] += slope * np.linspace(-0.5, 0.5, k)
        residuals = volts - F @ np.linalg.lstsq(F, volts, rcond=None)[0]
        result = lack_of_fit(residuals, jac, np.full((k, 3), sigma**2), {}, 1000.0)
        assert result.drift_significant == drifting and result.drift_dof == 3, (slope, result)
