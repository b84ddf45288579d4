"""`labcal resume` checks the bench it goes on with: the journal's snapshot validated by today's
models (an older labcal's snapshot, without the fields added since, still resumes), and
``--station NEW.toml`` accepted when only the links differ, refused field by field otherwise."""

from __future__ import annotations

import csv
import hashlib
import json
import sqlite3
import tomllib
from pathlib import Path

import pytest
from cli import cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.store.journal import Journal

pytestmark = pytest.mark.long(seconds=22)  # runs killed and resumed: handed out first

QUICK = "timeout_s = 0.1\nreconnect_s = 1"  # the injected fault costs timeouts: keep them short
DMM_GONE = '\n[[emulation.faults]]\ndevice = "dmm"\nkind = "close-port"\nafter = 40\nmatch = "FETC"\n'


def readings(run_dir: Path) -> list[dict]:
    with (run_dir / "readings.csv").open() as f:
        return list(csv.DictReader(f))


def interrupted_run(capsys, tmp_path: Path) -> tuple[Path, Path]:
    """An emulated AZ-on-Modbus-TCP run stopped part way (its DMM's port closes for good and the
    operator aborts at the pause): the run directory and the station file it started on."""
    station = private_file("az-modbus-tcp", tmp_path, DMM_GONE, QUICK)
    answers = tmp_path / "answers.txt"
    answers.write_text("y\ny\ny\na\n")
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--station", str(station), "--emulate", "--time-scale", str(TIME_SCALE),
                       "--no-report", "--answers", str(answers), "--out", str(run_dir))
    assert code == 1 and 16 < len(readings(run_dir)) < 64, err
    return run_dir, station


def resume(capsys, run_dir: Path, *extra: str) -> tuple[int, str, str]:
    answers = run_dir.parent / "resume-answers.txt"
    answers.write_text("y\ny\ny\n")  # confirm the mount to resume on, then the remaining mount(s)
    return cli(capsys, "resume", str(run_dir), "--answers", str(answers), "--json", "--no-report", *extra)


def new_station_file(tmp_path: Path, *replacements: tuple[str, str]) -> Path:
    """The same example station on other TCP ports (fresh free ones), with ``replacements``."""
    folder = tmp_path / "elsewhere"
    folder.mkdir(exist_ok=True)
    path = private_file("az-modbus-tcp", folder)
    text = path.read_text()
    for old, new in replacements:
        assert old in text
        text = text.replace(old, new)
    new_path = tmp_path / "new.toml"
    new_path.write_text(text)
    return new_path


def test_a_station_file_with_only_the_ports_changed_resumes_and_finishes(tmp_path, capsys, lab_database,
                                                                        no_leaks):  # noqa: F811
    run_dir, started_on = interrupted_run(capsys, tmp_path)
    before = readings(run_dir)
    new = new_station_file(tmp_path)
    old_ports, new_ports = ({tomllib.loads(f.read_text())[d]["tcp"] for d in ("pitch", "roll", "dmm")}
                            for f in (started_on, new))
    assert old_ports.isdisjoint(new_ports)  # the devices are on other ports, and nowhere else

    code, out, err = resume(capsys, run_dir, "--station", str(new))
    assert code == 0, err
    assert json.loads(out)["points"] == 64 and len(readings(run_dir)) == 64
    after = {(r["y_deg"], r["u_deg"], r["pitch_deg"], r["roll_deg"]): r for r in readings(run_dir)}
    assert all(after[(r["y_deg"], r["u_deg"], r["pitch_deg"], r["roll_deg"])] == r for r in before)
    with Journal(lab_database) as journal:
        resumed = [e for e in journal.events(1) if e.kind == "resume"]
    assert len(resumed) == 1 and str(new) in resumed[0].message
    assert resumed[0].data["station_file"] == str(new)
    assert resumed[0].data["station_sha256"] == hashlib.sha256(new.read_bytes()).hexdigest()
    assert resumed[0].data["station_text"] == new.read_text()
    # who answered: the run's metadata (and run.json) when it started, an event when it resumed
    with Journal(lab_database) as journal:
        started = journal.run(1).metadata["device_identity"]
        [identified] = [e.data for e in journal.events(1) if e.kind == "device_identity"]
    assert json.loads((run_dir / "run.json").read_text())["device_identity"] == started
    for identity in (started, identified):
        assert identity["dmm"]["model"] == "Keysight Technologies 34970A" and identity["dmm"]["serial"]
        assert identity["pitch"]["identity"].startswith("Oriental Motor AZ unit 1 on tcp 127.0.0.1:")
        assert identity["roll"]["model"] == "Oriental Motor AZ"


def test_a_station_file_of_another_bench_is_refused_naming_each_field(tmp_path, capsys, lab_database):
    run_dir, _ = interrupted_run(capsys, tmp_path)
    new = new_station_file(tmp_path, ("steps_per_degree = 1000    #", "steps_per_degree = 500    #"),
                           ("channels = [101, 102, 103]", "channels = [101, 102, 105]"))
    code, out, err = resume(capsys, run_dir, "--station", str(new))
    assert code == 2 and out == "" and "Traceback" not in err
    assert err.count("\n") == 1, err
    assert err.startswith(f"labcal: error: {new} is not the bench run 1 in {run_dir} started on: ")
    assert "pitch.steps_per_degree: 1000 in the run, 500 in new.toml; " \
           "dmm.channels: [101, 102, 103] in the run, [101, 102, 105] in new.toml; " in err
    assert "roll." not in err and "tcp" not in err  # the same roll table; other ports are allowed
    with sqlite3.connect(lab_database) as db:  # nothing was resumed
        assert db.execute("SELECT status FROM runs").fetchone() == ("stopped",)
        assert db.execute("SELECT COUNT(*) FROM events WHERE kind = 'resume'").fetchone() == (0,)


def test_a_snapshot_from_before_a_defaulted_field_still_resumes(tmp_path, capsys, lab_database,
                                                                no_leaks):  # noqa: F811
    """As an older labcal stored it: only the keys the station file gives, none of the defaulted
    fields added since (wrap, retries, poll_s, [sequencer.settle], [emulation.rig], ...)."""
    run_dir, started_on = interrupted_run(capsys, tmp_path)
    with sqlite3.connect(lab_database) as db:
        stored = json.loads(db.execute("SELECT station_text FROM runs").fetchone()[0])
    station = tomllib.loads(started_on.read_text())
    del station["emulation"]["faults"]
    older = json.dumps({"kind": "station", "station": station, "emulate": True,
                        "time_scale": stored["time_scale"], "seed": stored["seed"]})
    assert '"wrap"' not in older and '"retries"' not in older and '"rig"' not in older
    with sqlite3.connect(lab_database) as db:
        db.execute("UPDATE runs SET station_text = ?", (older,))

    code, out, err = resume(capsys, run_dir)
    assert code == 0, err
    assert json.loads(out)["points"] == 64


def test_a_snapshot_that_no_longer_validates_is_one_line_naming_the_field(tmp_path, capsys, lab_database):
    run_dir, _ = interrupted_run(capsys, tmp_path)
    with sqlite3.connect(lab_database) as db:
        stored = json.loads(db.execute("SELECT station_text FROM runs").fetchone()[0])
        stored["station"]["pitch"]["gear_ratio"] = 50  # a field this labcal does not know
        db.execute("UPDATE runs SET station_text = ?", (json.dumps(stored),))
    code, out, err = resume(capsys, run_dir)
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err
    assert f"run 1 in {run_dir}: the station it started on no longer validates (pitch.gear_ratio: unknown " \
           "key" in err



def test_stored_settings_that_no_longer_validate_are_one_line_naming_the_key(tmp_path, capsys, lab_database):
    """The run's settings are read with today's model too: a key this labcal no longer knows is one
    line, not a validation traceback."""
    run_dir, _ = interrupted_run(capsys, tmp_path)
    with sqlite3.connect(lab_database) as db:
        settings = json.loads(db.execute("SELECT settings FROM runs").fetchone()[0])
        settings["retired_option"] = 1
        db.execute("UPDATE runs SET settings = ?", (json.dumps(settings),))
    code, out, err = resume(capsys, run_dir)
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err
    assert f"{run_dir}: run 1's settings: retired_option: unknown key" in err

def test_a_simulated_run_resumes_from_an_older_snapshot_and_refuses_a_station(tmp_path, capsys, lab_database):
    """A dry run's rig snapshot stored without two defaulted fields resumes on its simulated rig;
    --station is for station-file runs only."""
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--sim", "--seed", "3", "--plan", "one-mount-16", "--yes",
                       "--no-report", "--out", str(run_dir))
    assert code == 0, err
    with sqlite3.connect(lab_database) as db:
        stored = json.loads(db.execute("SELECT station_text FROM runs").fetchone()[0])
        del stored["rig"]["lab_temp_period_h"], stored["rig"]["device"]["mount_repeat_arcsec"]
        db.execute("UPDATE runs SET status = 'interrupted', station_text = ?", (json.dumps(stored),))

    code, out, err = cli(capsys, "resume", str(run_dir), "--station", "az-modbus-tcp", "--yes")
    assert code == 2 and out == "" and "is a dry run on the simulated rig (--sim)" in err
    assert "omit --station" in err
    code, out, err = cli(capsys, "resume", str(run_dir), "--yes", "--json", "--no-report")
    assert code == 0, err
    assert json.loads(out)["points"] == 16
