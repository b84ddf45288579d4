"""The readings' scatter against what the station declares of it.

A static instrument's averaged reading scatters by the DMM's noise (σ_n per sample, σ_n/√n for
the mean of n samples) and by the tables' index and wobble errors, which turn gravity by a small,
different rotation at every table angle (a rotation by θ changes a unit g by at most θ, so a
sensor whose sensitivity vector is S_j reads at most |S_j|·θ differently). Both are stated: the
noise by the station's settle settings, the angle errors by its uncertainty inputs (± half-widths,
rectangular: σ = a/√3, GUM 4.3.7). The device's own misalignments (Soto Table 1) are not noise:
they are taken out to first order (Soto eq. 11 differentiated, `gravity_jacobian`) together with
the linear model's B and S, so that a plan whose fit leaves them in its residuals (one mount) is
judged alike.

What is left must look like the declared scatter: Σ eᵢⱼ²/σⱼ² is χ² with 3K − rank degrees of
freedom for good data (Tripp & Tcheng §3: S_E² against a known σ²; conservative here, since σⱼ
bounds each reading's scatter from above and the residuals' variance is σ²(1 − h) ≤ σ²), and each
residual is within a Šidák family-wise normal limit. A table slipped at its output, the tables
exchanged, or a reading taken at another attitude scatter hundreds of times more than that.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.distributions import chi2_quantile
from labcal.analysis.gross_errors import SENSORS, Flag, t_threshold
from labcal.analysis.kinematics import gravity_jacobian, nominal_gravity
from labcal.analysis.readings import Readings

if TYPE_CHECKING:
    from labcal.analysis.device_fit import AngleErrors

NOISE_ALPHA = 0.005  # each of the two tests (the χ² of the whole, the largest residual): 1 % together
RECTANGULAR = 1.0 / np.sqrt(3.0)  # standard deviation of a ± half-width of 1, rectangular
NO_ANGLE_ERRORS = ("the residual is not held to the declared noise: the station states no index or "
                   "wobble for its tables ([uncertainty] pitch_index, pitch_wobble, roll_index, "
                   "roll_wobble), and no table returns to an angle without them")


@dataclass(frozen=True)
class Declared:
    """What a station declares of one point's scatter: the DMM's noise per sample, the samples a
    point averages, and the tables' stated angle errors as (half-width in rad, how many of the
    device's rotations it turns) pairs (`labcal.analysis.device_fit.AngleErrors.inputs`)."""

    noise_v: float
    samples: float
    angle_half_widths: tuple[tuple[float, int], ...] = ()

    @classmethod
    def of(cls, noise_v: float, samples: float, errors: AngleErrors | None) -> Declared:
        """From a station's settle settings and its tables' stated angle errors (None: none stated)."""
        widths = () if errors is None else tuple((half, len(turns)) for _, turns, half in errors.inputs())
        return cls(float(noise_v), float(samples), widths)

    @property
    def angle_sd_rad(self) -> float:
        """The rms of the tables' per-point rotation: every stated component, independent."""
        return float(np.sqrt(sum(n * (a * RECTANGULAR) ** 2 for a, n in self.angle_half_widths)))

    def sd(self, sensitivity: NDArray[np.float64]) -> NDArray[np.float64]:
        """σⱼ of each sensor's averaged reading (3,), from S (3×3, column j sensor j's vector)."""
        reach = np.linalg.norm(np.asarray(sensitivity, dtype=float), axis=0)
        noise = self.noise_v / np.sqrt(self.samples)
        return np.asarray(np.hypot(noise, reach * self.angle_sd_rad), dtype=float)


@dataclass(frozen=True)
class NoiseCheck:
    """The outcome: χ² of the whole against its limit, each sensor's residual SE over its σ, and
    the readings (1-based rows) whose residuals pass their limit."""

    chi2: float
    dof: int
    limit: float
    sd: NDArray[np.float64]  # (m,) declared σ per sensor, V
    residual_se: NDArray[np.float64]  # (m,) what is left, per sensor, V
    flags: list[Flag] = field(default_factory=list)
    sensors: tuple[str, ...] = SENSORS  # the sensors judged: a package's, where it has fewer than three

    @property
    def passed(self) -> bool:
        return not (self.chi2 > self.limit) and not self.flags

    def summary(self, units: str = "V") -> str:
        """One line: how far the scatter is from the declared one, and the test that says so."""
        ratio = self.residual_se / self.sd
        j = int(np.argmax(ratio))
        return (f"the readings scatter {ratio[j]:.3g} times what the station declares "
                f"(sensor {self.sensors[j]}: "
                f"residual SE {self.residual_se[j]:.3g} {units} against {self.sd[j]:.3g} {units}; χ² "
                f"{self.chi2:.4g} on {self.dof} degrees of freedom, limit {self.limit:.4g} at a "
                f"{NOISE_ALPHA:.1%} false-alarm rate)")

    def to_json(self) -> dict[str, object]:
        return {"passed": self.passed, "chi2": self.chi2, "dof": self.dof, "limit": self.limit,
                "alpha": NOISE_ALPHA, "declared_sd": self.sd.tolist(),
                "residual_se": self.residual_se.tolist(), "flags": [f.to_json() for f in self.flags]}


def noise_check(readings: Readings, sensitivity: NDArray[np.float64], declared: Declared,
                alpha: float = NOISE_ALPHA) -> NoiseCheck:
    """Judge ``readings`` (one row per point mean) against ``declared``; ``sensitivity`` is S of a
    fit of them (3×m: m = 3, or a package's sensors, whose absent outputs are NaN), which sizes both
    the declared σ and the misalignments' effect. The readings
    it flags are those the least squares cannot explain however few of them it leaves out
    (`_culprits`): one reading far off pulls the fit, and the others' residuals, with it."""
    s = np.asarray(sensitivity, dtype=float)
    present = np.asarray(~np.isnan(readings.volts).all(axis=0))
    sensors = tuple(a for a, here in zip(SENSORS, present, strict=True) if here)
    sd = declared.sd(s)
    design, observed = _stacked(readings, s, sd, present)
    keep = np.ones(len(readings), dtype=bool)
    z, dof = _standardised(design, observed, keep)
    if dof < 1:
        return NoiseCheck(0.0, dof, float("inf"), sd, np.zeros(len(sensors)), sensors=sensors)
    chi2 = float(np.sum(z**2))
    limit = chi2_quantile(1.0 - alpha, dof)
    residual_se = sd * np.sqrt(np.sum(z**2, axis=0) / (dof / len(sensors)))
    per_reading = t_threshold(z.size, np.inf, alpha)
    flags = []
    if chi2 > limit or np.max(np.abs(z)) > per_reading:
        for i in _culprits(design, observed, alpha):
            j = int(np.argmax(np.abs(z[i])))
            flags.append(Flag(i + 1, "noise", f"sensor {sensors[j]}: residual {z[i, j] * sd[j]:+.3g} "
                              f"{readings.units} is {abs(z[i, j]):.3g} times what the station declares "
                              f"({sd[j]:.2g} {readings.units})"))
    return NoiseCheck(chi2, dof, limit, sd, residual_se, flags, sensors)


def _stacked(readings: Readings, s: NDArray[np.float64], sd: NDArray[np.float64], present: NDArray[np.bool_]
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The weighted design (K, m, 4m + 6) and readings (K, m) of the m sensors ``present``: per
    sensor [1 gᵀ]·Xⱼ, plus the six misalignments δ, common to the sensors, through (∂g/∂δ)·Sⱼ."""
    p, r = np.radians(readings.pitch_deg), np.radians(readings.roll_deg)
    y, u = np.radians(readings.y_deg), np.radians(readings.u_deg)
    g = nominal_gravity(p, r, y, u)  # (K, 3)
    _, dg = gravity_jacobian(p, r, y, u)  # (K, 6, 3)
    m = s.shape[1]
    design = np.zeros((len(g), m, 4 * m + 6))
    for j in range(m):
        design[:, j, 4 * j] = 1.0
        design[:, j, 4 * j + 1: 4 * j + 4] = g
        design[:, j, 4 * m:] = dg @ s[:, j]
    return design / sd[None, :, None], readings.volts[:, present] / sd[None, :]


def _standardised(design: NDArray[np.float64], observed: NDArray[np.float64], keep: NDArray[np.bool_]
                  ) -> tuple[NDArray[np.float64], int]:
    """Residuals in units of σ (K, 3; zero where not kept) of the least squares of the kept readings,
    and its degrees of freedom (a rank-deficient plan, one mount: e, f, k confounded with S, loses
    those it cannot identify)."""
    m = observed.shape[1]
    a, b = design[keep].reshape(-1, design.shape[2]), observed[keep].reshape(-1)
    coef, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    z = np.zeros_like(observed)
    z[keep] = (b - a @ coef).reshape(-1, m)
    return z, b.size - int(rank)


def _culprits(design: NDArray[np.float64], observed: NDArray[np.float64], alpha: float) -> list[int]:
    """The readings (0-based) to leave out, worst first, until the rest pass both tests; at most a
    quarter of them (beyond that no few readings are to blame: every one is named)."""
    keep = np.ones(len(observed), dtype=bool)
    out: list[int] = []
    while len(out) < len(observed) // 4:
        z, dof = _standardised(design, observed, keep)
        if dof < 1:
            break
        worst = int(np.argmax(np.max(np.abs(z), axis=1)))
        if (np.sum(z**2) <= chi2_quantile(1.0 - alpha, dof)
                and np.max(np.abs(z)) <= t_threshold(int(keep.sum()) * observed.shape[1], np.inf, alpha)):
            return out
        keep[worst] = False
        out.append(worst)
    return list(range(len(observed)))
