"""A misspelt key in any file labcal reads is refused as a new user would meet it: exit code 2, one
line naming the file, the key and the nearest valid name. Each command once through the real `labcal`
executable; the rest of the keys through the same command line in this process."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli import cli, labcal
from emulators import no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import shipped_stations

STATION = shipped_stations()["az-modbus-tcp"].read_text(encoding="utf-8")


def executable(*args: str, cwd: Path) -> tuple[int, str, str]:
    """``labcal ARGS`` as a new user runs it (the installed executable, in ``cwd``): exit code, stdout,
    stderr."""
    done = labcal(*args, cwd=cwd)
    return done.returncode, done.stdout, done.stderr


def refused(result: tuple[int, str, str], expected_line: str) -> None:
    code, out, err = result
    assert code == 2, err
    assert out == "" and "Traceback" not in err
    assert err.splitlines() == [f"labcal: error: {expected_line}"]


def with_line(table: str, line: str) -> str:
    """The example station with ``line`` in ``table`` (a table it lacks is appended)."""
    if not table:
        return f"{line}\n{STATION}"
    if f"\n{table}\n" in STATION:
        return STATION.replace(f"\n{table}\n", f"\n{table}\n{line}\n", 1)
    return f"{STATION}\n{table}\n{line}\n"


@pytest.mark.parametrize("table, line, where, nearest", [
    ("", 'descripton = "bench 2"', "descripton", "description"),
    ("[pitch]", "unti = 3", "pitch.unti", "unit"),
    ("[roll]", "step_per_degree = 1000", "roll.step_per_degree", "steps_per_degree"),
    ("[dmm]", "chanels = [101, 102, 103]", "dmm.chanels", "channels"),
    ("[sequencer]", "move_timout_s = 60", "sequencer.move_timout_s", "move_timeout_s"),
    ("[sequencer.settle]", "sampels = 12", "sequencer.settle.sampels", "samples"),
    ("[emulation]", "time_scal = 10", "emulation.time_scal", "time_scale"),
    ("[emulation.rig]", "clamp = 1.5", "emulation.rig.clamp", "clamp_s"),
    ("[emulation.rig.instrument]", "noise = 1e-6", "emulation.rig.instrument.noise", "noise_v"),
    ("[[emulation.faults]]", 'device = "dmm"\nkind = "no-reply"\nafterr = 3', "emulation.faults.0.afterr",
     "after"),
    ("[certificate]", 'laboratry = "Lab A, Hampton VA"', "certificate.laboratry", "laboratory"),
])
def test_an_unknown_key_in_each_table_of_a_station_file(table, line, where, nearest, tmp_path, capsys,
                                                       monkeypatch):
    (tmp_path / "station.toml").write_text(with_line(table, line), encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    refused(cli(capsys, "station", "check", "station.toml"),
            f"station.toml: {where}: unknown key; did you mean {nearest}?")


def test_a_typo_in_the_sequencer_fails_station_check_with_emulate(tmp_path, no_leaks):  # noqa: F811
    """The new user's case: `labcal station check --emulate` used to say ok: true."""
    path = private_file("az-modbus-tcp", tmp_path)
    path.write_text(path.read_text().replace("move_timeout_s = 120", "move_timout_s = 120"))
    refused(executable("station", "check", path.name, "--emulate", "--json", cwd=tmp_path),
            f"{path.name}: sequencer.move_timout_s: unknown key; did you mean move_timeout_s?")


def test_a_misspelt_required_key_is_named_before_the_missing_one(tmp_path, capsys, monkeypatch):
    """steps_per_degre is unknown and steps_per_degree missing: the spelling is what to fix."""
    misspelt = STATION.replace("steps_per_degree = 1000", "steps_per_degre = 1000", 1)
    (tmp_path / "station.toml").write_text(misspelt, encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    refused(cli(capsys, "station", "check", "station.toml"),
            "station.toml: pitch.steps_per_degre: unknown key; did you mean steps_per_degree? (and 1 more)")


def test_an_unknown_key_in_a_plan(tmp_path):
    (tmp_path / "plan.toml").write_text('name = "x"\nreplicate = 2\nmounts = [[0, 0]]\n'
                                        "points = [[0, 0], [90, 0], [0, 90], [0, 180]]\n", encoding="utf-8")
    refused(executable("plan", "show", "plan.toml", cwd=tmp_path),
            "plan.toml: replicate: unknown key; did you mean replicates?")


def test_an_unknown_key_in_a_rig_file(tmp_path):
    (tmp_path / "rig.toml").write_text("remount = 0\n[device]\nindex_arcsec = 1\n", encoding="utf-8")
    refused(executable("run", "--sim", "--rig", "rig.toml", "--yes", "--no-report", cwd=tmp_path),
            "rig.toml: remount: unknown key; did you mean remount_s?")


def test_an_unknown_misalignment_in_a_rig_file_is_refused_when_the_file_is_read(tmp_path, capsys,
                                                                                 monkeypatch):
    rig = "[device]\nmisalignment_deg = {a = 0.01, q = 0.02}\n"
    (tmp_path / "rig.toml").write_text(rig, encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    refused(cli(capsys, "run", "--sim", "--rig", "rig.toml", "--yes", "--no-report"),
            "rig.toml: device.misalignment_deg: unknown misalignment(s) q; use a, b, d, e, f, k")

