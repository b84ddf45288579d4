"""`labcal runs` and `labcal log RUN` (issue 15): the lab's runs and one run's journaled events."""

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
    monkeypatch.setenv("COLUMNS", "80")
    done, stopped = tmp_path / "done", tmp_path / "stopped"
    assert _run(capsys, monkeypatch, "run", "--sim", "--yes", "--no-report", "--serial", "ACC-7",
                "--operator", "A. Tech", "--out", str(done))[0] == 0
    assert _run(capsys, monkeypatch, "run", "--sim", "--no-report", "--out", str(stopped),
                stdin="y\nq\n")[0] == 1

    code, out, _ = _run(capsys, monkeypatch, "runs", "--json")
    runs = json.loads(out)["runs"]
    summary = [(r["id"], r["instrument"], r["status"], r["points"], r["operator"]) for r in runs]
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
    assert kinds[0] == "segment"  # the run's clock starts (its offset is journaled: issue 16)
    assert kinds[1:3] == ["prompt", "answer"] and all(e["utc"] for e in events)


def test_runs_and_log_without_a_database(tmp_path, capsys, monkeypatch):
    db = tmp_path / "none" / "lab.sqlite"
    code, out, _ = _run(capsys, monkeypatch, "runs", "--db", str(db))
    assert code == 0 and "(it does not exist yet)" in out and not db.parent.exists()  # nothing created
    code, _, err = _run(capsys, monkeypatch, "log", "3", "--db", str(db))
    assert code == 2 and "no lab database here" in err
    code, _, err = _run(capsys, monkeypatch, "log", str(tmp_path / "nope"))
    assert code == 2 and "neither a run id (see labcal runs) nor a run directory" in err
