"""The command line: contracts (CSV, JSON), bad input, prompts, interruption."""

from __future__ import annotations

import argparse
import csv
import io
import json
import signal
import subprocess
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from cli import LABCAL, cli, labcal

from labcal.cli import build_parser

CONTRACT = ("replicate", "y_deg", "u_deg", "pitch_deg", "roll_deg", "vx", "vy", "vz")  # docs/design.md §5
MISALIGN = "a=0.3,b=-0.2,d=0.1,e=0.4,f=-0.3,k=0.2"


# --- contracts -----------------------------------------------------------------------------
def test_simulate_then_fit_four_mounts_cancels_every_misalignment(tmp_path, capsys):
    out = tmp_path / "r.csv"
    code, _, _ = cli(capsys, "simulate", "--plan", "four-mount-64", "--misalign", MISALIGN,
                         "--noise", "0", "--seed", "1", "--out", str(out))
    assert code == 0
    with out.open() as f:
        header = next(csv.reader(f))
    assert tuple(header[:8]) == CONTRACT
    code, stdout, _ = cli(capsys, "fit", str(out), "--model", "linear", "--json")  # Soto's Part 1
    assert code == 0
    doc = json.loads(stdout)
    assert doc["model"] == "linear"
    X = np.array(doc["coefficients"])
    assert X.shape == (4, 3)
    off_diagonal = X[1:][~np.eye(3, dtype=bool)]
    assert np.max(np.abs(X[0])) < 1e-12 and np.max(np.abs(off_diagonal)) < 1e-12
    a, b, d, e, f, k = np.radians([0.3, -0.2, 0.1, 0.4, -0.3, 0.2])
    assert X[1, 0] == pytest.approx(np.cos(a) * np.cos(b) * np.cos(d) * np.cos(e) * np.cos(k), abs=1e-12)
    assert doc["degrees_of_freedom"] == 60 and doc["n_points"] == 64
    assert np.array(doc["standard_errors"]).shape == (4, 3)
    assert len(doc["residual_standard_error"]) == 3


def test_simulate_one_mount_leaks_e_f_k(tmp_path, capsys):
    out = tmp_path / "r.csv"
    cli(capsys, "simulate", "--plan", "one-mount-16", "--misalign", MISALIGN, "--out", str(out))
    _, stdout, _ = cli(capsys, "fit", str(out), "--json")
    X = np.array(json.loads(stdout)["coefficients"])
    e, f, k = np.radians([0.4, -0.3, 0.2])
    # Soto eq. 33 to first order (second-order terms ≤ 5e-5 for 0.4° angles)
    assert X[2, 0] == pytest.approx(-k, abs=5e-5) and X[1, 1] == pytest.approx(k, abs=5e-5)
    assert X[3, 0] == pytest.approx(e, abs=5e-5) and X[1, 2] == pytest.approx(-e, abs=5e-5)
    assert X[3, 1] == pytest.approx(f, abs=5e-5) and X[2, 2] == pytest.approx(-f, abs=5e-5)


def test_simulate_with_truth_file_and_noise(tmp_path, capsys):
    truth = tmp_path / "truth.toml"
    truth.write_text("B = [0.01, -0.02, 0.03]\nS = [[5.0, 0.01, 0.0], [0.0, 5.1, 0.0], [0.0, 0.0, 4.9]]\n")
    out = tmp_path / "r.csv"
    cli(capsys, "simulate", "--truth", str(truth), "--noise", "1e-5", "--seed", "4",
            "--index-error", "2", "--wobble", "3", "--out", str(out))
    _, stdout, _ = cli(capsys, "fit", str(out), "--json")
    doc = json.loads(stdout)
    X, se = np.array(doc["coefficients"]), np.array(doc["standard_errors"])
    assert np.all(np.abs(X[0] - [0.01, -0.02, 0.03]) < 4 * se[0] + 1e-6)
    assert X[1, 1] == pytest.approx(0.01, abs=1e-4)


def test_plan_list_and_show(capsys):
    code, stdout, _ = cli(capsys, "plan", "list", "--json")
    plans = {p["name"]: p for p in json.loads(stdout)["plans"]}
    assert code == 0 and plans["four-mount-64"]["points"] == 64 and plans["one-mount-16"]["points"] == 16
    code, stdout, _ = cli(capsys, "plan", "show", "four-mount-64")
    assert code == 0 and "bottom side of the plate, x sensor pointing backward" in stdout


def command_paths(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """Every parser of the real argparse tree, as the words that reach it (() is `labcal` itself),
    recursing into every subparsers action; an alias is the same parser and is walked once."""
    yield path
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen: set[int] = set()
            for name, child in action.choices.items():
                if id(child) not in seen:
                    seen.add(id(child))
                    yield from command_paths(child, (*path, name))


# Counted by hand from `labcal --help` and each group's help (today): labcal; run, resume, fit,
# simulate, attitude, report, history; plan + list, show, merit, audit, generate + d1, d0, tumble,
# fractional, grid; station + list, check; sim + serve. A walk that silently finds less fails.
PARSERS_COUNTED_BY_HAND = 24


def test_every_command_and_sub_command_has_help():
    """`labcal <path> --help` through the installed executable, for every parser in the tree: exit
    0, a usage line that names the whole path, and help text on stdout (nothing on stderr)."""
    paths = list(command_paths(build_parser()))
    assert len(paths) >= PARSERS_COUNTED_BY_HAND, paths
    assert len(set(paths)) == len(paths)
    with ThreadPoolExecutor(max_workers=4) as pool:  # 24 interpreter start-ups: ~2 s instead of ~8 s
        results = list(pool.map(lambda path: labcal(*path, "--help"), paths))
    for path, done in zip(paths, results, strict=True):
        usage = " ".join(("labcal", *path))
        assert done.returncode == 0, (path, done.stderr)
        assert done.stdout.startswith(f"usage: {usage} ") or done.stdout.startswith(f"usage: {usage}\n"), \
            (path, done.stdout[:200])
        body = done.stdout.split("\n\n", 1)
        assert len(body) == 2 and body[1].strip(), (path, done.stdout)  # more than the usage line
        assert "-h, --help" in done.stdout and done.stderr == "", (path, done.stderr)


def test_help_lists_exactly_what_the_whole_command_line_has():
    """`labcal --help` builds no command's parser (it lists them from `labcal.commands.COMMANDS`):
    its text is the same as the whole command line's, command for command, and a command named on
    the line gets its whole parser however it is placed there."""
    whole = build_parser()
    listed = build_parser(only={"--help"})
    assert listed.format_help() == whole.format_help()
    sub = next(a for a in whole._actions if isinstance(a, argparse._SubParsersAction))
    assert len(sub.choices) == 23  # counted by hand in the help text above
    assert build_parser(only={"--log-level", "debug", "log"}).parse_args(
        ["--log-level", "debug", "log", "7", "--json"]).json is True


# --- bad input: one line, exit 2, no traceback -------------------------------------------
READINGS_HEADER = ",".join(CONTRACT)
GOOD_ROW = "1,0,0,0,0,0.1,0.2,1.0"


@pytest.mark.parametrize("content,expected", [
    ("", "file is empty"),
    (READINGS_HEADER + "\n", "header only, no data rows"),
    ("replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy\n1,0,0,0,0,0.1,0.2\n", "missing column(s) vz"),
    (f"{READINGS_HEADER}\n{GOOD_ROW}\n1,0,0,0,90,0.1,abc,1.0\n", "line 3, column vy: 'abc' is not a number"),
    (f"{READINGS_HEADER}\n1,0,0,0,90,nan,0.2,1.0\n", "line 2, column vx: value is nan"),
    (f"{READINGS_HEADER}\n1,90,0,0,90,0.1,0.2,1.0\n", "column y_deg: 90 is not a mount angle"),
    (f"{READINGS_HEADER}\n1,0,0,0\n", "line 2: 4 fields, the header has 8"),
    (f"{READINGS_HEADER}\n" + "1,0,0,0,0,0.1,0.2,1.0\n" * 6, "singular"),
])
def test_bad_readings(tmp_path, capsys, content, expected):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    code, stdout, stderr = cli(capsys, "fit", str(path))
    assert code == 2 and stdout == ""
    assert expected in stderr and str(path) in stderr or expected == "singular" and expected in stderr
    assert stderr.strip().count("\n") == 0 and "Traceback" not in stderr


PLAN_HEAD = 'name = "x"\nmounts = [[0, 0]]\n'


@pytest.mark.parametrize("content,expected", [
    ('name = "x"\nmounts = [[0, 0]\n', "malformed TOML"),
    (PLAN_HEAD + "points = [[0, 0], [90, 0]]\n", "2 points per replicate cannot determine 4 coefficients"),
    (PLAN_HEAD + "points = [[0, 0], [400, 0], [0, 90], [0, 180]]\n", "point 2: pitch 400° is outside"),
    (PLAN_HEAD + "points = [[0, 0.5], [90, 0], [0, 90], [0, 180]]\n", "is not on the tables' 1° grid"),
    (PLAN_HEAD + "points = [[90, 0], [90, 90], [90, 180], [90, 270]]\n", "the design is singular"),
    ('name = "x"\nmounts = [[0, 90]]\npoints = [[0, 0]]\n', "y_deg and u_deg must each be 0 or 180"),
    (PLAN_HEAD + "points = [[0, 0]]\ncolour = 1\n",
     "colour: unknown key; the valid keys here are angle_step_deg, description,"),
    ('name = "x"\nmounts = [[0, 0]]\npoints = [[0, "a"]]\n', "points.0.1"),
])
def test_bad_plans(tmp_path, capsys, content, expected):
    path = tmp_path / "plan.toml"
    path.write_text(content)
    code, stdout, stderr = cli(capsys, "plan", "show", str(path))
    assert code == 2 and stdout == ""
    assert expected in stderr and str(path) in stderr
    assert stderr.strip().count("\n") == 0


@pytest.mark.parametrize("args,expected", [
    (["plan", "show", "no-such-plan"], "unknown plan 'no-such-plan'; shipped plans: four-mount-64"),
    (["fit", "missing.csv"], "missing.csv: no such readings file"),
    (["simulate", "--misalign", "q=1", "--out", "x.csv"], "'q=1' is not NAME=ANGLE"),
    (["simulate", "--misalign", "a=big", "--out", "x.csv"], "'big' for a is not a number"),
    (["simulate", "--truth", "nope.toml", "--out", "x.csv"], "nope.toml: no such truth file"),
    (["run"], "no station given: use --sim"),
    (["run", "--sim", "--plan", "nope"], "unknown plan 'nope'"),
])
def test_bad_arguments(tmp_path, capsys, monkeypatch, args, expected):
    monkeypatch.chdir(tmp_path)
    code, stdout, stderr = cli(capsys, *args)
    assert code == 2 and stdout == "" and expected in stderr
    assert stderr.strip().count("\n") == 0


def test_run_refuses_a_used_directory(tmp_path, capsys):
    (tmp_path / "old.csv").write_text("x")
    code, _, stderr = cli(capsys, "run", "--sim", "--yes", "--out", str(tmp_path))
    assert code == 2 and "exists and is not empty" in stderr
    assert (tmp_path / "old.csv").read_text() == "x"


# --- runs ----------------------------------------------------------------------------------
def test_run_sim_yes_end_to_end(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code, stdout, stderr = cli(capsys, "run", "--sim", "--yes", "--seed", "3", "--out", str(run_dir),
                               "--json", "--no-report")
    assert code == 0, stderr
    summary = json.loads(stdout)
    assert summary["points"] == 64 and summary["wall_time_s"] < 10
    assert summary["simulated_rig_time_s"] > 20 * 60  # 64 points and 4 remounts take real time
    # device.json too: the device estimate is the run's, report or not
    assert {p.name for p in run_dir.iterdir()} == {"readings.csv", "fit.json", "plan.toml", "run.json",
                                                   "device.json"}
    assert stderr.count("(--yes: confirmed)") == 4
    meta = json.loads((run_dir / "run.json").read_text())
    assert meta["status"] == "complete" and meta["points_recorded"] == 64
    X = np.array(json.loads((run_dir / "fit.json").read_text())["coefficients"])
    truth = np.array(meta["simulated_truth"]["coefficients"])
    # the default rig has arcsec misalignments, drift and a temperature swing: within 0.1 mV
    assert np.max(np.abs(X - truth)) < 1e-4


def test_run_prompts_are_answered_interactively(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO("y\nyes\nY\ny\n"))
    code, _, stderr = cli(capsys, "run", "--sim", "--no-report", "--out", str(tmp_path / "run"))
    assert code == 0, stderr
    assert stderr.count("Type y and Enter when mounted") == 4
    assert "bottom side of the plate, x sensor pointing backward" in stderr


def test_operator_stops_at_a_prompt_and_keeps_readings(tmp_path, capsys, monkeypatch):
    run_dir = tmp_path / "run"
    monkeypatch.setattr("sys.stdin", io.StringIO("y\nq\n"))
    code, _, stderr = cli(capsys, "run", "--sim", "--no-report", "--out", str(run_dir))
    assert code == 1
    assert "16 reading(s) kept" in stderr and stderr.strip().splitlines()[-1].startswith("stopped")
    assert len((run_dir / "readings.csv").read_text().strip().splitlines()) == 1 + 16
    assert json.loads((run_dir / "run.json").read_text())["status"] == "stopped"


def journal_points(db) -> int:
    """Points committed so far, read the way any other process would read the journal."""
    import sqlite3

    if not Path(db).exists():
        return 0
    with sqlite3.connect(db) as con:
        try:
            return con.execute("SELECT COUNT(*) FROM points").fetchone()[0]
        except sqlite3.OperationalError:
            return 0


def test_ctrl_c_at_a_prompt_keeps_every_reading(tmp_path, lab_database):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([LABCAL, "run", "--sim", "--no-report", "--out", str(run_dir)],
                            stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdin.write("y\n")
    proc.stdin.flush()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and journal_points(lab_database) < 16:  # mount 1 done
        time.sleep(0.05)
    time.sleep(0.5)  # now at the second prompt
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, stderr
    assert "16 reading(s) kept" in stderr and "Traceback" not in stderr
    rows = list(csv.DictReader((run_dir / "readings.csv").open()))
    assert len(rows) == 16 and {r["y_deg"] for r in rows} == {"0"}
    meta = json.loads((run_dir / "run.json").read_text())
    assert meta["status"] == "interrupted" and meta["points_recorded"] == 16


def test_no_answer_at_a_prompt_stops_cleanly(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # input closed
    code, _, stderr = cli(capsys, "run", "--sim", "--no-report", "--out", str(tmp_path / "run"))
    assert code == 1 and "no answer at the prompt" in stderr
    assert "0 reading(s) kept" in stderr


def test_rig_file_sets_the_simulated_rig(tmp_path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text("remount_s = 0\nspeed_dps = 40\n[device]\nmisalignment_deg = {}\n"
                   "[instrument]\nB = [0.1, 0.2, 0.3]\nnoise_v = 1e-6\n")
    code, stdout, _ = cli(capsys, "run", "--sim", "--yes", "--json", "--no-report", "--rig", str(rig),
                              "--out", str(tmp_path / "run"))
    assert code == 0
    summary = json.loads(stdout)
    assert summary["simulated_rig_time_s"] < 20 * 60  # no remount allowance, faster tables
    assert np.allclose(summary["fit"]["coefficients"][0], [0.1, 0.2, 0.3], atol=2e-5)
    bad = tmp_path / "bad.toml"
    bad.write_text("speed_dps = -1\n")
    code, _, stderr = cli(capsys, "run", "--sim", "--rig", str(bad), "--out", str(tmp_path / "r2"))
    assert code == 2 and "speed_dps: Input should be greater than 0" in stderr


def test_a_complete_run_issues_its_certificate_and_report(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code, stdout, _ = cli(capsys, "run", "--sim", "--yes", "--json", "--plan", "one-mount-16",
                              "--tolerance-deg", "0.5", "--out", str(run_dir))
    assert code == 0
    summary = json.loads(stdout)
    assert summary["certificate"] == str(run_dir / "certificate.json") and summary["verdict"] == "pass"
    assert {"certificate.json", "report.html", "report.pdf"} <= {p.name for p in run_dir.iterdir()}
    code, stdout, _ = cli(capsys, "history", "SIMULATED", "--json")
    assert code == 0 and len(json.loads(stdout)["calibrations"]) == 1
    code, _, stderr = cli(capsys, "run", "--sim", "--yes", "--plan", "one-mount-16",
                              "--tolerance-deg", "-1", "--out", str(tmp_path / "r2"))
    assert code == 2 and "argument --tolerance-deg: -1 is out of range; expected an angle 0 < x" in stderr
    assert not (tmp_path / "r2").exists()  # refused before the run began
