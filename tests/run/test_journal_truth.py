"""The journal is the truth: identity, lock, clock, exports and the environment's failures.

Each test makes its own small simulated run (one-mount-16, about a second) through the command
line and breaks one thing about it the way the lab's soak did.
"""

from __future__ import annotations

import errno
import io
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from labcal.cli import main
from labcal.config.files import write_atomic
from labcal.errors import LabcalError
from labcal.store import labdb
from labcal.store.journal import Journal
from labcal.store.lock import RunLock, held_by
from labcal.store.rundir import new_run_dir, slug

STATIC_LAB = str(Path(__file__).parent.parent / "data" / "rig_static_lab.toml")


def run(tmp_path: Path, name: str, db: Path, *extra: str) -> Path:
    out = tmp_path / name
    assert main(["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--out", str(out),
                 "--db", str(db), *extra]) == 0
    return out


def one_line(capsys, args: list[str]) -> str:
    capsys.readouterr()  # what came before is not this command's
    assert main(args) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()  # a run's progress may come first, on its own lines
    assert "Traceback" not in captured.err and lines[-1].startswith("labcal: error:"), captured.err
    assert sum(line.startswith("labcal: error:") for line in lines) == 1 and captured.out == "", captured
    return lines[-1]


def status(db: Path, run_id: int = 1) -> str:
    with sqlite3.connect(db) as con:
        return con.execute("SELECT status FROM runs WHERE id=?", (run_id,)).fetchone()[0]


# --- 1. exports derived, atomic, repairable -------------------------------------------------------
def test_a_failed_write_leaves_the_old_file_whole_and_says_where_and_how_much(tmp_path):
    target = tmp_path / "readings.csv"
    target.write_text("the old file\n")

    def disk_fills(file):
        file.write(b"x" * 1000)
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(LabcalError, match=rf"{tmp_path}: disk full writing readings.csv: .* free, "
                                          r"1\.0 MB needed"):
        write_atomic(target, disk_fills)
    assert target.read_text() == "the old file\n" and sorted(os.listdir(tmp_path)) == ["readings.csv"]
    write_atomic(target, "new\n")
    assert target.read_text() == "new\n" and sorted(os.listdir(tmp_path)) == ["readings.csv"]


def test_missing_and_edited_exports_are_rewritten_from_the_journal(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    folder = run(tmp_path, "r", db)
    original = {p.name: p.read_bytes() for p in folder.iterdir()}
    (folder / "readings.csv").write_text("replicate,y_deg\n1,0\n")  # edited by hand
    (folder / "fit.json").unlink()
    capsys.readouterr()
    assert main(["export", str(folder)]) == 0
    err = capsys.readouterr().err
    assert "readings.csv was edited by hand" in err and "fit.json was missing" in err
    assert (folder / "readings.csv.edited").read_text() == "replicate,y_deg\n1,0\n"  # nothing lost
    assert {n: (folder / n).read_bytes() for n in original} == original


def test_a_deleted_run_folder_is_recreated_from_the_run_id(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    folder = run(tmp_path, "r", db)
    original = {p.name: p.read_bytes() for p in folder.iterdir()}
    for p in folder.iterdir():
        p.unlink()
    folder.rmdir()
    assert "no such run directory" in one_line(capsys, ["report", str(folder), "--db", str(db)])
    assert main(["export", "1", "--db", str(db), "--out", str(tmp_path / "again")]) == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "again").iterdir()} == original
    with Journal(db) as journal:
        assert journal.run(1).run_dir == str(folder)  # a copy: the run is recorded where it was
    assert main(["export", str(tmp_path / "again")]) == 0  # rebuilding the copy makes it the run's folder
    assert main(["report", str(tmp_path / "again"), "--db", str(db)]) == 0
    with Journal(db) as journal:
        assert journal.run(1).run_dir == str(tmp_path / "again")  # the journal knows where it is now


# --- 2. one clock per run -----------------------------------------------------------------------
def resume(folder: Path, after=None):
    """Resume in this process on the simulated rig, its clock started where the journal says."""
    from conftest import quiet_console

    from labcal.bench.setup import sim_station
    from labcal.run.operator import AutoOperator
    from labcal.run.runner import execute, open_for_resume

    ctx = open_for_resume(folder)
    setup = sim_station(None, None, snapshot=ctx.station_text, start_time_s=ctx.journal.rig_time(ctx.run_id))
    with ctx.journal, ctx.lock:
        return execute(ctx.journal, ctx.run_id, folder, ctx.plan, setup.station,
                       AutoOperator(quiet_console()),
                       ctx.settings, after and after.events())


def test_rig_time_runs_on_across_resumes(tmp_path):
    """Two Ctrl-C's and two resumes: time_s never goes back and each segment's offset is journaled
    at the rig time the previous segment reached."""
    from test_sequencer import After, journal_run

    from labcal.bench.setup import sim_station

    def ctrl_c():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        journal_run(tmp_path, sim_station(STATIC_LAB, 3), After(20, ctrl_c))
    with pytest.raises(KeyboardInterrupt):
        resume(tmp_path / "run", After(20, ctrl_c))
    resume(tmp_path / "run")
    with Journal(tmp_path / "j.sqlite") as journal:
        points = journal.points(1)
        segments = [e for e in journal.events(1) if e.kind == "segment"]
    t_end = [p.t_end for p in points]
    assert len(points) == 64 and all(b > a for a, b in zip(t_end, t_end[1:], strict=False))
    offsets = [s.data["offset_s"] for s in segments]
    assert len(offsets) == 3 and offsets[0] == 0.0
    assert offsets[1] >= t_end[19] and offsets[2] >= t_end[39]  # each resume starts where time had got to
    assert t_end[20] > offsets[1] and t_end[40] > offsets[2]


# --- 3. a run folder knows its run ---------------------------------------------------------------
def test_a_folder_of_another_run_with_a_reused_id_is_refused(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    old = run(tmp_path, "old", db)
    for p in tmp_path.glob("lab.sqlite*"):
        p.unlink()  # the database is re-created (or restored from an older backup): ids are reused
    run(tmp_path, "new", db, "--seed", "5")
    capsys.readouterr()
    before = (old / "readings.csv").read_bytes()
    for args in (["report", str(old), "--db", str(db)], ["resume", str(old), "--yes"], ["export", str(old)]):
        err = one_line(capsys, args)
        assert "run_uuid" in err and "belongs to another run" in err, err
    assert (old / "readings.csv").read_bytes() == before and not (old / "certificate.json").exists()


# --- 4. one process per run ----------------------------------------------------------------------
def test_a_second_process_is_refused_with_who_holds_the_run(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    folder = run(tmp_path, "r", db)
    with sqlite3.connect(db) as con:  # as if the run were still measuring
        con.execute("UPDATE runs SET status='running'")
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path; from labcal.store.lock import RunLock\n"
        f"with RunLock(Path({str(db)!r}), 1):\n    print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert held_by(db, 1) is not None
        err = one_line(capsys, ["resume", str(folder), "--yes"])
        assert f"run 1 is in use by pid {holder.pid} on " in err, err
        assert status(db) == "running"  # the other process's run is untouched
    finally:
        holder.kill()
        holder.wait()
    assert held_by(db, 1) is None  # the kernel released it with the process: no stale lock
    assert main(["resume", str(folder), "--yes", "--no-report"]) == 0
    assert "was interrupted" in capsys.readouterr().err
    assert status(db) == "complete"


def test_the_lock_is_reentrant_within_a_process_only(tmp_path):
    db = tmp_path / "lab.sqlite"
    with RunLock(db, 7), RunLock(db, 7):
        assert held_by(db, 7) is not None
    assert held_by(db, 7) is None


# --- 5. the environment's failures ---------------------------------------------------------------
def test_a_full_database_is_one_line_and_keeps_every_committed_point(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    folder = run(tmp_path, "r", db)
    with Journal(db) as journal:
        journal.reopen(1)
        count = len(journal.points(1))
        journal.db.execute("PRAGMA max_page_count = 1")  # the disk is full from here on
        big = "x" * 100_000
        with pytest.raises(LabcalError, match=rf"{db}: disk full .* free at least"):
            journal.event(1, "note", big)
        assert len(journal.points(1)) == count
    assert folder.exists()


def test_a_read_only_or_damaged_database_is_named_with_what_to_do(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    run(tmp_path, "r", db)
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as ro:
        with pytest.raises(sqlite3.OperationalError) as caught:
            ro.execute("DELETE FROM events")
    message = str(labdb.failure(db, caught.value))
    assert f"{db}: the lab database is read-only" in message and "writable" in message
    damaged = tmp_path / "damaged.sqlite"
    damaged.write_bytes(b"SQLite format 3\x00" + os.urandom(4096))
    err = one_line(capsys, ["history", "X", "--db", str(damaged)])
    assert str(damaged) in err and ("damaged" in err or "cannot use" in err), err
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(b"not a database at all" * 100)
    err = one_line(capsys, ["run", "--sim", "--yes", "--plan", "one-mount-16", "--db", str(garbage),
                            "--out", str(tmp_path / "never")])
    assert "integrity_check" in err and "restore it from its latest backup" in err, err


# --- 8. paths from files never escape --------------------------------------------------------------
@pytest.mark.parametrize("name, expected", [("../../etc/x", "etc-x"), ("a/b c", "a-b-c"), ("..", "plan"),
                                            (".hidden", "hidden"), ("ok-name_1.2", "ok-name_1.2")])
def test_plan_names_in_paths_are_slugs(name, expected, tmp_path, monkeypatch):
    from labcal.config.plans import load_plan

    assert slug(name) == expected
    monkeypatch.chdir(tmp_path)
    plan = load_plan("one-mount-16")[0].model_copy(update={"name": name})
    folder = new_run_dir(None, plan)
    assert folder.resolve().parent == (tmp_path / "runs").resolve()


def test_an_emulator_never_replaces_or_deletes_what_it_did_not_make(tmp_path):
    from labcal.sim.ptys import PtyPair

    mine = tmp_path / "someone-elses-link"
    mine.symlink_to("/dev/null")
    plain = tmp_path / "a-file"
    plain.write_text("keep me")
    for path in (mine, plain):
        with pytest.raises(LabcalError, match="exists; the emulator will not replace it"):
            PtyPair(path)
    assert os.readlink(mine) == "/dev/null" and plain.read_text() == "keep me"
    with pytest.raises(LabcalError, match="cannot make the emulator's link folder"):
        PtyPair(tmp_path / "no" / "such" / "link")
    assert not (tmp_path / "no").exists()
    pair = PtyPair(tmp_path / "new" / "link")
    assert (tmp_path / "new" / "link").is_symlink()
    pair.close()
    assert not (tmp_path / "new").exists()  # the folder it made goes with it, and nothing else


def test_waiting_is_not_needed_for_the_lock_file_to_say_nothing(tmp_path):
    """A released lock file is emptied: no stale holder is ever reported."""
    db = tmp_path / "lab.sqlite"
    with RunLock(db, 3):
        pass
    time.sleep(0)
    assert (tmp_path / "lab.sqlite.run-3.lock").read_text() == "" and held_by(db, 3) is None


@pytest.fixture
def small_disk(tmp_path, request):
    """A filesystem of its own (tmpfs; 12 kB unless the test says, where a run's exports do not
    fit); skipped where this machine does not let the test mount one."""
    where = tmp_path / "small"
    where.mkdir()
    size = getattr(request, "param", "12k")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                          capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({made.stderr.decode().strip()})")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_full_disk_at_the_final_export_keeps_the_run_and_says_how_to_finish_it(tmp_path, small_disk,
                                                                                  capsys, monkeypatch):
    db = tmp_path / "lab.sqlite"
    # the pre-run checklist sees the disk too small: the operator goes on regardless, then y at each mount
    monkeypatch.setattr("sys.stdin", io.StringIO("y\n" * 5))
    err = one_line(capsys, ["run", "--sim", "--no-report", "--out", str(small_disk / "r"), "--db", str(db)])
    assert f"{small_disk / 'r'}: disk full writing" in err and "needed" in err, err
    assert "labcal export 1" in err, err
    assert status(db) == "stopped" and not list((small_disk / "r").glob(".*.tmp"))  # nothing half-made
    with Journal(db) as journal:
        assert len(journal.points(1)) == 64  # every reading kept
    assert main(["export", "1", "--db", str(db), "--out", str(tmp_path / "moved")]) == 0
    assert main(["resume", str(tmp_path / "moved"), "--yes", "--no-report"]) == 0
    assert status(db) == "complete" and (tmp_path / "moved" / "fit.json").exists()


@pytest.mark.parametrize("small_disk", ["2m"], indirect=True)
def test_a_read_only_database_is_one_line_and_leaves_no_run_folder(tmp_path, small_disk, capsys):
    db = small_disk / "lab.sqlite"
    with Journal(db):
        pass
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    err = one_line(capsys, ["run", "--sim", "--yes", "--plan", "one-mount-16", "--db", str(db),
                            "--out", str(tmp_path / "never")])
    assert f"{db}: the lab database is read-only" in err and "writable" in err, err
    assert not (tmp_path / "never").exists()


def test_a_killed_writes_temporary_file_is_removed_and_named(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    folder = run(tmp_path, "r", db)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    (folder / f".readings.csv.{dead}.tmp").write_text("half a fi")
    (folder / f".fit.json.{os.getpid()}.tmp").write_text("a live writer's")
    capsys.readouterr()
    assert main(["export", str(folder)]) == 0
    assert f".readings.csv.{dead}.tmp removed" in capsys.readouterr().err
    assert sorted(p.name for p in folder.glob(".*")) == [f".fit.json.{os.getpid()}.tmp"]
