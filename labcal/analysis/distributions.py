"""The few distribution functions the statistics need, from scipy.special.

scipy.stats would give the same numbers but takes about a second to import, which every
`labcal` command would pay; these are the same special functions scipy.stats calls.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

# scipy ships no type information: its ufuncs are Any to mypy. They return float64 arrays (numpy
# scalars for scalar arguments), which is what the casts below state.


def t_quantile(p: ArrayLike, dof: ArrayLike) -> NDArray[np.float64]:
    """Student t quantile: P(T ≤ x) = p."""
    return cast("NDArray[np.float64]", special.stdtrit(dof, p))


def f_sf(x: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> NDArray[np.float64]:
    """P(F > x) for F(dfn, dfd): the p-value of an F test."""
    return cast("NDArray[np.float64]", special.fdtrc(dfn, dfd, x))


def f_isf(alpha: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> NDArray[np.float64]:
    """The F(dfn, dfd) value exceeded with probability alpha: the test's critical value."""
    return cast("NDArray[np.float64]", special.fdtri(dfn, dfd, 1.0 - np.asarray(alpha)))


def chi2_quantile(p: ArrayLike, dof: ArrayLike) -> NDArray[np.float64]:
    """χ² quantile: P(X ≤ x) = p."""
    return cast("NDArray[np.float64]", special.chdtri(dof, 1.0 - np.asarray(p)))
