"""The budget's new-reading row is the instrument's repeatability in use: the scatter inside the
calibration's windows, pooled (GUM 4.2.4), over the root of the samples a reading in use averages
(GUM 4.2.3) — not the calibration's residual, which holds the tables' per-angle errors. Expected values
are computed here by hand from the readings' window statistics and the nominal design."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from labcal.analysis.budget import TypeBInputs, calibration_of, sources
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import IndexWobble, gravity
from labcal.analysis.repeatability import repeatability
from labcal.config.emulation import DeviceTruth, default_instrument
from labcal.config.plans import load_plan
from labcal.sim.direct import BenchEffects, simulate_readings

NEW_READING = "one new reading (instrument repeatability)"
FIT_ROW = "calibration fit (coefficients)"


@pytest.fixture(scope="module")
def readings():
    """Four-mount-64 with the rig's ±2″ tables, 20 µV per sample over windows of 10 samples."""
    plan, _ = load_plan("four-mount-64")
    truth = default_instrument()
    return simulate_readings(plan, truth, DeviceTruth().misalignment(), IndexWobble(2.0, 2.0, 3),
                             truth.noise_v, 3, BenchEffects(samples=10))


def _row(rows, name):
    return next(r for r in rows if r.name == name)


def test_pooled_scatter_weights_each_window_by_its_degrees_of_freedom(readings):
    # windows of unequal length: Σ(n−1)s² / Σ(n−1), ν = Σ(n−1); a one-sample window adds nothing
    n = np.array([10.0, 4.0, 1.0] + [10.0] * (len(readings) - 3))
    sd = np.tile([1.0, 2.0, 3.0], (len(readings), 1)) * 1e-5
    sd[1] *= 2.0
    rep = repeatability(replace(readings, window_n=n, window_sd=sd))
    assert rep is not None
    dof = 9 + 3 + 9 * (len(readings) - 3)
    expected = np.array([1.0, 2.0, 3.0]) * 1e-5 * np.sqrt((9 + 3 * 4 + 9 * (len(readings) - 3)) / dof)
    np.testing.assert_allclose(rep.sample_sd, expected, rtol=1e-12)
    assert rep.dof == dof and rep.windows == len(readings) - 1 and rep.window_samples == 10


def test_the_new_reading_row_is_the_pooled_scatter_over_the_root_of_the_samples_in_use(readings):
    n, sd = readings.window_n, readings.window_sd
    pooled = np.sqrt(np.sum((n - 1)[:, None] * sd**2, axis=0) / np.sum(n - 1))
    # the simulated noise is 20 µV per sample: pooled over 576 degrees of freedom it is within 3/√(2·576)
    np.testing.assert_allclose(pooled, 20e-6, rtol=3 / np.sqrt(2 * 576))
    fit = fit_readings(readings)
    for stated, samples in ((None, 10), (40, 40)):
        cal = calibration_of(fit, readings, stated)
        row = _row(sources(cal, TypeBInputs()), NEW_READING)
        assert row.u == pytest.approx(pooled.max() / np.sqrt(samples), rel=1e-12)
        assert row.dof == np.sum(n - 1)
        assert f"averages {samples} samples" in row.note
    # the residual standard error is several times larger: the tables' per-angle errors are in it
    assert np.all(fit.ls.residual_se > 2 * pooled / np.sqrt(10))


def test_the_coefficients_type_a_is_the_noise_through_the_design(readings):
    """Linear fit: cov(B, S) of sensor j = s_j²/N·(FᵀF)⁻¹, F = [1, g] on the nominal gravity."""
    n, sd = readings.window_n, readings.window_sd
    var = np.sum((n - 1)[:, None] * sd**2, axis=0) / np.sum(n - 1) / 10
    angles = (readings.pitch_deg, readings.roll_deg, readings.y_deg, readings.u_deg)
    p, r, y, u = (np.radians(a) for a in angles)
    F = np.column_stack([np.ones(len(p)), gravity(p, r, y, u)])
    inverse = np.linalg.inv(F.T @ F)
    cal = calibration_of(fit_readings(readings), readings)
    for j in range(3):
        # atol: the off-diagonal zeros of an orthogonal design come back as rounding, 1e-12 of the diagonal
        np.testing.assert_allclose(cal.covariance[j], var[j] * inverse, rtol=1e-9, atol=1e-12 * var[j])
    assert np.all(cal.dof == np.sum(n - 1))
    row = _row(sources(cal, TypeBInputs()), FIT_ROW)
    assert "the instrument's noise" in row.note


def test_readings_without_their_windows_keep_the_residual_rows(readings):
    plain = replace(readings, window_sd=None, window_n=None)
    fit = fit_readings(plain)
    cal = calibration_of(fit, plain)
    rows = sources(cal, TypeBInputs())
    assert _row(rows, NEW_READING).u == pytest.approx(fit.ls.residual_se.max(), rel=1e-12)
    assert _row(rows, NEW_READING).note.startswith("the fit's residual standard error")
    np.testing.assert_allclose(cal.covariance[0], fit.covariance(0)[:4, :4], rtol=1e-12)
    assert cal.repeatability is None and not cal.noise_type_a
