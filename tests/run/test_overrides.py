"""A run that went on past an unmet pre-run checklist item reaches the approver: the certificate
(and so the report) states it, and `labcal runs --attention` lists the run with the reason. On the
emulated SMC100 station, attended at a piped terminal; the expected sentence is written out here by
hand from the checklist's warm-up rule."""

from __future__ import annotations

import io
import json

from cli import cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.run_metadata import Checklist
from labcal.documents.issuing import checklist_overrides, override_statement

NO_STANDARDS = ("reference standards: the station names no reference standards ([[traceability]]): the "
                "certificate will state none; add the DMM's and the tables' certificates")
EMULATE = ["--emulate", "--time-scale", str(TIME_SCALE)]
WARM_UP_UNSAID = ("warm-up: the station asks 30 min after power-on and nobody said when the instrument was "
                  "switched on: give --powered-on HH:MM, or --warmed-up")


def test_a_run_that_went_on_past_an_unmet_item_says_so_on_the_certificate_and_in_the_attention_list(
        tmp_path, capsys, monkeypatch, lab_database, no_leaks):  # noqa: F811
    path = private_file("smc100-tcp", tmp_path, "\n[instrument]\nwarm_up_min = 30\n")
    monkeypatch.setattr("sys.stdin", io.StringIO("\ny\ny\n"))  # power-on unsaid; go on anyway; mounted
    code, _, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--plan", "one-mount-16", "--serial",
                       "ACC-0042", "--out", str(tmp_path / "run"))
    assert code == 0, err
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    stated = ("The pre-run checklist was not met and the calibration went on at the operator's decision: "
              + WARM_UP_UNSAID + ".")
    assert stated in cert["statements"]
    report = (tmp_path / "run" / "report.html").read_text(encoding="utf-8")
    assert "went on at the operator&#x27;s decision" in report
    code, out, _ = cli(capsys, "runs", "--attention", "--json")
    runs = json.loads(out)["runs"]
    assert [r["attention"] for r in runs] == [["went on regardless: " + WARM_UP_UNSAID, NO_STANDARDS]]


def test_a_run_that_met_its_checklist_needs_no_attention(tmp_path, capsys):
    from simulated_runs import simulated_run

    simulated_run(tmp_path / "run", tmp_path / "lab.sqlite", seed=4)
    capsys.readouterr()  # the run's own output
    code, out, _ = cli(capsys, "runs", "--attention", "--db", str(tmp_path / "lab.sqlite"), "--json")
    assert code == 0 and json.loads(out)["runs"] == []
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    assert not any("pre-run checklist was not met" in s for s in cert["statements"])


def test_only_the_unmet_items_of_a_run_that_went_on_are_stated():
    checklist = Checklist.model_validate({"went_on_regardless": True, "items": [
        {"item": "warm-up", "status": "fail", "message": "12 min of 30 since power-on."},
        {"item": "DMM", "status": "ok", "message": "configured"},
        {"item": "reference standards", "status": "warning", "message": "overdue"}]})
    assert checklist_overrides(checklist) == ["warm-up: 12 min of 30 since power-on."]
    assert override_statement(checklist) == [
        "The pre-run checklist was not met and the calibration went on at the operator's decision: "
        "warm-up: 12 min of 30 since power-on."]
    assert override_statement(checklist.model_copy(update={"went_on_regardless": False})) == []
    assert override_statement(None) == []


def test_the_customers_certificate_carries_no_command_line_hints_and_the_console_does(tmp_path, capsys):
    """The device model's note and the missing-tolerance caption reach the certificate (its JSON and
    its PDF) without an option to type; `labcal run` says the options to the technician, and so does
    the HTML report's technician's section, and only there."""
    code, out, err = cli(capsys, "run", "--sim", "--yes", "--seed", "8", "--out", str(tmp_path / "run"),
                         "--db", str(tmp_path / "lab.sqlite"))
    assert code == 0, err
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    report = (tmp_path / "run" / "report.html").read_text(encoding="utf-8")
    customers, _, technicians = report.partition("<h2>For the laboratory: technician&#x27;s notes</h2>")
    from pypdf import PdfReader

    pdf = " ".join(page.extract_text() for page in PdfReader(tmp_path / "run" / "report.pdf").pages)
    for text in (*cert["statements"], customers, pdf):
        assert "--model" not in text and "--tolerance-deg" not in text and "Give --" not in text
    assert "--model linear` gives Soto" in technicians and "--tolerance-deg" in technicians
    console = " ".join(out.split())  # the terminal wraps lines
    assert "--model linear` gives Soto's linear fit" in console
    assert "no statement of conformity: give --tolerance-deg" in console
