"""Replicated calibration analysis (Tripp & Tcheng §8, Table 2; reference/metrology_stats.md §2).

Readings of the same point (mount, pitch, roll) in several replicates separate precision from
bias: pure error is the scatter about the point means, lack of fit the distance of the point
means from the model. Drift between replicates is tested on per-replicate fits. Everything is
vectorised over the columns of Y (one per sensor, or one per Monte Carlo trial).

σ_bias: two conventions, and why labcal follows the first. Model (metrology_stats.md
§2.1): y_ri = f(x_i; θ) + β_i + ε_ri over m points, R replicates, N = mR readings, p coefficients,
with point biases β_i (variance σ_bias², repeated in every replicate) and precision errors ε_ri
(variance σ_prec²). With H the m×m hat matrix of the points, SS_LOF = R‖(I − H)(β + ε̄)‖², and
since E‖(I − H)β‖² = (m − p)σ_bias² and E‖(I − H)ε̄‖² = (m − p)σ_prec²/R,

    E[MS_LOF] = σ_prec² + R·σ_bias²,   E[MS_PE] = σ_prec²,

so σ̂_bias² = (MS_LOF − MS_PE)/c with c = R is unbiased for the variance of a point bias (with
unequal counts, c = [N − tr((XᵀWX)⁻¹XᵀW²X)]/(m − p), the same expectation argument). This is
the convention here.

Tripp & Tcheng's Table 2 states σ_E, σ_bias and σ_prec with σ_E² = σ_bias² + σ_prec² in every row
(to their three digits, e.g. fig. 24: 3.17² = 2.62² + 1.79²; fig. 44(a): 4.34² = 4.10² + 1.42²), with
σ_E² the regression's residual mean square over N − p. Since SS_residual = SS_LOF + SS_PE, that
convention is σ̂_bias,T² = σ_E² − MS_PE = (m − p)(MS_LOF − MS_PE)/(N − p), i.e. c_T = (N − p)/(m − p),
whose expectation is σ_bias²·R(m − p)/(N − p): the share of the residual variance the biases explain,
not their variance. It is low by the factor (N − p)/(R(m − p)) = 1 + p(R − 1)/(R(m − p)): 380/360 =
1.056 for 64 points × 6 replicates with p = 4, and more for small designs (6-point tumble × 6: 2.67),
because the fit absorbs p of each point set's bias degrees of freedom in every replicate's residuals
but only once in the point means. A new reading at an attitude carries the whole point bias, whose
variance is σ_bias² (the prediction variance σ_prec² + σ_bias² of `Fit.new_measurement_variance`), so
the unbiased c = R is the right one; `tripp_sigma_bias` converts to Table 2's convention for comparing
with published numbers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.distributions import f_isf, f_sf

ALPHA = 0.05
# Readings that a model fits to within this fraction of their size are exact to floating-point
# rounding (float64 resolves 2.2e-16; a fit adds a few hundred times that; no DMM resolves better than
# about 1e-9 of its range): their scatter is no noise to test against (`noise_free`).
NUMERIC_RESOLUTION = 1e-12


def noise_free(scatter: NDArray[np.float64], scale: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Per column: a standard deviation (residual or pure error) at floating-point rounding of data of
    size ``scale`` — a noise-free simulation, where F tests have no noise to compare against."""
    return np.asarray(scatter <= NUMERIC_RESOLUTION * np.maximum(scale, np.finfo(float).tiny))


@dataclass(frozen=True)
class FTest:
    """An F test per column: statistic, degrees of freedom, critical value at ALPHA, p-value."""

    statistic: NDArray[np.float64]
    df_num: int
    df_den: NDArray[np.int_] | int  # per column: the pure-error denominator may differ between sensors

    # cached: `to_json` asks for them once per column, and each is an inverted incomplete beta
    @cached_property
    def critical(self) -> NDArray[np.float64]:
        return f_isf(ALPHA, self.df_num, self.df_den)

    @cached_property
    def p_value(self) -> NDArray[np.float64]:
        return f_sf(self.statistic, self.df_num, self.df_den)

    @property
    def significant(self) -> NDArray[np.bool_]:
        return self.p_value < ALPHA

    def to_json(self, column: int) -> dict[str, Any]:
        df_den = int(np.broadcast_to(self.df_den, self.statistic.shape)[column])
        return {"F": float(self.statistic[column]), "df": [self.df_num, df_den],
                "critical_95": float(np.broadcast_to(self.critical, self.statistic.shape)[column]),
                "p_value": float(self.p_value[column]), "significant": bool(self.significant[column])}


@dataclass(frozen=True)
class DriftTest:
    """Drift of one scalar coefficient function between replicates (marginal form)."""

    name: str
    test: FTest
    sigma_drift: NDArray[np.float64]  # between-replicate standard deviation beyond what noise explains

    def to_json(self, column: int) -> dict[str, Any]:
        return {**self.test.to_json(column), "sigma_drift": float(self.sigma_drift[column])}


@dataclass(frozen=True)
class Replication:
    n_points: int  # distinct calibration points m
    n_replicates: int
    lack_of_fit_ms: NDArray[np.float64]
    lack_of_fit: FTest  # against the pure error the drift tests call for
    classical: FTest  # against one-way pure error (no drift allowed)
    drift_robust: FTest | None  # against the residual after all drift (balanced designs only)
    sigma_prec: NDArray[np.float64]
    sigma_bias: NDArray[np.float64]
    drift: tuple[DriftTest, ...]

    def to_json(self, column: int) -> dict[str, Any]:
        return {
            "distinct_points": self.n_points, "replicates": self.n_replicates,
            "sigma_prec": float(self.sigma_prec[column]), "sigma_bias": float(self.sigma_bias[column]),
            "lack_of_fit": self.lack_of_fit.to_json(column),
            "lack_of_fit_classical": self.classical.to_json(column),
            "lack_of_fit_drift_robust": None if self.drift_robust is None
            else self.drift_robust.to_json(column),
            "drift": {d.name: d.to_json(column) for d in self.drift},
        }


def point_groups(keys: NDArray[Any] | Sequence[NDArray[Any]],
                 canonical: Callable[[NDArray[Any]], NDArray[Any]] | None = None,
                 ) -> tuple[NDArray[np.intp], int]:
    """Group index of every row (rows with equal keys are the same calibration point), numbered in
    the keys' lexicographic order; ``keys`` is an (n, k) array or k columns. ``canonical`` maps a
    column's values to the ones compared (e.g. angles rounded modulo 360°).

    Each column is numbered by its distinct values (a 1-D unique, fast; ``canonical`` is applied to
    those few values only) and the numbers combined column by column in mixed radix, renumbered
    densely whenever the radix product outgrows the rows: O(n) passes, no row sort (np.lexsort or
    np.unique(axis=0) on a million float rows take seconds)."""
    columns = list(np.asarray(keys).T) if isinstance(keys, np.ndarray) else list(keys)
    n = len(columns[0])
    code = np.zeros(n, dtype=np.int64)
    size = 1
    for column in columns:
        values, index = distinct(column)
        if canonical is not None:
            values, merged = np.unique(canonical(values), return_inverse=True)
            index = merged[index]
        code = code * len(values) + index
        size *= len(values)
        if size > 2 * n + 1:
            code, size = _renumber(code, size)
    code, size = _renumber(code, size)
    return code.astype(np.intp, copy=False), size


def first_rows(groups: NDArray[np.intp], n_groups: int) -> NDArray[np.intp]:
    """The first row of each group (groups numbered 0..n_groups−1): where its identity is read."""
    first = np.zeros(n_groups, dtype=np.intp)
    first[groups[::-1]] = np.arange(len(groups))[::-1]  # the last write to each group wins: its first row
    return first


def distinct(column: NDArray[Any]) -> tuple[NDArray[Any], NDArray[np.intp]]:
    """The column's distinct values, ascending, and the index of each row's value among them.
    Whole numbers from 0 up to about the column's length (replicate numbers) are counted instead
    of sorted: one O(n) pass where a sort and a binary search per row take five times longer."""
    if column.dtype.kind in "iu" and len(column):
        low, high = int(column.min()), int(column.max())
        if low >= 0 and high <= 4 * len(column) + 64:
            present = np.bincount(column, minlength=high + 1) > 0
            return np.flatnonzero(present), (np.cumsum(present) - 1)[column]
    values = np.unique(column)
    return values, np.searchsorted(values, column)  # faster than np.unique's return_inverse


def _renumber(code: NDArray[np.int64], size: int) -> tuple[NDArray[np.int64], int]:
    """Codes below ``size`` renumbered 0.. in order, without gaps."""
    if size <= 4 * len(code) + 64:
        present = np.bincount(code, minlength=size) > 0
        renumbered = np.cumsum(present) - 1
        return renumbered[code], int(renumbered[-1]) + 1 if size else 0
    values, inverse = np.unique(code, return_inverse=True)
    return inverse.astype(np.int64, copy=False), len(values)


@dataclass(frozen=True)
class Cells:
    """What the replicated analysis takes from the observations whatever the model: the points'
    counts and means, the pure-error sum of squares and the (replicate, point) cells. Computed once
    per set of readings (`Readings.cells`), it serves the linear and the device model alike."""

    n_obs: int
    counts: NDArray[np.float64]  # (G,) observations of each point
    means: NDArray[np.float64]  # (G, m)
    ss_pe: NDArray[np.float64]  # (m,) Σ (y − ȳ_point)²
    n_replicates: int
    per_rep: NDArray[np.float64] | None  # (R, G, m) means per replicate and point, when balanced
    per_rep_count: NDArray[np.float64] | None  # (G,) observations of each point in every replicate

    @classmethod
    def of(cls, y: NDArray[np.float64], groups: NDArray[np.intp], replicate: NDArray[np.int_],
           n_groups: int, means: NDArray[np.float64] | None = None) -> Cells:
        """``means``: the points' means of ``y`` when the caller has them."""
        y = y if y.ndim == 2 else y[:, None]
        counts = np.bincount(groups, minlength=n_groups).astype(float)
        means = _group_means(y, groups, n_groups) if means is None else means
        pure = y - np.take(means, groups, axis=0)  # take: 7× faster than means[groups] on a million rows
        reps, rep_index = distinct(replicate)
        per_rep, per_rep_count = None, None
        if len(reps) > 1:
            # (replicate, point) cells, counted and averaged in one pass (not one pass per replicate)
            cells = rep_index * n_groups + groups
            counts_r = np.bincount(cells, minlength=len(reps) * n_groups).reshape(len(reps), n_groups)
            if np.all(counts_r == counts_r[0]):  # every replicate holds the same points
                per_rep = _group_means(y, cells, len(reps) * n_groups).reshape(len(reps), n_groups, -1)
                per_rep_count = counts_r[0].astype(float)
        ss_pe = np.einsum("ij,ij->j", pure, pure)
        return cls(len(y), counts, means, ss_pe, len(reps), per_rep, per_rep_count)


def analyse(design: NDArray[np.float64], y: NDArray[np.float64], groups: NDArray[np.intp],
            replicate: NDArray[np.int_],
            sensitivity: slice = slice(1, 4)) -> Replication | None:
    """Lack of fit, variance components and drift tests; None when nothing is replicated.

    ``design`` rows must depend only on the point (so that point means are well defined);
    ``sensitivity`` selects the coefficients whose vector norm is the sensor's sensitivity.
    """
    n_groups = int(groups.max()) + 1
    return analyse_points(design[first_rows(groups, n_groups)], Cells.of(y, groups, replicate, n_groups),
                          sensitivity)


def analyse_with_covariates(design: NDArray[np.float64], y: NDArray[np.float64], groups: NDArray[np.intp],
                            replicate: NDArray[np.int_], per_point: NDArray[np.bool_],
                            sensitivity: slice = slice(1, 4)) -> Replication | None:
    """`analyse` when some regressors change between readings of one point (``per_point`` False: the
    temperature terms of a temperature-corrected calibration, Tripp Table 2 footnote b).

    Point means are no longer the pure-error model, so every test is the extra-sum-of-squares F test
    between nested least-squares models that all carry the covariates T (q of them, rank counted):
    - pure error: a mean per point, + T (N − G − q degrees of freedom);
    - lack of fit: the point columns J + T against it (G − p);
    - drift: J + T + a per-replicate offset, or a per-replicate scale of the fitted sensitivity
      direction (g·ŝ/|ŝ|), each against J + T (R − 1, less what T already spans), over the residual of
      the model that lets every replicate have its own J coefficients (+ point means, + T).
    σ_prec and σ_bias follow `analyse_points`; a drift's σ is the one-way variance component,
    (MS_drift − MS_e)/(Σh²/R) with h its regressor. Tests that correct the readings by a γ fitted
    first and then test them as `analyse` does are not exact: γ takes up part of any trend between
    replicates, and its own error moves whole replicates (tests/analysis/test_temperature_replication.py)."""
    y = y if y.ndim == 2 else y[:, None]
    n_obs, n_cols = y.shape
    n_groups = int(groups.max()) + 1
    reps, rep_index = distinct(replicate)
    n_reps = len(reps)
    j, t = design[:, per_point], design[:, ~per_point]
    n_coef = j.shape[1]

    def within(a: NDArray[np.float64]) -> NDArray[np.float64]:
        return a - np.take(_group_means(a, groups, n_groups), groups, axis=0)

    def sse(x: NDArray[np.float64], target: NDArray[np.float64]) -> tuple[NDArray[np.float64], int]:
        coef, _, rank, _ = np.linalg.lstsq(x, target, rcond=None)
        resid = target - x @ coef
        return np.einsum("ij,ij->j", resid, resid), int(rank)

    t_w, y_w = within(t), within(y)
    ss_pe, q = sse(t_w, y_w)
    df_pe, df_lof = n_obs - n_groups - q, n_groups - n_coef
    if n_reps < 2 or df_pe <= 0 or df_lof <= 0:
        return None
    ss_fit, _ = sse(design, y)
    ms_lof, ms_pe = (ss_fit - ss_pe) / df_lof, ss_pe / df_pe
    one_hot = (rep_index[:, None] == np.arange(n_reps)[None, :]).astype(float)
    all_drift = np.hstack([within(j * one_hot[:, [k]]) for k in range(n_reps)] + [t_w])
    ss_e, rank_e = sse(all_drift, y_w)
    df_e = n_obs - n_groups - rank_e
    ms_e = ss_e / df_e
    exact = noise_free(np.sqrt(ms_pe), np.max(np.abs(y), axis=0))
    ratio = _ratio_where(~exact)

    coef = np.linalg.lstsq(design, y, rcond=None)[0]
    resid = y - design @ coef

    def extra_ms(blocks: list[NDArray[np.float64]], mix: NDArray[np.float64]
                 ) -> tuple[NDArray[np.float64], int]:
        """Per column c: the mean square that the R − 1 regressors Σ_k mix[k, c]·blocks[k] add to the
        common fit — its residual's projection on them once they are taken about the fit (Frisch–
        Waugh), all columns at once — and their degrees of freedom: fewer than R − 1 where the
        covariates already span part of them (a temperature read once per replicate is an offset
        per replicate)."""
        e = np.stack([x - design @ np.linalg.lstsq(design, x, rcond=None)[0] for x in blocks])  # K, N, R−1
        gram = np.einsum("kna,lnb->klab", e, e)
        a = np.einsum("kc,lc,klab->cab", mix, mix, gram)
        b = np.einsum("kc,kna,nc->ca", mix, e, resid)
        scale = np.max(np.abs(a), axis=(1, 2), keepdims=True)
        rank = int(np.min(np.linalg.matrix_rank(a / np.where(scale > 0, scale, 1.0), tol=1e-10)))
        x = np.einsum("cab,cb->ca", np.linalg.pinv(a, rcond=1e-10, hermitian=True), b)
        return np.asarray(np.einsum("ca,ca->c", b, x) / max(rank, 1), dtype=float), rank

    s_coef = coef[:n_coef][sensitivity]
    direction = s_coef / np.linalg.norm(s_coef, axis=0)  # each column's own sensitivity direction
    j_s = j[:, sensitivity]
    h_sens = j_s @ direction
    tests = {
        "offset": (*extra_ms([one_hot[:, 1:]], np.ones((1, n_cols))), np.full(n_cols, n_obs / n_reps)),
        "sensitivity": (*extra_ms([j_s[:, [k]] * one_hot[:, 1:] for k in range(j_s.shape[1])], direction),
                        np.sum(h_sens**2, axis=0) / n_reps),
    }
    drift = tuple(DriftTest(name, FTest(ratio(ms, ms_e) if df else np.full(n_cols, np.nan), max(df, 1), df_e),
                            np.sqrt(np.maximum(0.0, (ms - ms_e) / weight)))
                  for name, (ms, df, weight) in tests.items())
    drifting = np.any([d.test.significant for d in drift], axis=0)
    ms_star, df_star = np.where(drifting, ms_e, ms_pe), np.where(drifting, df_e, df_pe)
    counts = np.bincount(groups, minlength=n_groups).astype(float)[:, None]
    j_m = j[first_rows(groups, n_groups)]
    moment_inv = np.linalg.pinv(j_m.T @ (counts * j_m))
    c_bias = (n_obs - np.trace(moment_inv @ (j_m.T @ (counts**2 * j_m)))) / df_lof
    return Replication(n_groups, n_reps, ms_lof, FTest(ratio(ms_lof, ms_star), df_lof, df_star),
                       FTest(ratio(ms_lof, ms_pe), df_lof, df_pe), FTest(ratio(ms_lof, ms_e), df_lof, df_e),
                       np.sqrt(ms_star), np.sqrt(np.maximum(0.0, (ms_lof - ms_star) / c_bias)), drift)


def analyse_points(j_m: NDArray[np.float64], cells: Cells,
                   sensitivity: slice = slice(1, 4)) -> Replication | None:
    """`analyse` given one design row per distinct point (``j_m``, G×L) and the observations'
    `Cells`: what a model whose regressors are functions of the point needs, without a design row
    per observation."""
    n_obs = cells.n_obs
    n_groups, n_coef = j_m.shape
    if n_groups >= n_obs or cells.n_replicates < 2 or n_groups <= n_coef:
        return None
    means, n_reps = cells.means, cells.n_replicates
    w = cells.counts[:, None]
    moment_inv = np.linalg.inv(j_m.T @ (w * j_m))
    theta = moment_inv @ (j_m.T @ (w * means))
    ss_lof = np.sum(w * (means - j_m @ theta) ** 2, axis=0)
    df_lof, df_pe = n_groups - n_coef, n_obs - n_groups
    ms_lof, ms_pe = ss_lof / df_lof, cells.ss_pe / df_pe
    # Noise-free readings (a simulation with --noise 0) repeat exactly: with no pure error there is
    # nothing to test against, so their F statistics are undefined (NaN: not significant).
    exact = noise_free(np.sqrt(ms_pe), np.max(np.abs(means), axis=0))
    ratio = _ratio_where(~exact)
    classical = FTest(ratio(ms_lof, ms_pe), df_lof, df_pe)

    drift_robust: FTest | None = None
    drift: tuple[DriftTest, ...] = ()
    ms_star: NDArray[np.float64] = ms_pe
    df_star: NDArray[np.int_] | int = df_pe
    if cells.per_rep is not None and cells.per_rep_count is not None:  # every replicate holds the same points
        c = cells.per_rep_count[:, None]  # readings of each point per replicate
        per_rep = cells.per_rep
        unscaled = np.linalg.inv(j_m.T @ (c * j_m))
        hat = unscaled @ (j_m.T * c.T)  # weighted least squares on per-replicate point means
        theta_r = np.einsum("pm,rmc->rpc", hat, per_rep)
        dev = per_rep - means[None]  # D_r
        resid = dev - np.einsum("mp,rpc->rmc", j_m, np.einsum("pm,rmc->rpc", hat, dev))
        df_e = (n_reps - 1) * df_lof
        ms_e = np.sum(c[None] * resid**2, axis=(0, 1)) / df_e
        drift_robust = FTest(ratio(ms_lof, ms_e), df_lof, df_e)
        s_bar = theta_r.mean(axis=0)[sensitivity]
        grad = s_bar / np.linalg.norm(s_bar, axis=0)  # ∂|s|/∂s
        u_ss = unscaled[sensitivity, sensitivity]
        drift = (
            _drift("offset", theta_r[:, 0, :], unscaled[0, 0], ms_e, df_e, ratio),
            _drift("sensitivity", np.linalg.norm(theta_r[:, sensitivity, :], axis=1),
                   np.einsum("ic,ij,jc->c", grad, u_ss, grad), ms_e, df_e, ratio),
        )
        # Drift inflates one-way pure error: where it is found, test bias against the residual
        # after all drift instead (metrology_stats.md §2.6).
        drifting = np.any([d.test.significant for d in drift], axis=0)
        ms_star, df_star = np.where(drifting, ms_e, ms_pe), np.where(drifting, df_e, df_pe)
    lof = FTest(ratio(ms_lof, ms_star), df_lof, df_star)
    c = (n_obs - np.trace(moment_inv @ (j_m.T @ (w**2 * j_m)))) / df_lof
    sigma_bias = np.sqrt(np.maximum(0.0, (ms_lof - ms_star) / c))
    return Replication(n_groups, n_reps, ms_lof, lof, classical, drift_robust,
                       np.sqrt(ms_star), sigma_bias, drift)


def tripp_sigma_bias(sigma_bias: NDArray[np.float64] | float, n_points: int, n_replicates: int,
                     n_coefficients: int) -> NDArray[np.float64]:
    """σ_bias in Tripp & Tcheng's Table 2 convention (σ_E² = σ_bias² + σ_prec², module docstring)
    from labcal's (unbiased, c = R), for a balanced design of m points × R replicates, p coefficients."""
    m, r, p = n_points, n_replicates, n_coefficients
    return np.asarray(sigma_bias, dtype=float) * float(np.sqrt(r * (m - p) / (m * r - p)))


def _group_means(y: NDArray[np.float64], groups: NDArray[np.intp], n_groups: int) -> NDArray[np.float64]:
    sums = np.column_stack([np.bincount(groups, weights=column, minlength=n_groups) for column in y.T])
    return sums / np.bincount(groups, minlength=n_groups)[:, None]


def _ratio_where(defined: NDArray[np.bool_]
                 ) -> Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]:
    """a / b per column where ``defined``, NaN elsewhere (no division there, so no warning)."""
    def ratio(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.full(np.broadcast(a, b).shape, np.nan)
        np.divide(a, b, out=out, where=defined & (b > 0))
        return out
    return ratio


def _drift(name: str, values: NDArray[np.float64], factor: NDArray[np.float64] | float,
           ms_e: NDArray[np.float64], df_e: int,
           ratio: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]) -> DriftTest:
    n_rep = values.shape[0]
    between = np.var(values, axis=0, ddof=1)
    noise = ms_e * factor
    return DriftTest(name, FTest(ratio(between, noise), n_rep - 1, df_e),
                     np.sqrt(np.maximum(0.0, between - noise)))
