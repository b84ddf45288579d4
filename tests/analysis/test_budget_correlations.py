"""Correlations in the budget: the DMM's gain may be one error common to the three
channels (a scanning DMM reads them through one ADC) or independent per channel. Each row is checked
against the GUM formula u_i = |c_i|·u(x_i) with the sensitivity c_i found here by perturbing the
coefficients and inferring the attitude again, and the stated U95 against a Monte Carlo of the
bench's own error (not of the budget's Jacobians): it covers 95 % and is at most 25 % larger."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.analysis.attitude import (
    LOCAL_GRAVITY_U,
    calibration_from_json,
    output_variance,
    sphere_least_squares,
)
from labcal.analysis.budget import TypeBInputs, calibration_of, coefficient_budget, propagate, sources
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import Misalignment, gravity
from labcal.analysis.montecarlo import estimate
from labcal.config.emulation import InstrumentTruth
from labcal.config.plans import load_plan
from labcal.config.station import load_certificate_section
from labcal.sim.direct import simulate_readings

# biases of a few hundred mV, as servo accelerometers have: a common gain moves B as well as S, and B
# is what keeps it from cancelling completely in the direction
TRUTH = InstrumentTruth(B=[0.3, -0.25, 0.2], S=[[5.0, 0.01, 0.0], [0.0, 4.9, 0.02], [0.01, 0.0, 5.1]])
GAIN = 3.5e-5  # ± half-width, relative (34970A, 10 V range, 1 year)
ATTITUDES = np.radians([[30.0, 45.0], [60.0, -90.0], [-45.0, 150.0], [10.0, -20.0]])
ROW = "DMM accuracy, % of reading"


@pytest.fixture(scope="module")
def calibration():
    plan, _ = load_plan("four-mount-64")
    readings = simulate_readings(plan, TRUTH, Misalignment(), noise_v=1e-6, seed=3)
    fit = fit_readings(readings)
    return fit, calibration_of(fit, readings)


def _gain_row(cal, common: bool):
    inputs = TypeBInputs(dmm_reading=GAIN, common=("dmm_reading",) if common else ())
    return next(s for s in sources(cal, inputs) if s.name == ROW)


def _sensitivities(fit, attitudes, offset: bool = False):
    """∂(pitch, roll)/∂(relative gain of channel j) at each attitude, by central differences of the
    sphere estimator with the coefficients scaled as a DMM gain error scales them (n×2×3); with
    ``offset``, ∂/∂(offset of channel j in volts): the bias moves by it."""
    cal0 = calibration_from_json(fit.to_json(), "fit")
    g = gravity(attitudes[:, 0], attitudes[:, 1], 0.0, 0.0)
    volts = fit.coefficients[0] + g @ fit.coefficients[1:]
    h = 1e-6
    out = np.zeros((len(attitudes), 2, 3))
    for j in range(3):
        z = []
        for sign in (1, -1):
            X = fit.coefficients.copy()
            if offset:
                X[0, j] += sign * h
            else:
                X[:, j] *= 1 + sign * h
            att = sphere_least_squares(cal0.__class__(X, cal0.covariance, cal0.reading_sd, cal0.dof), volts,
                                       LOCAL_GRAVITY_U)  # the estimator `labcal attitude` uses
            z.append(np.column_stack([att.pitch, att.roll]))
        out[:, :, j] = (z[0] - z[1]) / (2 * h)
    return out


@pytest.mark.parametrize("common", [False, True])
def test_dmm_gain_row_is_the_gum_formula(calibration, common):
    fit, cal = calibration
    row = _gain_row(cal, common)
    u_gain = GAIN / np.sqrt(3)  # rectangular ± a: u = a/√3 (GUM 4.3.7)
    # to the coefficients: X_ij moves by X_ij·δ_j, so u(X_ij) = |X_ij|·a/√3 either way
    coef = coefficient_budget([row])
    np.testing.assert_allclose(coef.contributions[ROW], np.abs(fit.coefficients) * u_gain, rtol=1e-9)
    # to the attitude: independent, u² = Σ_j c_j² u²; common, u = |Σ_j c_j|·u
    c = _sensitivities(fit, ATTITUDES)
    expected = np.abs(c.sum(axis=2)) * u_gain if common else np.sqrt(np.sum(c**2, axis=2)) * u_gain
    p = propagate(cal, [row], ATTITUDES[:, 0], ATTITUDES[:, 1])
    np.testing.assert_allclose(p.contributions[ROW], expected, rtol=1e-4)
    np.testing.assert_allclose(p.u_c, expected, rtol=1e-4)
    np.testing.assert_allclose(p.k, 1.959963984540054, rtol=1e-14)  # infinite dof: the normal quantile


RANGE_V = 5e-5  # ± half-width in volts: 0.0005 % of the 10 V range


@pytest.mark.parametrize("common", [False, True])
def test_dmm_range_row_is_the_gum_formula(calibration, common):
    fit, cal = calibration
    label = "DMM accuracy, % of range"
    inputs = TypeBInputs(dmm_range_v=RANGE_V, common=("dmm_range",) if common else ())
    row = next(s for s in sources(cal, inputs) if s.name == label)
    u_offset = RANGE_V / np.sqrt(3)
    # an offset moves each bias by itself and no sensitivity
    expected_x = np.zeros((4, 3))
    expected_x[0] = u_offset
    np.testing.assert_allclose(coefficient_budget([row]).contributions[label], expected_x, rtol=1e-12)
    c = _sensitivities(fit, ATTITUDES, offset=True)
    expected = np.abs(c.sum(axis=2)) * u_offset if common else np.sqrt(np.sum(c**2, axis=2)) * u_offset
    p = propagate(cal, [row], ATTITUDES[:, 0], ATTITUDES[:, 1])
    np.testing.assert_allclose(p.contributions[label], expected, rtol=1e-4)


@pytest.mark.parametrize("common", [False, True])
def test_stated_u95_covers_the_bench_and_is_not_over_25_percent_conservative(calibration, common):
    """The bench: one gain error δ ~ U(−a, a) shared by the three channels, or three independent
    ones; the calibration's coefficients are scaled by it, the instrument in use is read exactly, and
    the attitude is inferred by the sphere estimator. 20 000 draws put the 95 % quantile of |error|
    within about 1 % (binomial: the quantile's rank has SD √(N·0.95·0.05) ≈ 31 of 1 000 beyond it)."""
    fit, cal = calibration
    row = _gain_row(cal, common)
    p = propagate(cal, [row], ATTITUDES[:, 0], ATTITUDES[:, 1])
    rng = np.random.default_rng(23)
    n = 20_000
    cal0 = calibration_from_json(fit.to_json(), "fit")
    for i, (pitch, roll) in enumerate(ATTITUDES):
        delta = rng.uniform(-GAIN, GAIN, (n, 1 if common else 3))
        X = fit.coefficients[None] * (1 + delta[:, None, :])
        g = gravity(np.array([pitch]), np.array([roll]), 0.0, 0.0)
        volts = np.broadcast_to(fit.coefficients[0] + g @ fit.coefficients[1:], (n, 3))
        w = 1 / output_variance(cal0, g)[0]
        est_p, est_r = estimate(X, volts, w, LOCAL_GRAVITY_U)  # as `labcal attitude` estimates
        errors = np.abs(np.column_stack([est_p - pitch, np.angle(np.exp(1j * (est_r - roll)))]))
        q95 = np.quantile(errors, 0.95, axis=0)
        ratio = p.U[i] / q95
        assert np.all(ratio >= 0.98), (common, i, ratio)  # covers (quantile's own scatter ~1 %)
        assert np.all(ratio <= 1.25), (common, i, ratio)


def test_a_scanning_dmm_s_gain_is_common_unless_the_station_says_otherwise(tmp_path):
    """Default: common for the 34970A (one ADC scans the channels); `common = []` declares them
    independent; the example station states it."""
    from pathlib import Path

    example = load_certificate_section(Path(__file__).resolve().parents[2] / "stations" / "lab-example.toml")
    assert example.dmm.common_inputs(example.uncertainty.common) == ("dmm_reading",)
    path = tmp_path / "station.toml"
    path.write_text('[dmm]\ndriver = "keysight-34970a"\n[uncertainty]\ndmm_reading = "0.0035 %"\n')
    section = load_certificate_section(path)
    assert section.dmm.common_inputs(section.uncertainty.common) == ("dmm_reading",)
    path.write_text('[dmm]\ndriver = "keysight-34970a"\n[uncertainty]\ncommon = []\n')
    section = load_certificate_section(path)
    assert section.dmm.common_inputs(section.uncertainty.common) == ()
    path.write_text('[uncertainty]\ncommon = ["dmm_range", "dmm_reading"]\n')
    section = load_certificate_section(path)
    assert section.dmm.common_inputs(section.uncertainty.common) == ("dmm_range", "dmm_reading")
