"""The GUM budget: it collapses to the Type A uncertainty when every Type B input is zero, a table
index error adds what refitting perturbed readings predicts, the four-mount plan cancels it, and
the JCGM 101 Monte Carlo agrees with the linear U95."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labcal.analysis.attitude import LOCAL_GRAVITY_U, calibration_from_json, sphere_least_squares
from labcal.analysis.budget import TypeBInputs, calibration_of, coefficient_budget, propagate, sources
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import ARCSEC, Misalignment, gravity
from labcal.analysis.montecarlo import monte_carlo
from labcal.config.emulation import InstrumentTruth
from labcal.config.plans import load_plan
from labcal.errors import LabcalError
from labcal.sim.direct import simulate_readings

TRUTH = InstrumentTruth(B=[0.01, -0.02, 0.005], S=[[5.0, 0.01, 0.0], [0.0, 4.9, 0.02], [0.01, 0.0, 5.1]])
INDEX = 2 * ARCSEC  # ± half-width, rectangular
AT = (np.radians(30.0), np.radians(45.0))  # an attitude in use


def _fit(plan_name: str, noise_v: float = 3e-5):
    plan, _ = load_plan(plan_name)
    readings = simulate_readings(plan, TRUTH, Misalignment(), noise_v=noise_v, seed=7)
    return readings, fit_readings(readings)


def _sphere(fit, volts):
    return sphere_least_squares(calibration_from_json(fit.to_json(), "fit"), volts, LOCAL_GRAVITY_U)


def test_collapses_to_the_type_a_uncertainty_without_type_b_inputs():
    readings, fit = _fit("four-mount-64")
    cal = calibration_of(fit, readings)
    pitch, roll = np.radians(np.meshgrid(np.arange(-60, 61, 20.0), np.arange(-180, 180, 45.0))).reshape(2, -1)
    budget = propagate(cal, sources(cal, TypeBInputs()), pitch, roll)
    g = gravity(pitch, roll, 0.0, 0.0)
    att = _sphere(fit, fit.coefficients[0] + g @ fit.coefficients[1:])
    np.testing.assert_allclose(budget.u_c[:, 0], att.u_pitch, rtol=1e-9)
    np.testing.assert_allclose(budget.u_c[:, 1], att.u_roll, rtol=1e-9)
    coef = coefficient_budget(sources(cal, TypeBInputs()))
    np.testing.assert_allclose(coef.u_c, fit.stderr[:4], rtol=1e-9)
    np.testing.assert_allclose(coef.nu_eff, np.broadcast_to(fit.variance_dof, (4, 3)), rtol=1e-9)


def _index_sensitivities(plan_name: str):
    """∂(inferred pitch, roll)/∂(pitch index error) at each table angle, and ∂/∂(amplitude of each of
    harmonics 1–3 of the pitch angle, cos and sin), by perturbing the readings as the instrument would
    have read them with the table off by δ·pattern, refitting, and inferring the attitude again — the
    budget's linearisation is not used."""
    readings, fit = _fit(plan_name)
    v_use = fit.coefficients[0] + gravity(*AT, 0.0, 0.0) @ fit.coefficients[1:]
    base = _sphere(fit, v_use)
    p, r, y, u = (np.radians(a) for a in
                  (readings.pitch_deg, readings.roll_deg, readings.y_deg, readings.u_deg))
    S = np.array(TRUTH.S)
    delta = 1e-8  # small against the noise, so that refitting leaves the estimator's weights as they were

    def slope(pattern):
        volts = readings.volts + (gravity(p + delta * pattern, r, y, u) - gravity(p, r, y, u)) @ S
        att = _sphere(fit_readings(dataclasses.replace(readings, volts=volts)), v_use)
        return [(att.pitch - base.pitch)[0] / delta, (att.roll - base.roll)[0] / delta]
    per_angle = [slope(np.isclose(readings.pitch_deg % 360, angle).astype(float))
                 for angle in np.unique(readings.pitch_deg % 360)]
    harmonics = [slope(f(h * p)) for h in (1, 2, 3) for f in (np.cos, np.sin)]
    return readings, fit, np.array(per_angle), np.array(harmonics)


def test_index_accuracy_adds_what_refitting_predicts():
    """GUM: u² = Σ c² u², with u = a/√3 (rectangular ± a) for each angle's error of a rough table and
    u²/3 for each harmonic's amplitude of a smooth one (the budget states both shapes)."""
    readings, fit, slopes, harmonics = _index_sensitivities("one-mount-16")
    u = INDEX / np.sqrt(3)
    expected = np.sqrt(np.sum(slopes**2, axis=0) * u**2 + np.sum(harmonics**2, axis=0) * u**2 / 3)
    cal = calibration_of(fit, readings)
    budget = propagate(cal, sources(cal, TypeBInputs(pitch_index=INDEX)), *AT)
    got = budget.contributions["pitch table index accuracy"][0]
    assert expected[0] > 0.1 * ARCSEC  # one mount does not cancel it: a real contribution
    # 1e-3: the budget uses the fitted S for δV = δg·S where the check uses the true S (≈ 1e-4 apart);
    # the same 1e-3 of the row's pitch term bounds its roll term, four orders smaller at this attitude
    np.testing.assert_allclose(got, expected, rtol=1e-3, atol=1e-3 * expected[0])
    no_index = propagate(cal, sources(cal, TypeBInputs()), *AT).u_c[0]
    np.testing.assert_allclose(budget.u_c[0], np.hypot(no_index, expected), rtol=5e-3)


def test_four_mounts_cancel_the_index_error():
    readings, fit, slopes, harmonics = _index_sensitivities("four-mount-64")
    # refitting: an index error leaves pitch and roll (Soto §7), at one angle or as a harmonic
    assert np.max(np.abs(slopes)) < 1e-4 and np.max(np.abs(harmonics)) < 1e-4
    cal = calibration_of(fit, readings)
    budget = propagate(cal, sources(cal, TypeBInputs(pitch_index=INDEX, roll_index=INDEX)), *AT)
    assert budget.contributions["pitch table index accuracy"].max() < 1e-9 * ARCSEC
    assert budget.contributions["roll table index accuracy"].max() < 1e-9 * ARCSEC


EXAMPLE = TypeBInputs(dmm_reading=3.5e-5, dmm_range_v=5e-6 * 10, pitch_index=INDEX, roll_index=INDEX,
                      pitch_wobble=ARCSEC, roll_wobble=ARCSEC, mount_repeatability=3 * ARCSEC)


@pytest.mark.parametrize("plan_name", ["four-mount-64", "one-mount-16"])
def test_monte_carlo_agrees_with_the_linear_budget(plan_name):
    readings, fit = _fit(plan_name)
    cal = calibration_of(fit, readings)
    rows = sources(cal, EXAMPLE)
    linear = propagate(cal, rows, *AT)
    # 4000 trials: the 95 % quantile's relative standard error is about 1.5 %, well inside 5 %
    mc = monte_carlo(cal, rows, *AT, trials=4000, seed=3)
    np.testing.assert_allclose(mc.half_width, linear.U[0], rtol=0.05)


def test_device_misalignment_row_is_absent_unless_given():
    readings, fit = _fit("four-mount-64")
    cal = calibration_of(fit, readings)
    names = [s.name for s in sources(cal, TypeBInputs())]
    assert "device misalignment estimates" not in names and "local gravity" in names
    given = sources(cal, TypeBInputs(device_misalignment={"e": 5 * ARCSEC, "a": 5 * ARCSEC}))
    row = next(s for s in given if s.name == "device misalignment estimates")
    assert len(row.components) == 2 and row.u == pytest.approx(5.0)


@pytest.mark.parametrize("value, message", [
    ('"2 V"', "uncertainty.pitch_index: '2 V': 'V' is not a unit of angle"),
    ("2", "uncertainty.pitch_index: give the unit with the number"),
    ('"-2 arcsec"', "must be a finite half-width"),
])
def test_a_type_b_entry_in_the_wrong_unit_is_one_line(tmp_path, value, message):
    from labcal.config.station import load_certificate_section

    path = tmp_path / "station.toml"
    path.write_text(f"[uncertainty]\npitch_index = {value}\n")
    with pytest.raises(LabcalError, match=None) as info:
        load_certificate_section(path)
    assert message in str(info.value) and str(path) in str(info.value) and "\n" not in str(info.value)
    path.write_text('[uncertainty]\npitch_index = "7.2 arcmin"\n')
    assert load_certificate_section(path).uncertainty.pitch_index == pytest.approx(432 * ARCSEC)


def test_certificate_states_both_estimators_and_undefined_near_90(tmp_path):
    """The closed form's U95 beside the sphere's; with the envelope reaching ±90° it is "undefined"
    there (None in the JSON), never a number like 1e148."""
    from labcal.analysis.attitude import closed_form
    from labcal.config.settings import CertificateSettings
    from labcal.documents.issuing import attitude_envelope

    readings, fit = _fit("four-mount-64")
    cal = calibration_from_json(fit.to_json(), "fit")
    env = attitude_envelope(cal, CertificateSettings(usage_pitch_deg=(-90, 90), grid_step_deg=10))
    cf = env.closed_form
    assert cf is not None and cf.undefined_points == 2 * 37  # pitch ±90° × every roll
    assert cf.pitch_U95_max_deg is not None and cf.pitch_U95_max_deg < 1  # the finite part stays sane
    assert "both estimators" in cf.statement
    # the closed form's pitch U95 at 60° is larger than the sphere's (about 1.9× in the case)
    g = gravity(np.radians(60.0), 0.0, 0.0, 0.0)[None]
    v = fit.coefficients[0] + g @ fit.coefficients[1:]
    assert closed_form(cal, v).u_pitch[0] > sphere_least_squares(cal, v).u_pitch[0]


def test_local_gravity_row_is_what_the_estimator_does_where_gravity_differs():
    """GUM: u = |c|·a/√3 for local |g| anywhere within ±a = 5e-4 of the calibration's (rectangular),
    with c = ∂(pitch, roll)/∂|g| found here by central differences of the estimator `labcal attitude`
    runs, fed readings of an instrument that sees |g| = 1 ± δ — not by the budget's linear algebra."""
    readings, fit = _fit("four-mount-64")
    cal = calibration_of(fit, readings)
    g = gravity(*AT, 0.0, 0.0)
    delta = 1e-6

    def attitude(scale: float) -> np.ndarray:
        volts = fit.coefficients[0] + scale * (g @ fit.coefficients[1:])
        att = _sphere(fit, volts)
        return np.array([att.pitch[0], att.roll[0]])
    c = (attitude(1 + delta) - attitude(1 - delta)) / (2 * delta)
    expected = np.abs(c) * 5e-4 / np.sqrt(3)
    got = propagate(cal, sources(cal, TypeBInputs()), *AT).contributions["local gravity"][0]
    assert expected[0] > 1e-3 * ARCSEC  # the prior leaves a share in pitch here: a real row
    np.testing.assert_allclose(got, expected, rtol=1e-3)
