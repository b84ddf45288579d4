"""Inferred pitch and roll, and their uncertainty, for every sensor package of Tripp & Tcheng §6:
single-axis without roll, single-axis with independently measured roll, the two-axis x–y and x–z
packages. (The three-axis package is `labcal.analysis.attitude`.)

Each sensor is Tripp's c = [b, S, Ω, A] (eq. 8) in Tripp's own sign convention: the outputs are
eqs. 14–16 (eqs. 2, 4, 5) and their derivatives with respect to pitch α and roll R are eqs. 87, 88
and 95. labcal's linear fit v = B + s·g, with g = [sin α, cos α sin R, cos α cos R], holds the same
sensor as a column s; `from_linear` maps one to the other (Tripp's y and z sensors read −g_y and
−g_z, so their S is the negative of |s|). Angles are in radians, outputs in volts.

σ_v, the standard deviation of a predicted output at the attitude of use, is the caller's: the
calibration's part fᵀ·C·f and one new reading's variance (Tripp eqs. 52, 73), `output_sd`. What is
here is how it becomes the uncertainty of the inferred angle, where that is unbounded, and where a
package can be used at all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.coning import _AXES
from labcal.analysis.fit import Fit
from labcal.analysis.kinematics import nominal_gravity
from labcal.errors import LabcalError

Array = NDArray[np.float64]

# The packages Tripp & Tcheng treat (§6.1–6.6), by the axes their accelerometers lie along.
PACKAGES: dict[str, tuple[str, ...]] = {
    "single-axis": ("x",),
    "two-axis-xy": ("x", "y"),
    "two-axis-xz": ("x", "z"),
    "three-axis": ("x", "y", "z"),
}
NEWTON_ITERATIONS = 30  # quadratic convergence from a start within a few degrees needs far fewer
NEWTON_TOLERANCE = 1e-13  # rad: below the rounding of the outputs' sines


@dataclass(frozen=True)
class Sensor:
    """One accelerometer, Tripp eq. 8: offset b (V), sensitivity S (V/g), coning angle Ω and
    azimuth A (rad), for the sensor nominally along ``axis``."""

    axis: str
    b: float
    S: float
    omega: float = 0.0
    azimuth: float = 0.0


def sensors_of(fit: Fit) -> list[Sensor]:
    """Tripp's [b, S, Ω, A] of every sensor the fit has (eq. 8), from its linear columns."""
    return [from_linear(fit.coefficients[0, j], fit.coefficients[1:, j], axis)
            for j, axis in enumerate(fit.sensors)]


def package_of(sensors: tuple[str, ...]) -> str:
    """The package whose sensors these are."""
    return {("x",): "single-axis", ("x", "y"): "two-axis-xy", ("x", "z"): "two-axis-xz",
            ("x", "y", "z"): "three-axis"}[sensors]


def without_roll(b: float, S: float, phi: float) -> Sensor:
    """The single-axis sensor without roll (Tripp eq. 1) as the x sensor of eq. 14: eq. 13 is eq. 14
    with Ω = φ, A = π/2 and R = 0 (eq. 17)."""
    return Sensor("x", b, S, phi, np.pi / 2)


def output(sensor: Sensor, alpha: ArrayLike, roll: ArrayLike = 0.0) -> Array:
    """The sensor's output at pitch α and roll R: Tripp eqs. 14, 15, 16."""
    a, r = np.asarray(alpha, dtype=float), np.asarray(roll, dtype=float)
    b, S, co, so, ca, sa = (sensor.b, sensor.S, np.cos(sensor.omega), np.sin(sensor.omega),
                            np.cos(sensor.azimuth), np.sin(sensor.azimuth))
    if sensor.axis == "x":  # eq. 14
        v = b + S * (co * np.sin(a) - so * np.cos(a) * np.sin(r + sensor.azimuth))
    elif sensor.axis == "y":  # eq. 15
        v = b - S * (co * np.sin(r) * np.cos(a) - so * (sa * np.sin(a) - ca * np.cos(r) * np.cos(a)))
    else:  # eq. 16
        v = b - S * (co * np.cos(r) * np.cos(a) - so * (ca * np.sin(a) - sa * np.sin(r) * np.cos(a)))
    return np.asarray(v, dtype=float)


def derivatives(sensor: Sensor, alpha: ArrayLike, roll: ArrayLike = 0.0) -> tuple[Array, Array]:
    """(∂f/∂α, ∂f/∂R) of the sensor's output: Tripp eqs. 87 (x), 88 (y), 95 (z)."""
    a, r = np.asarray(alpha, dtype=float), np.asarray(roll, dtype=float)
    S, co, so, ca, sa = (sensor.S, np.cos(sensor.omega), np.sin(sensor.omega), np.cos(sensor.azimuth),
                         np.sin(sensor.azimuth))
    if sensor.axis == "x":  # eq. 87
        f_a = S * (co * np.cos(a) + so * np.sin(a) * np.sin(r + sensor.azimuth))
        f_r = -S * so * np.cos(a) * np.cos(r + sensor.azimuth)
    elif sensor.axis == "y":  # eq. 88
        f_a = S * (co * np.sin(a) * np.sin(r) + so * (sa * np.cos(a) + ca * np.sin(a) * np.cos(r)))
        f_r = -S * np.cos(a) * (co * np.cos(r) - so * ca * np.sin(r))
    else:  # eq. 95
        f_a = S * (co * np.sin(a) * np.cos(r) + so * (ca * np.cos(a) + sa * np.sin(a) * np.sin(r)))
        f_r = S * np.cos(a) * (co * np.sin(r) - so * sa * np.cos(r))
    shape = np.broadcast_shapes(a.shape, r.shape)
    return np.broadcast_to(f_a, shape).astype(float), np.broadcast_to(f_r, shape).astype(float)


def from_linear(bias: float, column: ArrayLike, axis: str) -> Sensor:
    """Tripp's [b, S, Ω, A] of one sensor from labcal's fitted bias and sensitivity column
    (B; s_x, s_y, s_z): the change of variables of `labcal.analysis.coning`, with S signed as eqs.
    14–16 read (Tripp's y and z sensors see −g_y and −g_z, so S = −|s| for a sensor whose main
    component is positive)."""
    s = np.asarray(column, dtype=float)
    main, (i1, sign1), (i2, sign2) = _AXES[axis]
    m, t1, t2 = s[main], sign1 * s[i1], sign2 * s[i2]
    magnitude = float(np.linalg.norm(s))
    sign = 1.0 if axis == "x" else -1.0
    return Sensor(axis, float(bias), sign * magnitude, float(np.arctan2(np.hypot(t1, t2), m)),
                  float(np.arctan2(t2, t1)))


def output_sd(covariance: ArrayLike, reading_sd: ArrayLike, alpha: ArrayLike, roll: ArrayLike = 0.0
              ) -> Array:
    """σ_v at (α, R): √(fᵀ·C·f + σ₀²), f = [1, g(α, R)] and C the 4×4 covariance of (B, s) of the
    linear fit: the calibration's part (Tripp eq. 52) plus one new reading's variance σ₀² (eq. 73)."""
    g = nominal_gravity(alpha, roll, 0.0, 0.0)
    f = np.concatenate([np.ones(g.shape[:-1] + (1,)), g], axis=-1)
    c = np.asarray(covariance, dtype=float)
    return np.asarray(np.sqrt(np.einsum("...i,ij,...j->...", f, c, f) + np.asarray(reading_sd) ** 2),
                      dtype=float)


# --- single-axis sensor without roll (Tripp §6.1) ---------------------------------------------------
def pitch_without_roll(v: ArrayLike, b: float, S: float, phi: float) -> Array:
    """Inferred pitch α̂ = asin((v − b)/S) + φ, Tripp eq. 76; NaN where |v − b| > |S|."""
    with np.errstate(invalid="ignore"):
        return np.asarray(np.arcsin((np.asarray(v, dtype=float) - b) / S) + phi, dtype=float)


def sd_pitch_without_roll(sigma_v: ArrayLike, S: float, phi: float, alpha: ArrayLike) -> Array:
    """σ_α̂ = σ_v / (S·|cos(α − φ)|), Tripp eq. 78: unbounded as α − φ → ±90°."""
    with np.errstate(divide="ignore"):
        return np.asarray(np.asarray(sigma_v) / np.abs(S * np.cos(np.asarray(alpha) - phi)), dtype=float)


# --- pitch at an independently measured roll (Tripp §6.3, §6.5) -------------------------------------
def pitch_at_roll(v: ArrayLike, sensor: Sensor, roll: ArrayLike) -> Array:
    """Inferred pitch of a single x sensor at known roll R, Tripp eq. 79 (eq. 3 with the estimates);
    NaN where the output is beyond the sensor's reach at that roll."""
    if sensor.axis != "x":
        raise LabcalError(f"pitch at a known roll needs the x sensor, not the {sensor.axis} sensor")
    r = np.asarray(roll, dtype=float) + sensor.azimuth
    so, co = np.sin(sensor.omega), np.cos(sensor.omega)
    with np.errstate(invalid="ignore"):
        x = (np.asarray(v, dtype=float) - sensor.b) / sensor.S / np.sqrt(co**2 + np.sin(r) ** 2 * so**2)
        return np.asarray(np.arcsin(x) + np.arctan(np.tan(sensor.omega) * np.sin(r)), dtype=float)


def sd_pitch_at_roll(sensors: Sequence[Sensor], sigma_v: Sequence[ArrayLike], alpha: ArrayLike,
                     roll: ArrayLike, sigma_roll: ArrayLike = 0.0) -> Array:
    """σ_α̂ of pitch inferred at an independently measured roll R (its standard deviation σ_R) from
    one or more sensors with uncorrelated output errors σ_v each.

    The estimate is the least-squares solution in α alone: δα̂ = (δv − f_R·δR)·f_αᵀ/(f_α·f_αᵀ) —
    Tripp eq. 80 for the single x sensor (whose variance is eq. 81) and eq. 96 for the x–z package
    (eq. 97's f_α), with eq. 80's roll term carried into it. Unbounded where f_α = 0: for the single
    sensor α = ±90°, for the x–z package {±90°, ±90°} only (eq. 98)."""
    f_a, f_r = zip(*(derivatives(s, alpha, roll) for s in sensors), strict=True)
    norm = sum(fa**2 for fa in f_a)
    noise = sum(fa**2 * np.asarray(sv) ** 2 for fa, sv in zip(f_a, sigma_v, strict=True))
    roll_term = sum(fa * fr for fa, fr in zip(f_a, f_r, strict=True)) ** 2 * np.asarray(sigma_roll) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.sqrt(noise + roll_term) / norm, dtype=float)


# --- simultaneous pitch and roll from two sensors (Tripp §6.4, §6.5) --------------------------------
def jacobian(sensors: Sequence[Sensor], alpha: ArrayLike, roll: ArrayLike) -> Array:
    """F_z = ∂f/∂z, rows (α, R) and one column per sensor: Tripp eq. 86 (x–y), 94 (x–z), 102."""
    cols = [np.stack(derivatives(s, alpha, roll), axis=-1) for s in sensors]
    return np.stack(cols, axis=-1)  # (..., 2, n)


def inferred_covariance(sensors: Sequence[Sensor], sigma_v: Sequence[ArrayLike], alpha: ArrayLike,
                        roll: ArrayLike) -> Array:
    """Σ_ẑ (…, 2, 2) of the inferred (α̂, R̂) of a two-sensor package with uncorrelated outputs:
    Σ_ẑ = F_z⁻ᵀ Σ_v F_z⁻¹, Tripp eq. 90 (δẑ = δv F_z⁻¹, eq. 89). Infinite where F_z is singular."""
    if len(sensors) != 2:
        raise LabcalError(f"simultaneous pitch and roll from {len(sensors)} sensor(s): eq. 90 needs two "
                          "(three: the three-axis estimator)")
    F = jacobian(sensors, alpha, roll)
    det = F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    sv = np.stack(np.broadcast_arrays(*(np.asarray(s, dtype=float) for s in sigma_v)), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.stack([F[..., 1, 1], -F[..., 0, 1]], axis=-1),
                        np.stack([-F[..., 1, 0], F[..., 0, 0]], axis=-1)], axis=-2) / det[..., None, None]
        # δz = δv·F⁻¹: column k of F⁻¹ maps the outputs to angle k
        cov = np.einsum("...ik,...i,...il->...kl", inv, sv**2, inv)
    singular = ~np.isfinite(cov).all(axis=(-2, -1)) | (det == 0)
    cov[singular] = np.inf
    return np.asarray(cov, dtype=float)


def determinant(sensors: Sequence[Sensor], alpha: ArrayLike, roll: ArrayLike) -> Array:
    """det F_z of a two-sensor package: its zeros are the singularity loci (Tripp Figs. 9, 11)."""
    F = jacobian(sensors, alpha, roll)
    return np.asarray(F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0], dtype=float)


def infer(sensors: Sequence[Sensor], v: ArrayLike, start: ArrayLike = (0.0, 0.0)) -> Array:
    """(α̂, R̂) (…, 2) from a two-sensor package's outputs v (…, 2) by Newton–Raphson on eqs. 14–16
    (Tripp §6.2), every row from ``start`` (one (α, R), or one per row). A singular Jacobian or no
    convergence is refused: near
    a singular locus no solution exists (§6.4)."""
    target = np.asarray(v, dtype=float)
    rows = target.reshape(-1, len(sensors))
    z = np.broadcast_to(np.asarray(start, dtype=float), (len(rows), 2)).copy()  # one, or one per row
    scale = max(abs(s.S) for s in sensors) ** 2
    for _ in range(NEWTON_ITERATIONS):
        residual = rows - np.stack([output(s, z[:, 0], z[:, 1]) for s in sensors], axis=-1)
        F = jacobian(sensors, z[:, 0], z[:, 1])  # (n, 2, 2)
        singular = np.abs(np.linalg.det(F)) < 1e-12 * scale
        if singular.any():
            a, r = np.degrees(z[np.argmax(singular)])
            raise LabcalError(f"pitch {a:.3g}°, roll {r:.3g}°: the package's Jacobian is singular there; "
                              "pitch and roll cannot both be inferred")
        step = np.linalg.solve(np.swapaxes(F, -1, -2), residual[..., None])[..., 0]  # δv = δz·F
        z = z + step
        if np.max(np.abs(step)) < NEWTON_TOLERANCE:
            return np.asarray(z.reshape(target.shape), dtype=float)
    raise LabcalError("pitch and roll did not converge from the package's outputs: the attitude is near a "
                      "singularity of its Jacobian")


@dataclass(frozen=True)
class UsableBox:
    """The largest centred box |α| ≤ pitch, |R| ≤ roll (rad) over which both inferred angles'
    standard deviations stay within a limit."""

    pitch: float
    roll: float
    limit: float


def usable_box(sensors: Sequence[Sensor], sigma_v: Sequence[float], limit: float,
               step: float = np.radians(1.0)) -> UsableBox:
    """Where a two-sensor package infers pitch and roll together with σ_α̂ and σ_R̂ ≤ ``limit`` (rad),
    computed from its own coefficients (eq. 90) on a ``step`` grid: of the centred boxes whose every
    grid attitude qualifies, the one of largest area. Tripp §6.4–6.5 state such ranges read off their
    Figs. 9–11; near the singular loci of det F_z (eqs. 86, 94) σ grows without bound, so a box
    bounded by a finite limit excludes them."""
    n = int(np.floor(np.pi / 2 / step + 1e-9))
    angles = step * np.arange(-n, n + 1)
    alpha, roll = np.meshgrid(angles, angles, indexing="ij")
    cov = inferred_covariance(sensors, sigma_v, alpha, roll)
    ok = (np.sqrt(cov[..., 0, 0]) <= limit) & (np.sqrt(cov[..., 1, 1]) <= limit)
    best = (-1.0, 0, 0)
    for i in range(n + 1):  # half-width in pitch steps
        rows = ok[n - i:n + i + 1]
        for j in range(n + 1):
            if not rows[:, n - j:n + j + 1].all():
                break
            area = (2 * i + 1) * (2 * j + 1)
            if area > best[0]:
                best = (area, i, j)
    if best[0] < 0:
        raise LabcalError(f"the package cannot infer pitch and roll within {np.degrees(limit):.3g}° even "
                          "at the level attitude")
    return UsableBox(best[1] * step, best[2] * step, limit)


# --- can a package be used over a usage envelope? ---------------------------------------------------
def _envelope(lo: float, hi: float, step: float) -> Array:
    n = max(int(np.ceil((hi - lo) / step - 1e-9)), 1)
    return np.radians(np.linspace(lo, hi, n + 1))


def _where(alpha: Array, roll: Array, bad: NDArray[np.bool_]) -> str:
    i = np.argwhere(bad)[0]
    return f"pitch {np.degrees(alpha[tuple(i)]):.4g}°, roll {np.degrees(roll[tuple(i)]):.4g}°"


def package_problem(package: str, roll_in_use: str, usage_pitch_deg: tuple[float, float],
                    usage_roll_deg: tuple[float, float], step_deg: float = 1.0) -> str | None:
    """Why a package, with roll obtained as ``roll_in_use``, cannot give its angles over the usage
    envelope (pitch × roll ranges, °), or None. Judged on the nominal package (Ω = 0, the singular
    loci of every real one lie within its small Ω of these, Tripp Figs. 9, 11) on a ``step_deg`` grid
    with the ends included:

    - without roll (single-axis, eq. 1): only at roll 0, and eq. 78 is unbounded at α = ±90°;
    - at a measured roll: where f_α·f_αᵀ = 0 (eq. 81 at α = ±90°; eq. 98 at {±90°, ±90°} for x–z);
    - inferred by a two-axis package: where det F_z changes sign or vanishes (eqs. 86, 94): the x–y
      package at α = ±90° and R = ±90°, the x–z package at α = ±90° and R = 0°, ±180°;
    - a single sensor cannot infer roll at all; the three-axis package can everywhere but at ±90°,
      where roll is undefined and says so (eq. 106)."""
    axes = PACKAGES[package]
    nominal = [Sensor(a, 0.0, 1.0) for a in axes]
    alpha, roll = np.meshgrid(_envelope(*usage_pitch_deg, step_deg), _envelope(*usage_roll_deg, step_deg),
                              indexing="ij")
    if roll_in_use == "none":
        if package != "single-axis":
            return (f"a {package} package is not used without roll; roll_in_use \"none\" is a single-axis "
                    "sensor's")
        if usage_roll_deg != (0.0, 0.0):
            return ("a single-axis package used without roll measures pitch at roll 0 only (Tripp eq. 1), "
                    f"but the usage envelope spans roll {usage_roll_deg[0]:g}..{usage_roll_deg[1]:g}°")
        roll_in_use = "table"  # at R = 0 known: the same f_α (eq. 17)
    if roll_in_use in ("table", "sensor"):
        moment = np.sum([derivatives(s, alpha, roll)[0] ** 2 for s in nominal], axis=0)
        bad = np.asarray(moment <= 1e-12)
        if bad.any():
            return (f"the {package} package cannot infer pitch at {_where(alpha, roll, bad)} of the usage "
                    "envelope: no output changes with pitch there (f_α = 0, Tripp eqs. 81, 96–98)")
        return None
    if len(axes) == 1:
        return ("a single-axis package cannot infer roll: it is used without roll or at a roll measured by "
                "the table or a sensor")
    if len(axes) == 3:
        return None
    det = determinant(nominal, alpha, roll)
    scale = np.max(np.abs(det))
    zero = np.abs(det) <= 1e-9 * scale
    if zero.any() or (det.min() < 0 < det.max()):
        where = zero if zero.any() else np.sign(det) != np.sign(det.flat[np.argmax(np.abs(det))])
        return (f"the {package} package cannot infer pitch and roll together over the usage envelope: its "
                f"Jacobian F_z (Tripp eqs. 86, 94) is singular near {_where(alpha, roll, where)}; narrow the "
                "certificate's usage_pitch_deg / usage_roll_deg, or use it at a measured roll")
    return None


# --- a package in use: its angles from its outputs (Tripp §6.1-6.5) ----------------------------------
@dataclass(frozen=True)
class PackageCalibration:
    """What a package's certificate gives its use: each sensor's [b, S, Ω, A] and, for σ_v, its linear
    coefficients' covariance (B, s; 4×4 per sensor) and a new reading's standard deviation; k, how
    roll is obtained in use with its σ_R (rad), and where pitch and roll may be inferred together."""

    package: str
    sensors: tuple[Sensor, ...]
    covariance: Array  # (m, 4, 4)
    reading_sd: Array  # (m,)
    k: float
    roll_in_use: str
    roll_sd: float = 0.0
    usable: tuple[tuple[float, float], tuple[float, float]] | None = None  # (pitch, roll) ranges, rad


@dataclass(frozen=True)
class PackageAttitude:
    """Inferred pitch and roll (rad) with their U95 = k·σ; roll as given where the package does not
    infer it (its U95 NaN: the roll's own uncertainty is its measurement's)."""

    pitch: Array
    roll: Array
    U_pitch: Array
    U_roll: Array
    k: float


def pitch_at_known_roll(sensors: Sequence[Sensor], v: ArrayLike, roll: ArrayLike) -> Array:
    """Pitch from one or more sensors' outputs at a known roll: eq. 79 for the single x sensor; for
    the x–z package the least-squares solution in α alone (Tripp §6.5, eq. 96), by Gauss–Newton from
    atan2 of the two outputs' pitch components."""
    outputs = np.asarray(v, dtype=float).reshape(-1, len(sensors))
    r = np.broadcast_to(np.asarray(roll, dtype=float), outputs.shape[:1])
    if len(sensors) == 1:
        return pitch_at_roll(outputs[:, 0], sensors[0], r)
    x, z = sensors
    sin_a = (outputs[:, 0] - x.b) / x.S
    cos_a = -(outputs[:, 1] - z.b) / z.S * np.cos(r)  # f_z ≈ −S_z cos R cos α (eq. 16 at Ω = 0)
    a = np.arctan2(sin_a, cos_a)
    for _ in range(NEWTON_ITERATIONS):
        residual = outputs - np.stack([output(s, a, r) for s in sensors], axis=-1)
        f_a = np.stack([derivatives(s, a, r)[0] for s in sensors], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.sum(f_a * residual, axis=-1) / np.sum(f_a**2, axis=-1)
        a = a + step
        if np.all(np.abs(step[np.isfinite(step)]) < NEWTON_TOLERANCE):
            break
    return np.asarray(a, dtype=float)


def _output_sds(cal: PackageCalibration, alpha: Array, roll: Array) -> list[Array]:
    return [output_sd(cal.covariance[j], cal.reading_sd[j], alpha, roll) for j in range(len(cal.sensors))]


def package_attitude(cal: PackageCalibration, v: ArrayLike, roll: ArrayLike | None = None,
                     roll_sd: float | None = None) -> PackageAttitude:
    """A package's angles from its outputs v (n × m, its sensors' order), as its certificate says they
    are obtained: without roll (eqs. 76-78), at a roll measured in use, ``roll`` (rad, one or per row)
    with σ_R ``roll_sd`` or the certificate's (eqs. 79-82, 96-98), or pitch and roll together (eq. 90,
    Newton-Raphson), refused outside the usable range the certificate states."""
    outputs = np.asarray(v, dtype=float).reshape(-1, len(cal.sensors))
    n = len(outputs)
    nan = np.full(n, np.nan)
    if cal.roll_in_use == "inferred":
        if roll is not None:
            raise LabcalError(f"the {cal.package} package infers roll from its own outputs; leave out the "
                              "measured roll")
        x, y = cal.sensors
        a0 = np.arcsin(np.clip((outputs[:, 0] - x.b) / x.S, -1, 1))
        across = np.clip(-(outputs[:, 1] - y.b) / y.S / np.maximum(np.cos(a0), 1e-6), -1, 1)
        r0 = np.arcsin(across) if y.axis == "y" else np.arccos(-across)
        z = infer(cal.sensors, outputs, np.column_stack([a0, r0]))
        alpha, r = z[:, 0], z[:, 1]
        assert cal.usable is not None
        (p_lo, p_hi), (r_lo, r_hi) = cal.usable
        tol = 1e-9  # rad: the range's ends are in it
        outside = ~((p_lo - tol <= alpha) & (alpha <= p_hi + tol) & (r_lo - tol <= r) & (r <= r_hi + tol))
        if outside.any():
            i = int(np.argmax(outside))
            raise LabcalError(
                f"row {i + 1}: pitch {np.degrees(alpha[i]):.4g}°, roll {np.degrees(r[i]):.4g}° is outside "
                f"the {cal.package} package's usable range (pitch {np.degrees(p_lo):g}.."
                f"{np.degrees(p_hi):g}° × roll {np.degrees(r_lo):g}..{np.degrees(r_hi):g}°, where its "
                "certificate states U95; Tripp & Tcheng §6.4): its Jacobian approaches singular there")
        cov = inferred_covariance(cal.sensors, _output_sds(cal, alpha, r), alpha, r)
        return PackageAttitude(alpha, r, cal.k * np.sqrt(cov[:, 0, 0]), cal.k * np.sqrt(cov[:, 1, 1]), cal.k)
    if cal.roll_in_use == "none":
        if roll is not None and np.any(np.asarray(roll) != 0):
            raise LabcalError(f"the {cal.package} package is certified for use without roll (roll 0, Tripp "
                              "eq. 1); a measured roll needs a certificate that states how roll is obtained")
        r, sigma_r = np.zeros(n), 0.0
    else:
        if roll is None:
            raise LabcalError(f"the {cal.package} package's pitch is inferred at a roll measured in use (the "
                              f"{cal.roll_in_use}): give it (--roll-deg, or a roll_deg column)")
        r = np.broadcast_to(np.asarray(roll, dtype=float), (n,)).copy()
        sigma_r = cal.roll_sd if roll_sd is None else roll_sd
    alpha = pitch_at_known_roll(cal.sensors, outputs, r)
    sigma = sd_pitch_at_roll(cal.sensors, _output_sds(cal, alpha, r), alpha, r, sigma_r)
    return PackageAttitude(alpha, r, cal.k * sigma, nan, cal.k)
