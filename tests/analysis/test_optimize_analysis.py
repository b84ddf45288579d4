"""`labcal.analysis.optimize`: the predicted calibration, the D-optimal articulations and the frontier,
each against what a hand derivation gives."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from labcal.analysis import optimize
from labcal.analysis.budget import TypeBInputs
from labcal.analysis.kinematics import ARCSEC, nominal_gravity

TUMBLE = ((90.0, 0.0), (-90.0, 0.0), (0.0, 90.0), (0.0, -90.0), (0.0, 0.0), (0.0, 180.0))  # g = ±x, ±y, ±z


def bench(**type_b) -> optimize.Bench:
    X = np.vstack([np.zeros(3), 5.0 * np.eye(3)])
    return optimize.Bench(X, 20e-6, TypeBInputs(**type_b))


def test_predicted_covariance_of_the_tumble_is_sigma_squared_over_the_moment_matrix():
    """Six cardinal attitudes, one mount, noise only: FᵀF = diag(6, 2, 2, 2) (Σ g gᵀ = 2I, Σ g = 0),
    so var B = σ²/6, var S_ii = σ²/2 with σ² = σ_s²/N (Tripp & Tcheng eq. 50); the noise is known from
    the scatter inside the six windows of 16 samples, with 6 × 15 = 90 degrees of freedom."""
    c = optimize.Candidate(((0.0, 0.0),), TUMBLE, 16)
    cal = optimize.predicted_calibration(c, bench(), quantile=None)
    sigma2 = (20e-6) ** 2 / 16
    assert cal.reading_var == pytest.approx(np.full(3, sigma2), rel=1e-12)  # the fit's residual
    for j in range(3):
        assert np.diag(cal.covariance[j]) == pytest.approx([sigma2 / 6] + [sigma2 / 2] * 3, rel=1e-9)
    assert cal.dof == pytest.approx(np.full(3, 90.0))


def test_a_reading_in_use_is_predicted_as_the_certificate_states_it():
    """The new-reading row is the instrument's noise over the averaging in use, σ_s/√N (N the plan's
    window, or the certificate's stated averaging), not the fit's residual, which here also holds a
    2″ index error of each table; at the 95 % promise each channel's s is at its 0.95^(1/3) quantile
    of σ_s²·χ²_ν/ν (ν = 6 × 15), 2.121 standard normal deviates of χ²_ν/ν ≈ N(1, 2/ν) out, to first
    order: the three channels scatter independently."""
    c = optimize.Candidate(((0.0, 0.0),), TUMBLE, 16)
    tables = bench(pitch_index=2 * ARCSEC, roll_index=2 * ARCSEC)
    row = "one new reading (instrument repeatability)"

    def reading_u(b: optimize.Bench, quantile: float | None) -> float:
        cal = optimize.predicted_calibration(c, b, quantile=quantile)
        [source] = [s for s in optimize.sources(cal, b.type_b) if s.name == row]
        return source.u

    assert reading_u(tables, None) == pytest.approx(20e-6 / 4, rel=1e-12)
    assert reading_u(replace(tables, in_use_samples=100), None) == pytest.approx(20e-6 / 10, rel=1e-12)
    scale = (reading_u(tables, 0.95) / reading_u(tables, None)) ** 2
    assert scale == pytest.approx(1 + 2.121 * np.sqrt(2 / 90), rel=0.03)  # the χ² skew: 2 %


def test_table_errors_raise_the_predicted_residual_variance_but_not_beyond_their_size():
    """A stated index error adds to the residual variance what the fit cannot absorb: more than
    nothing, less than its whole size at the sensors: per table at most (5 V/rad × u)² per point with
    u = 2″/√3 (I − H shrinks, and each shape's columns carry u² at a point), over K − 4 dof."""
    c = optimize.Candidate(((0.0, 0.0),), tuple(optimize.d_optimal_sequence(
        [(0.0, 0.0)], optimize.candidate_articulations(), 24)), 10)
    quiet = optimize.predicted_calibration(c, bench(), quantile=None).reading_var
    tables = bench(pitch_index=2 * ARCSEC, roll_index=2 * ARCSEC)
    noisy = optimize.predicted_calibration(c, tables, quantile=None).reading_var
    added = noisy - quiet
    ceiling = 2 * (5.0 * 2 * ARCSEC / np.sqrt(3)) ** 2 * 24 / (24 - 4)
    assert np.all(added > 0) and np.all(added < ceiling)


@pytest.mark.parametrize("n", [6, 8, 12])
def test_greedy_articulations_are_nearly_d_optimal(n):
    """For n attitudes on the unit sphere det FᵀF ≤ n·(n/3)³ (Hadamard on [n, Σg; Σg, Σggᵀ] with
    trace Σggᵀ = n, AM–GM), reached by the tumble at n = 6: the greedy design's D-efficiency
    (det / bound)^¼ is within 5 % of it."""
    points = optimize.d_optimal_sequence([(0.0, 0.0)], optimize.candidate_articulations(), n)
    assert len(set(points)) == n
    g = nominal_gravity(*np.radians(np.array(points)).T, 0.0, 0.0)
    F = np.column_stack([np.ones(n), g])
    assert (np.linalg.det(F.T @ F) / (n * (n / 3) ** 3)) ** 0.25 >= 0.95


def test_the_frontier_keeps_only_the_undominated():
    def e(t: float, u: float) -> optimize.Evaluated:
        return optimize.Evaluated(optimize.Candidate(((0.0, 0.0),), TUMBLE, 4), t, u, u, True)

    found = [e(10, 5), e(20, 6), e(30, 3), e(15, 4), e(40, 3)]
    assert [(x.rig_time_s, x.u95_rad) for x in optimize.frontier(found)] == [(10, 5), (15, 4), (30, 3)]


def test_without_a_correction_fewer_mounts_are_never_offered():
    """The misalignments must be identified (four mounts) or known and seen: three mounts without a
    correction are no candidate at all, with one they are; one mount is none even with a correction
    (it never sees e, f or k, so a run could not notice them move)."""
    c = optimize.Candidate(((0.0, 0.0), (180.0, 0.0), (0.0, 180.0)), TUMBLE, 10)
    assert optimize.evaluate(c, bench(), None, 0.0) is None
    known = optimize.DeviceCorrection("CD", "run-1", dict.fromkeys("abdefk", 0.0),
                                      dict.fromkeys("abdefk", 1 * ARCSEC))
    result = optimize.evaluate(c, bench(), known, 0.0)
    assert result is not None and not result.identified
    assert optimize.evaluate(optimize.Candidate(((0.0, 0.0),), TUMBLE, 10), bench(), known, 0.0) is None
