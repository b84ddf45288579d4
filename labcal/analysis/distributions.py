"""The distribution functions the statistics need — Student t quantiles, F tail probabilities and
critical values, χ² probabilities and quantiles — from scipy.special, the well-kept implementation
(Cephes/Boost) every scientific-Python user already trusts.

They keep numpy's broadcasting and this module's names, so that every caller states which of them it
uses. scipy.special is imported at the first statistic computed (`labcal.lazy`): a command that
computes none (listing the lab's runs, a command's help) never loads it, and scipy.special alone
costs a run far less than scipy.stats would.
"""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.lazy import lazy

if TYPE_CHECKING:
    from scipy import special
else:
    special = lazy("scipy.special")  # about 0.2 s: not for a command that computes no statistic

Array = NDArray[np.float64]


def t_quantile(p: ArrayLike, dof: ArrayLike) -> Array:
    """Student t quantile: P(T ≤ x) = p; ν = ∞ gives the normal quantile, ν ≤ 0 or NaN gives NaN."""
    nu, pv = np.asarray(dof, dtype=float), np.asarray(p, dtype=float)
    with np.errstate(invalid="ignore"):
        x = special.stdtrit(np.where(nu > 0, nu, np.nan), pv)
        x = np.where(np.isinf(nu), special.ndtri(pv), x)
        return np.asarray(np.where((pv == 0) & (nu > 0), -np.inf, x), dtype=float)  # stdtrit(ν, 0) is +inf


def f_sf(x: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> Array:
    """P(F > x) for F(dfn, dfd): the p-value of an F test."""
    return np.asarray(special.fdtrc(dfn, dfd, np.maximum(np.asarray(x, dtype=float), 0.0)), dtype=float)


def f_isf(alpha: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> Array:
    """The F(dfn, dfd) value exceeded with probability alpha: the test's critical value."""
    return np.asarray(special.fdtri(dfn, dfd, 1.0 - np.asarray(alpha, dtype=float)), dtype=float)


def chi2_cdf(x: float, dof: int) -> float:
    """P(χ² ≤ x) with dof degrees of freedom."""
    return float(special.chdtr(dof, max(x, 0.0)))


@lru_cache(maxsize=64)  # the settle test asks for the same one at every window
def chi2_quantile(p: float, dof: int) -> float:
    """χ² quantile: P(X ≤ x) = p with dof degrees of freedom."""
    return float(special.chdtri(dof, 1.0 - p))


def noncentral_f2_cdf(x: ArrayLike, noncentrality: ArrayLike, dfd: float) -> Array:
    """P(F' ≤ x) for the noncentral F(2, dfd, λ): the distribution of |z|²/2 / (s²/σ²) for a
    2-vector z ~ N(μ, σ²I) with |μ|²/σ² = λ and s² on dfd degrees of freedom (the coning angle's
    interval, `labcal.analysis.coning`)."""
    return np.asarray(special.ncfdtr(2.0, dfd, noncentrality, np.maximum(np.asarray(x, dtype=float), 0.0)),
                      dtype=float)


def welch_satterthwaite(u_c: Array, parts: list[tuple[Array, float]]) -> Array:
    """ν_eff = u_c⁴ / Σ u_i⁴/ν_i (GUM G.2b) over the parts (variance u_i², dof ν_i); infinite dof add
    nothing, and with nothing finite ν_eff is infinite."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        denominator = sum((var**2 / dof for var, dof in parts if np.isfinite(dof) and dof > 0),
                          start=np.zeros_like(u_c))
        return np.asarray(np.where(denominator > 0, u_c**4 / denominator, np.inf), dtype=float)
