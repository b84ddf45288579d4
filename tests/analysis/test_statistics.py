"""The uncertainty engine: NIST certified regression, coning parameters, interval coverage by
Monte Carlo, lack-of-fit and drift tests, model extensions."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import FOUR_MOUNTS, soto_plan

from labcal.analysis.coning import coning
from labcal.analysis.fit import Fit, extension_tests, fit_readings, point_keys
from labcal.analysis.models import Model, Points
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.analysis.regression import least_squares
from labcal.analysis.replication import analyse, point_groups
from labcal.config.emulation import InstrumentTruth
from labcal.sim.direct import simulate_readings

DATA = Path(__file__).parent.parent / "data"
TRUTH = InstrumentTruth.from_coning(b=[0.0123, -0.0081, 0.0047], sensitivity=[4.9871, 5.0124, 4.9958],
                                    omega_deg=[0.21, 0.14, 0.09], azimuth_deg=[35, -120, 200])


def significant_digits(value: float, certified: float) -> float:
    """NIST's log relative error: the number of agreeing significant digits."""
    return np.inf if value == certified else -np.log10(abs(value - certified) / abs(certified))


def test_nist_norris_certified_values():
    lines = (DATA / "Norris.dat").read_text().splitlines()[60:]
    y, x = np.array([[float(v) for v in line.split()] for line in lines if line.strip()]).T
    ls = least_squares(np.column_stack([np.ones_like(x), x]), y)
    certified = {"B0": (-0.262323073774029, 0.232818234301152),
                 "B1": (1.00211681802045, 0.429796848199937e-03)}
    for k, (estimate, sd) in enumerate(certified.values()):
        assert significant_digits(ls.coef[k, 0], estimate) >= 9
        assert significant_digits(ls.stderr[k, 0], sd) >= 9
    assert significant_digits(ls.residual_se[0], 0.884796396144373) >= 9
    assert ls.dof == 34


def test_coning_parameters_recovered_within_stated_uncertainty():
    plan = Plan(**{**soto_plan(FOUR_MOUNTS).model_dump(), "replicates": 3})
    fit = fit_readings(simulate_readings(plan, TRUTH, noise_v=2e-4, seed=5))
    for sensor, b, s, omega, azimuth in zip(coning(fit), TRUTH.B, [4.9871, 5.0124, 4.9958],
                                            np.radians([0.21, 0.14, 0.09]), np.radians([35, -120, 200 - 360]),
                                            strict=True):
        se = np.sqrt(np.diag(sensor.covariance))
        error = sensor.values - [b, s, omega, azimuth]
        error[3] = (error[3] + np.pi) % (2 * np.pi) - np.pi
        assert sensor.azimuth_defined
        assert np.all(np.abs(error) < 3 * se), (sensor.name, error / se)


def test_azimuth_is_undefined_for_an_untilted_sensor():
    truth = InstrumentTruth.from_coning(b=[0, 0, 0], sensitivity=[5, 5, 5], omega_deg=[0.0, 0.0, 0.3],
                                        azimuth_deg=[0, 0, 45])
    fit = fit_readings(simulate_readings(soto_plan(FOUR_MOUNTS), truth, noise_v=1e-4, seed=1))
    x, _, z = coning(fit)
    assert not x.azimuth_defined and x.to_json()["azimuth_deg"] is None
    assert "azimuth A is undefined" in x.to_json()["azimuth_note"]
    assert z.azimuth_defined and z.to_json()["azimuth_deg"] == pytest.approx(45, abs=1.0)


def monte_carlo_readings(plan: Plan, trials: int, noise: float, seed: int) -> tuple[Readings, np.ndarray]:
    """One Readings whose volts hold `trials` independent calibrations side by side (3 columns each)."""
    exact = simulate_readings(plan, TRUTH)
    noise_v = np.random.default_rng(seed).normal(0, noise, (len(exact), 3 * trials))
    return exact, np.tile(exact.volts, trials) + noise_v


def test_confidence_and_prediction_intervals_cover_95_percent():
    """2000 simulated four-mount calibrations (6000 sensor fits): the 95 % confidence interval
    covers the true output and the prediction interval a new reading 93–97 % of the time."""
    trials, noise = 2000, 1e-4
    plan = soto_plan(FOUR_MOUNTS)
    exact, volts = monte_carlo_readings(plan, trials, noise, seed=42)
    names, design = Model().design(Points(exact.pitch_deg, exact.roll_deg, exact.y_deg, exact.u_deg))
    fit = Fit(Model(), names, least_squares(design, volts))
    rng = np.random.default_rng(7)
    for pitch, roll in ((10, 20), (-47, 133), (80, -60)):
        pred = fit.predict(Points.at(pitch, roll))
        true = np.tile(TRUTH.static_volts(Points.at(pitch, roll).nominal_gravity()), trials)[0]
        new_reading = true + rng.normal(0, noise, true.shape)
        ci = np.mean(np.abs(pred["volts"][0] - true) <= pred["confidence"][0])
        pi = np.mean(np.abs(pred["volts"][0] - new_reading) <= pred["prediction"][0])
        assert 0.93 <= ci <= 0.97 and 0.93 <= pi <= 0.97, (pitch, roll, ci, pi)


def test_lack_of_fit_test_has_its_nominal_size_when_the_model_is_right():
    """2000 replicated calibrations (2 × four-mount-64, 6000 sensor fits): each form of the
    lack-of-fit test rejects 5 % ± 2 % of the time at the 5 % level."""
    trials = 2000
    plan = Plan(**{**soto_plan(FOUR_MOUNTS).model_dump(), "replicates": 2})
    exact, volts = monte_carlo_readings(plan, trials, 1e-4, seed=3)
    _, design = Model().design(Points(exact.pitch_deg, exact.roll_deg, exact.y_deg, exact.u_deg))
    groups, _ = point_groups(point_keys(exact))
    rep = analyse(design, volts, groups, exact.replicate)
    assert rep.classical.df_num == 60 and rep.classical.df_den == 64 and rep.drift_robust.df_den == 60
    for test in (rep.classical, rep.drift_robust, rep.lack_of_fit):
        assert 0.03 <= np.mean(test.significant) <= 0.07, np.mean(test.significant)
    for drift in rep.drift:
        assert 0.03 <= np.mean(drift.test.significant) <= 0.07, (drift.name, np.mean(drift.test.significant))
    # variance components are unbiased: E[σ̂_prec²] = σ², and σ̂_bias mostly zero
    assert np.mean(rep.sigma_prec**2) == pytest.approx(1e-8, rel=0.02)


def test_bias_is_detected_and_scales_the_uncertainty():
    """A CD misalignment the model ignores repeats in every replicate: the lack-of-fit test finds
    it, σ_bias estimates it, and the coefficient uncertainty grows to the lack-of-fit scale."""
    from labcal.analysis.kinematics import Misalignment

    plan = Plan(**{**soto_plan(FOUR_MOUNTS).model_dump(), "replicates": 3})
    biased = simulate_readings(plan, TRUTH, Misalignment.from_degrees(a=0.01, d=0.01), noise_v=1e-5, seed=2)
    fit = fit_readings(biased)
    assert np.all(fit.bias_significant)
    assert fit.variance_basis == ["lack-of-fit mean square"] * 3
    assert np.all(fit.variance == fit.replication.lack_of_fit_ms)
    assert np.all(fit.replication.sigma_bias > 3 * fit.replication.sigma_prec)
    assert "scaled by the lack-of-fit mean square" in fit.notes[0]
    clean = fit_readings(simulate_readings(plan, TRUTH, noise_v=1e-5, seed=2))
    assert not np.any(clean.bias_significant) and clean.notes == ()


def test_offset_drift_between_replicates_is_detected():
    plan = Plan(**{**soto_plan(FOUR_MOUNTS).model_dump(), "replicates": 4})
    readings = simulate_readings(plan, TRUTH, noise_v=1e-5, seed=4)
    drifted = readings.volts + 5e-5 * (readings.replicate - 1)[:, None] * np.array([1, 0, 0])
    rep = fit_readings(replace(readings, volts=drifted)).replication
    offset, sensitivity = rep.drift
    assert offset.test.significant.tolist() == [True, False, False]
    assert offset.sigma_drift[0] == pytest.approx(np.std([0, 5e-5, 10e-5, 15e-5], ddof=1), rel=0.1)
    assert not np.any(sensitivity.test.significant)


def test_temperature_extension_is_warranted_only_when_temperature_matters():
    plan = Plan(**{**soto_plan(FOUR_MOUNTS).model_dump(), "replicates": 2})
    base = simulate_readings(plan, TRUTH, noise_v=1e-5, seed=8)
    temp = 20 + 2 * np.sin(np.arange(len(base)) / 9.0)
    effect = 2e-5 * (temp - temp.mean())[:, None]  # 20 µV/°C on every offset
    with_t = replace(base, volts=base.volts + effect, temp_c=temp)
    tests = {t.name: t for t in extension_tests(with_t)}
    assert np.all(tests["temperature"].p_value < 1e-6)
    fit = fit_readings(with_t, Model(("temperature",), float(temp.mean())))
    assert np.allclose(fit.ls.coef[4], 2e-5, atol=4 * fit.stderr[4])
    without = replace(base, temp_c=temp)
    assert np.all({t.name: t for t in extension_tests(without)}["temperature"].p_value > 0.01)
    # on Soto's 90° grid sin 2α and sin 2R vanish at every point: named as aliased, not tested
    assert tests["harmonics"].aliased == ("sin 2α", "sin 2R") and tests["harmonics"].df[0] == 2


def test_harmonic_extension_finds_a_2_alpha_pattern():
    from labcal.analysis.design import d1, make_plan

    plan = make_plan("d1", "", d1(90, 19, 8), four_mounts=False, replicates=2)
    readings = simulate_readings(plan, TRUTH, noise_v=1e-5, seed=9)
    pattern = 3e-5 * np.cos(2 * np.radians(readings.pitch_deg))[:, None]
    tests = {t.name: t for t in extension_tests(replace(readings, volts=readings.volts + pattern))}
    assert np.all(tests["harmonics"].p_value < 1e-6)
    assert tests["temperature"].reason.startswith("the temperature extension needs a temp_c column")


def test_replicates_that_visit_a_point_twice_still_get_drift_tests():
    """Tripp's 481-point design holds both −180° and 180°: each replicate sees those points twice.
    The drift-robust analysis uses per-replicate point means weighted by their counts."""
    from labcal.analysis.design import grid, make_plan

    plan = make_plan("t481", "", grid(-180, 180, 10, -180, 180, 30), four_mounts=False, replicates=3)
    readings = simulate_readings(plan, TRUTH, noise_v=1e-5, seed=12)
    rep = fit_readings(readings).replication
    assert rep.n_points == 36 * 12 and rep.drift_robust is not None
    assert rep.drift_robust.df_den == 2 * (432 - 4)
    assert rep.classical.df_den == len(readings) - 432
    assert np.mean(rep.sigma_prec) == pytest.approx(1e-5, rel=0.05)
