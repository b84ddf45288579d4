"""The simulated rig's single- and two-axis instruments (Tripp & Tcheng §6.1–6.5): a package reads
only its sensors' channels, its run is journaled and fitted sensor by sensor, and a drifting
temperature is corrected as Tripp §9.2.1 does."""

from __future__ import annotations

import math
import sqlite3

import numpy as np
import pytest
from conftest import run_on_rig

from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import fit_readings, reference_temperature
from labcal.analysis.models import Model
from labcal.config.emulation import DeviceTruth, InstrumentTruth, RigConfig
from labcal.config.settings import SequencerSettings, SettleSettings
from labcal.run.journal import Journal
from labcal.sim.rig import SimRig

QUIET_DEVICE = DeviceTruth(misalignment_deg={}, index_arcsec=0, wobble_arcsec=0)
NOISE = 50e-6  # V rms per DMM sample
SAMPLES = 10  # averaged per point: a point's noise is NOISE/√10
B_T, S_T = 5e-5, 3e-4  # the x sensor's offset (V/°C) and relative sensitivity (1/°C) coefficients
T_REF_RIG = 20.0  # the simulated instrument's own reference temperature


def instrument(package: str, **rest) -> InstrumentTruth:
    return InstrumentTruth.from_coning(
        b=[0.0123, -0.0081, 0.0047], sensitivity=[4.9871, 5.0124, 4.9958], omega_deg=[0.21, 0.14, 0.09],
        azimuth_deg=[35, -120, 200], noise_v=NOISE, tau_s=0.5, package=package, **rest)


def quiet_settings() -> SequencerSettings:
    """A fixed dwell of 20 time constants: the output's transient is e^-20 of a step, far below the
    noise, so what the fit sees beyond the noise is the instrument's own model."""
    return SequencerSettings(settle=SettleSettings(tau_s=0.5, noise_v=NOISE, samples=SAMPLES,
                                                   fixed_dwell_s=10.0))


def journal_columns(tmp_path) -> list[tuple]:
    with sqlite3.connect(tmp_path / "journal.sqlite") as db:
        return db.execute("SELECT vx, vy, vz, sd_vx, sd_vy, sd_vz FROM points").fetchall()


@pytest.mark.parametrize(("package", "present"), [("single-axis", (0,)), ("two-axis-xy", (0, 1)),
                                                  ("two-axis-xz", (0, 2))])
def test_a_package_journals_only_its_sensors_and_is_fitted_sensor_by_sensor(tmp_path, package, present):
    """Every point of a four-mount run of a package has its sensors' outputs and NULL in the columns
    of the sensors it lacks; the run's fit has a column per sensor present, each within 3 standard
    errors of the simulator's truth (no device misalignment, so the linear model is exact)."""
    truth = instrument(package)
    rig = SimRig(RigConfig(device=QUIET_DEVICE, instrument=truth), seed=5)
    result = run_on_rig(rig, "four-mount-64", tmp_path, quiet_settings())
    rows = journal_columns(tmp_path)
    assert len(rows) == 64
    for row in rows:
        for j in range(3):
            assert (row[j] is None) == (j not in present) and (row[3 + j] is None) == (j not in present)
    fit = result.fit
    assert fit.sensors == tuple("xyz"[j] for j in present)
    z = (fit.coefficients - truth.X[:, list(present)]) / fit.stderr[:4]
    assert np.all(np.abs(z) < 3), z


def test_a_single_sensor_checks_the_mount_by_its_x_direction_only(tmp_path):
    """A single x sensor sees the sign of g_x at the check attitude: it tells y = 0° from y = 180°
    (and the run says that is all it verified), not the top of the plate from the bottom."""
    from labcal.analysis.kinematics import MOUNTS
    from labcal.run.mounting import distinguishes, expected_gravity, identify

    for mount in MOUNTS:
        g = expected_gravity(mount)
        volts = np.array([5 * g[0], np.nan, np.nan])
        assert identify(volts, None, mount) == mount
        wrong_x = [m for m in MOUNTS if np.sign(expected_gravity(m)[0]) != np.sign(g[0])]
        assert all(identify(volts, None, m) != m for m in wrong_x)
        assert not distinguishes(volts)
        for kept in ((0, 1), (0, 2)):  # x–y and x–z: the four mounts differ in sign on the two axes
            two = np.full(3, np.nan)
            two[list(kept)] = 5 * g[list(kept)]
            assert distinguishes(two)
            assert all(identify(two, None, m) == mount for m in MOUNTS)


@pytest.mark.slow
def test_a_simulated_single_axis_calibration_drifting_one_degree_is_corrected_as_tripp_does(tmp_path):
    """Tripp §9.2.1's design (pitch −30..30° by 5°, roll −180..180° by 15° with 180° repeated, six
    replications: 1950 points) on a simulated single-axis sensor whose temperature rises about 1 °C
    over the run: with the temperature terms (Table 2 footnote b) every coefficient is within 3
    standard errors of the simulator's truth moved to the fit's reference temperature, the
    sensitivity's temperature term is significant (T_S), and the residual SD is within 10 % of a
    point's noise (σ/√10), which it is not without them. (~25 s.)"""
    from labcal.analysis.plan import Plan

    pitch, roll = np.meshgrid(np.arange(-30, 31, 5.0), np.arange(-180, 181, 15.0), indexing="ij")
    plan = Plan(name="tripp-9-2-1", mounts=[(0.0, 0.0)], replicates=6,
                points=[(float(p), float(r)) for p, r in zip(pitch.ravel(), roll.ravel(), strict=True)])
    assert plan.n_points == 1950
    plan_file = tmp_path / "tripp-9-2-1.toml"
    from labcal.config.plans import plan_toml

    plan_file.write_text(plan_toml(plan))
    truth = instrument("single-axis", tc_bias_v_per_c=[B_T, 0, 0], tc_scale_per_c=[S_T, 0, 0])
    # 1950 points of ~14 s each (move, 10 s dwell, 10 samples at 0.2 s): about 7.7 h of rig time
    rig = SimRig(RigConfig(device=QUIET_DEVICE, instrument=truth, lab_temp_swing_c=0.0,
                           lab_temp_drift_c_per_h=0.13), seed=921)
    run_on_rig(rig, str(plan_file), tmp_path, quiet_settings())
    with Journal(tmp_path / "journal.sqlite") as journal:
        readings = journal.readings(1)
    span = np.ptp(readings.temp_c)
    assert 0.8 < span < 1.2  # the design's drift: about 1 °C, as Tripp's 13 h calibration
    point_noise = NOISE / math.sqrt(SAMPLES)

    plain = fit_readings(readings)
    assert plain.sensors == ("x",)
    assert plain.ls.residual_se[0] > 1.5 * point_noise

    t_ref = reference_temperature(readings)
    corrected = fit_readings(readings, Model(("temperature",), t_ref=t_ref))
    assert corrected.names[4:] == ("dB/dT", "dS_x/dT", "dS_y/dT", "dS_z/dT")
    # the truth at t_ref, by hand: b(T) = b + b_T·(T − 20), s(T) = s·(1 + S_T·(T − 20)) (the
    # simulator's model, InstrumentTruth.static_volts); d/dT of each is b_T and s·S_T
    dt = t_ref - T_REF_RIG
    s_column = truth.X[1:, 0]
    expected = np.concatenate([[truth.B[0] + B_T * dt], s_column * (1 + S_T * dt), [B_T], s_column * S_T])
    coef, se = corrected.ls.coef[:, 0], corrected.stderr[:, 0]
    assert np.all(np.abs(coef - expected) <= 3 * se), (coef - expected) / se
    t_s = coef[5] / se[5]  # dS_x/dT: Tripp Table 2's T_S of the main sensitivity
    assert abs(t_s) > float(t_quantile(0.975, corrected.variance_dof[0]))
    assert corrected.ls.residual_se[0] == pytest.approx(point_noise, rel=0.10)
