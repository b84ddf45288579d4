"""Experimental design: generating plans (Tripp §4.1, §7), their figure of merit, and the audit
of how each calibration-device misalignment leaks into the fitted coefficients (Soto §7).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.kinematics import MISALIGNMENT_NAMES, Misalignment, gravity
from labcal.analysis.plan import INDEX_STEP_DEG, Plan, on_grid
from labcal.errors import LabcalError

FOUR_MOUNTS = [(0.0, 0.0), (180.0, 0.0), (0.0, 180.0), (180.0, 180.0)]
ONE_MOUNT = [(0.0, 0.0)]
LEAK_ZERO = 1e-9  # below this a leakage per radian is zero to rounding
GRID_MAX_PER_AXIS = 541  # -180..360 on the tables' 1° grid: a finer grid is a typing mistake


# --- generators (angles in degrees) -------------------------------------------------------------
def uniform_roll(n_roll: int) -> NDArray[np.float64]:
    """M roll angles uniformly over [−180°, 180° − ΔR] (designs D0 and D1)."""
    return -180.0 + 360.0 * np.arange(n_roll) / n_roll


def d0(pitch_deg: list[float], n_roll: int) -> list[tuple[float, float]]:
    """Design D0: any pitch set crossed with M uniformly spaced rolls."""
    return [(float(p), float(r)) for p in pitch_deg for r in uniform_roll(n_roll)]


def d1(pitch_max: float, n_pitch: int, n_roll: int, roll_closed: bool = False) -> list[tuple[float, float]]:
    """Design D1: N pitches uniform over [−α_max, α_max] crossed with M uniform rolls; with
    ``roll_closed`` the M rolls span [−180°, 180°] ends included, the roll point repeated at 180° of
    Tripp's Fig. 5 (convenient on a table that turns through the full circle)."""
    pitch = np.linspace(-pitch_max, pitch_max, n_pitch)
    if not roll_closed:
        return d0(list(pitch), n_roll)
    return [(float(p), float(r)) for p in pitch for r in np.linspace(-180.0, 180.0, n_roll)]


def _mirrored(half: list[float]) -> list[float]:
    """A pitch set symmetric about 0 from its non-negative half."""
    return sorted({-a for a in half} | set(half))


# Tripp Table 1 (M = 64, N = 33 unless stated): column → (figure, design, its points, calibration
# pitch range, usage pitch range of V_R or None). Columns 6 and 7 are described in §5.3.2 by their
# spacings (1° steps within ±10°, 4° steps beyond ±14°; and 1° steps beyond ±20°, 4° steps within
# ±16°): those spacings give 31 pitches, and the N = 33 of the table is reached by the one pitch
# pair that splits the gap between the two spacings evenly (±12°; ±18°).
_D0_CENTRE = _mirrored([*range(0, 11), 12, 14, 18, 22, 26, 30])
_D0_ENDS = _mirrored([0, 4, 8, 12, 16, 18, *range(20, 31)])
_D0_BOUNDARY = [-30.0] * 16 + [0.0] + [30.0] * 16


class TableColumn(NamedTuple):
    figure: str
    design: str
    points: Callable[[], list[tuple[float, float]]]
    calibration_pitch: tuple[float, float]
    usage_pitch: tuple[float, float] | None  # the range of V_R, where the table gives one


TRIPP_TABLE_1: dict[int, TableColumn] = {
    2: TableColumn("Figure 2(a)", "D1", lambda: d1(30, 33, 64), (-30, 30), None),
    3: TableColumn("Figure 2(b)", "D1", lambda: d1(45, 33, 64), (-45, 45), (-30, 30)),
    4: TableColumn("Figure 2(c)", "D1", lambda: d1(90, 33, 64), (-90, 90), (-30, 30)),
    5: TableColumn("Figure 2(d)", "D1", lambda: d1(180, 33, 64), (-180, 180), (-30, 30)),
    6: TableColumn("Figure 3 (top)", "D0, pitch points concentrated between -10° and 10°",
                   lambda: d0(_D0_CENTRE, 64), (-30, 30), (-10, 10)),
    7: TableColumn("Figure 3 (bottom)", "D0, pitch points concentrated between -30° to -20° and 20° to 30°",
                   lambda: d0(_D0_ENDS, 64), (-30, 30), (-10, 10)),
    8: TableColumn("Figure 4", "D0, pitch points concentrated at -30° and 30°",
                   lambda: d0(_D0_BOUNDARY, 64), (-30, 30), (-10, 10)),
    9: TableColumn("Figure 5", "D1, M = 65 with the roll repeated at 180°",
                   lambda: d1(30, 33, 65, roll_closed=True), (-30, 30), None),
}


def tripp_table_1(column: int) -> TableColumn:
    """The design of Tripp Table 1's ``column`` (2..9)."""
    if column not in TRIPP_TABLE_1:
        raise LabcalError(f"Tripp Table 1 has designs in columns 2..9, not {column}")
    return TRIPP_TABLE_1[column]


def tumble() -> list[tuple[float, float]]:
    """The six-point tumble T (Tripp eq. 56): the six cardinal attitudes."""
    return [(-90.0, 0.0), (0.0, 0.0), (90.0, 0.0), (180.0, 0.0), (0.0, -90.0), (0.0, 90.0)]


def fractional(pitch_max: float, n_pitch: int, roll_min: float, roll_max: float, n_roll: int,
               k_pitch: int, k_roll: int) -> list[tuple[float, float]]:
    """A D design thinned by decimation (Tripp §7, eq. 109): every k_roll-th roll column keeps all
    its pitches; the other columns keep every k_pitch-th pitch. Boundaries are never decimated."""
    pitch = np.linspace(-pitch_max, pitch_max, n_pitch)
    roll = np.linspace(roll_min, roll_max, n_roll)
    keep = []
    for j, r in enumerate(roll):
        full_column = j % k_roll == 0 or j == n_roll - 1
        for i, p in enumerate(pitch):
            if full_column or i % k_pitch == 0 or i == n_pitch - 1:
                keep.append((float(p), float(r)))
    return keep


def fractional_size(n_pitch: int, n_roll: int, k_pitch: int, k_roll: int) -> float:
    """Tripp eq. 109: the number of points C′ a fractional design keeps."""
    full_columns = (n_roll - 1) / k_roll + 1
    thinned_columns = (n_roll - 1) * (1 - 1 / k_roll)
    return n_pitch * full_columns + thinned_columns * ((n_pitch - 1) / k_pitch + 1)


def grid(pitch_min: float, pitch_max: float, pitch_step: float, roll_min: float, roll_max: float,
         roll_step: float) -> list[tuple[float, float]]:
    """Every (pitch, roll) on a rectangular grid, ends included."""
    def axis(lo: float, hi: float, step: float) -> NDArray[np.float64]:
        if not (step > 0 and hi >= lo):
            raise LabcalError(f"grid {lo:g}..{hi:g} step {step:g}: need step > 0 and max ≥ min")
        n = np.floor((hi - lo) / step + 1e-9) + 1
        if not n <= GRID_MAX_PER_AXIS:
            finest = (hi - lo) / (GRID_MAX_PER_AXIS - 1)
            raise LabcalError(f"grid {lo:g}..{hi:g} step {step:g}: {n:.3g} angles per axis; at most "
                              f"{GRID_MAX_PER_AXIS} (a step of at least {finest:.3g}°)")
        return lo + step * np.arange(int(n), dtype=np.float64)
    return [(float(p), float(r)) for p in axis(pitch_min, pitch_max, pitch_step)
            for r in axis(roll_min, roll_max, roll_step)]


def make_plan(name: str, description: str, points: list[tuple[float, float]], four_mounts: bool,
              replicates: int = 1) -> Plan:
    """A validated plan; angles off the 1° index grid mark it for continuous tables."""
    indexable = all(on_grid(a, INDEX_STEP_DEG) for point in points for a in point)
    return Plan(name=name, description=description, replicates=replicates,
                angle_step_deg=INDEX_STEP_DEG if indexable else 0.0,
                mounts=FOUR_MOUNTS if four_mounts else ONE_MOUNT, points=points)




# --- figure of merit (Tripp §3.4, eq. 53) -------------------------------------------------------
def design_matrix(plan: Plan) -> NDArray[np.float64]:
    """[1 gᵀ] of every point of the run (replicates included)."""
    g = np.tile(plan.nominal_gravity(), (plan.replicates, 1))
    return np.column_stack([np.ones(len(g)), g])


def normalised_variance(plan: Plan, pitch_deg: ArrayLike, roll_deg: ArrayLike) -> NDArray[np.float64]:
    """K·fᵀ(FᵀF)⁻¹f at attitudes of the instrument in use (top, forward mount): σ_v²·K/σ_E²."""
    f_cal = design_matrix(plan)
    moment_inv = np.linalg.inv(f_cal.T @ f_cal)
    g = gravity(np.radians(pitch_deg), np.radians(roll_deg), 0.0, 0.0)
    f = np.concatenate([np.ones(g.shape[:-1] + (1,)), g], axis=-1)
    q: NDArray[np.float64] = len(f_cal) * np.einsum("...i,ij,...j->...", f, moment_inv, f)
    return q


def figure_of_merit(plan: Plan, pitch_range: tuple[float, float]) -> float:
    """Box's V: mean of K·σ_v²/σ_E² over pitch in ``pitch_range`` and roll over the full circle.

    Pitch by 200-node Gauss–Legendre (the integrand is a trigonometric polynomial of low degree),
    roll by 72 uniform nodes, exact for its degree-2 dependence on roll.
    """
    lo, hi = pitch_range
    if not hi > lo:
        raise LabcalError(f"pitch range {lo:g}..{hi:g} is empty")
    x, w = np.polynomial.legendre.leggauss(200)
    pitch = lo + (x + 1) * (hi - lo) / 2
    roll = np.arange(72) * 5.0
    q = normalised_variance(plan, pitch[:, None], roll[None, :]).mean(axis=1)
    return float(np.sum(w * q) / 2)


# --- audit (Soto §7): ∂X/∂misalignment through the kinematic model --------------------------------
def audit(plan: Plan) -> dict[str, NDArray[np.float64]]:
    """First-order change of every coefficient of X (4×3) per radian of each CD misalignment,
    for an ideal instrument (B = 0, S = I). Complex-step derivatives: exact to rounding."""
    p, r = np.radians(np.array(plan.points)).T
    f = design_matrix(Plan(**{**plan.model_dump(), "replicates": 1}))
    pinv = np.linalg.pinv(f)
    step = 1e-30
    leaks = {}
    for name in MISALIGNMENT_NAMES:
        dg = np.concatenate([
            np.imag(gravity(p, r, np.radians(y), np.radians(u), Misalignment(**{name: 1j * step}))) / step
            for y, u in plan.mounts
        ])
        leaks[name] = pinv @ dg
    return leaks


def audit_summary(leaks: dict[str, NDArray[np.float64]]) -> dict[str, dict[str, Any]]:
    """Which misalignments leak into the bias and the off-diagonal of S (above LEAK_ZERO)."""
    off = ~np.eye(3, dtype=bool)
    summary = {}
    for name, d in leaks.items():
        bias, off_diagonal = float(np.max(np.abs(d[0]))), float(np.max(np.abs(d[1:][off])))
        summary[name] = {"bias_max": bias, "off_diagonal_max": off_diagonal,
                         "diagonal_max": float(np.max(np.abs(np.diag(d[1:])))),
                         "cancelled": bias < LEAK_ZERO and off_diagonal < LEAK_ZERO}
    return summary
