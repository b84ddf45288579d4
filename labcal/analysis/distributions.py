"""The few distribution functions the statistics need, from scipy.special.

scipy.stats would give the same numbers but takes about a second to import, which every
`labcal` command would pay; these are the same special functions scipy.stats calls.
"""

from __future__ import annotations

from numpy.typing import ArrayLike, NDArray
from scipy import special


def t_quantile(p: ArrayLike, dof: ArrayLike) -> NDArray:
    """Student t quantile: P(T ≤ x) = p."""
    return special.stdtrit(dof, p)


def f_sf(x: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> NDArray:
    """P(F > x) for F(dfn, dfd): the p-value of an F test."""
    return special.fdtrc(dfn, dfd, x)


def f_isf(alpha: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> NDArray:
    """The F(dfn, dfd) value exceeded with probability alpha: the test's critical value."""
    return special.fdtri(dfn, dfd, 1.0 - alpha)


def chi2_quantile(p: ArrayLike, dof: ArrayLike) -> NDArray:
    """χ² quantile: P(X ≤ x) = p."""
    return special.chdtri(dof, 1.0 - p)
