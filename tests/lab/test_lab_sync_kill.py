"""A bench's `labcal sync` killed (SIGKILL) at several points loses nothing and doubles nothing: against
a real PostgreSQL server (tests/services.py), a run made while the lab could not be reached is sent by
a `labcal sync` process that the test kills

1. while it waits to number the run (the lab's run-number lock, held by the test),
2. after it has sent the run and its points, while it waits to send the events (a lock on events),
3. after it has sent runs, points and events, while it waits to store the certificate,
4. after the lab has committed everything, while it waits to note so in its journal (the journal's
   write lock, held by the test);

after each kill the lab holds nothing of an uncommitted transaction (1-3) or all of the committed one
(4), and a last `labcal sync` completes: every point, event and certificate of the journal is in the
lab once, with the digests the journal wrote, and the run has the lab's first number (no number was
used up by the killed attempts).

Where the sync is when it is killed is known, not guessed: it is held by a lock the test holds and
seen waiting in pg_stat_activity (or its batch seen committed in the lab).
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import time
from contextlib import closing
from pathlib import Path

import psycopg
import pytest
from cli import LABCAL, at_bench, bench_env
from services import free_port

from labcal.store.sync import RUN_NUMBER_LOCK

pytestmark = pytest.mark.slow  # a simulated run and six syncs as processes: about 20 s


def environment(tmp_path: Path, db: str) -> dict[str, str]:
    return bench_env(tmp_path, db)


def labcal(tmp_path: Path, *args: str, db: str) -> subprocess.CompletedProcess:
    return at_bench(tmp_path, *args, db=db)


def seen(admin: str, condition: str, what: str, timeout_s: float = 60.0) -> None:
    """Poll the lab (as its administrator) until ``condition`` (SQL) holds."""
    deadline = time.monotonic() + timeout_s
    with psycopg.connect(admin, autocommit=True) as conn:
        while time.monotonic() < deadline:
            if conn.execute(f"SELECT {condition}").fetchone()[0]:
                return
            time.sleep(0.02)
    raise AssertionError(f"the sync never {what}")


def waiting_on(query: str) -> str:
    return (f"EXISTS (SELECT 1 FROM pg_stat_activity WHERE usename = 'labcal_bench_bench_1' AND "
            f"wait_event_type = 'Lock' AND query LIKE '%{query}%')")


QUERIES = {  # what a sync sends, as each side names it (the lab keeps an event's journal id as origin_id)
    "runs": "SELECT {lab_id}uuid, status, digest FROM runs ORDER BY id",
    "points": ("SELECT r.uuid, p.seq, p.vx, p.vy, p.vz, p.link, p.digest FROM points p JOIN runs r "
               "ON r.id = p.run_id ORDER BY r.uuid, p.seq"),
    "events": ("SELECT r.uuid, e.{event_id}, e.kind, e.message, e.link, e.digest FROM events e JOIN runs r "
               "ON r.id = e.run_id ORDER BY r.uuid, e.{event_id}"),
    "certificates": "SELECT certificate_id, sha256 FROM certificates ORDER BY 1",
}


def lab_rows(admin: str) -> dict[str, list[tuple]]:
    """What the lab holds, read with plain SQL (runs with the lab's number first)."""
    with psycopg.connect(admin) as conn:
        return {name: conn.execute(sql.format(lab_id="id, ", event_id="origin_id")).fetchall()
                for name, sql in QUERIES.items()}


def journal_rows(journal: Path) -> dict[str, list[tuple]]:
    with closing(sqlite3.connect(journal)) as db:
        return {name: db.execute(sql.format(lab_id="", event_id="id")).fetchall()
                for name, sql in QUERIES.items()}


def gone(admin: str) -> None:
    """The killed sync's server session has ended (its transaction rolled back, or committed before)."""
    seen(admin, "NOT EXISTS (SELECT 1 FROM pg_stat_activity WHERE usename = 'labcal_bench_bench_1')",
         "left the lab after it was killed")


def test_a_sync_killed_at_four_points_loses_and_doubles_nothing(tmp_path, postgres_url):
    admin = postgres_url
    assert labcal(tmp_path, "db", "upgrade", "--db", admin, db=admin).returncode == 0
    granted = labcal(tmp_path, "db", "grant-station", "bench-1", "--db", admin, db=admin)
    assert granted.returncode == 0, granted.stderr
    url = granted.stdout.strip().splitlines()[-1]
    away = url.replace(url.rpartition("@")[2].split("/")[0], f"127.0.0.1:{free_port()}")
    offline = labcal(tmp_path, "run", "--sim", "--yes", "--plan", "one-mount-16", "--serial", "ACC-0042",
                     "--out", str(tmp_path / "bench-1" / "run"), db=away)
    assert offline.returncode == 0 and "unreachable" in offline.stderr, offline.stderr
    journal = tmp_path / "bench-1" / "journal.sqlite"
    expected = journal_rows(journal)
    assert len(expected["points"]) == 16 and len(expected["certificates"]) == 1 and expected["events"]
    empty = {name: [] for name in expected}

    def killed_while(hold: str, waits_for: str) -> None:
        """A sync killed while it waits for the lock the test takes with ``hold``."""
        with psycopg.connect(admin) as gate:
            gate.execute(hold)
            sync = subprocess.Popen([LABCAL, "sync"], env=environment(tmp_path, url), stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE)
            try:
                seen(admin, waiting_on(waits_for), f"waited at {waits_for}")
            finally:
                os.kill(sync.pid, signal.SIGKILL)
                sync.communicate(timeout=60)
        gone(admin)

    killed_while(f"SELECT pg_advisory_lock({RUN_NUMBER_LOCK})", "pg_advisory_xact_lock")
    assert lab_rows(admin) == empty
    killed_while("LOCK TABLE events IN SHARE MODE", "INSERT INTO events")
    assert lab_rows(admin) == empty
    killed_while("LOCK TABLE certificates IN SHARE MODE", "INSERT INTO certificates")
    assert lab_rows(admin) == empty

    # 4: the lab commits; the journal's note of it waits for the journal, and the sync is killed there
    holder = sqlite3.connect(journal, isolation_level=None, timeout=30)
    try:
        holder.execute("BEGIN IMMEDIATE")
        sync = subprocess.Popen([LABCAL, "sync"], env=environment(tmp_path, url), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE)
        try:
            seen(admin, "(SELECT count(*) FROM certificates) = 1 AND (SELECT count(*) FROM points) = 16",
                 "committed its batch")
        finally:
            os.kill(sync.pid, signal.SIGKILL)
            sync.communicate(timeout=60)
        holder.execute("ROLLBACK")
    finally:
        holder.close()
    gone(admin)
    with closing(sqlite3.connect(journal)) as db:
        assert db.execute("SELECT count(*) FROM sync_cursors").fetchone() == (0,)  # nothing noted as sent
    committed = lab_rows(admin)
    assert [r[1:] for r in committed["runs"]] == expected["runs"] and committed["runs"][0][0] == 1

    done = labcal(tmp_path, "sync", db=url)
    assert done.returncode == 0, done.stderr
    lab = lab_rows(admin)
    assert lab == committed  # offered again, stored once
    assert [r[1:] for r in lab["runs"]] == expected["runs"] and [r[0] for r in lab["runs"]] == [1]
    assert lab["points"] == expected["points"] and lab["certificates"] == expected["certificates"]
    assert lab["events"] == expected["events"]
    again = labcal(tmp_path, "sync", db=url)
    assert again.returncode == 0 and "nothing to send" in " ".join(again.stdout.split()), again.stdout
