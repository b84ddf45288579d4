"""Does the model, with the bench's stated errors, explain the calibration's residuals?

The residuals r of a fit of K points are what the model leaves of the readings' errors: to first order
r = R·ε, R = I − J(JᵀWJ)⁻¹JᵀW the residual maker of the fit's Jacobian J (3K × p, the three outputs of
every point). What the budget says ε is: the instrument's noise, each point's mean scattering by
s_c²/n_k (s_c the pooled scatter inside the windows, `labcal.analysis.repeatability` — pure error,
even in a single pass, because the samples of one window repeat the point), and the bench's stated
errors — the tables' index and wobble at each angle, the plate's seating at each mounting — as the
budget's Type B inputs carry them into the readings (B, 3K × m, one column per elementary input
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

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.budget import Calibration, TypeBInputs, bench_in_readings
from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.device_model import Geometry, jacobian
from labcal.analysis.distributions import chi2_cdf, f_sf
from labcal.analysis.fit import Fit, readings_points
from labcal.analysis.readings import Readings

ALPHA = 0.01  # false alarms on a clean bench: at most one calibration in a hundred


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
    from scipy import special

    if mean <= 0 or var <= 0:
        return 1.0
    c, h = var / (2 * mean), 2 * mean**2 / var
    return float(special.chdtrc(h, max(t / c, 0.0)))  # h is not a whole number: scipy's, not chi2_cdf


def lack_of_fit(residuals: NDArray[np.float64], jacobian: NDArray[np.float64], noise_var: NDArray[np.float64],
                bench: dict[str, NDArray[np.float64]], noise_dof: float, alpha: float = ALPHA) -> LackOfFit:
    """``residuals`` (K × 3) of a fit whose Jacobian is ``jacobian`` (K × 3 × p), each point's noise
    variance ``noise_var`` (K × 3, with ``noise_dof`` degrees of freedom), and the bench's stated
    errors in the readings by group, ``bench`` (name → K × 3 × m, each column one input times its u).

    Whitened by the Cholesky factor of C = N + BBᵀ the residuals' generalised least-squares part e
    (what no change of the fitted parameters explains) is N(0, P) under the model, P the whitened
    residual maker: Q = ‖e‖² ~ χ²(3K − p); a group's score statistic T = ‖Aᵀe‖² (A its whitened
    columns) has mean tr(AᵀPA) and variance 2 tr((AᵀPA)²) — the locally most powerful test that the
    group's variance exceeds the stated one."""
    from scipy.linalg import cho_factor, solve_triangular

    k = residuals.shape[0]
    n = 3 * k
    groups = {name: b.reshape(n, -1) for name, b in bench.items() if b.size}
    B = np.concatenate(list(groups.values()), axis=1) if groups else np.zeros((n, 0))
    C = np.diag(noise_var.reshape(n)) + B @ B.T
    L, _ = cho_factor(C, lower=True)
    L = np.tril(L)

    def whiten(m: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(solve_triangular(L, m, lower=True), dtype=float)

    Jw = whiten(jacobian.reshape(n, -1))
    u, sv, _ = np.linalg.svd(Jw, full_matrices=False)
    U = u[:, sv > 1e-10 * sv.max()]  # the directions the fit absorbs

    def residual(m: NDArray[np.float64]) -> NDArray[np.float64]:
        return m - U @ (U.T @ m)

    e = residual(whiten(residuals.reshape(n)))
    nu1 = float(n - U.shape[1])
    q = float(e @ e)
    tests = []
    for name, columns in groups.items():
        A = whiten(columns)
        PA = residual(A)
        G = A.T @ PA  # AᵀPA
        t = float(np.sum((A.T @ e) ** 2))
        mean, var = float(np.trace(G)), 2.0 * float(np.sum(G * G))
        tests.append(BenchTest(name, t / mean if mean > 0 else 1.0, _scaled_chi2_sf(t, mean, var)))
    # a linear trend of each output in measurement order, seen through the fit and weighed by C⁻¹
    order = (np.arange(k, dtype=float) - (k - 1) / 2) / max(k - 1, 1)
    trend = np.zeros((k, 3, 3))
    for c in range(3):
        trend[:, c, c] = order
    T = residual(whiten(trend.reshape(n, 3)))
    beta, _, rank, _ = np.linalg.lstsq(T, e, rcond=None)
    drift = float(np.sum((T @ beta) ** 2))
    return LackOfFit(q / nu1, (nu1, float(noise_dof)), float(f_sf(q / nu1, nu1, noise_dof)), tuple(tests),
                     drift, int(rank), 1.0 - chi2_cdf(drift, int(rank)) if rank else 1.0, alpha)


def fit_lack_of_fit(cal: Calibration, inputs: TypeBInputs, readings: Readings, fit: Fit,
                    device: DeviceFit | None = None, alpha: float = ALPHA) -> LackOfFit | None:
    """The test of the certificate's fit (``device`` where it is built on the device model): its
    residuals and Jacobian, the pooled within-window scatter as the noise, the budget's point-to-point
    Type B inputs as the bench. None where the readings do not carry their windows' scatter."""
    rep = cal.repeatability
    if rep is None or readings.window_n is None:
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
    return lack_of_fit(residuals, jac, noise, bench_in_readings(cal, inputs), rep.dof, alpha)
