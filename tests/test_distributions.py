"""The t and F distribution functions against closed forms, published tables and scipy.special
(which labcal no longer imports at run time, so it is an independent reference here)."""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest
from scipy import special

from labcal.analysis.distributions import beta_inc, f_isf, f_sf, t_quantile

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


@pytest.mark.parametrize("dof", DOF)
def test_t_quantile_agrees_with_scipy(dof):
    # 1e-10: scipy's own stdtrit is no better than that in the far tails of small ν
    assert t_quantile(P, dof) == pytest.approx(special.stdtrit(dof, P), rel=1e-10)


def test_t_quantile_keeps_the_shape_and_edges():
    nu = np.array([[3.0, np.inf], [57.0, 1e7]])
    k = t_quantile(0.975, nu)
    assert k.shape == (2, 2) and k == pytest.approx(special.stdtrit(nu, 0.975), rel=1e-12)
    assert t_quantile(0.975, 57).shape == ()
    assert np.isnan(t_quantile(0.975, np.nan)) and np.isnan(t_quantile(0.975, 0.0))
    assert t_quantile(0.5, 7) == 0.0
    assert t_quantile([0.0, 1.0], 7).tolist() == [-math.inf, math.inf]
    many = np.random.default_rng(2).uniform(1, 500, 2000)  # an uncertainty budget's grid of ν_eff
    assert t_quantile(0.975, many) == pytest.approx(special.stdtrit(many, 0.975), rel=1e-12)


@pytest.mark.parametrize("dfn,dfd", [(1, 1), (2, 5), (3, 60), (6, 186), (18, 300), (1, 1000), (50, 3),
                                     (4.5, 17.2)])
def test_f_tail_and_critical_value_agree_with_scipy(dfn, dfd):
    x = np.array([0.0, 0.01, 0.5, 1.0, 2.5, 10.0, 100.0, 1e5, 2e33, np.inf])
    assert f_sf(x, dfn, dfd) == pytest.approx(special.fdtrc(dfn, dfd, x), rel=1e-11, abs=1e-300)
    alpha = np.array([0.001, 0.01, 0.05, 0.1, 0.5, 0.9])
    assert f_isf(alpha, dfn, dfd) == pytest.approx(special.fdtri(dfn, dfd, 1 - alpha), rel=1e-11)


def test_f_critical_values_match_a_published_table():
    """Upper 5 % points of F, NIST/SEMATECH e-Handbook §1.3.6.7.3 (three decimals)."""
    table = {(1, 10): 4.965, (3, 60): 2.758, (6, 100): 2.191, (10, 10): 2.978}
    for (dfn, dfd), value in table.items():
        assert float(f_isf(0.05, dfn, dfd)) == pytest.approx(value, abs=5e-4)


def test_incomplete_beta_agrees_with_scipy_and_its_symmetry():
    rng = np.random.default_rng(4)
    a, b, x = rng.uniform(0.2, 300, 500), rng.uniform(0.2, 300, 500), rng.uniform(0, 1, 500)
    assert beta_inc(a, b, x) == pytest.approx(special.betainc(a, b, x), rel=1e-11, abs=1e-300)
    assert beta_inc(a, b, x) + beta_inc(b, a, 1 - x) == pytest.approx(1.0, abs=1e-13)
    assert np.isnan(beta_inc(-1.0, 2.0, 0.5)) and np.isnan(beta_inc(1.0, 2.0, 1.5))
