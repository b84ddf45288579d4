"""The certificate: exact round trip, contents checked against the fit, sealing, ILAC-P14 numbers."""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats
from simulated_runs import simulated_run

from labcal.analysis.device_fit import preferred_fit
from labcal.analysis.fit import fit_readings
from labcal.cli import main
from labcal.config.run_metadata import RunMetadata
from labcal.config.settings import CertificateSettings
from labcal.documents.certificate import (
    format_result,
    format_uncertainty,
    load_calibration,
    read_certificate,
    write_certificate,
)
from labcal.documents.issuing import build_certificate, envelope_grid, load_settings
from labcal.errors import LabcalError
from labcal.store.record import load_run


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    base = tmp_path_factory.mktemp("cert")
    return load_run(simulated_run(base / "run", base / "lab.sqlite", seed=7, serial="SN-0042"))


@pytest.fixture(scope="module")
def cert(run):
    return build_certificate(run, fit_readings(run.readings),
                             CertificateSettings(attitude_u95_max_deg=0.01, bias_max_v=0.02))


def on_the_run_model(run, settings=None):
    """As `labcal run` issues it: on the device model its fit.json holds (the rig's misalignments
    are tens of arcseconds; the linear fit's U95 would not meet a 0.01° tolerance)."""
    fit = fit_readings(run.readings)
    device, note = preferred_fit(run.readings, fit)
    return build_certificate(run, fit, settings, device=device, model_note=note)


@pytest.fixture
def cert_file(cert, tmp_path):
    return write_certificate(tmp_path / "certificate.json", cert)


def test_round_trip_is_exact(cert, cert_file, tmp_path):
    again = read_certificate(cert_file)
    assert again == cert
    assert again.to_json() == cert.to_json()
    rewritten = write_certificate(tmp_path / "again.json", again)
    assert rewritten.read_bytes() == cert_file.read_bytes()
    # the seal a third party can check without labcal: SHA-256 of the canonical JSON (sorted keys,
    # no spaces, UTF-8) of everything but the digest, as the README documents it
    doc = json.loads(cert_file.read_text())
    canonical = json.dumps({k: v for k, v in doc.items() if k != "digest"}, sort_keys=True,
                           separators=(",", ":"), ensure_ascii=False)
    digest = hashlib.sha256(canonical.encode("utf-8")).hexdigest()
    assert cert.digest.value == doc["digest"]["value"] == digest


def test_contents_match_the_fit_and_the_run(run, cert):
    fit = fit_readings(run.readings)
    # The linear model leaves the device's misalignments (tens of arcseconds) in the residuals, and this
    # certificate states no bench error: the lack-of-fit test says so, and the budget is the fit's
    # residual (its ν and standard errors below), not the windows' noise
    check = cert.uncertainty_budget.fit_check
    assert check.lack_of_fit and check.statement in cert.statements and "LACK OF FIT" in check.statement
    assert cert.uncertainty_budget.in_use is None
    assert cert.to_json()["schema"] == "labcal.certificate/1"  # published (README); issued ones carry it
    assert cert.instrument.serial == "SN-0042"  # recorded by `labcal run --serial`
    assert cert.station.simulated and cert.station.simulated_truth.seed == 7
    np.testing.assert_array_equal(cert.coefficients, fit.coefficients)
    for j in range(3):
        np.testing.assert_array_equal(cert.fit.covariance[j], fit.covariance(j))
    # 64 points, 4 coefficients per sensor: ν = 60, k = t₀.₉₇₅(60) = 2.0003 (GUM G.4)
    assert cert.fit.degrees_of_freedom == 60 and cert.expanded_uncertainty.nu_eff == [60, 60, 60]
    assert cert.expanded_uncertainty.k == pytest.approx([2.000297822] * 3, abs=1e-9)
    # labcal's t quantile and scipy's are independent computations: they agree to a few ulp
    np.testing.assert_allclose(cert.U, stats.t.ppf(0.975, 60) * fit.stderr[:4], rtol=1e-14)
    assert cert.environment.temperature_c_min == run.readings.temp_c.min()
    assert cert.environment.temperature_c_max == run.readings.temp_c.max()
    assert cert.plan.sha256 == hashlib.sha256((run.directory / "plan.toml").read_bytes()).hexdigest()
    # the data digest names the journal's committed points, which the readings.csv export mirrors
    from labcal.store.journal import Journal
    from labcal.store.record import readings_digest

    info = json.loads((run.directory / "run.json").read_text())
    with Journal(info["journal"]) as journal:
        assert cert.data.readings_sha256 == readings_digest(journal.points(info["run_id"], status="ok"))
    assert len(journal_rows := (run.directory / "readings.csv").read_text().splitlines()) == 65, journal_rows
    # Soto's result: four mounts × 16 points cancel every misalignment in B and off-diagonal S.
    assert set(cert.plan_audit.misalignments) == set("abdefk")
    assert all(m.cancelled for m in cert.plan_audit.misalignments.values())


def test_attitude_uncertainty_is_in_degrees_and_matches_first_order_propagation(cert):
    """At level attitude the pitch comes from sensor x alone to first order: u_p = √(fᵀC_x f + σ_x²)/S_xx
    with f = (1, 0, 0, 1); off-axis sensitivities (≈ 0.2 % of S_xx) change it by far less than 1 %. The
    one sensor's variance estimate is then the only term of Welch–Satterthwaite: k = t₀.₉₇₅(ν)."""
    cal = cert.calibration()
    env = envelope_grid(cal, CertificateSettings())
    i, j = list(env.pitch_deg).index(0.0), list(env.roll_deg).index(0.0)
    f = np.array([1.0, 0.0, 0.0, 1.0])
    u_p = np.sqrt(f @ cal.covariance[0] @ f + cal.reading_sd[0] ** 2) / cal.X[1, 0]
    k = float(stats.t.ppf(0.975, cal.dof))
    assert env.u95_pitch_deg[i, j] == pytest.approx(k * np.degrees(u_p), rel=1e-2)
    a = cert.attitude
    assert a.pitch_U95_max_deg == pytest.approx(np.max(env.u95_pitch_deg), rel=1e-12)
    assert a.roll_U95_max_deg == pytest.approx(np.nanmax(env.u95_roll_deg), rel=1e-12)
    assert a.pitch_U95_rms_deg <= a.pitch_U95_max_deg and a.grid_points == 25 * 73
    assert a.roll_undefined_points == 0  # the default envelope stops at ±60° pitch


def test_conformity_follows_the_decision_rule(run):
    cert = on_the_run_model(run, CertificateSettings(attitude_u95_max_deg=0.01, bias_max_v=0.02))
    assert cert.conformity.passed  # U95 ≈ 0.0006–0.0015° < 0.01°, |B| + U ≤ 0.0124 V < 0.02 V
    worst = max(t.U95_arcsec for t in cert.uncertainty_budget.totals) / 3600  # the full budget's U95
    tight = on_the_run_model(run, CertificateSettings(attitude_u95_max_deg=worst * 0.999))
    assert not tight.conformity.passed
    assert [c.passed for c in tight.conformity.checks].count(False) == 1
    bias_x = abs(cert.coefficients[0, 0]) + cert.U[0, 0]
    biased = on_the_run_model(run, CertificateSettings(bias_max_v=bias_x * 0.999))
    assert [c.passed for c in biased.conformity.checks] == [False, True, True]
    assert on_the_run_model(run).conformity is None  # no tolerance, no statement


def _edit(path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc, indent=2))


@pytest.mark.parametrize("change, message", [
    (lambda d: d["fit"]["coefficients"][1].__setitem__(0, d["fit"]["coefficients"][1][0] + 1e-9),
     "digest mismatch: the content was altered after issue"),
    (lambda d: d["conformity"].__setitem__("passed", not d["conformity"]["passed"]), "digest mismatch"),
    (lambda d: d["digest"].__setitem__("value", "0" * 64), "digest mismatch"),
    (lambda d: d.__setitem__("schema", "labcal.certificate/9"),
     "schema 'labcal.certificate/9' is not supported"),
    (lambda d: d.pop("schema"), "not a labcal certificate"),
    (lambda d: d["fit"].pop("covariance"), "invalid certificate: fit.covariance: Field required"),
    (lambda d: d["fit"]["coefficients"].pop(), "coefficients must have shape 4×3, not 3×3"),
    (lambda d: d.__setitem__("extra", 1), "invalid certificate: extra: Extra inputs are not permitted"),
])
def test_altered_certificate_is_rejected(cert_file, change, message):
    _edit(cert_file, change)
    with pytest.raises(LabcalError, match=message.replace("(", r"\(")) as exc:
        read_certificate(cert_file)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.99])
def test_truncated_certificate_is_rejected(cert_file, keep):
    text = cert_file.read_text()
    cert_file.write_text(text[: int(len(text) * keep)])
    with pytest.raises(LabcalError, match="not valid JSON: the file is truncated"):
        read_certificate(cert_file)


def test_attitude_reads_a_certificate_and_refuses_a_tampered_one(cert, cert_file, tmp_path, capsys):
    cal = load_calibration(cert_file)
    np.testing.assert_array_equal(cal.X, cert.coefficients)
    volts = tmp_path / "v.csv"
    g = np.array([0.0, 0.0, 1.0])  # level: pitch 0, roll 0
    v = cert.coefficients[0] + g @ cert.coefficients[1:]
    volts.write_text("vx,vy,vz\n" + ",".join(f"{x:.12f}" for x in v) + "\n")
    assert main(["attitude", "--cert", str(cert_file), "--csv", str(volts), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)["rows"][0]["sphere_least_squares"]
    assert (row["pitch_deg"], row["roll_deg"]) == pytest.approx((0.0, 0.0), abs=1e-9)
    tampered = tmp_path / "tampered.json"
    shutil.copy(cert_file, tampered)
    _edit(tampered, lambda d: d["fit"]["reading_sd"].__setitem__(0, 1e-9))  # a smaller claimed noise
    assert main(["attitude", "--cert", str(tampered), "--csv", str(volts)]) == 2
    err = capsys.readouterr().err
    assert "digest mismatch" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("value, u, expected", [
    (4.98715012, 4.0658e-5, "4.987150 ± 0.000041"),  # y rounded to the last digit of U
    (1.23456, 0.0996, "1.23 ± 0.10"),  # rounding carries U to a new decade: still two digits
    (-0.0081049, 2.5e-5, "-0.008105 ± 0.000025"),
    (12345.6, 149.7, "12350 ± 150"),
    (0.5, 0.0, "0.5"),  # no uncertainty: no ±
])
def test_format_result_follows_ilac_p14(value, u, expected):
    assert format_result(value, u) == expected


def test_format_uncertainty_has_two_significant_digits():
    assert [format_uncertainty(u) for u in (0.000123456, 0.00996, 2.04, 97.6)] == ["0.00012", "0.010", "2.0",
                                                                                   "98"]


def test_settings_from_a_station_file_and_the_command_line(tmp_path):
    station = tmp_path / "station.toml"
    station.write_text('description = "bench 2"\n[certificate]\nlaboratory = "Lab A, Hampton VA"\n'
                       "attitude_u95_max_deg = 0.02\nusage_pitch_deg = [-30, 30]\n")
    s = load_settings(station, attitude_u95_max_deg=0.005, bias_max_v=None)
    assert (s.laboratory, s.attitude_u95_max_deg, s.usage_pitch_deg, s.bias_max_v) == \
        ("Lab A, Hampton VA", 0.005, (-30.0, 30.0), None)
    station.write_text("[certificate]\nusage_pitch_deg = [-95, 30]\n")
    with pytest.raises(LabcalError, match=r"station.toml: certificate.*must be increasing within -90..90"):
        load_settings(station)
    with pytest.raises(LabcalError, match="certificate.attitude_u95_max_deg: Input should be greater than 0"):
        load_settings(None, attitude_u95_max_deg=-1.0)


def test_serial_must_be_known_and_not_contradicted(run, tmp_path):
    fit = fit_readings(run.readings)
    with pytest.raises(LabcalError, match="the run records instrument serial 'SN-0042'; 'SN-9' disagrees"):
        build_certificate(run, fit, serial="SN-9")
    anonymous = replace(run, meta=RunMetadata.model_validate(run.meta.model_dump(  # as a bench run: no serial
        exclude_unset=True, exclude={"instrument_serial", "simulated_truth"})), station=None)
    with pytest.raises(LabcalError, match="does not record the instrument's serial number; give --serial"):
        build_certificate(anonymous, fit)
    assert build_certificate(anonymous, fit, serial="SN-7").instrument.serial == "SN-7"


def as_reported(run, settings=None):
    """As `labcal report` issues it: the run's model and the station's (here the simulator's) Type B
    inputs, so that the budget states the bench's errors."""
    from labcal.app.approving import fitted
    from labcal.documents.uncertainty import bench_section, type_b_inputs

    fit, device, note = fitted(run)
    return build_certificate(run, fit, settings, device=device, model_note=note,
                             inputs=type_b_inputs(bench_section(run, None), run, device))


def test_the_certificate_states_the_averaging_in_use_its_u95_applies_to(run):
    """The new-reading row assumes a reading in use averages as many samples as the calibration's
    windows (10 in a dry run), and the certificate says so; stated otherwise (40 samples), the row is
    half as large (1/√N) and the certificate says it was stated."""
    cert = as_reported(run)
    budget = cert.uncertainty_budget
    assert not budget.fit_check.lack_of_fit and "No lack of fit" in budget.fit_check.statement
    assert budget.fit_check.statement in cert.statements
    assert budget.in_use.samples == 10 and not budget.in_use.stated
    assert budget.in_use.statement in cert.statements
    assert "the mean of 10 samples of each output (as in this calibration's windows)" in \
        budget.in_use.statement
    forty = as_reported(run, CertificateSettings(in_use_samples=40))
    assert forty.uncertainty_budget.in_use.samples == 40 and forty.uncertainty_budget.in_use.stated
    assert "(as stated for this certificate)" in forty.uncertainty_budget.in_use.statement

    def reading_row(c):
        return next(r for r in c.uncertainty_budget.rows if r.source.startswith("one new reading"))
    half = reading_row(cert).standard_uncertainty / 2
    assert reading_row(forty).standard_uncertainty == pytest.approx(half, rel=1e-12)
    # the pooled scatter by hand (GUM 4.2.4) over √10
    n, sd = run.readings.window_n, run.readings.window_sd
    pooled = np.sqrt(np.sum((n - 1)[:, None] * sd**2, axis=0) / np.sum(n - 1))
    assert reading_row(cert).standard_uncertainty == pytest.approx(pooled.max() / np.sqrt(10), rel=1e-12)
    # the averaging is an issuing choice like the envelope: the approval's rebuild keeps it
    from labcal.app.approving import issue_settings
    assert issue_settings(forty).in_use_samples == 40 and issue_settings(cert).in_use_samples is None


@pytest.mark.parametrize("value", ["0", "-3", "2.5", "many"])
def test_an_in_use_averaging_that_is_no_count_of_samples_is_one_line(run, value, capsys):
    assert main(["report", str(run.directory), "--in-use-samples", value, "--db", "unused.sqlite"]) == 2
    err = capsys.readouterr().err
    assert "--in-use-samples" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_labcal_report_states_the_lack_of_fit_and_drift_tests(tmp_path, capsys):
    """`labcal report --json` carries the certificate's fit check; the report's HTML states it."""
    run_dir = simulated_run(tmp_path / "run", tmp_path / "lab.sqlite", seed=8, report=False)  # issued below
    capsys.readouterr()
    assert main(["report", str(run_dir), "--db", str(tmp_path / "lab.sqlite"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    cert = read_certificate(run_dir / "certificate.json")
    check = cert.uncertainty_budget.fit_check
    assert doc["fit_check"]["lack_of_fit"] == check.lack_of_fit and doc["fit_check"]["drift"] == check.drift
    readings = load_run(run_dir).readings
    assert doc["fit_check"]["degrees_of_freedom"][1] == np.sum(readings.window_n - 1)
    html = (run_dir / "report.html").read_text(encoding="utf-8")
    assert "Drift test (a trend of each output over the run" in html
