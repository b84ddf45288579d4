"""How far a calibration device's misalignments may have wandered since their last estimate: the
history's evidence of "in control" and the growth of a correction's uncertainty with its age.

Sittings. Two estimates are two pieces of evidence only if they could have disagreed: estimates
calibrated on the same UTC calendar day (one sitting: the same mounting of the device, the same
temperature, the same technician's hands) and estimates with identical values (the same readings
fitted twice, e.g. a simulated run repeated with one seed) count as one sitting, represented by its
latest estimate. "In control" needs two sittings.

Random walk. Between sittings the misalignments are modelled as a random walk: the true value's
variance grows by q per day (per misalignment). For consecutive sittings i, i+1, Δt_i days apart,
the change d_i = v_{i+1} − v_i then has variance s_i² + q·Δt_i with s_i² = u_i² + u_{i+1}² (each
estimate's own standard uncertainty), so E[Σ(d_i² − s_i²)] = q·ΣΔt_i: the moment estimate is
q̂ = max(0, Σ(d_i² − s_i²)/ΣΔt_i), and, the d_i being jointly normal (Cov(d_i², d_j²) = 2 C_ij²),
its standard uncertainty u(q̂) = √(2 Σ_ij C_ij²)/ΣΔt_i with C_ii = s_i² + q̂Δt_i and, consecutive
changes sharing an estimate, C_i,i+1 = −u_{i+1}². A correction t days old carries u(t)² = u₀² + q̂·t,
u₀ = U/k of the latest estimate: q̂ is the expected extra variance per day (GUM 4.1.4: the best
estimate of an input, here a variance, is its expectation), not a bound. With few sittings u(q̂) is
large (one difference: u(q̂) = √2·s²/Δt), which is stated beside the rate; what the rate may miss is
bounded twice over, by the run's own check of the misalignments (`correction_check`) and by the age
and use limits past which a correction is not used at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

import numpy as np
from numpy.typing import NDArray

SECONDS_PER_DAY = 86400.0
SAME_DATA = 1e-9  # arcsec: estimates this close are the same readings fitted again


@dataclass(frozen=True)
class Sittings:
    """The estimates that stand for distinct sittings (indices into the history, oldest first)."""

    kept: tuple[int, ...]

    @property
    def count(self) -> int:
        return len(self.kept)


def sittings(times: list[datetime], values: list[NDArray[np.float64]]) -> Sittings:
    """Group a history (oldest first) into sittings: the same UTC day, or the same values as an earlier
    estimate, is the same sitting; each is represented by its latest estimate."""
    kept: list[int] = []
    for i, (t, v) in enumerate(zip(times, values, strict=True)):
        same = [k for k in kept if times[k].date() == t.date()
                or np.max(np.abs(np.asarray(values[k]) - np.asarray(v))) <= SAME_DATA]
        for k in same:
            kept.remove(k)
        kept.append(i)
    return Sittings(tuple(kept))


@dataclass(frozen=True)
class WalkRate:
    """q̂ and u(q̂) per misalignment (arcsec² per day) from ``differences`` consecutive sittings."""

    q: NDArray[np.float64]
    u_q: NDArray[np.float64]
    differences: int

    def aged_u(self, u0: NDArray[np.float64], age_days: float) -> NDArray[np.float64]:
        """u(t) = √(u₀² + q̂·t) (arcsec) for a correction ``age_days`` old."""
        return np.asarray(np.sqrt(np.asarray(u0) ** 2 + self.q * max(age_days, 0.0)), dtype=float)


def walk_rate(times: list[datetime], values: list[NDArray[np.float64]], u: list[NDArray[np.float64]]
              ) -> WalkRate:
    """The random walk's variance rate from estimates of distinct sittings (oldest first): values and
    standard uncertainties (arcsec, (6,) each)."""
    if len(times) < 2:
        raise ValueError("a walk rate needs two sittings")
    v, s = np.array(values, dtype=float), np.array(u, dtype=float)
    dt = np.array([(b - a).total_seconds() / SECONDS_PER_DAY for a, b in zip(times, times[1:], strict=False)])
    if np.any(dt <= 0):
        raise ValueError("sittings must be in time order")
    d2 = np.diff(v, axis=0) ** 2
    s2 = s[:-1] ** 2 + s[1:] ** 2
    total = float(np.sum(dt))
    q = np.maximum(np.sum(d2 - s2, axis=0) / total, 0.0)
    shared = s[1:-1] ** 2  # C_i,i+1 = −u²_{i+1}: the estimate two consecutive changes share
    u_q = np.sqrt(2.0 * (np.sum((s2 + q[None, :] * dt[:, None]) ** 2, axis=0)
                         + 2.0 * np.sum(shared**2, axis=0))) / total
    return WalkRate(q, u_q, len(dt))
