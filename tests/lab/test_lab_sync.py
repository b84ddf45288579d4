"""A PostgreSQL lab database, against a real PostgreSQL server (tests/services.py): every
reading journaled by a station reaches it exactly once — from three stations at once, through a
10 s outage of the server mid-run, and by `labcal sync` after a run made while it was down — and
the one-line refusals of a database behind or ahead, an unknown scheme, a missing driver and an
unreachable server.

Every expectation is read independently of the code under test: the stations' journals with plain
sqlite3, the server with psycopg and plain SQL.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from contextlib import closing
from pathlib import Path

import cli
import psycopg
import pytest
from cli import LABCAL
from lab_readings import journal_points, server_points
from services import free_port

MOUNT_POINTS = 16  # four-mount-64 (the default plan): 4 mounts × 16 points = 64, one replicate
MOUNTS = 4
CERTIFICATE = "certificate_id, serial, calibrated_utc, issued_utc, sha256, document"


def assert_exactly_once(url: str, journals: list[Path]) -> int:
    """Every point of every journal on the server once, equal in every column; nothing else there."""
    expected: dict[tuple[str, int], tuple] = {}
    for journal in journals:
        expected.update(journal_points(journal))
    found = server_points(url)
    keys = [(row[0], row[1]) for row in found]
    assert len(keys) == len(set(keys)), "a point is on the server twice"
    assert {(row[0], row[1]): row[1:] for row in found} == expected
    return len(found)


def server_count(url: str, sql: str = "SELECT count(*) FROM points") -> int:
    try:
        with psycopg.connect(url, connect_timeout=2) as conn:
            return int(conn.execute(sql).fetchone()[0])
    except psycopg.Error:
        return -1  # not there yet (schema not created) or server down


@pytest.mark.slow
def test_three_stations_at_once_reach_one_server_exactly_once(tmp_path, postgres_url):
    stations = ("bench-north", "bench-south", "bench-east")
    runs = [subprocess.Popen([LABCAL, "run", "--sim", "--yes", "--no-report", "--seed", str(n + 1),
                              "--out", str(tmp_path / name / "run")],
                             env=cli.bench_env(tmp_path, postgres_url, name), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
            for n, name in enumerate(stations)]
    outputs = [run.communicate(timeout=240) for run in runs]
    for run, (_, stderr) in zip(runs, outputs, strict=True):
        assert run.returncode == 0, stderr
        assert "unreachable" not in stderr and "not yet in the lab database" not in stderr
    journals = [tmp_path / name / "journal.sqlite" for name in stations]
    total = assert_exactly_once(postgres_url, journals)
    assert total == len(stations) * MOUNTS * MOUNT_POINTS
    with psycopg.connect(postgres_url) as conn:
        rows = conn.execute("SELECT r.station, r.status, r.points_total, count(p.seq) FROM runs r "
                            "JOIN points p ON p.run_id = r.id GROUP BY r.id ORDER BY r.station").fetchall()
    every = MOUNTS * MOUNT_POINTS
    assert rows == [(name, "complete", every, every) for name in sorted(stations)]


def wait_for(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def local_count(journal: Path) -> int:
    if not journal.exists():
        return 0
    with closing(sqlite3.connect(journal, timeout=10)) as db:
        try:
            return int(db.execute("SELECT count(*) FROM points").fetchone()[0])
        except sqlite3.OperationalError:
            return 0


OUTAGE_S = 10.0
HANG_S = 240.0  # what a wait below may take before it is a hang: a deadline, never a measurement (a
# loaded machine starts labcal, creates the schema and measures a mount in far less, but not in 60 s)
FIGURES = Path(os.environ.get("LABCAL_OUTAGE_FIGURES", os.devnull))


@pytest.mark.slow
def test_a_run_that_loses_the_server_for_10_s_ends_with_every_reading_there_once(
        tmp_path, postgres_cluster):
    """The run is held at its remount prompts by its operator (answers on stdin, given when the test
    says), so the outage falls where the test wants on any machine: mount 1 measured with the
    server up, mount 2 (and the start of mount 3) while it is down, the rest after it is back."""
    url = postgres_cluster.url(postgres_cluster.create_database())
    journal = tmp_path / "bench" / "journal.sqlite"
    run = subprocess.Popen([LABCAL, "run", "--sim", "--no-report", "--out", str(tmp_path / "bench" / "run")],
                           env=cli.bench_env(tmp_path, url, "bench"), stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert run.stdin is not None

    def answer() -> None:
        assert run.stdin is not None
        run.stdin.write("y\n")
        run.stdin.flush()

    paused = False
    try:
        answer()  # mount 1
        wait_for(lambda: server_count(url) == MOUNT_POINTS, HANG_S, "mount 1 on the server")
        before = server_count(url)
        postgres_cluster.pause()
        paused = True
        down_at = time.monotonic()
        answer()  # mount 2, measured while the server is down
        wait_for(lambda: local_count(journal) == 2 * MOUNT_POINTS, HANG_S, "mount 2 in the journal")
        time.sleep(max(0.0, down_at + OUTAGE_S - 1.0 - time.monotonic()))
        assert run.poll() is None
        answer()  # mount 3 begins while the server is still down
        time.sleep(max(0.0, down_at + OUTAGE_S - time.monotonic()))
        during = local_count(journal) - before
        postgres_cluster.start()
        paused = False
        up_at = time.monotonic()
        answer()  # mount 4
        _, stderr = run.communicate(timeout=HANG_S)
    finally:
        if paused:
            postgres_cluster.start()
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, stderr
    assert up_at - down_at >= OUTAGE_S
    assert stderr.count("unreachable") == 1, stderr
    assert "not yet in the lab database" not in stderr
    total = assert_exactly_once(url, [journal])
    assert total == MOUNTS * MOUNT_POINTS
    assert before == MOUNT_POINTS and during >= MOUNT_POINTS
    with psycopg.connect(url) as conn:
        event = conn.execute("SELECT count(*) FROM events WHERE kind = 'lab_database'").fetchone()[0]
    assert event == 1  # the journal's record of the outage, sent too
    with FIGURES.open("a") as figures:
        figures.write(f"outage {OUTAGE_S:.0f} s: {before} points on the server before, {during} journaled "
                      f"while it was down, {total - before - during} after; {total} there once each\n")


def test_labcal_sync_sends_a_run_made_while_the_server_was_down(tmp_path, postgres_cluster, capsys,
                                                              monkeypatch):
    url = postgres_cluster.url(postgres_cluster.create_database())
    cli.as_bench(monkeypatch, tmp_path, url, "bench")
    postgres_cluster.pause()
    try:
        ran, _, ran_err = cli.cli(capsys, "run", "--sim", "--yes", "--no-report", "--replicates", "1",
                                  "--plan", "four-mount-64", "--out", str(tmp_path / "run"))
        refused, _, refused_err = cli.cli(capsys, "sync")
    finally:
        postgres_cluster.start()
    assert ran == 0, ran_err
    assert "not yet in the lab database" in ran_err and "labcal sync" in ran_err
    assert refused == 2 and "cannot reach the lab database" in refused_err
    assert len(refused_err.strip().splitlines()) == 1 and "Traceback" not in refused_err
    journal = tmp_path / "bench" / "journal.sqlite"
    points = local_count(journal)
    assert points == MOUNTS * MOUNT_POINTS
    code, out, err = cli.cli(capsys, "sync")
    assert code == 0, err
    assert f"{points} points" in out
    assert assert_exactly_once(url, [journal]) == points
    code, out, _ = cli.cli(capsys, "sync")
    assert code == 0 and "nothing to send" in out
    assert assert_exactly_once(url, [journal]) == points


# --- refusals: one line, exit 2, no traceback ----------------------------------------------------
def one_line_refusal(done: tuple[int, str, str], *words: str) -> str:
    """``done``: a labcal's exit code, stdout and stderr (`cli.cli`)."""
    code, _, stderr = done
    assert code == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def test_a_server_database_behind_is_refused_until_labcal_db_upgrade(tmp_path, postgres_url, capsys,
                                                                     monkeypatch):
    import sqlalchemy as sa

    from labcal.store import migrations

    engine = sa.create_engine(postgres_url.replace("postgresql://", "postgresql+psycopg://"))
    with engine.begin() as connection:
        migrations.upgrade(connection, "0006")
    engine.dispose()
    cli.as_bench(monkeypatch, tmp_path, postgres_url, "bench")
    run = cli.cli(capsys, "run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "r"))
    line = one_line_refusal(run, "0006", "older", "labcal db upgrade")
    assert not (tmp_path / "r").exists()  # refused before the run began
    one_line_refusal(cli.cli(capsys, "sync"), "0006", "labcal db upgrade")
    assert "labcal" in line
    code, out, _ = cli.cli(capsys, "db", "status")
    assert code == 0 and "0006" in out and "behind" in out
    code, _, err = cli.cli(capsys, "db", "upgrade")
    assert code == 0, err
    with psycopg.connect(postgres_url) as conn:
        assert conn.execute("SELECT version_num FROM alembic_version").fetchone()[0] == migrations.HEAD
        assert conn.execute("SELECT count(*) FROM information_schema.columns WHERE table_name = 'events' "
                            "AND column_name = 'origin_id'").fetchone()[0] == 1


def test_a_server_database_ahead_is_refused(tmp_path, postgres_url, capsys, monkeypatch):
    with psycopg.connect(postgres_url) as conn:
        conn.execute("CREATE TABLE alembic_version (version_num VARCHAR(32) PRIMARY KEY)")
        conn.execute("INSERT INTO alembic_version VALUES ('0042')")
    cli.as_bench(monkeypatch, tmp_path, postgres_url, "bench")
    one_line_refusal(cli.cli(capsys, "sync"), "0042", "newer", "upgrade labcal")
    one_line_refusal(cli.cli(capsys, "db", "upgrade"), "0042", "newer", "upgrade labcal")


def test_an_unreachable_server_is_one_line_at_upgrade_and_sync(tmp_path, capsys, monkeypatch):
    url = f"postgresql://labcal@127.0.0.1:{free_port()}/lab"  # nothing listens there
    cli.as_bench(monkeypatch, tmp_path, url, "bench")
    (tmp_path / "bench").mkdir()
    sqlite3.connect(tmp_path / "bench" / "journal.sqlite").close()
    for command in (("db", "upgrade"), ("sync",), ("db", "status")):
        one_line_refusal(cli.cli(capsys, *command), "cannot reach the lab database", "127.0.0.1")


def test_an_unknown_scheme_is_refused(tmp_path, capsys, monkeypatch):
    cli.as_bench(monkeypatch, tmp_path, "mysql://labcal@127.0.0.1:3306/lab", "bench")
    for command in (("runs",), ("db", "upgrade"), ("sync",)):
        one_line_refusal(cli.cli(capsys, *command), "unknown database scheme 'mysql'")


def test_a_server_url_without_its_driver_says_what_to_install(tmp_path):
    """psycopg made unimportable in the child (as when it is not installed), then labcal's main."""
    env = cli.bench_env(tmp_path, "postgresql://labcal@127.0.0.1:5432/lab", "bench")
    code = ("import sys; sys.modules['psycopg'] = None; from labcal.cli import main; "
            "sys.argv = ['labcal', *sys.argv[1:]]; sys.exit(main(sys.argv[1:]))")
    for command in (("runs",), ("sync",), ("db", "upgrade")):
        done = subprocess.run([sys.executable, "-c", code, *command], env=env, capture_output=True, text=True,
                              timeout=60)
        one_line_refusal((done.returncode, done.stdout, done.stderr), "psycopg", "pip install 'labcal[lab]'")


def test_a_sender_fills_an_empty_server_database_and_sends_nothing_twice(tmp_path, postgres_url, capsys,
                                                                          monkeypatch):
    """A journal made with a SQLite lab database (the same schema) sent to an empty server database,
    as a run's sender does when the server was away at the start: the schema is created first."""
    from labcal.config.lab import ServerDatabase
    from labcal.store.sync import Sender

    journal = tmp_path / "lab.sqlite"
    cli.as_bench(monkeypatch, tmp_path, str(journal), "bench")
    code, _, err = cli.cli(capsys, "run", "--sim", "--yes", "--out", str(tmp_path / "run"))
    assert code == 0, err
    with closing(sqlite3.connect(journal)) as db:
        events = db.execute("SELECT count(*) FROM events").fetchone()[0]
        certificate = db.execute(f"SELECT {CERTIFICATE} FROM certificates").fetchall()
    assert len(certificate) == 1  # the run's, issued at its end
    sender = Sender(journal, ServerDatabase(postgres_url, "test"), station="bench")
    try:
        first = sender.push()
        second = sender.push()
    finally:
        sender.close()
    with closing(sqlite3.connect(journal)) as db:
        records = {name: db.execute(f"SELECT count(*) FROM {name}").fetchone()[0]
                   for name in ("device_estimates", "approvers", "settle_pools", "audit")}
    assert first.offered == {"runs": 1, "points": MOUNTS * MOUNT_POINTS, "events": events, "certificates": 1,
                             **records}
    assert first.stored == first.offered
    assert second.total == 0
    assert assert_exactly_once(postgres_url, [journal]) == MOUNTS * MOUNT_POINTS
    with psycopg.connect(postgres_url) as conn:
        found = conn.execute("SELECT count(*), count(DISTINCT origin_id) FROM events").fetchone()
        assert found == (events, events)
        assert conn.execute("SELECT station, status FROM runs").fetchall() == [("bench", "complete")]
        assert conn.execute(f"SELECT {CERTIFICATE} FROM certificates").fetchall() == certificate
