"""The few distribution functions the statistics need, from scipy.special.

scipy.stats would give the same numbers but takes about a second to import, which every
`labcal` command would pay; these are the same special functions scipy.stats calls. scipy.special
itself is imported by the functions that use it: the sequencer needs only a χ² quantile of an
integer degree of freedom, which has a closed-form distribution function.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

# scipy ships no type information: its ufuncs are Any to mypy. They return float64 arrays (numpy
# scalars for scalar arguments), which is what the casts below state.


def t_quantile(p: ArrayLike, dof: ArrayLike) -> NDArray[np.float64]:
    """Student t quantile: P(T ≤ x) = p."""
    from scipy import special

    return cast("NDArray[np.float64]", special.stdtrit(dof, p))


def f_sf(x: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> NDArray[np.float64]:
    """P(F > x) for F(dfn, dfd): the p-value of an F test."""
    from scipy import special

    return cast("NDArray[np.float64]", special.fdtrc(dfn, dfd, x))


def f_isf(alpha: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> NDArray[np.float64]:
    """The F(dfn, dfd) value exceeded with probability alpha: the test's critical value."""
    from scipy import special

    return cast("NDArray[np.float64]", special.fdtri(dfn, dfd, 1.0 - np.asarray(alpha)))


def chi2_cdf(x: float, dof: int) -> float:
    """P(χ² ≤ x) for an integer number of degrees of freedom, in closed form: the regularized
    lower gamma function P(k/2, x/2) by its recurrence P(a + 1, y) = P(a, y) − yᵃe⁻ʸ/Γ(a + 1),
    from P(1, y) = 1 − e⁻ʸ (even k) or P(½, y) = erf √y (odd k)."""
    if x <= 0:
        return 0.0
    y = x / 2
    a, p = (1.0, -math.expm1(-y)) if dof % 2 == 0 else (0.5, math.erf(math.sqrt(y)))
    while a < dof / 2:
        p -= math.exp(a * math.log(y) - y - math.lgamma(a + 1))
        a += 1
    return p


@lru_cache(maxsize=64)  # the settle test asks for the same one at every window
def chi2_quantile(p: float, dof: int) -> float:
    """χ² quantile for an integer number of degrees of freedom: P(X ≤ x) = p, by bisection on
    `chi2_cdf` (to 1e-12 relative; no scipy, so that the sequencer does not import it)."""
    lo, hi = 0.0, dof + 10.0 * math.sqrt(2.0 * dof) + 50.0
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_cdf(mid, dof) < p else (lo, mid)
    return 0.5 * (lo + hi)
