"""The simulated rig's single- and two-axis instruments (Tripp & Tcheng §6.1–6.5): a package reads
only its sensors' channels, its run is journaled and fitted sensor by sensor, and a drifting
temperature is corrected as Tripp §9.2.1 does."""

from __future__ import annotations

import json
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
from labcal.sim.rig import SimRig
from labcal.store.journal import Journal

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
        assert identify(volts, None, mount)[0] == mount
        wrong_x = [m for m in MOUNTS if np.sign(expected_gravity(m)[0]) != np.sign(g[0])]
        assert all(identify(volts, None, m)[0] != m for m in wrong_x)
        assert not distinguishes(volts)
        for kept in ((0, 1), (0, 2)):  # x–y and x–z: the four mounts differ in sign on the two axes
            two = np.full(3, np.nan)
            two[list(kept)] = 5 * g[list(kept)]
            assert distinguishes(two)
            assert all(identify(two, None, m)[0] == mount for m in MOUNTS)


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


# --- the certificate's statement of a package (labcal.documents.package) --------------------------
def _fitted(package: str, seed: int, noise: float = 2e-3):
    """A package fitted from simulated readings over a D1 design (pitch −90..90° by 10°, roll
    −180..165° by 15°, two replicates), the outputs the simulator's static model gives."""
    from labcal.analysis.fit import fit_readings
    from labcal.analysis.kinematics import nominal_gravity
    from labcal.analysis.readings import Readings

    truth = instrument(package)
    pitch, roll = (a.ravel() for a in np.meshgrid(np.arange(-90, 91, 10.0), np.arange(-180, 180, 15.0),
                                                  indexing="ij"))
    pitch, roll = np.tile(pitch, 2), np.tile(roll, 2)
    g = nominal_gravity(np.radians(pitch), np.radians(roll), 0.0, 0.0)
    v = truth.static_volts(g) + np.random.default_rng(seed).normal(0.0, noise, size=g.shape)
    v[:, [j for j in range(3) if j not in truth.channels]] = np.nan
    zero = np.zeros(len(pitch))
    rep = np.repeat([1, 2], len(pitch) // 2)
    return fit_readings(Readings(replicate=rep, y_deg=zero, u_deg=zero, pitch_deg=pitch, roll_deg=roll,
                                 volts=v))


def _linear_output(fit, j: int, alpha, roll):
    """The fitted sensor's output B + s·g at (α, R) (rad), written out here from labcal's linear
    model, not from Tripp's eqs. 14-16."""
    g = np.array([np.sin(alpha), np.cos(alpha) * np.sin(roll), np.cos(alpha) * np.cos(roll)])
    return fit.coefficients[0, j] + np.tensordot(fit.coefficients[1:, j], g, axes=1)


def test_a_single_axis_certificate_states_pitch_u95_at_a_measured_roll_as_eqs_80_to_82_give():
    """The stated U95 of pitch at a roll the table sets (σ_R = 0.05°), recomputed by hand at the
    attitude the section names: σ_v from the fit's covariance and reading SD (fᵀCf + s²), f_α and
    f_R by central differences of the fitted linear output, σ_α = √(σ_v² + f_R²σ_R²)/|f_α| (the
    linearised inversion of eq. 79) times k; and the worst attitude is at the envelope's pitch edge."""
    from labcal.documents.package import package_section

    fit = _fitted("single-axis", 1)
    sec = package_section(fit, "single-axis", "table", 0.05, (-60.0, 60.0), (-30.0, 30.0))
    assert sec.equations.endswith("79-82") and sec.pitch_u95_at_deg is not None
    a, r = np.radians(sec.pitch_u95_at_deg)
    h = 1e-6
    f_a = (_linear_output(fit, 0, a + h, r) - _linear_output(fit, 0, a - h, r)) / (2 * h)
    f_r = (_linear_output(fit, 0, a, r + h) - _linear_output(fit, 0, a, r - h)) / (2 * h)
    f = np.array([1.0, np.sin(a), np.cos(a) * np.sin(r), np.cos(a) * np.cos(r)])
    sigma_v2 = f @ fit.covariance(0)[:4, :4] @ f + fit.new_measurement_variance()[0]
    sigma = np.sqrt(sigma_v2 + (f_r * np.radians(0.05)) ** 2) / abs(f_a)
    assert sec.pitch_u95_deg == pytest.approx(np.degrees(sec.k * sigma), rel=1e-5)
    assert abs(sec.pitch_u95_at_deg[0]) == 60.0  # cos α smallest at the envelope's pitch edge (eq. 81)
    assert sec.k == pytest.approx(float(t_quantile(0.975, fit.variance_dof[0])))
    none = package_section(fit, "single-axis", "none", None, (-60.0, 60.0), (-30.0, 30.0))
    assert none.usage_roll_deg == (0.0, 0.0) and none.equations.endswith("76-78")
    assert none.pitch_u95_deg < sec.pitch_u95_deg  # no roll error, roll 0 only


def test_a_two_axis_xy_certificates_usable_range_holds_its_u95_by_monte_carlo_and_avoids_the_singularity():
    """An x–y package fitted from noisy readings: its stated usable range (U95 ≤ 0.5°) lies clear of
    the attitudes where det F_z vanishes (R = ±90°, α = ±90°, Tripp eq. 86 — det computed here by
    central differences of the fitted linear outputs) and, at its centre, corners and edge
    midpoints, Monte Carlo of the use (coefficients drawn from their covariance, a new reading's
    noise, pitch and roll inferred by Newton–Raphson) keeps both angles' 95th percentile error
    within the stated limit (2000 draws each; tolerance 10 %: the percentile's own scatter); one
    degree beyond the range's pitch edge, at the roll edge, the stated limit is exceeded, as the
    range's largest-area rule says some attitude just outside must."""
    from labcal.analysis.packages import from_linear, infer
    from labcal.documents.package import package_section

    fit = _fitted("two-axis-xy", 2)
    sec = package_section(fit, "two-axis-xy", "inferred", None, (-60.0, 60.0), (-60.0, 60.0), 0.5)
    assert sec.usable_pitch_deg is not None and sec.usable_roll_deg is not None
    p_max, r_max = sec.usable_pitch_deg[1], sec.usable_roll_deg[1]
    assert 0 < p_max < 90 and 0 < r_max < 90

    a, r = np.meshgrid(np.radians(np.linspace(-p_max, p_max, 61)), np.radians(np.linspace(-r_max, r_max, 61)),
                       indexing="ij")
    h = 1e-6

    def grad(j):
        return ((_linear_output(fit, j, a + h, r) - _linear_output(fit, j, a - h, r)) / (2 * h),
                (_linear_output(fit, j, a, r + h) - _linear_output(fit, j, a, r - h)) / (2 * h))

    (xa, xr), (ya, yr) = grad(0), grad(1)
    det = xa * yr - xr * ya
    assert np.all(np.sign(det) == np.sign(det[30, 30])) and np.min(np.abs(det)) > 0.05 * np.abs(det[30, 30])

    rng = np.random.default_rng(86)
    reading = np.sqrt(fit.new_measurement_variance())
    n = 2000
    draws = [rng.multivariate_normal(np.concatenate([[fit.coefficients[0, j]], fit.coefficients[1:, j]]),
                                     fit.covariance(j)[:4, :4], size=n) for j in range(2)]

    def u95(alpha_deg, roll_deg):
        al, ro = np.radians(alpha_deg), np.radians(roll_deg)
        g = np.array([np.sin(al), np.cos(al) * np.sin(ro), np.cos(al) * np.cos(ro)])
        v = np.column_stack([d[:, 0] + d[:, 1:] @ g + rng.normal(0, reading[j], n)
                             for j, d in enumerate(draws)])
        sensors = [from_linear(fit.coefficients[0, j], fit.coefficients[1:, j], "xy"[j]) for j in range(2)]
        z = infer(sensors, v, (al, ro))
        return np.degrees(np.percentile(np.abs(z - [al, ro]), 95, axis=0))

    for at in ((0, 0), (p_max, r_max), (-p_max, -r_max), (p_max, 0), (0, -r_max), (-p_max, r_max)):
        assert np.all(u95(*at) <= 0.5 * 1.10), (at, u95(*at))
    beyond = max(u95(p_max + 1, r_max).max(), u95(p_max, r_max + 1).max())
    assert beyond > 0.5 * 0.9


def test_labcal_run_sim_single_axis_ends_in_a_sealed_certificate_with_its_package(tmp_path, capsys):
    """`labcal run --sim --instrument single-axis`: the journal holds vx only (vy, vz NULL), fit.json
    one column, and the run ends in the sealed certificate (digest verified on reading), its DCC
    (valid against PTB's schema, one result per sensor the package has) and its report, the
    certificate's package section stating pitch's U95 at the roll the table sets, with σ_R the roll
    table's ±2″ index error as uniform bounds (2″/√3), by Tripp eqs. 79-82; its budget's pitch
    total is that U95; the end-of-run checks judged the package's readings."""
    from xml.etree import ElementTree as ET

    from cli import cli

    from labcal.documents.certificate import read_certificate
    from labcal.documents.dcc import validation_error

    code, out, err = cli(capsys, "run", "--sim", "--instrument", "single-axis", "--yes", "--out",
                         str(tmp_path / "run"), "--db", str(tmp_path / "lab.sqlite"))
    assert code == 0, err
    with sqlite3.connect(tmp_path / "lab.sqlite") as db:
        rows = db.execute("SELECT vx, vy, vz FROM points").fetchall()
        checks = [m for (m,) in db.execute("SELECT message FROM events WHERE kind = 'checks'")]
    assert len(rows) == 64 and all(x is not None and y is None and z is None for x, y, z in rows)
    assert checks and checks[-1].startswith("the readings pass the checks of their fit; the x sensor(s)")
    fit = json.loads((tmp_path / "run" / "fit.json").read_text())
    assert fit["layout"]["columns"] == ["sensor x"]
    cert = read_certificate(tmp_path / "run" / "certificate.json")
    statement = cert.package
    assert statement is not None and statement.package == "single-axis" and statement.roll_in_use == "table"
    assert statement.roll_sd_deg == pytest.approx(2 / 3600 / math.sqrt(3))
    assert statement.equations == "Tripp & Tcheng eqs. 79-82" and statement.pitch_u95_deg > 0
    assert np.shape(cert.fit.coefficients) == (4, 1) and np.shape(cert.U) == (4, 1)
    assert cert.uncertainty_budget is not None
    (total,) = cert.uncertainty_budget.totals  # pitch only: a single sensor does not infer roll
    assert total.angle == "pitch" and total.U95_arcsec == pytest.approx(statement.pitch_u95_deg * 3600)
    assert cert.attitude.pitch_U95_max_deg == pytest.approx(statement.pitch_u95_deg)
    assert cert.attitude.roll_U95_max_deg is None
    dcc = (tmp_path / "run" / "certificate.dcc.xml").read_bytes()
    assert validation_error(dcc) is None
    labels = [e.text for e in ET.fromstring(dcc).iter("{https://ptb.de/si}label")]
    assert "B_x" in labels and not any(label.endswith(("_y", "_z")) for label in labels if label)
    assert (tmp_path / "run" / "report.pdf").stat().st_size > 0
    with sqlite3.connect(tmp_path / "lab.sqlite") as db:
        low, high, mean = db.execute("SELECT MIN(temp_c), MAX(temp_c), AVG(temp_c) FROM points "
                                     "WHERE status = 'ok'").fetchone()
    assert statement.temperature_c == pytest.approx([low, high])
    assert statement.t_ref_c == pytest.approx(mean)  # the coefficients refer to the run's mean
    code, _, err = cli(capsys, "report", str(tmp_path / "run"), "--db", str(tmp_path / "lab.sqlite"))
    assert code == 0, err
    assert read_certificate(tmp_path / "run" / "certificate.json").package == statement


def test_instrument_is_the_simulated_rigs_option_only(tmp_path, capsys):
    from cli import cli

    code, _, err = cli(capsys, "run", "--station", "bench", "--instrument", "single-axis", "--dry-run")
    assert code == 2 and err.count("\n") == 1 and "--instrument" in err


def test_a_single_axis_statements_pitch_u95_covers_95_percent_by_monte_carlo():
    """At the attitude where the statement's U95 is largest: the true sensor drawn about the fitted
    one from its covariance, a new reading's noise, and the table's roll off by σ_R = 0.05°; pitch
    inferred from the fitted sensor at the roll read (eq. 79, written out here from the linear model
    by Newton's method on α) is within the stated U95 95 ± 2 % of 4000 draws (standard error 0.35 %)."""
    from labcal.documents.package import package_section

    fit = _fitted("single-axis", 7)
    sec = package_section(fit, "single-axis", "table", 0.05, (-60.0, 60.0), (-30.0, 30.0))
    assert sec.pitch_u95_at_deg is not None and sec.pitch_u95_deg is not None
    alpha, roll = np.radians(sec.pitch_u95_at_deg)
    rng = np.random.default_rng(81)
    n = 4000
    coef = np.concatenate([[fit.coefficients[0, 0]], fit.coefficients[1:, 0]])
    true = rng.multivariate_normal(coef, fit.covariance(0)[:4, :4], size=n)
    g = np.array([np.sin(alpha), np.cos(alpha) * np.sin(roll), np.cos(alpha) * np.cos(roll)])
    v = true[:, 0] + true[:, 1:] @ g + rng.normal(0, np.sqrt(fit.new_measurement_variance()[0]), n)
    roll_read = roll + np.radians(0.05) * rng.normal(size=n)
    a = np.full(n, alpha)
    across = coef[2] * np.sin(roll_read) + coef[3] * np.cos(roll_read)  # s_y·sin R + s_z·cos R
    for _ in range(20):  # Newton on v = B + s·g(α, R_read) in α
        model = coef[0] + coef[1] * np.sin(a) + np.cos(a) * across
        a = a + (v - model) / (coef[1] * np.cos(a) - np.sin(a) * across)
    covered = np.mean(np.abs(np.degrees(a - alpha)) <= sec.pitch_u95_deg)
    assert 0.93 <= covered <= 0.97, covered


@pytest.mark.parametrize(("package", "equations", "field"), [
    ("two-axis-xy", "Tripp & Tcheng eqs. 83-90", "usable_pitch_deg"),
    ("two-axis-xz", "Tripp & Tcheng eqs. 96-98 with eq. 80", "pitch_u95_deg")])
def test_labcal_run_sim_two_axis_states_its_package(tmp_path, capsys, package, equations, field):
    """An x–y package infers roll and states its usable range; an x–z package, singular at roll 0
    (eq. 94), is stated at the roll the table sets (eqs. 96-98)."""
    from cli import cli

    from labcal.documents.certificate import read_certificate

    code, _, err = cli(capsys, "run", "--sim", "--instrument", package, "--yes", "--out",
                       str(tmp_path / "run"), "--db", str(tmp_path / "lab.sqlite"))
    assert code == 0, err
    statement = read_certificate(tmp_path / "run" / "certificate.json").to_json()["package"]
    assert statement["package"] == package and statement["equations"] == equations and field in statement


def test_a_package_whose_certificate_cannot_be_made_keeps_its_complete_run(tmp_path, capsys):
    """An x–y package with a U95 limit no attitude meets (1e-6°): the run completes, its readings
    and fit are kept, and it ends in one line saying why there is no certificate."""
    from cli import cli

    code, out, err = cli(capsys, "run", "--sim", "--instrument", "two-axis-xy", "--yes", "--tolerance-deg",
                         "1e-6", "--out", str(tmp_path / "run"), "--db", str(tmp_path / "lab.sqlite"))
    last = err.rstrip("\n").rsplit("\n", 1)[-1]  # the console's progress is on stderr before it
    assert code == 2 and last.startswith("labcal: error: the two-axis-xy package cannot infer pitch and roll "
                                         "with U95 ≤ 1e-06°"), err
    assert "Traceback" not in out + err
    assert (tmp_path / "run" / "fit.json").exists() and not (tmp_path / "run" / "certificate.json").exists()
    with sqlite3.connect(tmp_path / "lab.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM points WHERE status = 'ok'").fetchone() == (64,)
