"""`labcal runs` and `labcal log RUN`: the lab's runs and one run's journaled events."""

from __future__ import annotations

import io
import json
import sys

from labcal.cli import main


def _run(capsys, monkeypatch, *args, stdin: str = "") -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_runs_lists_and_filters_and_log_shows_prompts_and_answers(tmp_path, capsys, monkeypatch):
    done, stopped = tmp_path / "done", tmp_path / "stopped"
    assert _run(capsys, monkeypatch, "run", "--sim", "--yes", "--no-report", "--serial", "ACC-7",
                "--operator", "A. Tech", "--out", str(done))[0] == 0
    assert _run(capsys, monkeypatch, "run", "--sim", "--no-report", "--out", str(stopped),
                stdin="y\nq\n")[0] == 1

    code, out, _ = _run(capsys, monkeypatch, "runs", "--json")
    runs = json.loads(out)["runs"]
    summary = [(r["id"], r["serial"], r["status"], r["points_ok"], r["operator"]) for r in runs]
    assert code == 0 and summary == [(1, "ACC-7", "complete", 64, "A. Tech"), (2, None, "stopped", 16, None)]
    assert runs[1]["run_dir"] == str(stopped) and runs[0]["plan"] == "four-mount-64"
    code, out, _ = _run(capsys, monkeypatch, "runs", "--status", "stopped", "--json")
    assert [r["id"] for r in json.loads(out)["runs"]] == [2]
    code, out, _ = _run(capsys, monkeypatch, "runs", "--serial", "ACC-7")
    lines = out.splitlines()
    assert code == 0 and any(line.split()[:4] == ["1", "ACC-7", "four-mount-64", "complete"]
                             for line in lines)
    assert all(len(line) <= 80 for line in lines) and "stopped" not in out

    code, out, _ = _run(capsys, monkeypatch, "log", str(stopped))  # by run directory
    assert code == 0 and out.startswith("run 2: four-mount-64") and "stopped (operator stopped" in out
    assert "prompt: mount" in out and "answer: mount: confirmed" in out
    code, out, _ = _run(capsys, monkeypatch, "log", "2", "--json")  # by id
    events = json.loads(out)["events"]
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "segment"  # the run's clock starts (its offset is journaled:)
    # the tables go to the load position (each move journaled before it starts:), then the prompt
    assert kinds[1:4] == ["move", "prompt", "answer"] and all(e["utc"] for e in events)


def test_runs_and_log_without_a_database(tmp_path, capsys, monkeypatch):
    db = tmp_path / "none" / "lab.sqlite"
    code, out, _ = _run(capsys, monkeypatch, "runs", "--db", str(db))
    assert code == 0 and "(it does not exist yet)" in out and not db.parent.exists()  # nothing created
    code, _, err = _run(capsys, monkeypatch, "log", "3", "--db", str(db))
    assert code == 2 and "no lab database here" in err
    code, _, err = _run(capsys, monkeypatch, "log", str(tmp_path / "nope"))
    assert code == 2 and "neither a run number (see labcal runs), a run's uuid nor a run directory" in err


def test_a_killed_run_is_listed_as_interrupted_and_found_by_that_status(tmp_path, capsys, monkeypatch):
    """kill -9 leaves the journal saying "running"; nobody holds the run's lock any more, so
    `labcal runs` says what it is: interrupted (and `labcal resume` goes on with it)."""
    import os
    import signal
    import sqlite3
    import subprocess
    import time
    from pathlib import Path

    labcal = str(Path(sys.executable).with_name("labcal"))
    db = os.environ["LABCAL_DB"]
    proc = subprocess.Popen([labcal, "run", "--sim", "--no-report", "--out", str(tmp_path / "r")],
                            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            text=True)
    proc.stdin.write("y\n")  # mount 1; the prompt for mount 2 then waits for ever
    proc.stdin.flush()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            with sqlite3.connect(db, timeout=5) as con:
                if con.execute("SELECT COUNT(*) FROM points").fetchone()[0] >= 16:
                    break
        except sqlite3.OperationalError:
            pass  # not made yet
        time.sleep(0.05)
    code, out, _ = _run(capsys, monkeypatch, "runs", "--json")
    assert code == 0 and json.loads(out)["runs"][0]["status"] == "running"  # alive: its lock is held
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    code, out, _ = _run(capsys, monkeypatch, "runs", "--json")
    assert code == 0 and json.loads(out)["runs"][0]["status"] == "interrupted"
    code, out, _ = _run(capsys, monkeypatch, "runs", "--status", "interrupted", "--json")
    assert [r["id"] for r in json.loads(out)["runs"]] == [1]
    code, out, _ = _run(capsys, monkeypatch, "runs", "--status", "running", "--json")
    assert json.loads(out)["runs"] == []
