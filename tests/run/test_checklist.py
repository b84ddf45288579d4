"""The pre-run checklist: each item ok and failing on real station objects (the simulated
rig, and the emulated stations through the real drivers), `station check --json`, a run refused
before anything moves, and a station's output units reaching fit.json and the certificate.

Expected lines and figures are written out by hand from the rule each item states."""

from __future__ import annotations

import io
import json
import re
import shutil
import sqlite3
from datetime import date, datetime, timedelta, timezone

import pytest
from cli import cli
from emulators import TIME_SCALE, emulated, no_leaks, private_file  # noqa: F401 - fixture

from labcal.bench import checklist
from labcal.bench.checklist import Item, PowerOn
from labcal.config.emulation import FaultKind
from labcal.config.station import InstrumentSettings, load_station
from labcal.config.uncertainty import Traceability
from labcal.errors import LabcalError
from labcal.sim.faults import Fault

ZONE = timezone(timedelta(hours=1))  # any fixed zone: nothing here reads the wall clock
NOW = datetime(2026, 11, 26, 14, 42, tzinfo=ZONE)
WARM_30 = InstrumentSettings(warm_up_min=30)
EMULATE = ["--emulate", "--time-scale", str(TIME_SCALE)]


# --- warm-up ---------------------------------------------------------------------------------
def test_warm_up_ok_when_the_station_asks_none_or_the_operator_says_so():
    assert checklist.warm_up(None, PowerOn(), NOW).status == "ok"  # the simulated rig
    assert checklist.warm_up(InstrumentSettings(), PowerOn(), NOW) == Item(
        "warm-up", "ok", "the station declares no warm-up time ([instrument] warm_up_min)")
    assert checklist.warm_up(WARM_30, PowerOn(warmed_up=True), NOW) == Item(
        "warm-up", "ok", "warmed up, as the operator stated (30 min asked)")


def test_warm_up_counts_the_minutes_since_power_on():
    # on at 13:57, now 14:42: 45 min ≥ 30 min
    on = datetime(2026, 11, 26, 13, 57, tzinfo=ZONE)
    assert checklist.warm_up(WARM_30, PowerOn(on), NOW) == Item(
        "warm-up", "ok", "powered on at 13:57, 45 min ago (30 min asked)")
    # on at 14:30, now 14:42: 12 min < 30 min; warm at 14:30 + 30 min = 15:00
    on = datetime(2026, 11, 26, 14, 30, tzinfo=ZONE)
    assert checklist.warm_up(WARM_30, PowerOn(on), NOW) == Item(
        "warm-up", "fail", "powered on at 14:30, only 12 min ago; the station asks 30 min: wait until 15:00, "
                           "or go on with --warmed-up")


def test_warm_up_unsaid_fails_a_run_and_warns_a_check():
    why = ("the station asks 30 min after power-on and nobody said when the instrument was switched on: give "
           "--powered-on HH:MM, or --warmed-up")
    assert checklist.warm_up(WARM_30, PowerOn(), NOW) == Item("warm-up", "fail", why)
    assert checklist.warm_up(WARM_30, PowerOn(), NOW, unsaid="warning") == Item("warm-up", "warning", why)


def test_power_on_time_as_a_technician_writes_it():
    assert checklist.parse_power_on("14:05", NOW) == datetime(2026, 11, 26, 14, 5, tzinfo=ZONE)
    assert checklist.parse_power_on("2026-11-25 23:30", NOW) == datetime(2026, 11, 25, 23, 30, tzinfo=ZONE)
    with pytest.raises(LabcalError, match=r"^--powered-on: 15:10 is later than now \(14:42\); give when"):
        checklist.parse_power_on("15:10", NOW)
    with pytest.raises(LabcalError, match=r"^--powered-on: 'noon' is not a time; give HH:MM"):
        checklist.parse_power_on("noon", NOW)


# --- reference standards -----------------------------------------------------------------------
def standard(due: date) -> Traceability:
    return Traceability(equipment="DMM", identity="Keysight 34970A MY1", certificate="C-7", due=due)


def test_reference_standards_in_date_and_overdue():
    today = date(2026, 11, 26)
    assert checklist.standards([standard(date(2027, 3, 1)), standard(date(2026, 12, 1))], today) == Item(
        "reference standards", "ok", "2 in date (next due 2026-12-01)")
    overdue = checklist.standards([standard(date(2026, 11, 25))], today)
    assert overdue.status == "warning"
    assert overdue.why.startswith("Reference standard DMM (Keysight 34970A MY1, certificate C-7) is overdue "
                                  "for calibration: due 25 November 2026, today 26 November 2026.")
    assert checklist.standards([standard(today)], today).status == "ok"  # due today is not yet overdue
    assert checklist.standards([], today).status == "warning"  # the certificate would name none
    assert checklist.standards(None, today).status == "ok"  # the simulated rig


# --- tables homed ------------------------------------------------------------------------------
def test_simulated_tables_are_homed():
    from labcal.bench.setup import sim_station

    assert checklist.tables_homed(None, sim_station(None, 1).station) == Item(
        "tables homed", "ok", "simulated tables: homed")


def test_smc100_tables_not_referenced_then_homed(tmp_path, no_leaks):  # noqa: F811
    """An SMC100 powers up NOT REFERENCED (0Ah; hardware_protocols.md §2.2); homing (OR) leaves it
    READY from HOMING (32h)."""
    with emulated("smc100-tcp", tmp_path) as (_, bench):
        before = checklist.tables_homed(bench, None)
        assert before.status == "warning"
        assert before.why.startswith("pitch: NOT REFERENCED from reset (0Ah); roll: NOT REFERENCED from "
                                     "reset (0Ah) (the run homes a table NOT REFERENCED first")
        for axis in bench.axes:
            axis.prepare()  # homes it
        assert checklist.tables_homed(bench, None) == Item(
            "tables homed", "ok", "pitch: READY from HOMING (32h); roll: READY from HOMING (32h)")


def test_az_tables_ok_then_an_alarm_fails(tmp_path, no_leaks):  # noqa: F811
    """An AZ drive has an absolute encoder: no homing; alarm 4Ah (return-to-home incomplete, §2.1
    alarm table) on the roll drive fails the item with the drive's own words."""
    from labcal.sim.az_emulator import AzServer

    with emulated("az-modbus-tcp", tmp_path) as (emulation, bench):
        ok = checklist.tables_homed(bench, None)
        assert ok.status == "ok" and ok.why.count("absolute encoder, no alarm") == 2, ok.why
        server = next(s for _, _, s in emulation.servers.values() if isinstance(s, AzServer))
        unit = next(u for u in server.drives.units.values() if u.name == "roll")
        server.drives.raise_alarm(unit, 0x4A)
        failed = checklist.tables_homed(bench, None)
        assert failed.status == "fail"
        assert "roll: alarm 4Ah (return-to-home incomplete)" in failed.why
        assert failed.why.startswith("pitch: READY")


def test_an_az_drive_whose_stop_input_is_on_fails(tmp_path, no_leaks):  # noqa: F811
    """STOP on (reference input 007Dh bit 5, hardware_protocols.md §2.1) and the drive starts no move:
    the item fails with what to do, though no alarm is on."""
    with emulated("az-modbus-tcp", tmp_path) as (_, bench):
        bench.pitch.link.write_one(bench.pitch.unit, 0x007D, 1 << 5)
        item = checklist.tables_homed(bench, None)
    assert item.status == "fail" and item.why.startswith("pitch: "), item.why
    assert "its STOP input is on" in item.why and "--reset-alarms" in item.why
    assert "roll: READY" in item.why


# --- DMM -----------------------------------------------------------------------------------
def test_dmm_configured_and_read_back(tmp_path, no_leaks):  # noqa: F811
    with emulated("smc100-tcp", tmp_path) as (_, bench):
        item = checklist.dmm(bench)
    assert item.status == "ok"
    assert re.fullmatch(r"Keysight Technologies 34970A serial \S+ configured and read back as declared "
                        r"\(10 V range, 10 PLC, channels 101,102,103\)", item.why), item.why
    assert checklist.dmm(None) == Item("DMM", "ok", "simulated DMM: nothing to test")


def test_dmm_that_does_not_answer_fails(tmp_path, no_leaks):  # noqa: F811
    with emulated("smc100-tcp", tmp_path, dmm={"timeout_s": 0.1, "reconnect_s": 0.0}) as (emulation, bench):
        emulation.faults["dmm"].add(Fault(FaultKind.NO_REPLY, count=100, match="IDN"))
        item = checklist.dmm(bench)
    assert item.status == "fail" and item.why.startswith("dmm (Keysight 34970A, tcp 127.0.0.1:"), item.why
    assert "): no reply within 0.1 s; check that it is powered and cabled" in item.why


# --- free disk ---------------------------------------------------------------------------------
def test_bytes_needed_by_hand():
    # 64 points × 3 tries × (10 samples × 4 channels × 8 B + 4 000 B) = 64 × 3 × 4 320 = 829 440 B;
    # the folder: 64 × 300 B + 5 000 000 B = 5 019 200 B
    assert checklist.bytes_needed(64, 10) == (829_440, 5_019_200)


def test_free_disk_ok_and_short(tmp_path):
    free = shutil.disk_usage(tmp_path).free
    ok = checklist.free_disk(tmp_path, tmp_path / "runs" / "new", 64, 10)
    # one disk: the two needs add up, 829 440 + 5 019 200 = 5 848 640 B = "5.8 MB"
    assert ok.why.endswith("the run needs about 5.8 MB (64 points)") and ok.why.count("free in") == 1
    assert ok.status == ("ok" if free >= 2 * 5_848_640 else "warning" if free >= 5_848_640 else "fail")
    points = free // (3 * 4_320) + 1  # one point more than the disk holds, by the journal alone
    short = checklist.free_disk(tmp_path, tmp_path, points, 10)
    assert short.status == "fail" and short.why.endswith("; free space there before the run")


@pytest.fixture
def small_disk(tmp_path):
    """A 12 kB filesystem of its own (tmpfs): no run folder fits; skipped where none can be mounted."""
    import subprocess

    where = tmp_path / "small"
    where.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=12k", "tmpfs", str(where)],
                          capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({made.stderr.decode().strip()})")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_run_whose_folder_does_not_fit_is_refused(tmp_path, small_disk, capsys, lab_database):
    code, _, err = cli(capsys, "run", "--sim", "--yes", "--no-report", "--out", str(small_disk / "r"))
    assert code == 2
    line = err.strip().splitlines()[-1]
    # 12 kB free against 64 × 300 B + 5 MB = 5.0 MB for the folder (the journal is elsewhere)
    assert line.startswith("labcal: error: pre-run checklist: free disk: ") and line.endswith(
        f"free in {small_disk}, the run needs about 5.0 MB (64 points); free space there before the run; "
        "nothing was moved"), line
    assert list(small_disk.iterdir()) == []


# --- lab database ------------------------------------------------------------------------------
def test_lab_database_opens_or_says_why(tmp_path):
    assert checklist.lab_database(tmp_path / "lab.sqlite") == Item(
        "lab database", "ok", f"{tmp_path / 'lab.sqlite'} opens")
    (tmp_path / "a-file").write_text("not a folder")
    failed = checklist.lab_database(tmp_path / "a-file" / "lab.sqlite")
    assert failed == Item("lab database", "fail",
                          f"{tmp_path / 'a-file'}: cannot create the database folder (File exists)")


# --- the commands ------------------------------------------------------------------------------
ITEMS = ["warm-up", "reference standards", "tables homed", "DMM", "free disk", "lab database"]


def test_station_check_json_carries_the_checklist(tmp_path, capsys, no_leaks):  # noqa: F811
    path = private_file("az-modbus-tcp", tmp_path, "\n[instrument]\nwarm_up_min = 20\n")
    code, out, err = cli(capsys, "station", "check", str(path), *EMULATE, "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert set(doc) == {"station", "ok", "devices", "checklist", "overdue_standards"} and doc["ok"] is True
    assert [i["item"] for i in doc["checklist"]] == ITEMS
    assert all(set(i) == {"item", "status", "message"} and i["status"] in ("ok", "warning")
               for i in doc["checklist"])
    by = {i["item"]: i for i in doc["checklist"]}
    assert by["warm-up"]["status"] == "warning"  # a check asks nobody: it says what a run will want
    assert by["tables homed"]["status"] == "ok" and by["DMM"]["status"] == "ok"


def test_station_check_fails_on_an_unmet_item(tmp_path, capsys, no_leaks):  # noqa: F811
    (tmp_path / "a-file").write_text("")
    code, _, err = cli(capsys, "station", "check", str(private_file("az-modbus-tcp", tmp_path)), *EMULATE,
                       "--db", str(tmp_path / "a-file" / "lab.sqlite"))
    assert code == 2
    assert err.strip().splitlines()[-1] == ("labcal: error: pre-run checklist: lab database not met; see the "
                                            "lines above (a run would be refused)")


def test_an_unwarmed_run_with_yes_is_refused_before_anything_moves(tmp_path, capsys, lab_database,
                                                                    no_leaks):  # noqa: F811
    """--yes with the station's warm-up unsaid: one line, exit 2, no run journaled, and the tables
    asked only their state (TS) — never homed (OR), enabled (MM) or moved (PA)."""
    path = private_file("smc100-tcp", tmp_path, "\n[instrument]\nwarm_up_min = 30\n")
    log = tmp_path / "devices.log"
    code, _, err = cli(capsys, "--log-file", str(log), "--log-level", "debug", "run", "--station", str(path),
                       *EMULATE, "--yes", "--no-report", "--out", str(tmp_path / "run"))
    assert code == 2
    assert err.strip().splitlines()[-1] == (
        "labcal: error: pre-run checklist: warm-up: the station asks 30 min after power-on and nobody said "
        "when the instrument was switched on: give --powered-on HH:MM, or --warmed-up; nothing was moved")
    assert "Traceback" not in err and not (tmp_path / "run").exists()
    with sqlite3.connect(lab_database) as db:
        assert db.execute("SELECT count(*) FROM runs").fetchone() == (0,)
        assert db.execute("SELECT count(*) FROM points").fetchone() == (0,)
    sent = re.findall(r" > (\S+)", log.read_text())
    to_tables = [s for s in sent if re.match(r"[12][A-Z]", s)]  # SMC100 commands start with the address
    assert to_tables and set(to_tables) == {"1TS", "2TS"}, to_tables


def test_an_attended_run_asks_whether_to_go_on(tmp_path, capsys, monkeypatch, lab_database, no_leaks):  # noqa: F811
    """At the terminal an unmet item is a question; 'n' (or nothing) stops, nothing moved. Here the
    warm-up: the station asks 30 min, and the technician leaves the power-on time unsaid."""
    path = private_file("smc100-tcp", tmp_path, "\n[instrument]\nwarm_up_min = 30\n")
    monkeypatch.setattr("sys.stdin", io.StringIO("\nn\n"))
    code, _, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--no-report", "--out",
                       str(tmp_path / "run"))
    assert code == 2
    assert "1 item(s) not met (warm-up). Go on anyway? (y/N)" in err
    # (the answer read from a pipe is not echoed: the error line follows the question on its line)
    assert err.strip().splitlines()[-1].endswith(
        "(y/N) labcal: error: pre-run checklist: warm-up: the station asks 30 min after power-on and "
        "nobody said when the instrument was switched on: give --powered-on HH:MM, or --warmed-up; "
        "nothing was moved")
    assert not (tmp_path / "run").exists()
    with sqlite3.connect(lab_database) as db:
        assert db.execute("SELECT count(*) FROM runs").fetchone() == (0,)


def test_an_unreachable_lab_server_is_a_warning_not_a_refusal(tmp_path, capsys):
    """A run never waits for the lab's server: the checklist says it cannot be reached and that the
    records will follow, and the item does not stop the run."""
    from services import free_port

    url = f"postgresql://labcal@127.0.0.1:{free_port()}/lab"  # nothing listens there
    code, out, err = cli(capsys, "station", "check", str(private_file("az-modbus-tcp", tmp_path)), *EMULATE,
                         "--db", url, "--json")
    doc = json.loads(out)
    by = {i["item"]: i for i in doc["checklist"]}
    assert by["lab database"]["status"] == "warning", by["lab database"]
    assert "cannot reach the lab database" in by["lab database"]["message"]
    assert "send its records when the server is back" in by["lab database"]["message"]


def test_the_warm_up_question_at_the_terminal(tmp_path, capsys, monkeypatch, lab_database, no_leaks):  # noqa: F811
    """Asked when it was switched on, the technician answers 'warm'; the run journals it."""
    path = private_file("az-modbus-tcp", tmp_path, "\n[instrument]\nwarm_up_min = 30\n")
    monkeypatch.setattr("sys.stdin", io.StringIO("warm\ny\n"))  # then y at the one mount's prompt
    code, _, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--no-report", "--plan",
                       "one-mount-16", "--out", str(tmp_path / "run"))
    assert code == 0, err
    assert "The instrument needs 30 min of warm-up: when was it switched on?" in err
    meta = json.loads((tmp_path / "run" / "run.json").read_text())["checklist"]
    assert meta["warmed_up_stated"] is True and meta["items"][0] == {
        "item": "warm-up", "status": "ok", "message": "warmed up, as the operator stated (30 min asked)"}


# --- units ---------------------------------------------------------------------------------------
def test_station_units_are_spelled_as_fit_takes_them(tmp_path):
    assert InstrumentSettings(units="millivolts").units == "mV"
    assert InstrumentSettings(units="m/s^2").units == "m/s2"
    bad = tmp_path / "bad.toml"
    bad.write_text(private_file("az-modbus-tcp", tmp_path).read_text()
                   + '\n[instrument]\nunits = "furlongs"\n')
    with pytest.raises(LabcalError, match=r"instrument\.units.*'furlongs' is not one of V, mV, counts, m/s2"):
        load_station(bad)


def test_station_units_reach_fit_json_and_the_certificate(tmp_path, capsys, no_leaks):  # noqa: F811
    """[instrument] units = "counts": readings.csv states it, fit.json and the certificate give B in
    counts and S in counts per g, and `labcal fit` of the run's readings agrees."""
    path = private_file("az-modbus-tcp", tmp_path, '\n[instrument]\nunits = "counts"\n')
    run = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--yes", "--plan", "one-mount-16",
                       "--out", str(run))
    assert code == 0, err
    assert (run / "readings.csv").read_text().splitlines()[0] == "# units = counts"
    fit = json.loads((run / "fit.json").read_text())
    assert fit["units"] == "counts" and fit["layout"]["units"] == "counts (bias), counts/g (sensitivity)"
    cert = json.loads((run / "certificate.json").read_text())
    assert cert["fit"]["layout"]["units"] == "counts (bias), counts/g (sensitivity)"
    # the budget: nothing in volts (the DMM's range and noise terms are volts, and counts are not
    # read through its range); the residual row in counts; the note says why
    budget = cert["uncertainty_budget"]
    assert budget["inputs"]["output_unit"] == "counts" and budget["inputs"]["dmm_range_v"] == 0
    assert "not volts" in budget["inputs"]["dmm_conditions"]
    units = {row["source"]: row["unit"] for row in budget["rows"]}
    assert "V" not in units.values() and "counts" in units.values(), units
    html = re.sub(r"data:[^\"')]*", "", (run / "report.html").read_text())  # figures' base64 bytes aside
    assert "B (counts)" in html and "counts/g" in html and "V/g" not in html
    dcc = (run / "certificate.dcc.xml").read_text(encoding="utf-8")
    assert "<si:unit>\\one</si:unit>" in dcc  # counts: dimensionless; S per m s⁻²
    assert "<si:unit>\\metre\\tothe{-1}\\second\\tothe{2}</si:unit>" in dcc
    assert "\\volt" not in dcc and "bias (counts) and sensitivity" in dcc
    code, out, err = cli(capsys, "fit", str(run / "readings.csv"), "--model", "linear", "--json")
    assert code == 0, err
    assert json.loads(out)["units"] == "counts"


def test_a_volts_station_writes_what_it_always_wrote(tmp_path, capsys, no_leaks):  # noqa: F811
    path = private_file("az-modbus-tcp", tmp_path)
    run = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--yes", "--no-report", "--plan",
                       "one-mount-16", "--out", str(run))
    assert code == 0, err
    assert (run / "readings.csv").read_text().startswith("replicate,")
    fit = json.loads((run / "fit.json").read_text())
    assert "units" not in fit and fit["layout"]["units"] == "V (bias), V/g (sensitivity)"


@pytest.mark.parametrize("unit, base", [("V", r"\volt"), ("mV", r"\milli\volt"), ("counts", r"\one"),
                                        ("m/s2", r"\metre\second\tothe{-2}")])
def test_dcc_units_per_output_unit_read_by_ptbs_parser(unit, base):
    """The DCC's D-SI spellings for each output unit, read by PTB's dsiunits (a second library): the
    bias in the unit, each sensitivity in it per m s⁻², the covariances their products."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from dsi_unit import DsiUnit

    from labcal.documents.dcc import DSI_UNITS

    _, units, covariances = DSI_UNITS[unit]
    b = DsiUnit(base)
    s = b / DsiUnit(r"\metre\second\tothe{-2}")
    assert all(DsiUnit(text).valid for text in (*units, *covariances))
    assert DsiUnit(units[0]) == b and all(DsiUnit(text) == s for text in units[1:])
    assert [DsiUnit(text) for text in covariances] == [b * b, b * s, s * s]
