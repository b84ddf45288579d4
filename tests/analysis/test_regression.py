"""The least-squares core: exactness, honest standard errors, and refusal of singular designs."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FOUR_MOUNTS, soto_plan

from labcal.analysis.fit import fit_readings
from labcal.analysis.regression import least_squares
from labcal.config.emulation import InstrumentTruth
from labcal.errors import LabcalError
from labcal.sim.direct import simulate_readings


def test_qr_keeps_digits_the_normal_equations_lose():
    """Cubic in x on [10, 11]: cond(F) ≈ 7e7, so the normal equations (cond²) keep ~2 digits
    where QR keeps ~8 (error ≈ cond · machine epsilon)."""
    x = np.linspace(10, 11, 50)
    F = np.vander(x, 4, increasing=True)
    beta = np.array([1.0, -2.0, 3.0, -4.0])
    y = F @ beta
    qr_error = np.max(np.abs(least_squares(F, y).coef[:, 0] - beta) / np.abs(beta))
    normal_error = np.max(np.abs(np.linalg.solve(F.T @ F, F.T @ y) - beta) / np.abs(beta))
    assert qr_error < 1e-6
    assert normal_error > 100 * qr_error


def test_standard_errors_equal_textbook_formula():
    rng = np.random.default_rng(7)
    F = np.column_stack([np.ones(40), rng.normal(size=(40, 3))])
    Y = F @ rng.normal(size=(4, 2)) + rng.normal(0, 0.1, (40, 2))
    ls = least_squares(F, Y)
    beta, *_ = np.linalg.lstsq(F, Y, rcond=None)
    s2 = np.sum((Y - F @ beta) ** 2, axis=0) / 36
    se = np.sqrt(np.outer(np.diag(np.linalg.inv(F.T @ F)), s2))
    assert np.allclose(ls.coef, beta, rtol=1e-12)
    assert np.allclose(ls.stderr, se, rtol=1e-10)
    assert ls.dof == 36


def test_fewer_points_than_coefficients_is_refused():
    with pytest.raises(LabcalError, match="3 points cannot determine 4 coefficients"):
        least_squares(np.ones((3, 4)), np.ones(3))


def test_singular_design_is_refused():
    F = np.column_stack([np.ones(10), np.arange(10), 2 * np.arange(10)])
    with pytest.raises(LabcalError, match="singular"):
        least_squares(F, np.arange(10.0))


def test_standard_errors_are_honest_monte_carlo():
    """Over 400 noisy four-mount calibrations the scatter of every coefficient equals the
    standard error the fit reports (within the ±10 % a 400-sample SD allows at ~3σ)."""
    truth = InstrumentTruth(B=[0.01, -0.02, 0.005], S=[[5, 0.01, 0], [0, 4.9, 0.02], [0.01, 0, 5.1]])
    plan = soto_plan(FOUR_MOUNTS)
    fits = [fit_readings(simulate_readings(plan, truth, noise_v=1e-4, seed=s)) for s in range(400)]
    X = np.array([f.coefficients for f in fits])
    reported = np.mean([f.ls.stderr for f in fits], axis=0)
    ratio = X.std(axis=0, ddof=1) / reported
    assert np.all(np.abs(ratio - 1) < 0.12), ratio
    # and the estimates are unbiased: the mean sits within 4 standard errors of the mean
    assert np.all(np.abs(X.mean(axis=0) - truth.X) < 4 * reported / np.sqrt(400))
