"""What a run records about itself: where its folder is (absolute, so that `labcal
export RUN_ID` finds it from any folder), why it stopped (`labcal log`), every answer at a prompt,
and the device estimate whether or not a report is made."""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path

from labcal.cli import main
from labcal.store.journal import Journal


def _run(capsys, monkeypatch, *args, stdin: str = "") -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# --- 1. the run's folder is recorded absolute ---------------------------------------------------
def test_export_by_id_from_another_folder_uses_the_runs_folder(tmp_path, capsys, monkeypatch):
    db, here, elsewhere = tmp_path / "lab.sqlite", tmp_path / "bench", tmp_path / "elsewhere"
    here.mkdir()
    elsewhere.mkdir()
    monkeypatch.chdir(here)
    assert _run(capsys, monkeypatch, "run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16",
                "--out", "r", "--db", str(db))[0] == 0  # a relative --out, as a technician types it
    with Journal(db) as journal:
        assert journal.run(1).run_dir == str(here / "r")
    original = {p.name: p.read_bytes() for p in (here / "r").iterdir()}
    monkeypatch.chdir(elsewhere)
    (here / "r" / "fit.json").unlink()
    code, _, err = _run(capsys, monkeypatch, "export", "1", "--db", str(db))
    assert code == 0 and "fit.json was missing" in err and not any(elsewhere.iterdir())  # no second folder
    for p in (here / "r").iterdir():
        p.unlink()
    (here / "r").rmdir()
    assert _run(capsys, monkeypatch, "export", "1", "--db", str(db))[0] == 0  # recreated where it was
    assert not any(elsewhere.iterdir())
    assert {p.name: p.read_bytes() for p in (here / "r").iterdir()} == original


def test_an_older_runs_relative_folder_is_resolved_only_where_it_shows_that_run(tmp_path, capsys,
                                                                                  monkeypatch):
    db, here, elsewhere = tmp_path / "lab.sqlite", tmp_path / "bench", tmp_path / "elsewhere"
    here.mkdir()
    elsewhere.mkdir()
    monkeypatch.chdir(here)
    assert _run(capsys, monkeypatch, "run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16",
                "--out", "r", "--db", str(db))[0] == 0
    with Journal(db) as journal:
        journal.set_run_dir(1, "r")  # what an older labcal recorded: the --out as typed
    monkeypatch.chdir(elsewhere)
    code, out, err = _run(capsys, monkeypatch, "export", "1", "--db", str(db))
    assert code == 2 and out == "" and err.strip() == (
        "labcal: error: run 1: its folder was recorded as r, relative to the folder the run was started "
        "in, which the journal does not say; run this there, or give --out DIR")
    assert not any(elsewhere.iterdir())
    (elsewhere / "r").mkdir()  # a folder of that name that is not this run's is not taken for it
    assert _run(capsys, monkeypatch, "export", "1", "--db", str(db))[0] == 2
    monkeypatch.chdir(here)
    assert _run(capsys, monkeypatch, "export", "1", "--db", str(db))[0] == 0
    with Journal(db) as journal:
        assert journal.run(1).run_dir == str(here / "r")  # recorded absolute from now on
        events = [e for e in journal.events(1) if e.kind == "export"]
    assert [e.message for e in events] == [f"run folder recorded as {here / 'r'} (was r)"]


# --- 2. the log names why the tables stopped, and every answer ------------------------------------
def _log_text(capsys, monkeypatch, run: str, db: Path | None = None) -> str:
    """`labcal log RUN` as one line of words (the console wraps at its width; the words are the test)."""
    code, out, _ = _run(capsys, monkeypatch, "log", run, *(["--db", str(db)] if db else []))
    assert code == 0
    return " ".join(out.split())


def test_every_answer_at_a_prompt_is_journaled_and_the_stop_names_the_operator(tmp_path, capsys,
                                                                                 monkeypatch):
    code, _, _ = _run(capsys, monkeypatch, "run", "--sim", "--no-report", "--out", str(tmp_path / "r"),
                      stdin="n\nwait\nhuh\ny\nq\n")
    assert code == 1
    code, out, _ = _run(capsys, monkeypatch, "log", "1", "--json")
    answers = [e["message"] for e in json.loads(out)["events"] if e["kind"] == "answer"]
    assert answers == ["mount: 'n' (not yet; the prompt stays open)",
                       "mount: 'wait' (not yet; the prompt stays open)",
                       "mount: 'huh' (not one of the answers; the prompt stays open)",
                       "mount: confirmed", "mount: declined"]
    text = _log_text(capsys, monkeypatch, "1")
    assert ("answer: mount: declined (operator stopped the run at the remount prompt)" in text
            and "stop: both tables stopped (after operator stopped the run at the remount prompt)" in text)


def _committed(db: Path) -> int:
    import sqlite3

    try:
        with sqlite3.connect(db) as con:
            return con.execute("SELECT COUNT(*) FROM points").fetchone()[0]
    except sqlite3.OperationalError:  # not created yet
        return 0


def _terminated(args: list[str], db: Path, after_points: int) -> int:
    """`labcal ARGS` in a child process, sent SIGTERM once ``after_points`` points are journaled."""
    import signal
    import subprocess
    import time

    proc = subprocess.Popen([sys.executable, "-m", "labcal.cli", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while _committed(db) < after_points:
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.stderr else ""
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert "Traceback" not in err, err
    return proc.returncode


def test_a_sigterm_is_named_on_the_stop_line_also_after_a_resume(tmp_path, capsys, monkeypatch, lab_database):
    import signal

    folder = tmp_path / "r"
    assert _terminated(["run", "--sim", "--yes", "--no-report", "--replicates", "20", "--out", str(folder)],
                       lab_database, 20) == 128 + signal.SIGTERM
    done = _committed(lab_database)
    assert _terminated(["resume", str(folder), "--yes", "--no-report"], lab_database,
                       done + 20) == 128 + signal.SIGTERM
    text = _log_text(capsys, monkeypatch, str(folder))
    assert text.count("stop: both tables stopped (after SIGTERM)") == 2, text
    assert text.index("resume") < text.rindex("stop: both tables stopped (after SIGTERM)")


def test_a_fault_in_an_unattended_run_is_its_recorded_cause(tmp_path, capsys, monkeypatch, lab_database):
    """--yes with nobody at the console (input closed): the drive alarm that paused the run is
    why it stopped, not the unanswered pause prompt."""
    from emulators import private_file

    fault = '\n[[emulation.faults]]\ndevice = "roll"\nkind = "alarm"\ncode = 16\nafter = 150\n'
    station = private_file("az-modbus-rtu", tmp_path, fault, "timeout_s = 0.2")
    code, _, err = _run(capsys, monkeypatch, "run", "--station", str(station), "--emulate", "--time-scale",
                        "1000", "--no-report", "--yes", "--out", str(tmp_path / "r"))  # stdin: none
    assert code == 1 and "Traceback" not in err, err
    with Journal(lab_database) as journal:
        reason = journal.run(1).reason
    # the alarm is met by a move's check or, as here since every window is vouched for, by the
    # status read after a measurement window: either way the fault, naming the table, is the cause
    assert reason.startswith("fault: ") and "roll table (Oriental Motor AZ, unit 2 on " in reason and \
        "alarm 10h (excessive position deviation)" in reason, reason
    assert reason.endswith("; paused, and no answer at the prompt (input closed)")
    text = _log_text(capsys, monkeypatch, "1")
    (stop,) = [line for line in text.splitlines() if "stop: both tables stopped (after " in line]
    assert "roll table (Oriental Motor AZ, unit 2 on" in stop, stop


# --- 3. the device estimate is the run's ----------------------------------------------------------
def test_a_run_without_a_report_still_reaches_the_device_history(tmp_path, capsys, monkeypatch):
    """--no-report skips the certificate, not the device: device.json and the history entry are
    there, and they are the estimate the run printed (its --json)."""
    db = tmp_path / "lab.sqlite"
    code, out, _ = _run(capsys, monkeypatch, "run", "--sim", "--yes", "--no-report", "--json", "--db",
                        str(db), "--out", str(tmp_path / "run"))
    assert code == 0
    printed = json.loads(out)["device"]["misalignments"]
    assert not (tmp_path / "run" / "certificate.json").exists()
    device = json.loads((tmp_path / "run" / "device.json").read_text())
    code, out, _ = _run(capsys, monkeypatch, "device", "history", "SIMULATED", "--db", str(db), "--json")
    (stored,) = json.loads(out)["estimates"]
    assert stored["source"] == "run"
    for name, m in stored["misalignments"].items():
        assert m["value_arcsec"] == device["misalignments"][name]["value_arcsec"] \
            == printed[name]["value_arcsec"]
        assert m["U_arcsec"] == device["misalignments"][name]["U_arcsec"]
