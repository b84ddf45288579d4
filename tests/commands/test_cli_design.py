"""The command line of the design tools and the extended fit."""

from __future__ import annotations

import gc
import importlib.metadata
import json
import subprocess
import sys

import numpy as np
import pytest

from labcal import cli
from labcal.cli import main


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_generate_d1_and_its_figure_of_merit(tmp_path, capsys):
    plan = tmp_path / "d1.toml"
    code, _, err = run(capsys, "plan", "generate", "d1", "--pitch-max", "45", "--n-pitch", "33",
                       "--n-roll", "64", "--out", str(plan))
    assert code == 0 and "2112 points" in err and "continuously positioned tables" in err
    code, out, _ = run(capsys, "plan", "merit", str(plan), "--usage-pitch", "-30", "30", "--json")
    doc = json.loads(out)
    assert code == 0 and set(doc) == {"V_sqrt", "V_R_sqrt"}
    assert round(doc["V_sqrt"], 3) == 1.993 and round(doc["V_R_sqrt"], 3) == 1.927  # Tripp Table 1
    png = tmp_path / "merit.png"
    assert run(capsys, "plan", "merit", str(plan), "--plot", str(png))[0] == 0
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("args,points", [
    (["tumble", "--four-mounts"], 24),
    (["fractional", "--pitch-max", "30", "--n-pitch", "19", "--n-roll", "13", "--k-pitch", "3",
      "--k-roll", "4"], 139),
    (["grid", "--pitch-min", "-30", "--pitch-max", "30", "--pitch-step", "15", "--roll-min", "0",
      "--roll-max", "270", "--roll-step", "90", "--replicates", "2"], 40),
    (["d0", "--pitch=-20,0,5,20", "--n-roll", "8"], 32),
])
def test_generate_every_design(tmp_path, capsys, args, points):
    plan = tmp_path / "p.toml"
    code, _, err = run(capsys, "plan", "generate", *args, "--out", str(plan))
    assert code == 0 and f"{points} points" in err
    code, out, _ = run(capsys, "plan", "show", str(plan), "--json")
    shown = json.loads(out)
    assert len(shown["points"]) * len(shown["mounts"]) * shown["replicates"] == points


def test_audit_json(capsys):
    code, out, _ = run(capsys, "plan", "audit", "four-mount-64", "--json")
    doc = json.loads(out)
    assert code == 0 and all(s["cancelled"] for s in doc["summary"].values())
    code, out, _ = run(capsys, "plan", "audit", "one-mount-16", "--json")
    doc = json.loads(out)
    assert [n for n, s in doc["summary"].items() if not s["cancelled"]] == ["e", "f", "k"]
    assert np.array(doc["per_radian"]["k"]).shape == (4, 3)


def test_fit_coning_intervals_and_extension_tests(tmp_path, capsys):
    truth = tmp_path / "truth.toml"
    truth.write_text("B = [0.01, 0.02, 0.03]\nS = [[5.0, 0.01, 0.0], [0.0, 5.0, 0.0], [0.0, 0.0, 5.0]]\n")
    readings = tmp_path / "r.csv"
    run(capsys, "simulate", "--truth", str(truth), "--noise", "1e-5", "--out", str(readings))
    code, out, _ = run(capsys, "fit", str(readings), "--model", "coning", "--at", "10,20",
                       "--at", "0,0,180,180", "--test-extensions", "--json")
    doc = json.loads(out)
    assert code == 0 and doc["model"] == "coning"
    assert doc["coefficients"][0] == pytest.approx([0.01, 0.02, 0.03], abs=1e-4)  # linear contract kept
    y = doc["sensors"]["y"]
    assert y["omega_deg"] == pytest.approx(np.degrees(np.arctan2(0.01, 5.0)), abs=1e-3)
    assert doc["sensors"]["z"]["azimuth_deg"] is None  # untilted: azimuth undefined, said so
    assert "undefined" in doc["sensors"]["z"]["azimuth_note"]
    first, second = doc["predictions"]
    assert 0 < first["confidence_half_width"][0] < first["prediction_half_width"][0]
    assert second["volts"][2] == pytest.approx(0.03 - 5.0, abs=1e-3)  # bottom mount, level: −1 g on z
    assert doc["extension_tests"]["temperature"]["tested"] is False


def test_fit_rejects_bad_options(tmp_path, capsys):
    readings = tmp_path / "r.csv"
    run(capsys, "simulate", "--out", str(readings))
    code, _, err = run(capsys, "fit", str(readings), "--at", "10")
    assert code == 2 and "expected PITCH,ROLL" in err
    code, _, err = run(capsys, "fit", str(readings), "--extend", "cubic")
    assert code == 2 and "unknown model extension 'cubic'" in err
    code, _, err = run(capsys, "fit", str(readings), "--extend", "temperature")
    assert code == 2 and "needs a temp_c column" in err
    code, _, err = run(capsys, "plan", "merit", "four-mount-64", "--pitch-range", "10", "10")
    assert code == 2 and "pitch range 10..10 is empty" in err


def test_a_command_collects_garbage_every_50000_new_objects_and_gives_the_callers_setting_back(
        capsys, monkeypatch):
    """`labcal.cli.main` runs its command at one young collection per 50 000 new objects (CPython's
    700 cost a dry run a tenth of its time), and leaves a caller's process (a script, a test) with
    the thresholds it had. Seen from the command's parser, which `main` builds for every command."""
    seen: list[tuple[int, int, int]] = []
    build = cli.build_parser

    def noting(*args, **kwargs):
        seen.append(gc.get_threshold())
        return build(*args, **kwargs)

    monkeypatch.setattr(cli, "build_parser", noting)
    mine = (900, 11, 12)
    before = gc.get_threshold()
    gc.set_threshold(*mine)
    try:
        code = main(["plan", "list"])
        after = gc.get_threshold()
    finally:
        gc.set_threshold(*before)
    assert code == 0, capsys.readouterr().err
    assert seen == [(50_000, 20, 10)]
    assert after == mine


def test_the_installed_command_leaves_nothing_for_the_collection_at_exit():
    """The `labcal` console script is `labcal.cli.script`: after its command every object is frozen,
    so the interpreter's last collection at exit has nothing to walk (that walk took 0.45 s of a dry
    run). Seen in a process of its own, where the generations' objects are counted after it; without
    the freeze they are the 19 000 or so that `labcal plan list` leaves."""
    (entry,) = [e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == "labcal"]
    assert entry.value == "labcal.cli:script"
    probe = ("import gc, sys\nfrom labcal import cli\nsys.argv = ['labcal', 'plan', 'list']\n"
             "code = cli.script()\nprint(code, len(gc.get_objects()), file=sys.stderr)\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    code, unfrozen = map(int, done.stderr.split()[-2:])
    assert code == 0 and "four-mount-64" in done.stdout
    assert unfrozen < 100  # the probe's own few: the list, the ints, the frame's
