"""The lab's instrument register, due dates and recall, and the serial a run certifies, checked
before anything moves: `labcal`'s command line (in this process) and the app's use cases against a
real SQLite lab database (and one register on the private PostgreSQL cluster). Every expected date
is computed here by hand from the certificate the run wrote."""

from __future__ import annotations

import json
import subprocess
from datetime import date, datetime, timedelta
from pathlib import Path

import cli
import pytest
from services import postgres_cluster, postgres_url  # noqa: F401 - fixtures
from simulated_runs import simulated_run
from test_notify import endpoint

from labcal.app.calibration import StartRun, run_serial
from labcal.app.instruments import (
    Calibration,
    checked_serial,
    interval_days,
    serial_for_run,
    suggested_interval,
)
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.errors import LabcalError


class InProcess:
    """`labcal ARGS` in this process (the same command line, without a Python start-up per call)."""

    def __init__(self, capsys) -> None:
        self.capsys = capsys

    def __call__(self, *args: str, check: int | None = 0) -> subprocess.CompletedProcess:
        self.capsys.readouterr()  # what came before (a simulated run's own output) is not this command's
        code, out, err = cli.cli(self.capsys, *args)
        if check is not None:
            assert code == check, err
        return subprocess.CompletedProcess(list(args), code, out, err)

    def json(self, *args: str) -> dict:
        return json.loads(self(*args, "--json").stdout)


@pytest.fixture
def lc(capsys) -> InProcess:
    return InProcess(capsys)


class Front:
    """A front end that records what the run says and answers the ad-hoc question as told."""

    def __init__(self, answer: bool = False) -> None:
        self.lines: list[str] = []
        self.answer = answer
        self.asked: list[str] = []

    def say(self, text: str, markup: bool = True) -> None:
        self.lines.append(text)

    def unregistered(self, serial: str) -> bool:
        self.asked.append(serial)
        return self.answer


# --- the serial, before anything moves ------------------------------------------------------------


@pytest.mark.slow
def test_a_serial_with_a_trailing_space_is_certified_without_it_and_says_so(lc, tmp_path):
    done = lc("run", "--sim", "--yes", "--seed", "3", "--serial", "ACC-0042 ", "--out", str(tmp_path / "run"))
    assert "surrounding whitespace removed, certified as 'ACC-0042'" in done.stderr
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    assert cert["instrument"]["serial"] == "ACC-0042"
    dcc = (tmp_path / "run" / "certificate.dcc.xml").read_text(encoding="utf-8")
    assert ">ACC-0042<" in dcc and "ACC-0042 <" not in dcc


def test_a_serial_with_a_line_break_is_refused_in_one_line_before_any_run_folder(lc, tmp_path):
    done = lc("run", "--sim", "--yes", "--serial", "ACC-\n0042", "--out", str(tmp_path / "run"), check=2)
    assert done.stderr.count("\n") == 1 and "control character" in done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("given", ["", "   ", "ACC\t0042", "ACC\x000042", "A" * 65])
def test_an_empty_or_unprintable_or_overlong_serial_is_refused(given):
    with pytest.raises(LabcalError):
        checked_serial(given)


def test_a_clean_serial_passes_unchanged_without_a_note():
    assert checked_serial("ACC-0042") == ("ACC-0042", None)


def test_with_an_empty_register_any_serial_is_taken_as_before(lab_database):
    found = serial_for_run("whatever-1", None)
    assert (found.serial, found.unregistered, found.notes) == ("whatever-1", False, [])


def test_a_serial_in_another_case_takes_the_registers_spelling(lc, lab_database):
    lc("instrument", "add", "ACC-0042", "--interval", "12m")
    found = serial_for_run(" acc-0042", None)
    assert found.serial == "ACC-0042" and not found.unregistered
    assert any("registered as 'ACC-0042'" in note for note in found.notes)


def test_an_unregistered_serial_is_refused_with_yes_and_nothing_moves(lc, tmp_path):
    lc("instrument", "add", "ACC-0042")
    done = lc("run", "--sim", "--yes", "--serial", "ACC-0043", "--out", str(tmp_path / "run"), check=2)
    assert "not in the lab's instrument register" in done.stderr and done.stderr.count("\n") == 1
    assert not (tmp_path / "run").exists()


def test_an_unregistered_serial_is_asked_about_and_taken_when_the_technician_says_so(lc, lab_database):
    lc("instrument", "add", "ACC-0042")
    yes, no = Front(answer=True), Front(answer=False)
    assert run_serial(StartRun(sim=True, serial="ACC-0043"), yes) == (  # type: ignore[arg-type]
        "ACC-0043", "not in the instrument register; the operator said to calibrate it as an ad-hoc serial")
    assert yes.asked == ["ACC-0043"]
    with pytest.raises(LabcalError, match="not in the lab's instrument register"):
        run_serial(StartRun(sim=True, serial="ACC-0043"), no)  # type: ignore[arg-type]


def test_the_lab_file_may_allow_ad_hoc_serials_without_asking(lc, lab_database, tmp_path):
    (tmp_path / "config" / "labcal").mkdir(parents=True)
    (tmp_path / "config" / "labcal" / "lab.toml").write_text("[instruments]\nallow_adhoc = true\n",
                                                              encoding="utf-8")
    lc("instrument", "add", "ACC-0042")
    front = Front(answer=False)
    assert run_serial(StartRun(sim=True, serial="ACC-0043"), front) == (  # type: ignore[arg-type]
        "ACC-0043", "not in the instrument register; the lab file allows ad-hoc serials")
    assert front.asked == [] and any("allows ad-hoc serials" in line for line in front.lines)
    simulated_run(tmp_path / "run", lab_database, seed=9, serial="ACC-0043", report=False)  # --yes: taken
    runs = lc.json("runs", "--attention")["runs"]
    assert [r["attention"] for r in runs] == [
        ["serial not in the instrument register; the lab file allows ad-hoc serials"]]


# --- the register ---------------------------------------------------------------------------------


def test_the_register_adds_lists_searches_shows_and_edits_by_any_case_of_the_serial(lc):
    lc("instrument", "add", "ACC-0042", "--model", "AX-3", "--customer", "Acme Aero", "--interval", "1y",
           "--location", "rack 4")
    lc("instrument", "add", "ZT-7", "--model", "Tilt-2", "--customer", "Zenith", "--interval", "90d")
    assert [i["serial"] for i in lc.json("instrument", "list")["instruments"]] == ["ACC-0042", "ZT-7"]
    def found(text: str) -> list[str]:
        return [i["serial"] for i in lc.json("instrument", "list", "--search", text)["instruments"]]

    assert found("ACME") == ["ACC-0042"] and found("tilt") == ["ZT-7"]
    assert lc.json("instrument", "list", "--search", "_")["instruments"] == []  # a wildcard is a character
    again = lc("instrument", "add", "acc-0042", check=2)
    assert "already registered as ACC-0042" in again.stderr
    edited = lc.json("instrument", "edit", "acc-0042", "--status", "out-for-repair", "--interval", "6m")
    assert (edited["serial"], edited["status"]) == ("ACC-0042", "out-for-repair")
    assert edited["interval_days"] == round(6 * 365.25 / 12)  # 182.625 days → 183
    shown = lc.json("instrument", "show", "ACC-0042")
    assert (shown["customer"], shown["location"], shown["last_calibration"]) == ("Acme Aero", "rack 4", None)
    missing = lc("instrument", "show", "NOPE-1", check=2)
    assert "no such instrument" in missing.stderr


@pytest.mark.parametrize(("text", "days"), [("365d", 365), ("12m", 365), ("1y", 365), ("2y", 730), ("1m", 30),
                                             ("30D", 30)])
def test_an_interval_is_read_in_days_months_or_years(text, days):
    assert interval_days(text) == days  # a month 365.25/12 = 30.44 days, a year 365.25, rounded


@pytest.mark.parametrize("text", ["0d", "12", "twelve months", "-3d", "1.5y"])
def test_an_interval_that_is_not_one_is_refused(text):
    with pytest.raises(LabcalError):
        interval_days(text)


def test_a_bad_status_or_interval_is_refused_before_the_database_is_created(lc, lab_database):
    done = lc("instrument", "add", "ACC-0042", "--interval", "soon", check=2)
    assert "--interval" in done.stderr and not lab_database.exists()


# --- due dates and the staircase ------------------------------------------------------------------


def calibrated_on(run: Path) -> date:
    cert = json.loads((run / "certificate.json").read_text(encoding="utf-8"))
    return datetime.fromisoformat(cert["calibrated_utc"]).date()


def test_next_due_is_the_last_calibration_plus_the_interval_a_dry_run_none(lc, tmp_path, lab_database):
    lc("instrument", "add", "ACC-0042", "--interval", "365d")
    run = simulated_run(tmp_path / "cal", lab_database, seed=5, serial="ACC-0042")
    on = calibrated_on(run)
    real_only = lc.json("instrument", "show", "ACC-0042", "--on", on.isoformat())
    assert real_only["last_calibration"] is None and real_only["next_due"] == on.isoformat()  # never: due now
    shown = lc.json("instrument", "show", "acc-0042", "--include-simulated", "--on", on.isoformat())
    assert shown["last_calibration"]["date"] == on.isoformat()
    assert shown["next_due"] == (on + timedelta(days=365)).isoformat()


def test_show_suggests_the_staircase_interval_from_the_last_verdict(lc, tmp_path):
    """ILAC-G24 method 1 on real certificates: a verdict of PASS (1° tolerance, far above the U95 of
    a few arcseconds) lengthens 360 days to 360 × 1.25 = 450; FAIL (0.0001°, 0.36″, below it) shortens
    them to 360 × 0.5 = 180."""
    for serial, tolerance, suggested in (("PASS-1", "1", 450), ("FAIL-1", "0.0001", 180)):
        lc("instrument", "add", serial, "--interval", "360d")
        lc("run", "--sim", "--yes", "--seed", "5", "--serial", serial, "--tolerance-deg", tolerance,
           "--out", str(tmp_path / serial))
        shown = lc.json("instrument", "show", serial, "--include-simulated")
        assert shown["last_calibration"]["in_tolerance"] is (suggested > 360)
        assert shown["suggested_interval_days"] == suggested


def test_due_lists_overdue_and_due_soon_soonest_first_and_leaves_out_the_rest(lc, tmp_path, lab_database):
    lc("instrument", "add", "OLD-1", "--interval", "30d")
    lc("instrument", "add", "NEVER-1", "--interval", "1y")  # never calibrated: due on the day asked
    lc("instrument", "add", "LATER-1", "--interval", "1y")
    lc("instrument", "add", "RETIRED-1", "--interval", "30d", "--status", "retired")
    lc("instrument", "add", "NOINTERVAL-1")
    on = calibrated_on(simulated_run(tmp_path / "a", lab_database, seed=6, serial="OLD-1"))
    simulated_run(tmp_path / "b", lab_database, seed=7, serial="LATER-1")
    asked = on + timedelta(days=40)  # OLD-1 fell due on day 30: 10 days overdue; LATER-1 due on day ~365
    doc = lc.json("due", "--within", "30d", "--on", asked.isoformat(), "--include-simulated")
    rows = [(d["serial"], d["due"], d["days_left"], d["overdue"]) for d in doc["due"]]
    assert rows == [("OLD-1", (on + timedelta(days=30)).isoformat(), -10, True),
                    ("NEVER-1", asked.isoformat(), 0, False)]
    text = lc("due", "--within", "30d", "--on", asked.isoformat(), "--include-simulated").stdout
    assert "OLD-1" in text and "OVERDUE 10 d" in text and "LATER-1" not in text


def test_due_notify_sends_one_notification_per_instrument_falling_due(lc, monkeypatch):
    lc("instrument", "add", "ACC-0042", "--interval", "1y", "--customer", "Acme Aero")
    lc("instrument", "add", "ZT-7", "--interval", "1y")
    lc("instrument", "add", "ZT-8")  # no interval: never due
    with endpoint() as (url, inbox):
        monkeypatch.setenv("LABCAL_NOTIFY", url)
        doc = lc.json("due", "--notify", "--on", "2027-03-01")
        bodies = inbox.wait_for(2)
    assert doc["notifications"] == {"sent": 2, "failed": 0}
    assert sum("ACC-0042" in b and "Acme Aero" in b for b in bodies) == 1
    assert sum("ZT-7" in b for b in bodies) == 1


def test_due_notify_without_a_notification_url_says_so_in_one_line(lc):
    lc("instrument", "add", "ACC-0042", "--interval", "1y")
    done = lc("due", "--notify", check=2)
    assert "no notification URLs" in done.stderr and done.stderr.count("\n") == 1


def test_the_staircase_lengthens_after_in_tolerance_and_shortens_after_out_of_tolerance():
    """ILAC-G24:2007 method 1: one step per calibration, by the lab's factors ×1.25 and ×0.5."""
    def history(result: bool | None) -> list[Calibration]:
        return [Calibration("c1", date(2025, 1, 31), True), Calibration("c2", date(2026, 1, 31), result)]

    assert suggested_interval(360, history(True)) == 450  # 360 × 1.25
    assert suggested_interval(360, history(False)) == 180  # 360 × 0.5
    assert suggested_interval(360, history(None)) is None  # nothing to judge by
    assert suggested_interval(None, history(True)) is None
    assert suggested_interval(360, []) is None


# --- PostgreSQL -----------------------------------------------------------------------------------


def test_the_register_on_the_labs_postgresql_server_is_one_instrument_whatever_the_case(postgres_url):  # noqa: F811
    lab = open_lab(OpenLab(postgres_url, must_exist=False))
    try:
        from labcal.app import instruments

        instruments.add(lab, "ACC-0042", instruments.InstrumentFields(customer="Acme 100%", interval="12m"))
        with pytest.raises(LabcalError, match="already registered as ACC-0042"):
            instruments.add(lab, "acc-0042", instruments.InstrumentFields())
        assert [i.serial for i in instruments.listed(lab, "100%")] == ["ACC-0042"]
        assert instruments.listed(lab, "0%x") == []
        assert instruments.registered(lab, "Acc-0042").interval_days == 365
    finally:
        lab.close()
    assert serial_for_run("acc-0042", postgres_url).serial == "ACC-0042"


def test_a_run_recorded_with_a_trailing_space_in_its_serial_is_mended_by_report(lc, tmp_path, lab_database):
    """A run journaled by a labcal before serials were checked holds "ACC-0042 " (set here in its
    journal row and run.json, as that labcal wrote them): `labcal report RUN --serial ACC-0042`
    issues the certificate and a schema-valid DCC for ACC-0042 rather than refusing the two as
    different serials."""
    import sqlite3

    lc("run", "--sim", "--yes", "--no-report", "--seed", "2", "--serial", "ACC-0042", "--out",
       str(tmp_path / "run"))
    with sqlite3.connect(lab_database) as db:
        db.execute("UPDATE runs SET instrument_serial = 'ACC-0042 '")
    run_json = tmp_path / "run" / "run.json"
    run_json.write_text(json.dumps({**json.loads(run_json.read_text(encoding="utf-8")),
                                    "instrument_serial": "ACC-0042 "}), encoding="utf-8")
    lc("report", str(tmp_path / "run"), "--serial", "ACC-0042")
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    assert cert["instrument"]["serial"] == "ACC-0042"
    assert ">ACC-0042<" in (tmp_path / "run" / "certificate.dcc.xml").read_text(encoding="utf-8")
