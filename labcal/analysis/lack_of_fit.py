"""Does the model, with the bench's stated errors, explain the calibration's residuals?

The residuals r of a fit of K points are what the model leaves of the readings' errors: to first order
r = R·ε, R = I − J(JᵀWJ)⁻¹JᵀW the residual maker of the fit's Jacobian J (3K × p, the three outputs of
every point). What the budget says ε is: the instrument's noise, each point's mean scattering by
s_c²/n_k (s_c the pooled scatter inside the windows, `labcal.analysis.repeatability` — pure error,
even in a single pass, because the samples of one window repeat the point), and the bench's stated
errors — the tables' index and wobble at each angle, the plate's seating at each mounting, and the
instrument's stated temperature coefficients through each point's temperature about the run's mean —
as the budget's Type B inputs carry them into the readings (B, 3K × m, one column per elementary input
scaled by its u). Under that model r has covariance Σ = R(N + BBᵀ)Rᵀ, and

    Q = rᵀ Σ⁺ r  ~  χ²(ν₁),  ν₁ = rank Σ = 3K − p,

the whitened residual sum of squares. Q/ν₁ against F(ν₁, ν₂), ν₂ the pooled scatter's degrees of
freedom, allows for the noise being estimated (the classical lack-of-fit F test, Tripp & Tcheng §8,
with the within-window scatter as pure error and the stated bench errors added to it). Anything the
model and the station's statement leave out — tables worse than stated, an unstated seating scatter,
a bias drift over the run, a nonlinearity — adds to Q beyond ν₁; a clean bench, stated truly, does not.
Bench errors that are rectangular, not normal, make Q's tail lighter than χ²'s: the test stays at or
below its nominal size.

The drift test looks in the same residuals for one thing: a linear trend of each output in the order
the points were measured (the run's time), estimated by generalised least squares in the metric Σ⁺
and tested as χ²(3) — the single-pass counterpart of the replicated runs' offset-drift test (Tripp &
Tcheng §8).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.budget import Calibration, TypeBInputs, bench_in_readings
from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.device_model import Geometry, jacobian
from labcal.analysis.distributions import chi2_cdf, f_sf
from labcal.analysis.fit import Fit, readings_points
from labcal.analysis.readings import Readings
from labcal.lazy import lazy

if TYPE_CHECKING:
    from scipy import special
else:
    special = lazy("scipy.special")  # as labcal.analysis.distributions: at the first statistic

ALPHA = 0.01  # false alarms on a clean bench: at most one calibration in a hundred
# Readings beyond which the test is not made: its matrices are (3 × readings) × (the bench's inputs); a
# day's replicated calibration has a few thousand readings, a file of a million is not a calibration run
MAX_READINGS = 20_000


@dataclass(frozen=True)
class BenchTest:
    """The score test of one group of the bench's stated errors: is its variance larger than stated?"""

    name: str
    ratio: float  # T / E[T]: about 1 where the stated u is right, larger where the bench errs more
    p_value: float


@dataclass(frozen=True)
class LackOfFit:
    statistic: float  # Q / ν₁
    dof: tuple[float, float]  # ν₁, ν₂
    p_value: float
    bench: tuple[BenchTest, ...]
    drift_statistic: float  # χ² of the three outputs' trends in measurement order
    drift_dof: int
    drift_p_value: float
    alpha: float = ALPHA

    @property
    def tests(self) -> int:
        return 1 + len(self.bench)

    @property
    def significant(self) -> bool:
        """Any of the omnibus and the bench groups' tests at α / their number (Bonferroni): at most α
        false alarms in all."""
        return min([self.p_value, *(b.p_value for b in self.bench)]) < self.alpha / self.tests

    @property
    def drift_significant(self) -> bool:
        return self.drift_p_value < self.alpha


def _scaled_chi2_sf(t: float, mean: float, var: float) -> float:
    """P(T > t) for a quadratic form of normals with this mean and variance, as a scaled χ²
    (Satterthwaite): T ≈ c·χ²(h), c = var / 2mean, h = 2mean² / var."""
    if mean <= 0 or var <= 0:
        return 1.0
    c, h = var / (2 * mean), 2 * mean**2 / var
    return float(special.chdtrc(h, max(t / c, 0.0)))  # h is not a whole number: scipy's, not chi2_cdf


def lack_of_fit(residuals: NDArray[np.float64], jacobian: NDArray[np.float64], noise_var: NDArray[np.float64],
                bench: dict[str, NDArray[np.float64]], noise_dof: float, alpha: float = ALPHA) -> LackOfFit:
    """``residuals`` (K × 3) of a fit whose Jacobian is ``jacobian`` (K × 3 × p), each point's noise
    variance ``noise_var`` (K × 3, with ``noise_dof`` degrees of freedom), and the bench's stated
    errors in the readings by group, ``bench`` (name → K × 3 × m, each column one input times its u).

    With C = N + BBᵀ the readings' covariance under the model, M = C⁻¹ − C⁻¹J(JᵀC⁻¹J)⁻¹JᵀC⁻¹ keeps what
    no change of the fitted parameters explains: Q = rᵀMr ~ χ²(3K − p) (the generalised least-squares
    residual sum of squares); a group's score statistic T = ‖B_gᵀMr‖² has mean tr(B_gᵀMB_g) and
    variance 2 tr((B_gᵀMB_g)²) — the locally most powerful test that the group's variance exceeds the
    stated one. C⁻¹ is applied by the Woodbury identity through N (diagonal) and the m × m matrix
    I + BᵀN⁻¹B, so nothing of size 3K × 3K is formed: a day's replicated run has thousands of readings."""
    k = residuals.shape[0]
    n = 3 * k
    groups = {name: b.reshape(n, -1) for name, b in bench.items() if b.size}
    B = np.concatenate(list(groups.values()), axis=1) if groups else np.zeros((n, 0))
    n_inv = 1.0 / noise_var.reshape(n)
    core = np.linalg.inv(np.eye(B.shape[1]) + (B.T * n_inv) @ B)

    def c_inv(x: NDArray[np.float64]) -> NDArray[np.float64]:
        nx = x * n_inv[:, None]
        return np.asarray(nx - (B * n_inv[:, None]) @ (core @ (B.T @ nx)), dtype=float)

    J = jacobian.reshape(n, -1)
    cj = c_inv(J)
    gram = J.T @ cj
    rank = int(np.linalg.matrix_rank(gram, hermitian=True))
    gram_inv = np.linalg.pinv(gram, hermitian=True)

    def m(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(c_inv(x) - cj @ (gram_inv @ (cj.T @ x)), dtype=float)

    r = residuals.reshape(n, 1)
    mr = m(r)[:, 0]
    nu1 = float(n - rank)
    q = float(r[:, 0] @ mr)
    tests = []
    for name, columns in groups.items():
        g = columns.T @ m(columns)  # B_gᵀ M B_g
        t = float(np.sum((columns.T @ mr) ** 2))
        mean, var = float(np.trace(g)), 2.0 * float(np.sum(g * g))
        tests.append(BenchTest(name, t / mean if mean > 0 else 1.0, _scaled_chi2_sf(t, mean, var)))
    # a linear trend of each output in measurement order, in the same metric: (tᵀMr)ᵀ(tᵀMt)⁻¹(tᵀMr)
    order = (np.arange(k, dtype=float) - (k - 1) / 2) / max(k - 1, 1)
    trend = np.zeros((k, 3, 3))
    for c in range(3):
        trend[:, c, c] = order
    t3 = trend.reshape(n, 3)
    info = t3.T @ m(t3)
    score = t3.T @ mr
    drift_dof = int(np.linalg.matrix_rank(info, hermitian=True))
    drift = float(score @ np.linalg.pinv(info, hermitian=True) @ score)
    return LackOfFit(q / nu1, (nu1, float(noise_dof)), float(f_sf(q / nu1, nu1, noise_dof)), tuple(tests),
                     drift, drift_dof, 1.0 - chi2_cdf(drift, drift_dof) if drift_dof else 1.0, alpha)


def fit_lack_of_fit(cal: Calibration, inputs: TypeBInputs, readings: Readings, fit: Fit,
                    device: DeviceFit | None = None, alpha: float = ALPHA) -> LackOfFit | None:
    """The test of the certificate's fit (``device`` where it is built on the device model): its
    residuals and Jacobian, the pooled within-window scatter as the noise, the budget's point-to-point
    Type B inputs as the bench. None where the readings do not carry their windows' scatter, or are
    more than `MAX_READINGS`."""
    rep = cal.repeatability
    if rep is None or readings.window_n is None or len(readings) > MAX_READINGS:
        return None
    noise = rep.sample_sd[None, :] ** 2 / np.asarray(readings.window_n, dtype=float)[:, None]
    if device is not None:
        where = Geometry.from_degrees(readings.pitch_deg, readings.roll_deg, readings.y_deg, readings.u_deg)
        predicted, jac = jacobian(device.theta, where)
        residuals = readings.volts - predicted
    else:
        _, design = fit.model.design(readings_points(readings))
        jac = np.zeros((len(design), 3, 3 * design.shape[1]))
        for c in range(3):
            jac[:, c, c * design.shape[1]:(c + 1) * design.shape[1]] = design
        residuals = fit.ls.residuals
    bench = bench_in_readings(cal, inputs)
    warmth = temperature_in_readings(cal, inputs, readings)
    if warmth is not None:
        bench["temperature"] = warmth
    return lack_of_fit(residuals, jac, noise, bench, rep.dof, alpha)


def temperature_in_readings(cal: Calibration, inputs: TypeBInputs, readings: Readings
                            ) -> NDArray[np.float64] | None:
    """How the stated temperature coefficients move each reading with its point's temperature about
    the run's mean (K × 3 × 6: per channel its bias, tc_b·ΔT_k, and its sensitivity, tc_s·ΔT_k·(v − B)),
    each coefficient an input whose standard uncertainty is its stated size (either sign): the
    temperature row of the budget bounds the same effect by the run's range, but over a run the
    temperature moves from point to point, and with long windows the readings see it. None where the
    readings carry no temperature or no coefficient is stated."""
    t = readings.temp_c
    tc_b, tc_s = inputs.bias_tempco_v_per_k, inputs.sensitivity_tempco_per_k
    if t is None or not (tc_b > 0 or tc_s > 0) or not np.all(np.isfinite(t)):
        return None
    dt = np.asarray(t, dtype=float) - float(np.mean(t))
    k = len(dt)
    columns = np.zeros((k, 3, 6))
    for c in range(3):
        columns[:, c, c] = tc_b * dt
        columns[:, c, 3 + c] = tc_s * dt * (readings.volts[:, c] - cal.X[0, c])
    return columns
