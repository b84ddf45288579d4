"""Pitch and roll from voltages: exactness, honest uncertainty, the ±90° singularity, the CLI."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import FOUR_MOUNTS, soto_plan

from labcal.analysis.attitude import Calibration, closed_form, sphere_least_squares
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import gravity
from labcal.analysis.plan import Plan
from labcal.cli import main
from labcal.config.emulation import InstrumentTruth
from labcal.documents.certificate import load_calibration
from labcal.errors import LabcalError
from labcal.sim.direct import simulate_readings

TRUTH = InstrumentTruth.from_coning(b=[0.0123, -0.0081, 0.0047], sensitivity=[4.9871, 5.0124, 4.9958],
                                    omega_deg=[0.21, 0.14, 0.09], azimuth_deg=[35, -120, 200])


def exact_calibration(reading_sd=(1e-5, 1e-5, 1e-5)) -> Calibration:
    return Calibration(TRUTH.X, np.zeros((3, 4, 4)), np.array(reading_sd), dof=1000)


def volts_at(pitch_deg, roll_deg) -> np.ndarray:
    return TRUTH.static_volts(gravity(np.radians(pitch_deg), np.radians(roll_deg), 0, 0))


@pytest.mark.parametrize("method", [closed_form, sphere_least_squares])
def test_noise_free_voltages_give_the_attitude_back(method):
    rng = np.random.default_rng(1)
    pitch, roll = rng.uniform(-89, 89, 1000), rng.uniform(-180, 180, 1000)
    att = method(exact_calibration(), volts_at(pitch, roll))
    assert np.allclose(np.degrees(att.pitch), pitch, atol=1e-9)
    assert np.allclose((np.degrees(att.roll) - roll + 180) % 360 - 180, 0, atol=1e-9)


@pytest.mark.parametrize("method", [closed_form, sphere_least_squares])
def test_stated_uncertainty_matches_the_scatter(method):
    """With unequal sensor noise (σ_y = σ_z = 4 σ_x) the errors' spread equals u to within 3 %."""
    sd = np.array([1e-5, 4e-5, 4e-5])
    rng = np.random.default_rng(2)
    pitch, roll = rng.uniform(-70, 70, 40000), rng.uniform(-180, 180, 40000)
    v = volts_at(pitch, roll) + rng.normal(0, 1, (40000, 3)) * sd
    att = method(exact_calibration(sd), v)
    z_pitch = (np.degrees(att.pitch) - pitch) / np.degrees(att.u_pitch)
    z_roll = ((np.degrees(att.roll) - roll + 180) % 360 - 180) / np.degrees(att.u_roll)
    assert np.std(z_pitch) == pytest.approx(1, abs=0.03) and np.std(z_roll) == pytest.approx(1, abs=0.03)


@pytest.mark.parametrize("pitch", [0.0, 30.0, 75.0])
def test_sphere_uncertainty_follows_tripp_eq_108(pitch):
    """Equal sensor noise: eq. 108 gives σ_α = σ and σ_R = σ / cos α (σ in g: volts / S ≈ 5 V/g).
    Unequal noise (σ_y = σ_z = 10 σ_x): the weighted solution's σ_α = (cos²α/σ_x² + sin²α/σ_y²)^−½,
    never worse than eq. 108's unweighted σ_α² = σ_x² cos²α + σ_y² sin²α, nor than the closed form."""
    v = volts_at(np.array([pitch]), np.array([40.0]))
    alpha = np.radians(pitch)
    equal = sphere_least_squares(exact_calibration((1e-5, 1e-5, 1e-5)), v)
    assert equal.u_pitch[0] == pytest.approx(1e-5 / 5, rel=0.01)
    assert equal.u_roll[0] == pytest.approx(1e-5 / 5 / np.cos(alpha), rel=0.01)
    sx, sy = 1e-5 / 5, 1e-4 / 5
    cal = exact_calibration((1e-5, 1e-4, 1e-4))
    weighted = sphere_least_squares(cal, v)
    information = np.cos(alpha) ** 2 / sx**2 + np.sin(alpha) ** 2 / sy**2
    assert weighted.u_pitch[0] == pytest.approx(information**-0.5, rel=0.01)
    assert weighted.u_pitch[0] <= np.sqrt((sx * np.cos(alpha)) ** 2 + (sy * np.sin(alpha)) ** 2) * 1.01
    assert weighted.u_pitch[0] <= closed_form(cal, v).u_pitch[0] * (1 + 1e-9)


def test_roll_is_undefined_at_pitch_90():
    cal = exact_calibration()
    v = volts_at(np.array([90.0, -90.0, 89.0]), np.array([30.0, 30.0, 30.0]))
    for method in (closed_form, sphere_least_squares):
        att = method(cal, v)
        assert att.roll_defined.tolist() == [False, False, True]
        assert np.allclose(np.degrees(att.pitch[:2]), [90, -90], atol=1e-6)
    assert np.isfinite(sphere_least_squares(cal, v).u_pitch).all()
    # asin has no usable slope at |g_x| = 1: the closed form's pitch uncertainty is undefined there,
    # never a number like 1e148°
    assert np.isnan(closed_form(cal, v).u_pitch).tolist() == [True, True, False]


def test_95_percent_intervals_cover_when_the_calibration_is_uncertain_too():
    """400 noisy calibrations, each converting 50 noisy readings: the U95 intervals of the sphere
    solution cover the true pitch and roll 93–97 % of the time."""
    plan = Plan(**{**soto_plan(FOUR_MOUNTS).model_dump(), "replicates": 1})
    rng = np.random.default_rng(11)
    hits_p, hits_r = [], []
    for seed in range(400):
        fit = fit_readings(simulate_readings(plan, TRUTH, noise_v=5e-5, seed=seed))
        doc = fit.to_json()
        cal = Calibration(fit.coefficients, np.array(doc["covariance"])[:, :4, :4],
                          np.array(doc["reading_sd"]), fit.ls.dof)
        pitch, roll = rng.uniform(-60, 60, 50), rng.uniform(-180, 180, 50)
        att = sphere_least_squares(cal, volts_at(pitch, roll) + rng.normal(0, 5e-5, (50, 3)))
        hits_p.append(np.abs(np.degrees(att.pitch) - pitch) <= np.degrees(att.U_pitch))
        err_r = (np.degrees(att.roll) - roll + 180) % 360 - 180
        hits_r.append(np.abs(err_r) <= np.degrees(att.U_roll))
    assert 0.93 <= np.mean(hits_p) <= 0.97 and 0.93 <= np.mean(hits_r) <= 0.97


def test_cli_attitude_from_a_fit(tmp_path, capsys):
    readings = tmp_path / "r.csv"
    assert main(["simulate", "--noise", "1e-5", "--seed", "3", "--out", str(readings)]) == 0
    capsys.readouterr()
    assert main(["fit", str(readings), "--json"]) == 0
    fit_path = tmp_path / "fit.json"
    fit_path.write_text(capsys.readouterr().out)
    volts = tmp_path / "v.csv"
    # the fit is of an ideal instrument (B = 0, S = I): feed it what that instrument reads
    v = gravity(np.radians([10.0, 90.0]), np.radians([20.0, 0.0]), 0, 0)
    rows = "\n".join(f"p{i},{a},{b},{c}" for i, (a, b, c) in enumerate(v))
    volts.write_text(f"note,vx,vy,vz\n{rows}\n")
    assert main(["attitude", "--cert", str(fit_path), "--csv", str(volts), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    first, second = doc["rows"]
    for method in ("closed_form", "sphere_least_squares"):
        assert first[method]["pitch_deg"] == pytest.approx(10, abs=1e-3)
        assert first[method]["roll_deg"] == pytest.approx(20, abs=1e-3)
        assert 0 < first[method]["U95_pitch_deg"] < 0.01
        assert second[method]["roll_deg"] is None and "roll is undefined" in second[method]["roll_note"]
    assert main(["attitude", "--cert", str(fit_path), "--csv", str(volts), "--method", "sphere"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("row,ls_pitch_deg,ls_roll_deg,ls_u_pitch_deg") and len(lines) == 3
    assert lines[2].split(",")[2] == ""  # undefined roll is an empty cell


@pytest.mark.parametrize("content,expected", [
    ("{not json", "not valid JSON"),
    ('{"model": "linear"}', "not a labcal fit or certificate"),
    ('{"coefficients": [[1, 2, 3]], "covariance": [], "residual_standard_error": [1, 1, 1], '
     '"degrees_of_freedom": 3}', "coefficients must be 4×3"),
])
def test_bad_calibration_files(tmp_path, capsys, content, expected):
    path = tmp_path / "fit.json"
    path.write_text(content)
    with pytest.raises(LabcalError, match=re.escape(f"{path}: {expected}")):  # a user error: exit 2, one line
        load_calibration(path)
    assert main(["attitude", "--cert", str(path), "--csv", str(path)]) == 2
    assert expected in capsys.readouterr().err


def test_sphere_pitch_near_the_pole_does_not_assume_a_roll():
    """Within the noise of ±90° roll is undefined and not estimated, but gravity's small horizontal
    part still has a direction: pitch is then 90° minus its size whichever way it points. Holding
    roll at 0° instead made pitch wrong by the whole horizontal part where gravity leans sideways."""
    cal = exact_calibration(reading_sd=(5e-4, 5e-4, 5e-4))  # u_h ≈ 1e-4 g: 0.002° of lean is within it
    lean_deg = 0.002
    for roll_deg in (0.0, 90.0, -135.0):
        v = volts_at(np.array([90.0 - lean_deg]), np.array([roll_deg]))
        att = sphere_least_squares(cal, v)
        assert not att.roll_defined[0]
        # noise-free volts: pitch exactly 90° − lean, whatever the roll (1e-7°: iteration round-off)
        assert np.degrees(att.pitch[0]) == pytest.approx(90.0 - lean_deg, abs=1e-7), roll_deg
