"""A run of a plan that relies on a device correction: `labcal run` checks the correction
still applies, fits with the calibration device's misalignments held at its values and carries their u
as a Type B input, and the certificate, the report and the DCC say so.

Expectations come from the simulator, not from the fit: the coefficients are compared with the
simulated instrument's truth at the run's own temperature and time (the rig's `InstrumentTruth`
model: tempco and drift, evaluated here by hand), the misalignments corrected for with the rig's
configured ones, the rig time with four-mount-64's run on the same rig; the Monte Carlo draws the
device's true misalignments around the correction with its stated u, simulates each run with the
simulator's noise, index errors and wobble, and counts how often the stated U95 covers the attitude
error of new readings against the attitude the simulator put them at.
"""

from __future__ import annotations

import csv
import json
import math
import tomllib

import numpy as np
import pytest
from simulated_runs import characterised_device, corrected_runs_under_a_step, days_ago

from labcal.analysis.attitude import LOCAL_GRAVITY_U, sphere_least_squares
from labcal.analysis.attitude import Calibration as AttitudeCalibration
from labcal.analysis.budget import calibration_of, propagate, sources
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble, Misalignment, gravity
from labcal.analysis.plan import Plan
from labcal.cli import main
from labcal.config.corrections import DeviceCorrectionTable
from labcal.config.emulation import RigConfig
from labcal.config.plans import correction_toml, plan_correction, plan_toml
from labcal.documents import device_history
from labcal.documents.certificate import read_certificate
from labcal.documents.device_history import DeviceEstimate
from labcal.sim.direct import simulate_readings
from labcal.store.exports import run_fits

RIG = RigConfig()  # the simulated rig of `labcal run --sim`
ROW = "device misalignment estimates"  # the budget's row of the device's misalignments


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# --- (a) end to end on the simulated rig -----------------------------------------------------------
def truth_at_the_run(run_dir) -> np.ndarray:
    """The simulated instrument's coefficients at the run's mean temperature and time, by hand from
    the rig's instrument model (`InstrumentTruth.static_volts`: B + drift·t + tc_bias·ΔT, and S scaled
    by 1 + tc_scale·ΔT), the truth run.json states at its reference (20 °C, t = 0) moved there."""
    run = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    X = np.array(run["simulated_truth"]["coefficients"])
    with open(run_dir / "readings.csv", encoding="utf-8") as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    dt = float(np.mean([float(r["temp_c"]) for r in rows])) - RIG.instrument.t_ref_c
    hours = float(np.mean([float(r["time_s"]) for r in rows])) / 3600
    inst = RIG.instrument
    X[0] += np.array(inst.drift_v_per_h) * hours + np.array(inst.tc_bias_v_per_c) * dt
    X[1:] *= 1 + np.array(inst.tc_scale_per_c) * dt
    return X


@pytest.mark.slow
def test_a_run_of_the_corrected_plan_applies_the_correction_and_states_it(tmp_path, capsys):
    """Two earlier sittings (other seeds, other days) and a four-mount-64 dry run today characterise the
    rig's device; `plan optimize --device SIMULATED` for 6 × the U95 that run's certificate states
    (where the correction pays: a corrected plan carries each misalignment at a third of the change its
    run would detect, 2–4″ here) leaves out a remount; its run completes on the same rig, fits with the
    misalignments corrected for, is within U of the simulator's truth, states a U95 within the target
    and takes less rig time."""
    db = str(tmp_path / "lab.sqlite")
    characterised_device(tmp_path / "lab.sqlite", (31, 32))
    assert main(["run", "--sim", "--yes", "--db", db, "--out", str(tmp_path / "first")]) == 0
    assert main(["run", "--sim", "--yes", "--db", db, "--out", str(tmp_path / "second"), "--no-report"]) == 0
    # the target where the correction pays, from what four-mount-64's certificate states (the
    # optimizer's prediction of it is built by the certificate's rule: test_optimizer_promise)
    first = read_certificate(tmp_path / "first" / "certificate.json").attitude
    target = 6.0 * max(first.pitch_U95_max_deg, first.roll_U95_max_deg)
    capsys.readouterr()
    plan_file, run_dir = tmp_path / "fast.toml", tmp_path / "fast"
    assert main(["plan", "optimize", "--target-attitude-u95-deg", repr(target), "--device", "SIMULATED",
                 "--db", db, "--out", str(plan_file), "--json"]) == 0
    planned = json.loads(capsys.readouterr().out)
    assert len(planned["mounts"]) < 4 and planned["device_correction"]["source"] == "second"
    assert main(["run", "--sim", "--yes", "--db", db, "--plan", str(plan_file), "--samples",
                 str(planned["samples"]), "--out", str(run_dir)]) == 0
    captured = capsys.readouterr()
    printed = " ".join((captured.out + captured.err).split())  # however the terminal wraps it
    assert "held at device SIMULATED's estimate from run second" in printed

    cert = read_certificate(run_dir / "certificate.json")  # schema and digest checked
    history = {e.source: e for e in device_history.estimates_for("SIMULATED", db)}
    # the corrected run identifies nothing: stores nothing
    assert set(history) == {"run-1", "run-2", "first", "second"}
    second = history["second"]
    c = cert.device_correction
    assert c is not None and cert.device is None and cert.fit.model == "linear"
    assert (c.device_id, c.source, c.calibrated_utc) == ("SIMULATED", "second", second.calibrated_utc)
    assert c.value_arcsec == pytest.approx(second.value_arcsec, rel=1e-12)
    assert c.U_arcsec == pytest.approx(second.U_arcsec, rel=1e-12)
    # what was corrected for is the rig's device, within the history's U (the simulator's truth)
    truth_mis = RIG.device.misalignment_deg
    for n in MISALIGNMENT_NAMES:
        assert abs(c.value_arcsec[n] - truth_mis[n] * 3600) <= c.U_arcsec[n], n
    # said on the certificate, in its report and in its DCC, with every value and its u
    assert c.statement in cert.statements and "were not measured in this run" in c.statement
    for n in MISALIGNMENT_NAMES:
        assert f"{n} = {c.value_arcsec[n]:.2f}″ (u = {c.u_arcsec[n]:.2f}″)" in c.statement
    assert "were not measured in this run" in (run_dir / "report.html").read_text(encoding="utf-8")
    assert "were not measured in this run" in (run_dir / "certificate.dcc.xml").read_text(encoding="utf-8")
    # the budget shows the term: the plan's u per misalignment, as a Type B input and row
    budget = cert.uncertainty_budget
    assert budget is not None
    assert budget.inputs.device_misalignment == pytest.approx({n: c.u_arcsec[n] * ARCSEC
                                                               for n in MISALIGNMENT_NAMES}, rel=1e-12)
    [row] = [r for r in budget.rows if r.source == ROW]
    assert row.type == "B" and row.added and "from device SIMULATED's estimate from run second" in row.note
    assert row.standard_uncertainty == pytest.approx(max(c.u_arcsec.values()), rel=1e-12)
    assert row.pitch_worst_arcsec > 0
    # the coefficients are within their U of the simulated instrument at the run's conditions
    X, U = np.array(cert.fit.coefficients), np.array(cert.expanded_uncertainty.U)
    assert np.all(np.abs(X - truth_at_the_run(run_dir)) <= U), np.abs(X - truth_at_the_run(run_dir)) / U
    # the stated U95 is within the target; the run's rig time is what the issue asked
    assert max(cert.attitude.pitch_U95_max_deg, cert.attitude.roll_U95_max_deg) <= target
    rig = [json.loads((tmp_path / name / "run.json").read_text())["rig_time_s"] for name in ("first", "fast")]
    # the issue's 0.45× is out of reach for a plan that must see every misalignment it corrects for:
    # three mounts at the least (no pair of mounts reverses all of e, f and k)
    print(f"corrected plan's run: {rig[1] / rig[0]:.3f}× four-mount-64's rig time (target ≤ 0.45×)")
    assert rig[1] / rig[0] <= 0.70


@pytest.mark.slow
def test_a_run_that_sees_the_device_moved_issues_no_certificate_from_the_correction(tmp_path, capsys):
    """The device characterised, the corrected plan written; then the rig's misalignment e moved by 4 of
    the plan's u (a knock between the estimate and the run): the run completes and keeps its readings,
    names the change on one line with the plan that identifies the device again, journals it as an
    event, and writes no certificate; the same run on the unmoved rig is certified."""
    import sqlite3

    db = tmp_path / "lab.sqlite"
    characterised_device(db, (21, 22))
    plan_file = tmp_path / "fast.toml"
    assert main(["plan", "optimize", "--target-attitude-u95-deg", "0.0052", "--device", "SIMULATED",
                 "--db", str(db), "--out", str(plan_file)]) == 0
    text = plan_file.read_text(encoding="utf-8")
    samples = text.split("Run it with --samples ")[1].split()[0]
    correction = plan_correction(text, "the plan")
    assert correction is not None
    moved = dict(RIG.device.misalignment_deg)
    moved["e"] += 4 * correction.u_arcsec["e"] / 3600
    rig = tmp_path / "moved.toml"
    rig.write_text("[device]\nmisalignment_deg = { " + ", ".join(f"{n} = {v!r}" for n, v in moved.items())
                   + " }\n", encoding="utf-8")
    run = ["run", "--sim", "--yes", "--db", str(db), "--plan", str(plan_file), "--samples", samples]
    assert main([*run, "--out", str(tmp_path / "same")]) == 0
    assert (tmp_path / "same" / "certificate.json").is_file()
    capsys.readouterr()
    assert main([*run, "--rig", str(rig), "--out", str(tmp_path / "moved")]) == 2
    err = capsys.readouterr().err  # the run's progress, then the one line
    [line] = [row for row in err.splitlines() if "error:" in row]
    assert "Traceback" not in err
    assert "misalignment e has moved by +" in line and "since its estimate of run run-2" in line, line
    assert "labcal run --plan four-mount-64" in line
    stated = float(line.split("moved by +")[1].split("″")[0])  # within 3 of its null sd of the 8.6″ moved
    assert abs(stated - 4 * correction.u_arcsec["e"]) < 3 * 1.2 * correction.u_arcsec["e"]
    assert not (tmp_path / "moved" / "certificate.json").exists()
    assert (tmp_path / "moved" / "readings.csv").is_file()
    with sqlite3.connect(db) as conn:
        [(message, data)] = conn.execute(
            "SELECT message, data FROM events WHERE kind = 'device_moved'").fetchall()
    assert message.endswith(line.split("error: ", 1)[-1])
    assert any(c["misalignment"] == "e" and c["detected"] for c in json.loads(data)["changes"])
    # a report asked for later is refused the same way: the check belongs to the certificate
    assert main(["report", str(tmp_path / "moved"), "--db", str(db)]) == 2
    assert "misalignment e has moved" in one_line(capsys.readouterr().err)


# --- (b) Monte Carlo of simulated runs of the corrected plan -----------------------------------------
@pytest.fixture(scope="module")
def corrected_plan(tmp_path_factory):
    """The plan `plan optimize --device SIMULATED` writes for an attitude U95 of 0.0052° (about 16 ×
    four-mount-64's U95 on this rig, where relying on the correction pays), its text and the window it
    names."""
    folder = tmp_path_factory.mktemp("corrected")
    db, out = folder / "lab.sqlite", folder / "fast.toml"
    characterised_device(db, (21, 22))
    assert main(["plan", "optimize", "--target-attitude-u95-deg", "0.0052", "--device", "SIMULATED",
                 "--db", str(db), "--out", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    samples = int(text.split("Run it with --samples ")[1].split()[0])
    return text, samples, db, out


def test_monte_carlo_of_runs_of_the_corrected_plan_covers_its_u95(corrected_plan):
    """60 simulated runs: the device's true misalignments drawn about the correction's values with its
    own u (the history's, normal; the budget's is larger, covering a change the run's check would miss),
    the simulator's noise over the window, a new table (index errors and wobble at the
    rig's ±2″) per run; each run fitted as `labcal run` fits it (`run_fits`), its budget the
    certificate's (the simulator's Type B inputs, the plan's u), five new readings per run at random
    attitudes in the envelope; the attitude error against the simulator's attitude lies within U95
    in ≥ 93 % of cases for pitch and for roll."""
    from labcal.app.planning import planning_bench

    text, samples, _, _ = corrected_plan
    correction = plan_correction(text, "the plan")
    assert correction is not None
    plan = Plan.model_validate({k: v for k, v in tomllib.loads(text).items() if k != "device_correction"})
    assert len(plan.mounts) < 4
    bench, _, _ = planning_bench(None)  # the simulated rig's Type B inputs, as its dry runs' certificates
    inputs = bench.type_b.__class__(**{**vars(bench.type_b), "device_misalignment": correction.u_rad(),
                                      "device_misalignment_source": correction.describe()})
    truth, device = RIG.instrument, RIG.device
    noise = truth.noise_v / math.sqrt(samples)
    rng = np.random.default_rng(2027)
    covered, ratios = [], []
    for trial in range(60):
        seed = 5000 + trial
        drawn = Misalignment(**{n: correction.value_arcsec[n] * ARCSEC + rng.normal(0.0, u)
                                for n, u in correction.u_history_rad().items()})
        table = IndexWobble(device.index_arcsec, device.wobble_arcsec, seed)
        readings = simulate_readings(plan, truth, drawn, table, noise, seed)
        fit, dev, _ = run_fits(readings, text, None)
        assert dev is None and fit.model.device is not None
        cal = calibration_of(fit, readings)
        pitch, roll = np.radians(rng.uniform(-60, 60, 5)), np.radians(rng.uniform(-180, 180, 5))
        U = propagate(cal, sources(cal, inputs), pitch, roll).U
        volts = truth.static_volts(gravity(pitch, roll, 0.0, 0.0)) + rng.normal(0.0, noise, (5, 3))
        att = sphere_least_squares(AttitudeCalibration(fit.coefficients, cal.covariance,
                                                       np.sqrt(cal.reading_var), int(cal.dof[0])),
                                   volts, LOCAL_GRAVITY_U)
        error = np.column_stack([att.pitch - pitch, np.angle(np.exp(1j * (att.roll - roll)))])
        covered.append(np.abs(error) <= U)
        ratios.append(error / U)
    coverage = np.concatenate(covered).mean(axis=0)
    assert np.all(coverage >= 0.93), coverage
    # not by an absurd margin either: a normal error within U95 = 1.96 u has an RMS ratio of 0.51. Here
    # about 0.15: the "one new reading" row still takes the fit's residual scatter (the tables' per-angle
    # errors, about four times the instrument's repeatability), and the three-mount plan the check
    # requires leaks little of the misalignments
    assert float(np.sqrt(np.mean(np.concatenate(ratios) ** 2))) > 0.1


def test_the_fit_holds_the_misalignments_at_the_corrections_values(corrected_plan):
    """Noise-free readings of a device whose misalignments are exactly the correction's: the corrected
    fit gives the simulated instrument's coefficients to rounding, the nominal one does not (one
    mount leaks e, f, k into the coefficients, Soto Tables 5–8)."""
    text, _, _, _ = corrected_plan
    correction = plan_correction(text, "the plan")
    assert correction is not None
    plan = Plan.model_validate({k: v for k, v in tomllib.loads(text).items() if k != "device_correction"})
    readings = simulate_readings(plan, RIG.instrument, correction.misalignment())
    fit, _, note = run_fits(readings, text, None)
    assert np.max(np.abs(fit.coefficients - RIG.instrument.X)) < 1e-10
    nominal, _, _ = run_fits(readings, plan_toml(plan), None)
    assert np.max(np.abs(nominal.coefficients - RIG.instrument.X)) > 1e-5
    assert "held at device SIMULATED's estimate from run run-2" in note


# --- (c) refusals before anything moves --------------------------------------------------------------
def plan_with(correction: DeviceCorrectionTable) -> str:
    """Three mounts (fore/aft and top/bottom reversals): they see every misalignment corrected for."""
    plan = Plan(name="three-mounts", mounts=[(0, 0), (180, 0), (0, 180)],
                points=[(p, r) for p in (-60, 0, 60) for r in (0, 90, 180, 270)])
    return plan_toml(plan) + "\n" + correction_toml(correction)


def stored(db, source: str, date: str, a: float) -> DeviceEstimate:
    estimate = DeviceEstimate("SIMULATED", date, source,
                              {m: (a if m == "a" else 20.0) for m in MISALIGNMENT_NAMES},
                              {m: 1.0 for m in MISALIGNMENT_NAMES})
    device_history.store(estimate, db)
    return estimate


def correction_of(e: DeviceEstimate, device_id: str = "SIMULATED") -> DeviceCorrectionTable:
    return DeviceCorrectionTable(device_id=device_id, source=e.source, calibrated_utc=e.calibrated_utc,
                                 value_arcsec=e.value_arcsec, U_arcsec=e.U_arcsec,
                                 u_arcsec={n: u / 1.96 for n, u in e.U_arcsec.items()})


@pytest.mark.parametrize("case, words", [
    ("another device", "this plan corrects for calibration device CD-7's misalignments but this station's "
                       "device is SIMULATED"),
    ("changed since", "device SIMULATED changed since run-2, whose estimate this plan corrects for: a moved "
                      "between run-2 and run-3"),
    ("not in the history", "device SIMULATED's history has no estimate from run-9"),
])
def test_a_correction_that_no_longer_applies_is_refused_before_anything_moves(case, words, tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    stored(db, "run-1", days_ago(40), 36.0)
    latest = stored(db, "run-2", days_ago(10), 36.5)  # |Δ| 0.5″ < √2″: in control
    correction = correction_of(latest, "CD-7" if case == "another device" else "SIMULATED")
    if case == "changed since":  # a later run found a moved by 3″ > √(1² + 1²)
        stored(db, "run-3", days_ago(5), 39.5)
    if case == "not in the history":
        correction = correction.model_copy(update={"source": "run-9"})
    plan_file, run_dir = tmp_path / "plan.toml", tmp_path / "run"
    plan_file.write_text(plan_with(correction), encoding="utf-8")
    code = main(["run", "--sim", "--yes", "--db", str(db), "--plan", str(plan_file), "--out", str(run_dir)])
    assert code == 2
    assert words in one_line(capsys.readouterr().err)
    assert not run_dir.exists()  # nothing started: no run folder, no journaled run
    import sqlite3

    with sqlite3.connect(db) as conn:
        tables = {t for (t,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        assert "runs" not in tables or conn.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 0


def test_a_corrected_plan_that_cannot_see_what_it_corrects_is_refused_before_anything_moves(tmp_path,
                                                                                           capsys):
    """One mount never sees e, f or k: a run of it could not notice them move, so it does not start."""
    db = tmp_path / "lab.sqlite"
    stored(db, "run-1", days_ago(40), 36.0)
    latest = stored(db, "run-2", days_ago(10), 36.5)
    plan = Plan(name="one-mount", mounts=[(0, 0)],
                points=[(p, r) for p in (-60, 0, 60) for r in (0, 90, 180, 270)])
    plan_file, run_dir = tmp_path / "plan.toml", tmp_path / "run"
    plan_file.write_text(plan_toml(plan) + "\n" + correction_toml(correction_of(latest)), encoding="utf-8")
    code = main(["run", "--sim", "--yes", "--db", str(db), "--plan", str(plan_file), "--out", str(run_dir)])
    assert code == 2
    line = one_line(capsys.readouterr().err)
    assert "its mounts cannot see e, f, k: a run could not notice them move" in line
    assert not run_dir.exists()


def test_an_in_control_correction_runs_and_says_which_estimate_it_used(tmp_path, capsys):
    """The same history without the change since: the run goes ahead, fit.json's first note names the
    estimate, and a later change of the history does not alter the finished run's certificate."""
    db = tmp_path / "lab.sqlite"
    stored(db, "run-1", days_ago(40), 36.0)
    latest = stored(db, "run-2", days_ago(10), 36.5)
    plan_file, run_dir = tmp_path / "plan.toml", tmp_path / "run"
    plan_file.write_text(plan_with(correction_of(latest)), encoding="utf-8")
    assert main(["run", "--sim", "--yes", "--db", str(db), "--plan", str(plan_file), "--out", str(run_dir),
                 "--no-report"]) == 0
    fit = json.loads((run_dir / "fit.json").read_text(encoding="utf-8"))
    assert fit["model"] == "linear"
    assert fit["notes"][0].startswith("linear model on the gravity the calibration device's misalignments")
    assert f"estimate from run run-2 (calibrated {latest.calibrated_utc})" in fit["notes"][0]
    # the journal keeps the plan with its correction: the certificate is derived from it
    journaled = (run_dir / "plan.toml").read_text(encoding="utf-8")
    assert plan_correction(journaled, "plan") == correction_of(latest)


@pytest.mark.parametrize("edit, words", [
    (lambda t: "\n".join(row for row in t.splitlines() if not row.startswith("calibrated_utc = ")) + "\n",
     "[device_correction]: calibrated_utc: Field required"),
    (lambda t: t.replace("u_arcsec = { a = ", "u_arcsec = { a = -"), "an uncertainty cannot be negative"),
    (lambda t: t.replace("value_arcsec = { a = ", "value_arcsec = { q = 1.0, a = "),
     "needs exactly the misalignments a, b, d, e, f, k"),
])
def test_a_malformed_correction_is_one_line_naming_the_field(edit, words, tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    latest = stored(db, "run-2", days_ago(10), 36.5)
    plan_file, run_dir = tmp_path / "plan.toml", tmp_path / "run"
    plan_file.write_text(edit(plan_with(correction_of(latest))), encoding="utf-8")
    code = main(["run", "--sim", "--yes", "--db", str(db), "--plan", str(plan_file), "--out", str(run_dir)])
    assert code == 2
    line = one_line(capsys.readouterr().err)
    assert str(plan_file) in line and words in line
    assert not run_dir.exists()


@pytest.mark.slow
def test_a_moved_device_leaves_no_corrected_certificate_under_90_percent_coverage(corrected_plan):
    """A step of ±4 u in any one misalignment, or of 3 u in all six, after the estimate (u: the plan's):
    in 50 simulated runs per case, no certificate is issued from the correction that covers less than
    90 % of new readings (pitch or roll) — each run is refused by its check or covers; and with
    nothing moved, the check refuses at most 5 of 50 (its false alarm is ≤ 1 %)."""
    from labcal.analysis.kinematics import MISALIGNMENT_NAMES

    text, _, _, _ = corrected_plan
    correction = plan_correction(text, "the plan")
    assert correction is not None
    u = correction.u_arcsec
    steps = [{n: sign * 4 * u[n]} for n in MISALIGNMENT_NAMES for sign in (1, -1)]
    steps.append({n: 3 * u[n] for n in MISALIGNMENT_NAMES})
    failures = []
    for i, step in enumerate(steps):
        runs = corrected_runs_under_a_step(text, step, 50, 60000 + 1000 * i, new_readings=100)
        for refused, coverage in runs:
            if not refused and coverage < 0.90:
                failures.append((step, coverage))
    print(f"issued corrected certificates under 90 % coverage: {len(failures)} of {50 * len(steps)} runs "
          "(target 0)")
    assert not failures, failures
    unmoved = corrected_runs_under_a_step(text, {}, 50, 90000, new_readings=100)
    assert sum(r for r, _ in unmoved) <= 5
    assert all(c >= 0.90 for r, c in unmoved if not r)
