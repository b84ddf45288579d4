"""The lab database's schema version and migrations, against a file the previous labcal wrote.

tests/data/v0/ was made by labcal a8863ee (before the schema had a version) with
tests/data/make_v0_database.py: one complete dry run whose certificate is stored, and one run the
operator stopped at its second mount after 16 readings.
"""

from __future__ import annotations

import ast
import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import threading
from contextlib import closing
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

import labcal as labcal_package
from labcal.cli import main
from labcal.documents.history import certificates_for, store
from labcal.errors import LabcalError
from labcal.run import labdb
from labcal.run.journal import Journal, Manifest, PointRecord

LABCAL = str(Path(sys.executable).with_name("labcal"))
V0 = Path(__file__).parent / "data" / "v0"
SOURCE = Path(labcal_package.__file__).parent  # the labcal under test: the source tree or the wheel


@pytest.fixture
def v0(tmp_path) -> Path:
    """A copy of the previous labcal's lab database and run directories, run.json pointing at it."""
    lab = tmp_path / "v0"
    shutil.copytree(V0, lab)
    for run in ("complete", "stopped"):
        info = json.loads((lab / run / "run.json").read_text())
        (lab / run / "run.json").write_text(json.dumps({**info, "journal": str(lab / "labcal.sqlite")}))
    return lab


def raw(path: Path) -> sqlite3.Connection:
    """The file as any other program reads it: plain sqlite3, no labcal."""
    return sqlite3.connect(path)


def user_version(path: Path) -> int:
    with closing(raw(path)) as con:
        return con.execute("PRAGMA user_version").fetchone()[0]


def dump(path: Path) -> list[str]:
    """Every table, index and row, as SQL: equal dumps are equal databases."""
    with closing(raw(path)) as con:
        return list(con.iterdump())


def schema(path: Path) -> set[tuple[str, str, str]]:
    with closing(raw(path)) as con:
        return set(con.execute("SELECT type, name, sql FROM sqlite_master WHERE sql IS NOT NULL"))


def point_rows(path: Path, run_id: int) -> list[tuple]:
    with closing(raw(path)) as con:
        cols = [r[1] for r in con.execute("PRAGMA table_info(points)")]
        return con.execute(f"SELECT {', '.join(cols)} FROM points WHERE run_id=? ORDER BY seq",
                           (run_id,)).fetchall()


def labcal(db: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([LABCAL, *args], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "LABCAL_DB": str(db)})


# --- (a) the previous labcal's database --------------------------------------------------------
def test_fixture_is_the_unversioned_schema():
    """Guards the fixture itself: what the old labcal wrote, before any migration."""
    assert user_version(V0 / "labcal.sqlite") == 0
    names = {name for _, name, _ in schema(V0 / "labcal.sqlite")}
    assert {"runs", "points", "events", "certificates", "certificates_by_serial"} <= names
    assert "events_by_run" not in names


def test_previous_database_is_migrated_resumed_and_its_certificate_read(v0):
    db = v0 / "labcal.sqlite"
    old = dump(db)
    stopped_run = json.loads((v0 / "stopped" / "run.json").read_text())["run_id"]
    earlier = point_rows(db, stopped_run)
    assert len(earlier) == 16
    with closing(raw(db)) as con:
        (cert_id, digest), = con.execute("SELECT certificate_id, sha256 FROM certificates")

    proc = labcal(db, "resume", str(v0 / "stopped"), "--yes", "--no-report")
    assert proc.returncode == 0, proc.stderr

    assert user_version(db) == labdb.SCHEMA_VERSION >= 1  # every later migration must migrate this file too
    assert ("index", "events_by_run") in {(t, n) for t, n, _ in schema(db)}
    backup = v0 / "labcal.sqlite.v0.bak"
    assert user_version(backup) == 0 and dump(backup) == old  # the whole old database, unchanged
    after = point_rows(db, stopped_run)
    assert len(after) == 64 and all(p[-1] is not None for p in after)  # 48 more, samples kept
    assert after[:16] == earlier  # every earlier reading (values, samples, times) unchanged
    with closing(raw(db)) as con:
        assert con.execute("SELECT status FROM runs WHERE id=?", (stopped_run,)).fetchone() == ("complete",)
    assert json.loads((v0 / "stopped" / "run.json").read_text())["status"] == "complete"

    proc = labcal(db, "history", "SIMULATED", "--json")
    assert proc.returncode == 0, proc.stderr
    calibrations = json.loads(proc.stdout)["calibrations"]
    assert [(c["certificate_id"], c["digest"]) for c in calibrations] == [(cert_id, digest)]


def test_the_resumed_run_of_the_old_database_gets_a_certificate(v0):
    db = v0 / "labcal.sqlite"
    assert labcal(db, "resume", str(v0 / "stopped"), "--yes").returncode == 0  # reports when done
    proc = labcal(db, "history", "SIMULATED", "--json")
    assert proc.returncode == 0, proc.stderr
    assert len(json.loads(proc.stdout)["calibrations"]) == 2  # the old certificate and the new one


def version_0(tmp_path: Path, tables: tuple[str, ...]) -> Path:
    """A version-0 file with only some of the tables, made with the old labcal's own statements."""
    path = tmp_path / f"only-{'-'.join(tables) or 'nothing'}.sqlite"
    with closing(raw(V0 / "labcal.sqlite")) as old, closing(raw(path)) as con:
        for tbl_name, sql in old.execute("SELECT tbl_name, sql FROM sqlite_master WHERE sql IS NOT NULL "
                                         "ORDER BY rowid"):
            if tbl_name in tables:
                con.execute(sql)
    return path


@pytest.mark.parametrize("tables", [("runs", "points", "events"), ("certificates",), ()])
def test_every_version_0_file_migrates_to_the_schema_of_a_new_one(tmp_path, tables):
    """The journal or the history alone may have created the file; either way, one schema after."""
    path = version_0(tmp_path, tables)
    with Journal(path):
        pass
    fresh = tmp_path / "new" / "labcal.sqlite"
    with Journal(fresh):
        pass
    migrated = tmp_path / "migrated.sqlite"
    shutil.copy(V0 / "labcal.sqlite", migrated)
    labdb.connect(migrated).close()
    assert schema(path) == schema(fresh) == schema(migrated)
    assert user_version(path) == user_version(fresh) == labdb.SCHEMA_VERSION
    assert labdb.backup_path(path, 0).exists() == bool(tables)  # nothing to keep in an empty file
    assert not labdb.backup_path(fresh, 0).exists()
    with pytest.raises(LabcalError, match="no certificates for instrument 'SIMULATED'"):
        certificates_for("SIMULATED", path)  # the table is there, empty


# --- (b) a column added later breaks nothing -----------------------------------------------------
def test_added_columns_break_no_read_or_write(v0):
    db = v0 / "labcal.sqlite"
    labdb.connect(db).close()
    with closing(raw(db)) as con:  # what a later migration might do to every table
        for table in ("runs", "points", "events", "certificates"):
            con.execute(f"ALTER TABLE {table} ADD COLUMN later_note TEXT NOT NULL DEFAULT 'later'")
        con.commit()

    (cert,) = certificates_for("SIMULATED", db)
    store(cert, db)  # replaces it: the same calibration
    (again,) = certificates_for("SIMULATED", db)
    assert again.digest.value == cert.digest.value and again.certificate_id == cert.certificate_id

    with Journal(db) as journal:
        old = journal.run(1)
        assert old.status == "complete" and old.plan_name == "one-mount-16"
        points = journal.points(1, status="ok")
        assert len(points) == 16 and journal.readings(1).volts.shape == (16, 3)
        samples = journal.samples(1, points[0].seq)
        assert samples.shape[1] == 4 and len(samples) == points[0].n_samples
        run_id = journal.start_run(Manifest(
            run_dir=str(v0 / "later"), plan_name=old.plan_name, plan_text=old.plan_text,
            station_text=old.station_text, software_version="test", settings=old.settings,
            metadata=old.metadata))
        for p in points:
            journal.record_point(run_id, p, journal.samples(1, p.seq))
        journal.event(run_id, "note", "a column was added", {"by": "a later labcal"}, 1.5)
        journal.finish(run_id, "stopped", "test")
        journal.reopen(run_id)
        journal.finish(run_id, "complete")
        assert journal.points(run_id) == journal.points(1)
        assert np.array_equal(journal.samples(run_id, points[3].seq), journal.samples(1, points[3].seq))
        assert [(e["kind"], e["data"], e["station_time"]) for e in journal.events(run_id)] == [
            ("note", {"by": "a later labcal"}, 1.5)]
        assert journal.run(run_id).status == "complete"
    with closing(raw(db)) as con:  # the new column got its default, never a shifted value
        assert con.execute("SELECT DISTINCT later_note FROM points").fetchall() == [("later",)]
        assert con.execute("SELECT DISTINCT later_note FROM certificates").fetchall() == [("later",)]


def sql_strings(path: Path) -> list[str]:
    """The string literals of a module, docstrings left out (they may name what is forbidden)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
                  and node.body and isinstance(node.body[0], ast.Expr)}
    return [node.value for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings]


def test_no_statement_depends_on_column_order():
    """No `SELECT *` and no `INSERT … VALUES` without a column list anywhere in labcal."""
    offenders = []
    for path in SOURCE.rglob("*.py"):
        for text in sql_strings(path):
            for pattern in (r"SELECT\s+\*", r"INSERT\s+(?:OR\s+\w+\s+)?INTO\s+\w+\s+VALUES"):
                offenders += [f"{path.relative_to(SOURCE)}: {m.group(0)}"
                              for m in re.finditer(pattern, text, re.IGNORECASE)]
    assert offenders == []
    assert any("INSERT INTO points (run_id, " in s for s in sql_strings(SOURCE / "run" / "journal.py"))


def test_point_columns_are_the_journal_record():
    """The journal writes PointRecord's fields by name: each must be a column of points."""
    with closing(raw(V0 / "labcal.sqlite")) as con:
        columns = {r[1] for r in con.execute("PRAGMA table_info(points)")}
    assert {f.name for f in fields(PointRecord)} <= columns


# --- (c) a newer database is refused -------------------------------------------------------------
def test_newer_database_is_refused_in_one_line_and_left_alone(v0, capsys):
    db = v0 / "labcal.sqlite"
    newer = labdb.SCHEMA_VERSION + 2
    with closing(raw(db)) as con:
        con.execute(f"PRAGMA user_version = {newer}")
    before = dump(db)
    message = (f"{db}: lab database schema {newer} is newer than this labcal ({labdb.SCHEMA_VERSION}); "
               "upgrade labcal")
    with pytest.raises(LabcalError) as exc:
        Journal(db)
    assert str(exc.value) == message
    assert main(["history", "SIMULATED", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    proc = labcal(db, "resume", str(v0 / "stopped"), "--yes", "--no-report")
    assert proc.returncode == 2 and message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert user_version(db) == newer and dump(db) == before
    assert not labdb.backup_path(db, newer).exists() and not labdb.backup_path(db, 0).exists()


# --- (d) migrating twice, and a migration that fails ---------------------------------------------
def test_migrating_twice_is_a_no_op(v0):
    db = v0 / "labcal.sqlite"
    labdb.connect(db).close()
    migrated = dump(db)
    backup = labdb.backup_path(db, 0)
    backup.unlink()
    with closing(labdb.connect(db)) as again:
        assert labdb.migrate(again, db) == labdb.SCHEMA_VERSION  # already there: nothing found to do
    with Journal(db):
        pass
    assert dump(db) == migrated and user_version(db) == labdb.SCHEMA_VERSION
    assert not backup.exists()  # no migration, no backup


def test_a_failing_step_rolls_every_step_back(v0):
    db = v0 / "labcal.sqlite"
    old = dump(db)

    def half_done(con: sqlite3.Connection) -> None:
        con.execute("CREATE TABLE half (x)")
        raise RuntimeError("power cut in the middle of a migration")

    broken = (*labdb.MIGRATIONS, labdb.Migration(labdb.SCHEMA_VERSION + 1, "fails", half_done))
    with pytest.raises(RuntimeError, match="power cut"):
        labdb.connect(db, broken)
    assert user_version(db) == 0 and dump(db) == old  # version 1's index rolled back with it
    assert dump(labdb.backup_path(db, 0)) == old
    with Journal(db) as journal:  # and the real migrations still go through afterwards
        assert journal.run(2).status == "stopped"
    assert user_version(db) == labdb.SCHEMA_VERSION


def test_a_database_error_in_a_migration_is_one_line_and_changes_nothing(v0, capsys):
    db = v0 / "labcal.sqlite"
    with closing(raw(db)) as con:  # someone's own index already holds version 1's name
        con.execute("CREATE INDEX events_by_run ON certificates (issued_utc)")
        con.commit()
    old = dump(db)
    assert main(["history", "SIMULATED", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert f"{db}: cannot migrate the lab database from schema 0 to {labdb.SCHEMA_VERSION}" in err
    assert "events_by_run already exists" in err and "the file is unchanged" in err
    assert user_version(db) == 0 and dump(db) == old


def test_backup_is_consistent_while_another_program_holds_the_wal(v0):
    """The last points of a WAL database can still sit in the -wal file when labcal migrates it."""
    db = v0 / "labcal.sqlite"
    with closing(raw(db)) as writer:
        writer.execute("PRAGMA wal_autocheckpoint=0")  # keep every new page in the -wal file
        writer.execute("UPDATE runs SET operator='in the wal' WHERE id=1")
        writer.commit()
        assert Path(f"{db}-wal").stat().st_size > 0
        labdb.connect(db).close()
        with closing(raw(labdb.backup_path(db, 0))) as backup:
            assert backup.execute("SELECT operator FROM runs WHERE id=1").fetchone() == ("in the wal",)
            assert backup.execute("PRAGMA user_version").fetchone() == (0,)



def test_programs_opening_an_old_database_at_once_migrate_it_once(v0):
    """The journal of a starting run and a history query may both find version 0: the version is
    read again under the write lock, so the second one finds the work done."""
    db = v0 / "labcal.sqlite"
    old = dump(db)
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def open_it() -> None:
        start.wait()
        try:
            labdb.connect(db).close()
        except BaseException as exc:  # reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=open_it) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert errors == [] and user_version(db) == labdb.SCHEMA_VERSION
    assert dump(labdb.backup_path(db, 0)) == old
