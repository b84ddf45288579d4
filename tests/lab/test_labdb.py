"""The lab database's schema version and migrations, against a file the previous labcal wrote.

tests/data/v0/ was made by labcal a8863ee (before the schema had a version) with
tests/data/make_v0_database.py: one complete dry run whose certificate is stored, and one run the
operator stopped at its second mount after 16 readings.
"""

from __future__ import annotations

import ast
import json
import re
import shutil
import sqlite3
import threading
from contextlib import closing
from dataclasses import fields
from pathlib import Path

import cli
import numpy as np
import pytest
from legacy_schema import legacy_file
from test_schema import shape

import labcal as labcal_package
from labcal.cli import main
from labcal.documents.history import certificates_for, store
from labcal.errors import LabcalError
from labcal.store import labdb, migrations
from labcal.store.journal import Journal, Manifest, PointRecord

V0 = Path(__file__).parent.parent / "data" / "v0"
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


@pytest.fixture
def cli_on(capsys, monkeypatch):
    """``cli_on(db, ARGS)``: ``labcal ARGS`` in this process on the lab database ``db`` ($LABCAL_DB):
    exit code, stdout, stderr."""
    def on(db: Path, *args: str) -> tuple[int, str, str]:
        monkeypatch.setenv("LABCAL_DB", str(db))
        return cli.cli(capsys, *args)
    return on


# --- (a) the previous labcal's database --------------------------------------------------------
def test_fixture_is_the_unversioned_schema():
    """Guards the fixture itself: what the old labcal wrote, before any migration."""
    assert user_version(V0 / "labcal.sqlite") == 0
    names = {name for _, name, _ in schema(V0 / "labcal.sqlite")}
    assert {"runs", "points", "events", "certificates", "certificates_by_serial"} <= names
    assert "events_by_run" not in names


HEAD = migrations.head()  # Alembic's own walk of the scripts, not the constant labcal checks on open


def alembic_revision(path: Path) -> str | None:
    with closing(raw(path)) as con:
        if not con.execute("SELECT 1 FROM sqlite_master WHERE name='alembic_version'").fetchone():
            return None
        return con.execute("SELECT version_num FROM alembic_version").fetchone()[0]


def upgrade(cli_on, db: Path) -> str:
    """`labcal db upgrade` of ``db``, which must succeed: its stdout."""
    code, out, err = cli_on(db, "db", "upgrade")
    assert code == 0, err
    return out


def test_previous_database_is_refused_then_upgraded_resumed_and_its_certificate_read(v0, cli_on):
    db = v0 / "labcal.sqlite"
    old = dump(db)
    stopped_run = json.loads((v0 / "stopped" / "run.json").read_text())["run_id"]
    earlier = point_rows(db, stopped_run)
    assert len(earlier) == 16
    with closing(raw(db)) as con:
        (cert_id, digest), = con.execute("SELECT certificate_id, sha256 FROM certificates")

    code, _, err = cli_on(db, "resume", str(v0 / "stopped"), "--yes", "--no-report")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "older than this labcal" in err and "labcal db upgrade" in err
    assert dump(db) == old and not list(v0.glob("*.bak"))  # opening never migrates

    done = upgrade(cli_on, db)
    backup = v0 / "labcal.sqlite.v0000.bak"
    assert "upgraded from schema 0000" in done and backup.name in done.replace("\n", "")
    assert alembic_revision(db) == HEAD
    assert user_version(db) == 6  # > 5: the labcal before Alembic refuses the file as newer
    assert ("index", "events_by_run") in {(t, n) for t, n, _ in schema(db)}
    assert user_version(backup) == 0 and dump(backup) == old  # the whole old database, unchanged

    code, _, err = cli_on(db, "resume", str(v0 / "stopped"), "--yes", "--no-report")
    assert code == 0, err
    after = point_rows(db, stopped_run)
    width = len(earlier[0])  # the old file's columns, samples last (later revisions add columns after)
    assert len(after) == 64 and all(p[width - 1] is not None for p in after)  # 48 more, samples kept
    assert [p[:width] for p in after[:16]] == earlier  # every earlier reading (values, samples, times)
    assert all(p[width:] == (None, None) for p in after)  # a run journaled before digests stays unchained
    with closing(raw(db)) as con:
        assert con.execute("SELECT status FROM runs WHERE id=?", (stopped_run,)).fetchone() == ("complete",)
    assert json.loads((v0 / "stopped" / "run.json").read_text())["status"] == "complete"

    code, out, err = cli_on(db, "history", "SIMULATED", "--json")
    assert code == 0, err
    calibrations = json.loads(out)["calibrations"]
    assert [(c["certificate_id"], c["digest"]) for c in calibrations] == [(cert_id, digest)]


def test_the_resumed_run_of_the_old_database_gets_a_certificate(v0, cli_on):
    db = v0 / "labcal.sqlite"
    upgrade(cli_on, db)
    code, _, err = cli_on(db, "resume", str(v0 / "stopped"), "--yes")  # reports when done
    assert code == 0, err
    code, out, err = cli_on(db, "history", "SIMULATED", "--json")
    assert code == 0, err
    assert len(json.loads(out)["calibrations"]) == 2  # the old certificate and the new one


@pytest.mark.parametrize("version", [1, 3, 5])
def test_a_file_behind_is_refused_by_every_command_before_anything_moves(tmp_path, cli_on, version):
    db = legacy_file(tmp_path / "lab.sqlite", version)
    old = dump(db)
    for command in (("runs",), ("history", "SIMULATED"),
                    ("run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "run"))):
        code, _, err = cli_on(db, *command)
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        line = err.strip()
        assert f"schema {version:04d} (user_version {version}, before Alembic), older than this labcal's " \
               f"({HEAD}); run: labcal db upgrade --db {db}" in line.replace("\n", "")
    assert not (tmp_path / "run").exists()  # the run was refused before its folder (or a move)
    assert dump(db) == old
    code, out, _ = cli_on(db, "db", "status")
    assert code == 0 and "behind" in out
    assert f"upgraded from schema {version:04d}" in upgrade(cli_on, db)
    assert dump(labdb.backup_path(db, f"{version:04d}")) == old
    assert cli_on(db, "runs")[0] == 0


def test_an_alembic_revision_behind_is_refused_and_upgraded(tmp_path):
    import sqlalchemy as sa

    db = tmp_path / "lab.sqlite"
    engine = sa.create_engine(f"sqlite:///{db}")
    with engine.begin() as connection:
        migrations.upgrade(connection, "0006")
    engine.dispose()
    with pytest.raises(LabcalError, match=r"schema 0006, older than this labcal's .*labcal db upgrade"):
        Journal(db)
    labdb.upgrade(db)
    assert alembic_revision(db) == HEAD
    with closing(raw(db)) as con:
        assert "origin_id" in {r[1] for r in con.execute("PRAGMA table_info(events)")}


def test_a_new_file_is_created_at_the_newest_revision_without_setup(tmp_path, cli_on):
    db = tmp_path / "new" / "labcal.sqlite"
    with Journal(db):
        pass
    assert alembic_revision(db) == HEAD and user_version(db) == 6
    assert not list(db.parent.glob("*.bak"))  # nothing to keep
    code, out, _ = cli_on(db, "db", "status")
    assert code == 0 and f"schema {HEAD}" in out and "current" in out


def test_a_new_file_is_the_file_alembics_steps_make(tmp_path):
    """A new journal is written from a script (no Alembic at every run): it must hold exactly what an
    empty file brought to the newest revision by Alembic's own steps holds — every table, index and
    row, and the user_version — and the shipped script must be that file's dump."""
    by_alembic = tmp_path / "alembic" / "labcal.sqlite"
    by_alembic.parent.mkdir()
    migrations_run = labdb.upgrade  # on an existing empty file: Alembic's steps, no script
    by_alembic.touch()
    assert migrations_run(by_alembic).reached == HEAD
    new = tmp_path / "new" / "labcal.sqlite"
    labdb.connect(new).close()
    assert dump(new) == dump(by_alembic) and dump(new)
    assert user_version(new) == user_version(by_alembic) == 6
    assert labdb.HEAD_SCRIPT.read_text(encoding="utf-8") == labdb.alembic_head_script(tmp_path), \
        f"{labdb.HEAD_SCRIPT.name} is not the newest revision's dump: rewrite it (labdb.alembic_head_script)"


def test_files_created_at_once_are_created_once(tmp_path):
    """Programs creating the same new file at once, and opening and closing it again: one creates it,
    the others find it made, and none is told the file is busy. Thirty new files, six threads each
    opening one three times: before the switch to WAL was tried again while busy, 7 in 100 such files
    failed (an 89 % chance that these thirty catch it: 1 − 0.93³⁰)."""
    errors: list[BaseException] = []
    for trial in range(30):
        path = tmp_path / f"labcal-{trial}.sqlite"

        def create(path: Path = path) -> None:
            try:
                for _ in range(3):
                    labdb.connect(path).close()
            except BaseException as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        threads = [threading.Thread(target=create) for _ in range(6)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        assert alembic_revision(path) == HEAD
        with closing(raw(path)) as con:
            assert con.execute("SELECT count(*) FROM alembic_version").fetchone()[0] == 1
    assert not errors


def version_0(tmp_path: Path, tables: tuple[str, ...]) -> Path:
    """A version-0 file with only some of the tables, made with the old labcal's own statements."""
    path = tmp_path / f"only-{'-'.join(tables) or 'nothing'}.sqlite"
    with closing(raw(V0 / "labcal.sqlite")) as old, closing(raw(path)) as con:
        for tbl_name, sql in old.execute("SELECT tbl_name, sql FROM sqlite_master WHERE sql IS NOT NULL "
                                         "ORDER BY rowid"):
            if tbl_name in tables:
                con.execute(sql)
    return path


def shape_of(path: Path) -> dict:
    import sqlalchemy as sa

    engine = sa.create_engine(f"sqlite:///{path}")
    with engine.connect() as connection:
        found = shape(connection)
    engine.dispose()
    return found


@pytest.mark.parametrize("tables", [("runs", "points", "events"), ("certificates",), ()])
def test_every_version_0_file_upgrades_to_the_schema_of_a_new_one(tmp_path, tables):
    """The journal or the history alone may have created the file; either way, one schema after."""
    path = version_0(tmp_path, tables)
    labdb.upgrade(path)
    fresh = tmp_path / "new" / "labcal.sqlite"
    with Journal(fresh):
        pass
    migrated = tmp_path / "migrated.sqlite"
    shutil.copy(V0 / "labcal.sqlite", migrated)
    labdb.upgrade(migrated)
    assert shape_of(path) == shape_of(fresh) == shape_of(migrated)
    assert alembic_revision(path) == alembic_revision(fresh) == HEAD
    assert labdb.backup_path(path, "0000").exists() == bool(tables)  # nothing to keep in an empty file
    with pytest.raises(LabcalError, match="no certificates for instrument 'SIMULATED'"):
        certificates_for("SIMULATED", path)  # the table is there, empty


# --- (b) a column added later breaks nothing -----------------------------------------------------
def test_added_columns_break_no_read_or_write(v0):
    db = v0 / "labcal.sqlite"
    labdb.upgrade(db)
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
        assert [(e.kind, e.data, e.station_time) for e in journal.events(run_id)] == [
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
    assert any("INSERT INTO points (run_id, " in s for s in sql_strings(SOURCE / "store" / "journal.py"))


def test_point_columns_are_the_journal_record():
    """The journal writes PointRecord's fields by name: each must be a column of points."""
    with closing(raw(V0 / "labcal.sqlite")) as con:
        columns = {r[1] for r in con.execute("PRAGMA table_info(points)")}
    assert {f.name for f in fields(PointRecord)} <= columns


# --- (c) a newer database is refused -------------------------------------------------------------
@pytest.mark.parametrize("newer", ["alembic", "user_version"])
def test_newer_database_is_refused_in_one_line_and_left_alone(v0, capsys, cli_on, newer):
    db = v0 / "labcal.sqlite"
    if newer == "alembic":
        labdb.upgrade(db)
        for backup in v0.glob("*.bak"):
            backup.unlink()
        with closing(raw(db)) as con:
            con.execute("UPDATE alembic_version SET version_num='0099'")
            con.commit()
        found = "0099"
    else:  # a labcal before Alembic never wrote 9; no alembic_version: not this history's
        with closing(raw(db)) as con:
            con.execute("PRAGMA user_version = 9")
        found = "user_version 9"
    before = dump(db)
    message = (f"{db}: the lab database is at schema {found}, newer than this labcal's ({HEAD}); "
               "upgrade labcal")
    with pytest.raises(LabcalError) as exc:
        Journal(db)
    assert str(exc.value) == message
    for command in (["history", "SIMULATED", "--db", str(db)], ["db", "upgrade", "--db", str(db)]):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1
        assert "newer than this labcal" in err and "upgrade labcal" in err
    code, _, err = cli_on(db, "resume", str(v0 / "stopped"), "--yes", "--no-report")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "upgrade labcal" in err
    assert dump(db) == before and not list(v0.glob("*.bak"))


# --- (d) upgrading twice, and an upgrade that fails ----------------------------------------------
def test_upgrading_twice_is_a_no_op(v0, cli_on):
    db = v0 / "labcal.sqlite"
    upgrade(cli_on, db)
    migrated = dump(db)
    backup = labdb.backup_path(db, "0000")
    backup.unlink()
    assert "already at schema" in upgrade(cli_on, db)
    with Journal(db):
        pass
    assert dump(db) == migrated and alembic_revision(db) == HEAD
    assert not list(v0.glob("*.bak"))  # no upgrade, no backup


def test_a_failing_step_rolls_every_step_back(v0, capsys):
    """Someone's own ``users`` table: revision 0006 fails after 0001–0005 have run; all undone."""
    db = v0 / "labcal.sqlite"
    with closing(raw(db)) as con:
        con.execute("CREATE TABLE users (who TEXT)")
        con.commit()
    old = dump(db)
    assert main(["db", "upgrade", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert f"{db}: cannot upgrade the lab database from schema 0000" in err.replace("\n", "")
    assert "users already exists" in err and "the file is unchanged" in err
    assert user_version(db) == 0 and dump(db) == old  # 0001's index, 0002's column… rolled back with it
    assert alembic_revision(db) is None
    assert dump(labdb.backup_path(db, "0000")) == old
    with closing(raw(db)) as con:
        con.execute("DROP TABLE users")
        con.commit()
    labdb.upgrade(db)  # and the upgrade still goes through afterwards
    with Journal(db) as journal:
        assert journal.run(2).status == "stopped"
    assert alembic_revision(db) == HEAD


def test_a_database_error_in_the_first_step_is_one_line_and_changes_nothing(v0, capsys):
    db = v0 / "labcal.sqlite"
    with closing(raw(db)) as con:  # someone's own index already holds revision 0001's name
        con.execute("CREATE INDEX events_by_run ON certificates (issued_utc)")
        con.commit()
    old = dump(db)
    assert main(["db", "upgrade", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "events_by_run already exists" in err and "the file is unchanged" in err
    assert user_version(db) == 0 and dump(db) == old


def test_backup_is_consistent_while_another_program_holds_the_wal(v0):
    """The last points of a WAL database can still sit in the -wal file when labcal upgrades it."""
    db = v0 / "labcal.sqlite"
    with closing(raw(db)) as writer:
        writer.execute("PRAGMA journal_mode=WAL")
        writer.execute("PRAGMA wal_autocheckpoint=0")  # keep every new page in the -wal file
        writer.execute("UPDATE runs SET operator='in the wal' WHERE id=1")
        writer.commit()
        assert Path(f"{db}-wal").stat().st_size > 0
        labdb.upgrade(db)
        with closing(raw(labdb.backup_path(db, "0000"))) as backup:
            assert backup.execute("SELECT operator FROM runs WHERE id=1").fetchone() == ("in the wal",)
            assert backup.execute("PRAGMA user_version").fetchone() == (0,)


def test_programs_upgrading_an_old_database_at_once_upgrade_it_once(v0):
    """The revision is read again under the write lock, so the second one finds the work done."""
    db = v0 / "labcal.sqlite"
    old = dump(db)
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def upgrade_it() -> None:
        start.wait()
        try:
            labdb.upgrade(db)
        except BaseException as exc:  # reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=upgrade_it) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert errors == [] and alembic_revision(db) == HEAD
    assert dump(labdb.backup_path(db, "0000")) == old
