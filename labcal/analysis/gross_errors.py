"""Gross-error checks: what physics guarantees every reading of a static instrument, tested so
that good data raises a flag rarely, at a stated rate.

- Gravity is 1 g: m = |(V − B)S⁻¹| must be 1 within its standard uncertainty u_m (first order,
  from the output variance Σ_v of `labcal.analysis.attitude.output_variance`). A dead input
  (0 V), a saturated channel, a value typed wrong or a shaken instrument are not.
- A reading belongs to its stated mount: each (replicate, mount) group is predicted from a fit of
  every other group; a group its stated mount does not explain but another mount does is a
  missed or wrong remount (the readings then fit S at half its value, with no other warning).
- Residuals: externally studentised residuals t_i = e_i / (s_(i)·√(1 − h_ii)), which are Student t
  with K − L − 1 degrees of freedom for good normal data.

Every threshold is a Šidák family-wise one: over all the tests of one check on one file, good data
raises any flag with probability at most FAMILY_ALPHA (exactly for independent tests, less for the
positively dependent ones here). `tests/analysis/test_gross_errors.py` checks that rate by Monte Carlo.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.attitude import Attitude, Calibration, output_variance
from labcal.analysis.distributions import chi2_quantile, t_quantile
from labcal.analysis.fit import Fit, readings_points
from labcal.analysis.kinematics import nominal_gravity
from labcal.analysis.models import BASE_NAMES, Model
from labcal.analysis.readings import Readings
from labcal.analysis.regression import LeastSquares, least_squares, least_squares_of_means
from labcal.analysis.replication import first_rows, point_groups
from labcal.errors import LabcalError

FAMILY_ALPHA = 0.001  # chance that one check flags anything in a file of good readings
VOLTS_MAX = 1000.0  # no bench DMM has a range above 1000 V (the 34970A's highest is 300 V)
SENSORS = ("x", "y", "z")
BLOCK_ROWS = 1 << 16  # rows a per-reading check handles at once: a few MiB of temporaries
MOUNTS = ((0.0, 0.0), (180.0, 0.0), (0.0, 180.0), (180.0, 180.0))
# gravity on each mount is gravity on the first one with axes reversed: y = 180° reverses x and y,
# u = 180° reverses y and z (the sines of 180° are rounding noise, ~1e-16)
MOUNT_SIGNS = {(0.0, 0.0): (1, 1, 1), (180.0, 0.0): (-1, -1, 1), (0.0, 180.0): (1, -1, -1),
               (180.0, 180.0): (-1, 1, -1)}


@dataclass(frozen=True)
class Flag:
    """One reading (1-based row of the data) that a check refuses, and why, in words."""

    row: int
    check: str  # "gravity", "mount", "residual", "methods"
    message: str

    def to_json(self) -> dict[str, object]:
        return {"row": self.row, "check": self.check, "message": self.message}


def sidak_per_test(n_tests: int, alpha: float = FAMILY_ALPHA) -> float:
    """The per-test level that keeps the family-wise level at ``alpha`` over n independent tests."""
    return float(-np.expm1(np.log1p(-alpha) / max(n_tests, 1)))


def t_threshold(n_tests: int, dof: float, alpha: float = FAMILY_ALPHA) -> float:
    """Two-sided Student t threshold for the largest of n tests (normal when dof is infinite)."""
    if not dof > 0:
        return float("inf")
    return float(t_quantile(1.0 - sidak_per_test(n_tests, alpha) / 2, min(dof, 1e7)))


def gravity_magnitude(cal: Calibration, volts: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                             NDArray[np.float64]]:
    """m = |(V − B)S⁻¹| per row (in g) and its standard uncertainty from Σ_v (calibration and reading).

    In blocks of rows: a million readings need a few n×3 temporaries each, not all of them at once."""
    m, u_m = np.empty(len(volts)), np.empty(len(volts))
    s_inv = cal.s_inv
    for start in range(0, len(volts), BLOCK_ROWS):
        block = slice(start, start + BLOCK_ROWS)
        with np.errstate(all="ignore"):
            g = (volts[block] - cal.X[0]) @ s_inv
            m[block] = mb = np.sqrt(np.einsum("ij,ij->i", g, g))
            unit = np.where((mb > 1e-9)[:, None] & np.isfinite(g), g / np.where(mb > 0, mb, 1.0)[:, None],
                            np.array([0.0, 0.0, 1.0]))
            dm_dv = unit @ s_inv.T  # ∂m/∂v_j = Σ_k S⁻¹[j, k] ĝ_k (row convention dg = dv·S⁻¹)
            dm_dv *= dm_dv
            u_m[block] = np.sqrt(np.einsum("ij,ij->i", dm_dv, output_variance(cal, unit)))
    return m, u_m


def gravity_flags(cal: Calibration, volts: NDArray[np.float64], describe: Callable[[int], str] | None = None,
                  alpha: float = FAMILY_ALPHA, tolerance: float = 0.0) -> list[Flag]:
    """Rows whose |g| is not 1 g within the family-wise threshold (or not a number at all).

    ``tolerance``: how far local |g| may lie from the calibration's (relative), e.g. readings taken
    in another lab (`labcal.analysis.attitude.LOCAL_GRAVITY_TOLERANCE`); only what lies beyond it
    is tested. The calibration's own readings are at its gravity: 0."""
    m, u_m = gravity_magnitude(cal, volts)
    limit = t_threshold(len(volts), cal.dof, alpha)
    flags = []
    with np.errstate(all="ignore"):
        z = np.maximum(np.abs(m - 1.0) - tolerance, 0.0) / u_m
    allowed = f" beyond the ±{tolerance:.2g} local gravity may differ by" if tolerance else ""
    for i in np.flatnonzero(~(z <= limit)):
        where = describe(int(i)) if describe else ""
        flags.append(Flag(int(i) + 1, "gravity",
                          f"|(V − B)S⁻¹| = {m[i]:.6g} g{where}; a static instrument reads 1 g "
                          f"(± {u_m[i]:.2g}, limit {limit:.2g} standard uncertainties{allowed})"))
    return flags


def _describe(readings: Readings, i: int) -> str:
    return (f" at pitch {readings.pitch_deg[i]:g}°, roll {readings.roll_deg[i]:g}°, mount "
            f"y={readings.y_deg[i]:g} u={readings.u_deg[i]:g}")


def _rows(indices: NDArray[np.int_]) -> str:
    """'3–18' for a run of consecutive rows, else a list."""
    rows = indices + 1
    if len(rows) > 1 and np.all(np.diff(rows) == 1):
        return f"{rows[0]}–{rows[-1]}"
    return ", ".join(str(r) for r in rows)


GroupFits = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]


Batches = list[tuple[NDArray[np.intp], NDArray[np.intp]]]


def _batches_of_equal_groups(groups: NDArray[np.intp], n_groups: int) -> Batches:
    """Groups of one size together, as (their numbers, their rows as a groups × size array), about
    BLOCK_ROWS rows at a time: per-group sums become batched matrix products, without a gather of
    per-group values for every row. A calibration's groups mostly share one size. A list, made
    once per check (its sort is most of its cost) and walked by every pass over the groups."""
    order = np.argsort(groups, kind="stable")
    sizes = np.bincount(groups, minlength=n_groups)
    starts = np.cumsum(sizes) - sizes
    batches = []
    for size in np.unique(sizes):
        same = np.flatnonzero(sizes == size)
        step = max(1, BLOCK_ROWS // int(size))
        for i in range(0, len(same), step):
            ks = same[i:i + step]
            batches.append((ks, order[starts[ks][:, None] + np.arange(size)]))
    return batches


def _leave_group_out(design: NDArray[np.float64], volts: NDArray[np.float64], full: LeastSquares,
                     groups: NDArray[np.intp], n_groups: int, batches: Batches) -> GroupFits:
    """For each group k (the rows with groups == k): the coefficients (K×L×m), unscaled covariance
    (K×L×L) and residual SE (K×m) of the fit of every *other* row, and whether those rows determine
    the model (K,). ``full`` is the fit of every row. Each group is taken out of the full fit by
    downdating at the residuals' scale (Fᵀe = 0 for the full fit, so the others' Fᵀe is −F_kᵀe_k),
    all groups at once from per-group sums: O(rows) in all, no loop over groups. A group whose
    removal leaves the design near singular is refitted by QR, as before."""
    n_coef = design.shape[1]
    e = full.residuals
    gram_k = np.empty((n_groups, n_coef, n_coef))
    ft_e = np.empty((n_groups, n_coef, e.shape[1]))  # F_kᵀe_k
    rss_k = np.empty((n_groups, e.shape[1]))
    for ks, rows in batches:  # the groups', `_batches_of_equal_groups`
        f, e_k = np.take(design, rows, axis=0), np.take(e, rows, axis=0)
        f_t = np.swapaxes(f, 1, 2)
        gram_k[ks], ft_e[ks], rss_k[ks] = f_t @ f, f_t @ e_k, np.einsum("ksj,ksj->kj", e_k, e_k)
    rest = design.T @ design - gram_k
    dof = len(design) - np.bincount(groups, minlength=n_groups) - n_coef
    scale = np.sqrt(np.clip(np.diagonal(rest, axis1=1, axis2=2), 0.0, None))
    unit = np.where(scale > 0, scale, 1.0)
    eig = np.linalg.eigvalsh(rest / (unit[:, :, None] * unit[:, None, :]))
    good = (dof >= 1) & np.all(scale > 0, axis=1) & (eig[:, 0] > 1e-12 * eig[:, -1])
    cov = np.full_like(rest, np.nan)
    cov[good] = np.linalg.inv(rest[good])
    coef = full.coef - cov @ ft_e
    rss_rest = np.einsum("ij,ij->j", e, e) - rss_k - np.sum(ft_e * (cov @ ft_e), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.sqrt(np.maximum(rss_rest, 0.0) / dof[:, None])
    determined = good.copy()
    for k in np.flatnonzero(~good):
        others = groups != k
        try:
            ls = least_squares(design[others], volts[others])
        except LabcalError:
            continue
        if ls.dof >= 1:
            coef[k], cov[k], se[k], determined[k] = ls.coef, ls.cov_unscaled, ls.residual_se, True
    return coef, cov, se, determined


def mount_flags(readings: Readings, alpha: float = FAMILY_ALPHA, base_fit: LeastSquares | None = None
                ) -> list[Flag]:
    """Groups of readings (one replicate, one mount) that their stated mount does not explain and
    another mount does: each group predicted from the base fit of all the other groups
    (``base_fit``: the base model's fit of every reading, when the caller has it).

    The design is the point's (every reading of a point has the same nominal gravity); each group's χ²
    under its stated mount, and under the other three where that one does not explain it, is summed
    from the readings in batches of equal-sized groups."""
    points = readings.points
    mount_of_point = 2 * (readings.y_deg[points.first] % 360 != 0) + (readings.u_deg[points.first] % 360 != 0)
    index, n_groups = point_groups([readings.replicate, mount_of_point[points.groups]])
    first = first_rows(index, n_groups)
    keys = np.column_stack([readings.replicate[first], readings.y_deg[first] % 360,
                            readings.u_deg[first] % 360])
    if n_groups < 2:
        return []
    _, point_design = Model().design(readings_points(readings, points.first))
    try:
        full = base_fit or least_squares_of_means(point_design, readings.point_means, points.counts,
                                                  readings.volts, points.groups)
    except LabcalError:
        return []  # every subset of a singular design is singular: nothing to compare with
    batches = _batches_of_equal_groups(index, n_groups)
    coef, cov, residual_se, determined = _leave_group_out(np.take(point_design, points.groups, axis=0),
                                                          readings.volts, full, index, n_groups, batches)
    usable = determined & np.all(residual_se > 0, axis=1)
    sizes = np.bincount(index, minlength=n_groups)
    limits = {int(n): float(chi2_quantile(1.0 - sidak_per_test(n_groups, alpha),
                                                    readings.volts.shape[1] * int(n)))
              for n in np.unique(sizes[usable])}  # one bisection per group size, not per group
    limit = np.array([limits.get(int(n), np.inf) for n in sizes])
    # each point's nominal gravity on the first mount: on the others it is this with axes reversed
    base = nominal_gravity(np.radians(readings.pitch_deg[points.first]),
                           np.radians(readings.roll_deg[points.first]), 0.0, 0.0)
    stated = np.array([MOUNTS.index((float(y), float(u))) for y, u in keys[:, 1:]])
    # [1, s∘g]·c = [1, g]·(diag(1, s) c): a mount's axis signs s go on each group's coefficients
    signs = np.array([[1.0, *MOUNT_SIGNS[mount]] for mount in MOUNTS])
    chi2 = np.full((len(MOUNTS), n_groups), np.inf)

    def chi2_under(mounts: NDArray[np.intp], ks: NDArray[np.intp], rows: NDArray[np.intp]) -> None:
        """χ² of the groups ``ks`` (their rows ``rows``, groups × size) under ``mounts[k]`` each."""
        f = np.ones((*rows.shape, 4))
        f[..., 1:] = np.take(base, np.take(points.groups, rows), axis=0)
        s = signs[mounts]
        z = np.take(readings.volts, rows, axis=0) - f @ (coef[ks] * s[:, :, None])
        with np.errstate(divide="ignore", invalid="ignore"):  # a group with no scatter left is not
            z /= residual_se[ks, None, :]                    # usable: its χ² is never judged
        q = np.einsum("ksa,ksa->ks", f @ (cov[ks] * s[:, :, None] * s[:, None, :]), f)
        with np.errstate(invalid="ignore"):
            chi2[mounts, ks] = np.sum(np.einsum("ksj,ksj->ks", z, z) / (1.0 + q), axis=1)

    # A group its stated mount explains is never flagged: the other mounts are tried only on the
    # groups it does not (none, in a good file)
    for ks, rows in batches:
        chi2_under(stated[ks], ks, rows)
    suspect = usable & (chi2[stated, np.arange(n_groups)] > limit)
    if suspect.any():
        for ks, rows in batches:
            if suspect[ks].any():
                for m in range(len(MOUNTS)):
                    chi2_under(np.full(int(suspect[ks].sum()), m), ks[suspect[ks]], rows[suspect[ks]])
    best = np.argmin(chi2, axis=0)
    chi2_stated, chi2_best = chi2[stated, np.arange(n_groups)], chi2[best, np.arange(n_groups)]
    wrong = suspect & (best != stated) & (chi2_best <= limit)
    flags: list[Flag] = []
    for k in np.flatnonzero(wrong):
        rows = np.flatnonzero(index == k)
        (_, y, u), (by, bu) = keys[k], MOUNTS[best[k]]
        message = (f"readings {_rows(rows)} (replicate {keys[k][0]:g}) are labelled mount y={y:g} "
                   f"u={u:g} but read like mount y={by:g} u={bu:g}: a missed or wrong "
                   f"remount? (χ² {chi2_stated[k]:.3g} against {chi2_best[k]:.3g}, limit {limit[k]:.3g})")
        flags.extend(Flag(int(i) + 1, "mount", message) for i in rows)
    return flags


def residual_flags(design: NDArray[np.float64], ls: LeastSquares,
                   skip: set[int] | frozenset[int] = frozenset(), alpha: float = FAMILY_ALPHA,
                   rows: NDArray[np.intp] | None = None, units: str = "V", sensors: tuple[str, ...] = SENSORS
                   ) -> tuple[list[Flag], float]:
    """Externally studentised residuals beyond the family-wise Student t threshold (over every
    reading and sensor) of the fit ``ls`` of ``design``; returns the flags and the threshold.
    ``design`` has a row per reading, or one per point with ``rows`` the point of every reading
    (the leverage is a function of the design row). In row blocks: a few MiB of temporaries. A
    residual with no scatter left to judge it by (0/0: an exact fit) is not flagged."""
    dof = ls.dof
    if dof < 2:
        return [], float("inf")
    h = np.einsum("ij,jk,ik->i", design, ls.cov_unscaled, design)
    e = ls.residuals
    limit = t_threshold(e.size, dof - 1, alpha)
    flags = []
    for start in range(0, len(e), BLOCK_ROWS):
        block = slice(start, start + BLOCK_ROWS)
        eb, hb = e[block], (h[block] if rows is None else h[rows[block]])[:, None]
        with np.errstate(all="ignore"):
            s2_without = (dof * ls.residual_se**2 - eb**2 / (1 - hb)) / (dof - 1)
            t = eb / np.sqrt(np.maximum(s2_without, 0) * (1 - hb))
        for i, j in zip(*np.nonzero(~(np.abs(t) <= limit) & ~np.isnan(t)), strict=True):
            if start + int(i) + 1 in skip:
                continue
            flags.append(Flag(start + int(i) + 1, "residual",
                              f"sensor {sensors[j]}: residual {eb[i, j]:+.3g} {units} is {abs(t[i, j]):.3g} "
                              f"times its standard error (limit {limit:.3g}, studentised)"))
    return flags, limit


# The largest output an instrument can give, per unit: a DMM's highest range for volts; for counts
# the largest integer a double holds exactly (no converter comes near it); for m/s² 100 000 g.
OUTPUT_MAX = {"V": VOLTS_MAX, "mV": VOLTS_MAX * 1e3, "counts": 2.0**53, "m/s2": 1e6}


def implausible_volts(volts: NDArray[np.float64], units: str = "V") -> None:
    """Refuse readings no instrument can have produced (they would make every statistic infinite):
    volts beyond any DMM range, other units beyond their `OUTPUT_MAX`. The volts' message names
    --units: counts or m/s² read as volts are the usual cause."""
    limit = OUTPUT_MAX[units]
    volts = volts[:, ~np.isnan(volts).all(axis=0)]  # a package's absent sensors: not outputs at all
    if np.max(volts, initial=-np.inf) <= limit and np.min(volts, initial=np.inf) >= -limit:
        return  # two reductions say so for a clean file (a NaN fails both comparisons)
    bad = np.flatnonzero(~np.all(np.abs(volts) <= limit, axis=1))
    if len(bad):
        i = bad[0]
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        values = f"reading {i + 1}: ({', '.join(f'{v:.3g}' for v in volts[i])}) {units}"
        if units in ("V", "mV"):
            raise LabcalError(f"{values} is beyond any DMM range (|V| ≤ {VOLTS_MAX:g} V){more}; correct or "
                              "remove it, or give {0} (mV, counts, m/s2) if the outputs are not volts",
                              "units")
        raise LabcalError(f"{values} is beyond any instrument's output (|x| ≤ {limit:g} {units}){more}; "
                          "correct or remove it")


def calibration_of(fit: Fit) -> Calibration:
    """What the attitude (and the gravity check) needs from a fit: X, the covariance of (B, S) per
    sensor, the standard deviation of one new reading and the degrees of freedom."""
    return Calibration(fit.coefficients, np.stack([fit.covariance(j)[:4, :4] for j in range(3)]),
                       np.sqrt(fit.new_measurement_variance()), int(np.min(fit.variance_dof)))


def fit_flags(readings: Readings, fit: Fit, alpha: float = FAMILY_ALPHA) -> list[Flag]:
    """Every gross-error check of a calibration's readings, row by row (mount groups first: one missed
    remount otherwise shows as dozens of gravity and residual flags)."""
    if np.all(fit.noise_free(readings)):
        return []  # every reading fits to rounding: none is a gross error, and there is no noise to test with
    if readings.volts.shape[1] != len(fit.sensors):  # a package's: judged by the outputs it has
        readings = replace(readings, volts=readings.volts[:, [SENSORS.index(s) for s in fit.sensors]])
    rows = readings.points.groups if fit.model.per_point else None
    _, design = fit.model.design(readings_points(readings, None if rows is None else readings.points.first))
    mount = mount_flags(readings, alpha, fit.ls if fit.names == BASE_NAMES else None)
    seen = {f.row for f in mount}
    gravity = []  # |g| = 1 is a check of three sensors' outputs together: a package of fewer has no |g|
    if len(fit.sensors) == 3:
        gravity = [f for f in gravity_flags(calibration_of(fit), readings.volts,
                                            lambda i: _describe(readings, i), alpha) if f.row not in seen]
    seen |= {f.row for f in gravity}
    residual, _ = residual_flags(design, fit.ls, seen, alpha, rows, readings.units, fit.sensors)
    return mount + gravity + residual


def methods_disagree(closed: Attitude, sphere: Attitude) -> list[Flag]:
    """Rows where the two estimators differ by more than their combined expanded uncertainty: they
    agree to first order on any reading of 1 g, so a difference means the reading is not one."""
    def wrapped(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(np.abs(np.angle(np.exp(1j * x))), dtype=float)

    flags = []
    with np.errstate(all="ignore"):
        limits = {"pitch": closed.k_pitch * np.hypot(closed.u_pitch, sphere.u_pitch),
                  "roll": closed.k_roll * np.hypot(closed.u_roll, sphere.u_roll)}
        # (p, r) and (±180° − p, r + 180°) are one direction: near the pole one estimator may state
        # it the other way, which is no disagreement (the roll is 180° apart, the gravity is not)
        across = ((wrapped(np.sign(closed.pitch) * np.pi - closed.pitch - sphere.pitch) <= limits["pitch"])
                  & (wrapped(closed.roll + np.pi - sphere.roll) <= limits["roll"]))
    for name, a, b in (("pitch", closed.pitch, sphere.pitch), ("roll", closed.roll, sphere.roll)):
        with np.errstate(all="ignore"):
            diff, limit = wrapped(a - b), limits[name]
            # where the closed form's uncertainty is undefined (at the pole) nothing is compared:
            # the gravity check still sees a reading that is not 1 g
            bad = np.isfinite(diff) & np.isfinite(limit) & (diff > limit) & ~across
        for i in np.flatnonzero(bad):
            flags.append(Flag(int(i) + 1, "methods",
                              f"closed form and sphere solution differ by {np.degrees(diff[i]):.3g}° in "
                              f"{name} (more than their combined U95, {np.degrees(limit[i]):.2g}°)"))
    return flags
