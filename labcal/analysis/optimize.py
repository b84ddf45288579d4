"""Plan for the uncertainty the customer needs: the predicted attitude U95 of a candidate
plan before anything moves, and a small search for the quickest plan that reaches a target.

Prediction. A candidate is mounts × articulations (pitch, roll) × a measurement window of N DMM
samples. Its calibration is predicted as its certificate's budget will see the run's fit
(`labcal.analysis.budget`), by the same rules: the moment matrix R = FᵀF of the nominal design (Tripp &
Tcheng §3.2, eqs. 49–50), the coefficients' Type A σ²R⁻¹ per sensor with σ² = σ_s²/N the instrument's
noise over the window (`budget.windows_noise_covariance`), and one reading in use, σ_s²/N over the
averaging in use (`budget.new_reading`), both with the pooled within-window scatter's K(N − 1) degrees
of freedom; the bench's errors (the tables' index and wobble, the plate's seating, the device's
misalignments) reach the attitude only through the coefficients, as Type B rows. A run states its U95
from its own estimate s of σ_s, which scatters from run to run (s² = σ_s²χ²_ν/ν): predicted with each
channel's s at its 0.95^(1/3) quantile, the plan's certificates state a U95 within the target in at
least 95 % of its runs (the three channels scatter independently, and the U95 grows with each). The
fit's expected residual variance (the noise plus what of the bench's errors the fit cannot absorb,
each through I − H) sets only the estimator's weights, as a run's fit covariance does. The Type B
rows are the budget's own (`budget.sources`), and the attitude U95 over the usage envelope comes from
`budget.propagate`, that is `attitude.combined_uncertainty` with `attitude.sphere_sensitivity`: the one
estimator every stated U95 comes from, here given a predicted instead of a fitted calibration.

The calibration device's misalignments a…k are never left in the coefficients: either the plan
identifies them with the instrument (the device model, `plan audit` full rank: each one's uncertainty
from `device_model.identifiability` enters as the budget's device-misalignment row), or they are known
from the device's recent, in-control history and applied as a correction, whose uncertainty is that
same row (a Type B input). Only then may a plan use fewer than the four mounts.

Search. Articulations come from a candidate grid (pitch and roll on a 30° lattice); for each mount set
they are taken by greedy forward selection maximising det R (D-optimality: the confidence ellipsoid of
the coefficients, Tripp & Tcheng eq. 51, has volume ∝ det R^-½), so every prefix of the sequence is the
design of that size. Every (mount set, size, window) is timed by the caller (the station's timing
model, the tour included) and its U95 predicted; the quickest whose U95 meets the target wins. About a
hundred candidates, each timed and predicted in tens of milliseconds: seconds, deterministic.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri

from labcal.analysis.budget import (
    Calibration,
    Propagated,
    TypeBInputs,
    _gravity_derivative,
    _membership,
    propagate,
    sources,
    windows_noise_covariance,
)
from labcal.analysis.correction_check import sensitivity
from labcal.analysis.design import FOUR_MOUNTS, grid
from labcal.analysis.device_fit import AngleErrors, angle_error_shapes
from labcal.analysis.device_model import Geometry, identifiability
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, nominal_gravity
from labcal.analysis.models import Points
from labcal.analysis.repeatability import Repeatability
from labcal.errors import LabcalError

SQRT3 = float(np.sqrt(3.0))
N_COEFFICIENTS = 4  # per sensor: B and the three sensitivities
CANDIDATE_STEP_DEG = 30.0  # the articulation grid: 62 distinct attitudes, every one on the 1° index grid
SIZES = (6, 8, 12, 16, 24, 32, 48, 64)  # articulations per mount
WINDOWS = (4, 10, 20, 40)  # DMM samples per point (4: the sequencer's least, `SettleSettings.samples`)
# One mount, two, three and four. A plan relying on a device correction must see every misalignment it
# corrects for (`correction_check`): one mount never sees e, f, k, and each pair reverses only two of
# them (fore/aft e and f, top/bottom e and k, both f and k), so with a correction three mounts covering
# both reversals are the fewest that may do without the four; the smaller sets stay as candidates that
# the check turns down, so the search says why.
MOUNT_SETS: tuple[tuple[tuple[float, float], ...], ...] = (
    ((0.0, 0.0),), ((0.0, 0.0), (180.0, 180.0)), ((0.0, 0.0), (180.0, 0.0), (0.0, 180.0)),
    tuple(FOUR_MOUNTS))
PROMISE = 0.95  # the share of a plan's runs whose stated U95 is within the target it was chosen for
SEARCH_GRID_STEP_DEG = 15.0  # the envelope during the search; the chosen plan is checked on the certificate's


@dataclass(frozen=True)
class Bench:
    """What the prediction needs of the station and the instrument: the nominal coefficients (4×3),
    the noise of one DMM sample (V rms), the bench's Type B inputs, and the usage envelope (degrees)."""

    X: NDArray[np.float64]
    noise_v: float
    type_b: TypeBInputs
    usage_pitch_deg: tuple[float, float] = (-60.0, 60.0)
    usage_roll_deg: tuple[float, float] = (-180.0, 180.0)
    grid_step_deg: float = 5.0
    in_use_samples: int | None = None  # the certificate's averaging in use (None: the plan's window)


@dataclass(frozen=True)
class DeviceCorrection:
    """The device's misalignments as its history knows them (radians), to be corrected for, each with
    its standard uncertainty: what a plan of fewer mounts relies on."""

    device_id: str
    source: str  # the run whose estimate this is
    value_rad: dict[str, float]
    u_rad: dict[str, float]  # what the plan carries as the Type B input
    U_rad: dict[str, float] = field(default_factory=dict)  # the estimate's own U (95 %), as stated
    calibrated_utc: str = ""  # when the source run calibrated


@dataclass(frozen=True)
class Candidate:
    mounts: tuple[tuple[float, float], ...]
    points: tuple[tuple[float, float], ...]
    samples: int

    @property
    def n_points(self) -> int:
        return len(self.mounts) * len(self.points)


@dataclass(frozen=True)
class Evaluated:
    candidate: Candidate
    rig_time_s: float
    u95_pitch_rad: float  # the largest over the envelope
    u95_roll_rad: float
    identified: bool  # the device model identifies a…k from this plan; else it relies on the correction
    contributions: dict[str, float] = field(default_factory=dict)  # u (rad) at the worst pitch attitude

    @property
    def u95_rad(self) -> float:
        """The attitude U95: the larger of pitch's and roll's worst over the envelope."""
        return max(self.u95_pitch_rad, self.u95_roll_rad)


def envelope_attitudes(bench: Bench, step_deg: float | None = None) -> tuple[NDArray[np.float64], ...]:
    """The usage envelope's grid (radians), as the certificate's (`documents.uncertainty.envelope`)."""
    step = bench.grid_step_deg if step_deg is None else step_deg
    points = np.radians(np.array(grid(*bench.usage_pitch_deg, step, *bench.usage_roll_deg, step)))
    return points[:, 0], points[:, 1]


def _points(c: Candidate) -> Points:
    rows = np.array([(p, r, y, u) for y, u in c.mounts for p, r in c.points], dtype=float)
    return Points.at(*rows.T)


def _residual_covariance(points: Points, X: NDArray[np.float64], design: NDArray[np.float64],
                         b: TypeBInputs, noise_var: float, held_u: dict[str, float] | None = None
                         ) -> NDArray[np.float64]:
    """Per sensor, the covariance (3 × K × K) of the fit's residuals: the noise σ²(I − H), plus what the
    tables' index and wobble errors and the remounts leave there, each input of the budget's (one per
    table angle for a rough table, harmonics 1–3 for a smooth one; the mean of the two, as the budget
    bounds by their sum) through I − H; and, for a plan that holds the misalignments at a correction
    (``held_u``: its own u per misalignment, rad), the correction's error, one offset of each for every
    point, which the coefficients absorb only in part. Its trace over K − L is E[s²]: what the
    attitude estimator weights the sensors by, as it weights by a run's fit."""
    k = len(design)
    hat = design @ np.linalg.pinv(design)
    rest = np.eye(k) - hat
    total = np.repeat((noise_var * rest)[None], 3, axis=0)

    def add(dv: NDArray[np.float64], basis: NDArray[np.float64], var: float) -> None:
        for j in range(3):
            r = rest @ (dv[:, j:j + 1] * basis)  # K × m
            total[j] += var * (r @ r.T)

    pitch_shapes = angle_error_shapes(np.radians(points.pitch_deg))
    roll_shapes = angle_error_shapes(np.radians(points.roll_deg))
    for names, shapes, half in ((("a",), pitch_shapes, b.pitch_index),
                                (("d", "f"), pitch_shapes, b.pitch_wobble),
                                (("f",), roll_shapes, b.roll_index),
                                (("e", "k"), roll_shapes, b.roll_wobble)):
        if half <= 0:
            continue
        for name in names:
            dv = _gravity_derivative(points, name) @ X[1:]  # (K, 3) per radian
            for basis, share in shapes:
                add(dv, basis, 0.5 * (half / SQRT3) ** 2 * share)
    if b.mount_repeatability > 0:
        keys = np.column_stack([np.mod(points.y_deg, 360.0), np.mod(points.u_deg, 360.0)])
        _, installation = np.unique(keys, axis=0, return_inverse=True)
        basis = _membership(np.asarray(installation).ravel())
        for name in ("e", "f", "k"):
            add(_gravity_derivative(points, name) @ X[1:], basis, (b.mount_repeatability / SQRT3) ** 2)
    for name, u in (held_u or {}).items():
        add(_gravity_derivative(points, name) @ X[1:], np.ones((k, 1)), u**2)
    return total


def expected_residual_variance(covariance: NDArray[np.float64], dof: int) -> NDArray[np.float64]:
    """Per sensor, E[s²] = tr Σ/ν of the fit's residual variance (Σ from `_residual_covariance`)."""
    return np.asarray(np.einsum("jii->j", covariance) / dof, dtype=float)


def repeatability_quantile(c: Candidate, bench: Bench, p: float | None) -> Repeatability | None:
    """The pooled within-window scatter a run of ``c`` will state (`labcal.analysis.repeatability`):
    σ per sample over K windows of N samples, ν = K(N − 1) degrees of freedom; at its ``p``-quantile
    over runs (s² = σ²χ²_ν/ν, GUM G.3: the scatter of a Type A estimate with its degrees of freedom),
    or σ itself (None); the p-quantile of the stated U95 where it is the channels' joint one. None where the
    windows are single samples (no scatter inside them)."""
    # deferred: the plan commands that predict nothing (plan list, --help) start without scipy
    k = c.n_points
    dof = k * (c.samples - 1)
    if dof <= 0:
        return None
    # the stated U95 grows with each channel's s, and the three channels scatter independently: all
    # three lie within their p^(1/3)-quantile in a share p of the runs, and then so does the U95
    scale = 1.0 if p is None else float(chdtri(dof, 1.0 - p ** (1.0 / 3.0))) / dof
    return Repeatability(np.full(3, bench.noise_v * np.sqrt(scale)), float(dof), k, c.samples)


def predicted_calibration(c: Candidate, bench: Bench, quantile: float | None = PROMISE,
                          held_u: dict[str, float] | None = None) -> Calibration:
    """The budget's view of the fit a run of ``c`` gives (one replicate), as the certificate builds it
    (`budget.with_noise_covariance`, `budget.new_reading`): the coefficients' Type A and one reading in
    use from the instrument's noise, its pooled within-window scatter at its ``quantile`` over runs
    (`repeatability_quantile`; None: σ itself); the bench's errors enter as the Type B rows. The fit's
    residual variance (its expectation; ``held_u``: the u of a correction the fit holds the
    misalignments at, `_residual_covariance`) is what the estimator weights by, as the certificate's
    fit covariance, and the whole budget where the windows carry no scatter."""
    points = _points(c)
    g = nominal_gravity(*(np.radians(a) for a in (points.pitch_deg, points.roll_deg, points.y_deg,
                                                  points.u_deg)))
    design = np.column_stack([np.ones(len(g)), g])
    inverse = np.linalg.inv(design.T @ design)  # R⁻¹ (Tripp eq. 50)
    dof = len(g) - N_COEFFICIENTS
    covariance = _residual_covariance(points, bench.X, design, bench.type_b, bench.noise_v**2 / c.samples,
                                      held_u)
    residual = expected_residual_variance(covariance, dof)
    keys = np.column_stack([np.mod(points.y_deg, 360.0), np.mod(points.u_deg, 360.0)])
    _, installation = np.unique(keys, axis=0, return_inverse=True)
    fitted = Calibration(X=bench.X, covariance=residual[:, None, None] * inverse[None], reading_var=residual,
                         dof=np.full(3, float(dof)), projection=(inverse @ design.T)[:4], points=points,
                         installation=np.asarray(installation, dtype=int).ravel(),
                         in_use_samples=bench.in_use_samples)
    rep = repeatability_quantile(c, bench, quantile)
    if rep is None:
        return fitted
    return windows_noise_covariance(fitted, rep, np.full(len(g), float(c.samples)))


def identified_u(c: Candidate, bench: Bench, cal: Calibration) -> dict[str, float] | None:
    """Each misalignment's standard uncertainty (rad) where the device model identifies a…k from
    ``c``'s points with the instrument (`device_model.identifiability`, per µg of a point's noise: the
    windows' scatter over N samples where ``cal`` has it, as the device model's noise share), else
    None."""
    ident = identifiability(Geometry.of_plan(list(c.points), list(c.mounts)))
    if ident.problem():
        return None
    sensitivity = float(np.mean(np.abs(np.diag(bench.X[1:]))))
    rep = cal.repeatability
    point_var = cal.reading_var if rep is None else rep.reading_variance(c.samples)
    noise_ug = float(np.sqrt(np.max(point_var))) / sensitivity * 1e6
    return {n: ident.u_per_ug[n] * noise_ug * ARCSEC for n in MISALIGNMENT_NAMES}


def corrected_u(c: Candidate, bench: Bench, correction: DeviceCorrection) -> dict[str, float] | None:
    """The u (rad) a run of ``c`` carries for each misalignment it corrects for: the larger of the
    correction's own and a third of the change the run's check detects with 95 % power
    (`correction_check.Sensitivity.budget_u`); None where the run cannot see one of them at all."""
    b = bench.type_b
    sens = sensitivity(Geometry.of_plan(list(c.points), list(c.mounts)), bench.X,
                       np.full(3, bench.noise_v / np.sqrt(c.samples)),
                       np.array([correction.value_rad[n] for n in MISALIGNMENT_NAMES]),
                       AngleErrors(b.pitch_index, b.pitch_wobble, b.roll_index, b.roll_wobble))
    u = sens.budget_u(np.array([correction.u_rad[n] for n in MISALIGNMENT_NAMES]))
    if not np.all(np.isfinite(u)):
        return None
    return {n: float(v) for n, v in zip(MISALIGNMENT_NAMES, u, strict=True)}


def predicted_u95(c: Candidate, bench: Bench, correction: DeviceCorrection | None,
                  pitch: NDArray[np.float64], roll: NDArray[np.float64]) -> tuple[Propagated, bool] | None:
    """Pitch and roll U95 (rad) a run of ``c`` is expected to state at these attitudes (radians), from
    the budget's rows and `budget.propagate`, and whether the plan identifies a…k itself; None where
    its misalignments would be left in the coefficients (neither identified by the plan nor known)."""
    four = len(c.mounts) == len(FOUR_MOUNTS)
    cal = predicted_calibration(c, bench, held_u=None if four or correction is None else correction.u_rad)
    identified = identified_u(c, bench, cal) if four else None
    device_u = identified if identified is not None else None if correction is None else \
        corrected_u(c, bench, correction)
    if device_u is None:
        return None
    rows = sources(cal, replace(bench.type_b, device_misalignment=dict(device_u)))
    return propagate(cal, rows, pitch, roll), identified is not None


def evaluate(c: Candidate, bench: Bench, correction: DeviceCorrection | None, rig_time_s: float,
             step_deg: float | None = None) -> Evaluated | None:
    """``c``'s predicted worst U95 over the envelope (its grid at ``step_deg``, default the
    certificate's); None where `predicted_u95` is."""
    predicted = predicted_u95(c, bench, correction, *envelope_attitudes(bench, step_deg))
    if predicted is None:
        return None
    p, identified = predicted
    U = p.U
    worst = int(np.nanargmax(U[:, 0]))
    return Evaluated(c, rig_time_s, float(np.nanmax(U[:, 0])), float(np.nanmax(U[:, 1])), identified,
                     {name: float(v[worst, 0]) for name, v in p.contributions.items()})


def candidate_articulations(step_deg: float = CANDIDATE_STEP_DEG) -> list[tuple[float, float]]:
    """Pitch −90…90° × roll −180…180° on a ``step_deg`` lattice; at pitch ±90° one roll only (gravity
    lies along the roll axis there: other rolls are the same attitude)."""
    pitches = np.arange(-90.0, 90.0 + 1e-9, step_deg)
    rolls = np.arange(-180.0, 180.0 - 1e-9, step_deg)
    return [(float(p), float(r)) for p in pitches for r in rolls if abs(p) < 90 or r == 0.0]


def d_optimal_sequence(mounts: Sequence[tuple[float, float]], candidates: list[tuple[float, float]],
                       length: int) -> list[tuple[float, float]]:
    """Greedy forward selection maximising det R of the rows of every mount (D-optimality): each step
    adds the articulation with the largest fᵀR⁻¹f summed over the mounts (the matrix determinant lemma
    for a rank-one update; for several mounts the sum is its first-order form), the first on ties.
    A small ridge starts R nonsingular; deterministic."""
    rows = np.stack([np.column_stack([np.ones(len(candidates)), nominal_gravity(
        *np.radians(np.array(candidates)).T, *np.radians([y, u]))]) for y, u in mounts], axis=1)  # (C, M, 4)
    R = 1e-6 * np.eye(N_COEFFICIENTS)
    chosen: list[int] = []
    for _ in range(min(length, len(candidates))):
        inv = np.linalg.inv(R)
        gain = np.einsum("cmi,ij,cmj->c", rows, inv, rows)
        gain[chosen] = -np.inf
        best = int(np.argmax(gain))
        chosen.append(best)
        R = R + np.einsum("mi,mj->ij", rows[best], rows[best])
    return [candidates[i] for i in chosen]


def candidates(mount_sets: Sequence[tuple[tuple[float, float], ...]] = MOUNT_SETS,
               sizes: Sequence[int] = SIZES, windows: Sequence[int] = WINDOWS) -> list[Candidate]:
    """Every (mount set, size, window) of the search, articulations by `d_optimal_sequence`."""
    grid_ = candidate_articulations()
    out = []
    for mounts in mount_sets:
        sequence = d_optimal_sequence(mounts, grid_, max(sizes))
        for n in sizes:
            if n * len(mounts) < N_COEFFICIENTS + 2 or n > len(grid_):
                continue
            out += [Candidate(tuple(mounts), tuple(sequence[:n]), w) for w in windows]
    return out


def search(bench: Bench, correction: DeviceCorrection | None, rig_time: Callable[[Candidate], float],
           candidate_list: list[Candidate] | None = None) -> list[Evaluated]:
    """Every candidate that keeps the misalignments out of the coefficients, timed and predicted on the
    search's envelope grid; quickest first. Mount sets of fewer than four only with a ``correction``."""
    found = []
    for c in candidate_list if candidate_list is not None else candidates():
        if correction is None and len(c.mounts) < len(FOUR_MOUNTS):
            continue
        e = evaluate(c, bench, correction, rig_time(c), SEARCH_GRID_STEP_DEG)
        if e is not None:
            found.append(e)
    return sorted(found, key=lambda e: (e.rig_time_s, e.u95_rad))


def frontier(found: list[Evaluated]) -> list[Evaluated]:
    """The candidates no other beats in both rig time and U95, quickest first."""
    best, out = np.inf, []
    for e in sorted(found, key=lambda e: (e.rig_time_s, e.u95_rad)):
        if e.u95_rad < best:
            out.append(e)
            best = e.u95_rad
    return out


def choose(found: list[Evaluated], bench: Bench, correction: DeviceCorrection | None,
           target_rad: float) -> Evaluated:
    """The quickest candidate whose U95, checked again on the certificate's envelope grid, is within
    ``target_rad``; one line naming the best reachable U95 where none is."""
    for e in found:
        if e.u95_rad > target_rad:
            continue
        full = evaluate(e.candidate, bench, correction, e.rig_time_s)
        if full is not None and full.u95_rad <= target_rad:
            return full
    best = min(found, key=lambda e: e.u95_rad, default=None)
    full = None if best is None else evaluate(best.candidate, bench, correction, best.rig_time_s)
    reachable = np.inf if full is None else full.u95_rad  # on the grid the target was checked on
    raise LabcalError(f"no candidate plan reaches an attitude U95 of {np.degrees(target_rad):.4g}°; the best "
                      f"reachable is {np.degrees(reachable):.4g}° (raise --target-attitude-u95-deg)")
