"""What a run journals reaches its certificate: the identities the devices reported (the latest after
a resume), the device model the run's fit used, the ambient conditions entered at the start."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import pytest
from cli import cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import CertificateSection
from labcal.documents.administration import ItemGiven, administration
from labcal.documents.certificate import read_certificate
from labcal.sim.dmm_emulator import IDN
from labcal.sim.smc100_emulator import VERSION
from labcal.store.journal import EventRow
from labcal.store.record import load_run


def test_an_emulated_run_certifies_the_identities_the_emulators_reported(tmp_path, capsys, no_leaks):  # noqa: F811
    """`labcal run --emulate` on the SMC100 station: the certificate's equipment gives maker, model,
    serial and firmware as the emulators answer `*IDN?`, `ID?` and `VE` (their own constants, not
    the drivers'); a later `device_identity` event (a resume on a swapped DMM) wins."""
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--station", str(private_file("smc100-serial", tmp_path)), "--emulate",
                       "--time-scale", str(TIME_SCALE), "--yes", "--serial", "SN-7", "--out", str(run_dir))
    assert code == 0, err
    equipment = json.loads((run_dir / "certificate.json").read_text())["administration"]["equipment"]
    pitch, roll, dmm = equipment
    maker, model, serial, firmware = IDN.split(",")
    del dmm["description"]  # the station file's settings, not the subject
    assert dmm == {"role": "DMM", "identity": IDN, "maker": maker, "model": model, "serial": serial,
                   "firmware": firmware}
    for table in (pitch, roll):
        assert table["maker"] == "Newport" and table["firmware"] == VERSION and "serial" not in table
        assert table["model"] == "SMC100 with stage URS100BCC"
    assert f"{maker} {model}, serial {serial}, firmware {firmware}" in (run_dir / "report.html").read_text()

    record = load_run(run_dir)
    swapped = {"dmm": {"model": "Keysight Technologies 34970A", "identity": "swapped", "maker": "Keysight",
                       "serial": "MY99", "firmware": "1-0-0"}}
    resumed = dataclasses.replace(record, events=record.events + (
        EventRow("", 0.0, "device_identity", "", swapped),))
    *_, dmm = administration(resumed, CertificateSection(), ItemGiven(), "SN-7").equipment
    assert (dmm.serial, dmm.firmware, dmm.identity) == ("MY99", "1-0-0", "swapped")


def test_the_default_dry_run_is_certified_on_the_device_model_it_fitted(tmp_path, capsys):
    """`labcal run --sim --yes`: fit.json holds the device model (the plan identifies all six), and so
    does the certificate: its coefficients are fit.json's, its device section gives the rig's
    tens-of-arcsecond misalignments, the budget's device-misalignment row carries their standard
    uncertainties, and the run still conforms to a 0.05° attitude tolerance."""
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--sim", "--yes", "--tolerance-deg", "0.05", "--out", str(run_dir))
    assert code == 0, err
    fit = json.loads((run_dir / "fit.json").read_text())
    cert = read_certificate(run_dir / "certificate.json")  # schema and digest checked
    assert fit["model"] == cert.fit.model == "device"
    assert cert.fit.coefficients == fit["coefficients"] and cert.fit.covariance == fit["covariance"]
    truth = json.loads((run_dir / "run.json").read_text())["simulated_truth"]["misalignment_deg"]
    assert cert.device is not None and set(cert.device.misalignments) == set(truth)
    for name, m in cert.device.misalignments.items():
        assert abs(truth[name] * 3600) >= 18  # the rig's default is realistic: tens of arcseconds
        # The ±2″ index errors and wobble the rig adds at each table angle bias each estimate by up to
        # about their amplitude; the device model now carries them, so its U covers that.
        assert abs(m.value_arcsec - truth[name] * 3600) <= m.U_arcsec, (name, m, truth[name] * 3600)
        assert m.U_arcsec == pytest.approx(cert.device.coverage_factor_95 * m.u_arcsec)
    # the budget's device-misalignment row is the readings' share of their u (the fit without the
    # tables' errors); the tables' index and wobble are their own rows, at the rig's ±2″
    from labcal.analysis.device_fit import fit_device
    from labcal.analysis.kinematics import ARCSEC

    noise_only = fit_device(load_run(run_dir).readings)
    [row] = [r for r in cert.uncertainty_budget.rows if r.source == "device misalignment estimates"]
    assert row.standard_uncertainty == pytest.approx(max(noise_only.misalignment_u_rad) / ARCSEC, rel=1e-6)
    tables = {r.source: r.standard_uncertainty for r in cert.uncertainty_budget.rows if "table" in r.source}
    u_rig = 2 / 3**0.5  # ± 2″ rectangular: u = a/√3 (GUM 4.3.7)
    assert tables == pytest.approx({"pitch table index accuracy": u_rig, "pitch table wobble": u_rig,
                                    "roll table index accuracy": u_rig, "roll table wobble": u_rig})
    assert cert.uncertainty_budget.inputs.device_misalignment.keys() == truth.keys()
    assert cert.conformity is not None and cert.conformity.passed
    intrinsic = cert.device.intrinsic  # every sensor's |s| and every pair's angle
    assert set(intrinsic.sensitivity_v_per_g) == {"x", "y", "z"}
    assert set(intrinsic.inter_axis_angle_deg) == {"xy", "xz", "yz"}
    assert len(cert.device.covariance) == 18 and cert.method.startswith("Device model")


def test_a_certificate_issued_before_the_device_and_identity_fields_still_reads(tmp_path, capsys):
    """labcal.certificate/1 as issued before: no device section, equipment without maker/model/
    serial/firmware, sealed over that content; it reads back and verifies unchanged."""
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--sim", "--yes", "--out", str(run_dir))
    assert code == 0, err
    doc = json.loads((run_dir / "certificate.json").read_text())
    del doc["device"]
    doc["fit"]["model"] = "linear"
    for e in doc["administration"]["equipment"]:
        for key in ("maker", "model", "serial", "firmware"):
            e.pop(key, None)
    content = {k: v for k, v in doc.items() if k != "digest"}
    doc["digest"]["value"] = hashlib.sha256(json.dumps(content, sort_keys=True, separators=(",", ":"),
                                                       ensure_ascii=False).encode()).hexdigest()
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    cert = read_certificate(old)
    assert cert.device is None and cert.to_json() == doc


def test_ambient_conditions_entered_at_the_start_reach_the_certificate(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--sim", "--yes", "--ambient-temp", "22.5", "--humidity", "41",
                       "--out", str(run_dir))
    assert code == 0, err
    assert json.loads((run_dir / "run.json").read_text())["ambient"] == {
        "temperature_c": 22.5, "humidity_pct": 41.0, "source": "entered at the start of the run"}
    cert = read_certificate(run_dir / "certificate.json")
    assert cert.administration.ambient == ("air temperature 22.5 °C, relative humidity 41 % (entered at the "
                                           "start of the run)")
    assert "relative humidity 41 %" in (run_dir / "report.html").read_text()


@pytest.mark.parametrize("option, value, expected", [
    ("--ambient-temp", "75", "75 is out of range; expected a number x with -20 ≤ x ≤ 60"),
    ("--ambient-temp", "nan", "nan is not a finite number"),
    ("--humidity", "101", "101 is out of range; expected a number x with 0 ≤ x ≤ 100"),
    ("--humidity", "damp", "'damp' is not a number"),
])
def test_ambient_conditions_out_of_range_are_one_line_and_nothing_runs(option, value, expected, tmp_path,
                                                                        capsys):
    code, out, err = cli(capsys, "run", "--sim", "--yes", option, value, "--out", str(tmp_path / "run"))
    assert code == 2 and out == "" and err.strip().count("\n") == 0 and expected in err, err
    assert f"argument {option}" in err and not (tmp_path / "run").exists()
