"""The few distribution functions the statistics need: Student t quantiles, F tail probabilities
and F critical values, and a χ² quantile, in numpy and the standard library.

scipy.special has them, but importing it costs a process about a third of a second (it now loads
numpy.testing and numpy.f2py through its array-API layer), several times what a dry run's own work
takes. Both t and F reduce to the regularized incomplete beta function I_x(a, b), evaluated here by
its continued fraction (Numerical Recipes §6.4, modified Lentz) and inverted by safeguarded Newton
steps; very large t degrees of freedom use the Cornish–Fisher expansion (Abramowitz & Stegun
26.7.5). The tests check every function against scipy.special over the ranges labcal uses.
"""

from __future__ import annotations

import math
from functools import lru_cache
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
CF_TOLERANCE = 1e-15  # relative change of the continued fraction at which it has converged (~5 ulp)
CF_MAX_TERMS = 5000  # enough for a, b up to ~10⁷ (terms grow as √max(a, b))
NEWTON_STEPS = 100  # safeguarded Newton converges in under ten; bisection halves the bracket otherwise
NEWTON_TOLERANCE = 1e-13  # a Newton step this small (relative) leaves an error of its square
CORNISH_FISHER_DOF = 1e4  # from here on the t quantile's expansion in 1/ν is exact to ~1e-13
TINY = 1e-300
_lgamma = np.frompyfunc(math.lgamma, 1, 1)
_normal_quantile = np.frompyfunc(NormalDist().inv_cdf, 1, 1)


def _log_beta(a: Array, b: Array) -> Array:
    return np.asarray(_lgamma(a) + _lgamma(b) - _lgamma(a + b), dtype=float)


def _continued_fraction(a: Array, b: Array, x: Array) -> Array:
    """The continued fraction of I_x(a, b) (converges fast for x < (a + 1)/(a + b + 2))."""
    def nonzero(v: Array) -> Array:
        return np.where(np.abs(v) < TINY, TINY, v)

    c = np.ones_like(x)
    d = 1.0 / nonzero(1.0 - (a + b) * x / (a + 1.0))
    h = d.copy()
    for m in range(1, CF_MAX_TERMS + 1):
        even = m * (b - m) * x / ((a - 1.0 + 2 * m) * (a + 2 * m))
        d = 1.0 / nonzero(1.0 + even * d)
        c = nonzero(1.0 + even / c)
        h *= d * c
        odd = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 1.0 + 2 * m))
        d = 1.0 / nonzero(1.0 + odd * d)
        c = nonzero(1.0 + odd / c)
        delta = d * c
        h *= delta
        if np.all(np.abs(delta - 1.0) <= CF_TOLERANCE):
            break
    return h


def _arrays(*values: ArrayLike) -> list[Array]:
    return [np.asarray(v, dtype=float) for v in np.broadcast_arrays(*values)]


def beta_inc(a: ArrayLike, b: ArrayLike, x: ArrayLike) -> Array:
    """The regularized incomplete beta function I_x(a, b) (scipy.special.betainc); nan outside
    a, b > 0 and 0 ≤ x ≤ 1."""
    av, bv, xv = _arrays(a, b, x)
    out = np.full(av.shape, np.nan)
    valid = (av > 0) & (bv > 0) & np.isfinite(av) & np.isfinite(bv) & (xv >= 0) & (xv <= 1)
    out[valid & (xv == 0)] = 0.0
    out[valid & (xv == 1)] = 1.0
    inside = valid & (xv > 0) & (xv < 1)
    av, bv, xv = av[inside], bv[inside], xv[inside]
    swap = xv > (av + 1.0) / (av + bv + 2.0)  # there I_x(a, b) = 1 − I_{1−x}(b, a) converges fast
    av, bv, xv = np.where(swap, bv, av), np.where(swap, av, bv), np.where(swap, 1.0 - xv, xv)
    part = (np.exp(av * np.log(xv) + bv * np.log1p(-xv) - _log_beta(av, bv)) / av
            * _continued_fraction(av, bv, xv))
    out[inside] = np.where(swap, 1.0 - part, part)
    return out


def _beta_inc_inverse(a: Array, b: Array, target: Array, start: Array) -> Array:
    """x in (0, 1) with I_x(a, b) = target (0 < target < 1), by Newton steps from ``start`` kept
    inside a bracket that every evaluation narrows (a step leaving it is a bisection instead)."""
    x = np.clip(start, TINY, 1.0 - 1e-16)
    lo, hi, done = np.zeros_like(x), np.ones_like(x), np.zeros(x.shape, bool)
    log_beta = _log_beta(a, b)
    for _ in range(NEWTON_STEPS):
        todo = ~done
        if not todo.any():
            break
        xt, at, bt = x[todo], a[todo], b[todo]
        g = beta_inc(at, bt, xt) - target[todo]
        lo[todo] = np.where(g < 0, xt, lo[todo])
        hi[todo] = np.where(g > 0, xt, hi[todo])
        with np.errstate(all="ignore"):  # a density that under- or overflows makes no Newton step
            density = np.exp((at - 1.0) * np.log(xt) + (bt - 1.0) * np.log1p(-xt) - log_beta[todo])
            newton = xt - g / density
        converged = (g == 0) | (np.abs(newton - xt) <= NEWTON_TOLERANCE * xt)  # rounding decides the side
        inside = converged | (np.isfinite(newton) & (newton > lo[todo]) & (newton < hi[todo]))
        x[todo] = np.where(g == 0, xt, np.where(inside, newton, 0.5 * (lo[todo] + hi[todo])))
        done[todo] = converged
    return x


def t_quantile(p: ArrayLike, dof: ArrayLike) -> Array:
    """Student t quantile: P(T ≤ x) = p (scipy.special.stdtrit); ν = ∞ gives the normal quantile."""
    shape = np.broadcast_shapes(np.shape(p), np.shape(dof))
    pv, dofv = (np.atleast_1d(v).ravel() for v in _arrays(p, dof))
    out = np.full(pv.shape, np.nan)
    ok = (pv > 0) & (pv < 1) & (dofv > 0)
    out[(dofv > 0) & (pv == 0)], out[(dofv > 0) & (pv == 1)] = -np.inf, np.inf
    q = np.minimum(pv, 1.0 - pv)  # the tail beyond |t|
    z = np.zeros_like(q)
    z[ok] = np.asarray(_normal_quantile(q[ok]), dtype=float)
    nu = np.where(ok, dofv, 1.0)
    # Cornish–Fisher (A&S 26.7.5): a start for Newton, and the answer itself for large ν
    g1 = (z**3 + z) / 4
    g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96
    g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384
    g4 = (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160
    with np.errstate(over="ignore", invalid="ignore"):
        t = -np.where(np.isinf(nu), z, z + g1 / nu + g2 / nu**2 + g3 / nu**3 + g4 / nu**4)  # ≥ 0
    # P(|T| > t) = I_w(ν/2, ½) with w = ν/(ν + t²); near the centre, 1 − w = t²/(ν + t²) is solved
    # for instead (I_{1−w}(½, ν/2) = 1 − 2q), which keeps its digits when t is small
    small = ok & (nu < CORNISH_FISHER_DOF)
    centre, tail = small & (q > 0.25), small & (q <= 0.25)
    if centre.any():
        n, t0 = nu[centre], np.minimum(t[centre], 1e150)
        v = _beta_inc_inverse(np.full_like(n, 0.5), n / 2, 1.0 - 2.0 * q[centre], t0**2 / (n + t0**2))
        t[centre] = np.sqrt(n * v / (1.0 - v))
    if tail.any():
        n, t0 = nu[tail], np.where(np.isfinite(t[tail]), t[tail], 1e150)
        w = _beta_inc_inverse(n / 2, np.full_like(n, 0.5), 2.0 * q[tail], n / (n + t0**2))
        t[tail] = np.sqrt(n * (1.0 - w) / w)
    out[ok] = np.where(pv[ok] < 0.5, -t[ok], t[ok])
    return out.reshape(shape)


def f_sf(x: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> Array:
    """P(F > x) for F(dfn, dfd): the p-value of an F test (scipy.special.fdtrc)."""
    xv, m, n = _arrays(x, dfn, dfd)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.isinf(xv), 0.0, n / (n + m * np.maximum(xv, 0.0)))
    return np.where(np.isnan(xv), np.nan, beta_inc(n / 2, m / 2, w))


def f_isf(alpha: ArrayLike, dfn: ArrayLike, dfd: ArrayLike) -> Array:
    """The F(dfn, dfd) value exceeded with probability alpha: the test's critical value
    (scipy.special.fdtri(dfn, dfd, 1 − alpha))."""
    av, m, n = _arrays(alpha, dfn, dfd)
    out = np.full(av.shape, np.nan)
    ok = (av > 0) & (av < 1) & (m > 0) & (n > 0) & np.isfinite(m) & np.isfinite(n)
    if ok.any():
        w = _beta_inc_inverse(n[ok] / 2, m[ok] / 2, av[ok], np.full_like(av[ok], 0.5))
        out[ok] = n[ok] * (1.0 - w) / (m[ok] * w)
    return out


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


def welch_satterthwaite(u_c: Array, parts: list[tuple[Array, float]]) -> Array:
    """ν_eff = u_c⁴ / Σ u_i⁴/ν_i (GUM G.2b) over the parts (variance u_i², dof ν_i); infinite dof add
    nothing, and with nothing finite ν_eff is infinite."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        denominator = sum((var**2 / dof for var, dof in parts if np.isfinite(dof) and dof > 0),
                          start=np.zeros_like(u_c))
        return np.asarray(np.where(denominator > 0, u_c**4 / denominator, np.inf), dtype=float)
