"""The t, F and χ² functions (scipy.special underneath) against closed forms and published tables:
what labcal asks of them — the quantile for a probability, the tail for a statistic, at the
degrees of freedom it uses, with numpy's shapes — checked against numbers it did not compute."""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest

from labcal.analysis.distributions import chi2_cdf, chi2_quantile, f_isf, f_sf, t_quantile

P = np.array([1e-9, 1e-6, 0.001, 0.025, 0.05, 0.3, 0.45, 0.55, 0.7, 0.9, 0.95, 0.975, 0.99, 0.999, 1 - 1e-6])
DOF = [1.5, 3, 4.7, 10, 57, 186.3, 1e3, 5e3, 9999, 1e4, 1e5, 1e7]


def test_t_quantile_matches_its_closed_forms():
    """ν = 1 is Cauchy, tan(π(p − ½)); ν = 2 is (2p − 1)/√(2p(1 − p)); ν = ∞ is the normal."""
    p = P[2:-1]  # where the closed forms themselves keep their digits
    assert t_quantile(p, 1) == pytest.approx(np.tan(np.pi * (p - 0.5)), rel=1e-12)
    assert t_quantile(p, 2) == pytest.approx((2 * p - 1) / np.sqrt(2 * p * (1 - p)), rel=1e-12)
    assert t_quantile(p, np.inf) == pytest.approx([NormalDist().inv_cdf(x) for x in p], rel=1e-14)


def test_t_quantile_matches_a_published_table():
    """Two-sided 95 % critical values, NIST/SEMATECH e-Handbook §1.3.6.7.2 (three decimals)."""
    table = {1: 12.706, 2: 4.303, 5: 2.571, 10: 2.228, 30: 2.042, 100: 1.984}
    for dof, value in table.items():
        assert float(t_quantile(0.975, dof)) == pytest.approx(value, abs=5e-4)


def test_t_quantile_keeps_the_shape_and_edges():
    nu = np.array([[3.0, np.inf], [57.0, 1e7]])
    k = t_quantile(0.975, nu)
    assert k.shape == (2, 2) and k[0, 1] == pytest.approx(NormalDist().inv_cdf(0.975), rel=1e-14)
    assert k[0, 0] == pytest.approx(3.182, abs=5e-4)  # NIST/SEMATECH §1.3.6.7.2, ν = 3
    assert t_quantile(0.975, 57).shape == ()
    assert np.isnan(t_quantile(0.975, np.nan)) and np.isnan(t_quantile(0.975, 0.0))
    assert t_quantile(0.5, 7) == 0.0
    assert t_quantile([0.0, 1.0], 7).tolist() == [-math.inf, math.inf]
    many = np.arange(1, 2001, dtype=float)  # an uncertainty budget's grid of ν_eff: one call, in order
    k = t_quantile(0.975, many)
    assert k.shape == (2000,) and np.all(np.diff(k) < 0) and k[1] == pytest.approx(4.303, abs=5e-4)


def test_f_critical_values_match_a_published_table():
    """Upper 5 % points of F, NIST/SEMATECH e-Handbook §1.3.6.7.3 (three decimals)."""
    table = {(1, 10): 4.965, (3, 60): 2.758, (6, 100): 2.191, (10, 10): 2.978}
    for (dfn, dfd), value in table.items():
        assert float(f_isf(0.05, dfn, dfd)) == pytest.approx(value, abs=5e-4)


@pytest.mark.parametrize("dfd", [1, 3, 10, 57, 300])
def test_f_with_two_numerator_degrees_matches_its_closed_form(dfd):
    """F(2, n) has the tail P(F > x) = (1 + 2x/n)^(−n/2) (Johnson, Kotz & Balakrishnan, ch. 27),
    and the critical value inverts it: x = n/2 · (α^(−2/n) − 1)."""
    x = np.array([0.0, 0.01, 0.5, 1.0, 2.5, 10.0, 100.0])
    assert f_sf(x, 2, dfd) == pytest.approx((1 + 2 * x / dfd) ** (-dfd / 2), rel=1e-12)
    alpha = np.array([0.001, 0.01, 0.05, 0.1, 0.5, 0.9])
    assert f_isf(alpha, 2, dfd) == pytest.approx(dfd / 2 * (alpha ** (-2 / dfd) - 1), rel=1e-10)
    assert f_sf(np.inf, 2, dfd) == 0.0 and f_sf(-1.0, 2, dfd) == 1.0 and np.isnan(f_sf(np.nan, 2, dfd))


def test_f_one_numerator_degree_is_the_square_of_t():
    """F(1, n) = T_n²: P(F > t²) = 2·P(T > t), from the t quantile's published values."""
    for dof, t975 in {1: 12.706, 10: 2.228, 30: 2.042}.items():
        assert float(f_sf(t975**2, 1, dof)) == pytest.approx(0.05, rel=2e-3)


def test_chi2_matches_its_closed_forms_and_a_published_table():
    """ν = 2: P(χ² ≤ x) = 1 − e^(−x/2), so the quantile is −2 ln(1 − p); ν = 1: erf √(x/2). The
    0.999 quantiles are NIST/SEMATECH §1.3.6.7.4's table (three decimals)."""
    for x in (0.1, 1.0, 5.0, 20.0):
        assert chi2_cdf(x, 2) == pytest.approx(-math.expm1(-x / 2), rel=1e-14)
        assert chi2_cdf(x, 1) == pytest.approx(math.erf(math.sqrt(x / 2)), rel=1e-13)
    assert chi2_cdf(-1.0, 3) == 0.0
    for p in (0.001, 0.5, 0.95, 0.999):
        assert chi2_quantile(p, 2) == pytest.approx(-2 * math.log1p(-p), rel=1e-12)
    for dof, value in {1: 10.828, 5: 20.515, 10: 29.588, 30: 59.703}.items():
        assert chi2_quantile(0.999, dof) == pytest.approx(value, abs=5e-4)
