"""Races between a bench's `labcal sync` and the other writers of a certificate, with real processes
against a real PostgreSQL server (tests/services.py):

- a draft re-issued at the bench while its `labcal sync` is receiving the lab's approved copy of that
  certificate is not overwritten (it is the bench's own change, not yet sent); the next sync sends it,
  the lab keeps its approved certificate (a draft never replaces an approved one) and the journal
  receives that;
- the lab keeps one approved file of each name per run, whoever stores a second.

The sync is held at known points by locks the test takes — PostgreSQL's on the certificates table, and
SQLite's write lock on the journal — and observed through pg_stat_activity, so that the interleaving
is the same on every run, whatever the machine's speed.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import time
from contextlib import closing
from pathlib import Path

import psycopg
import pytest
from cli import LABCAL, at_bench, bench_env

APPROVAL = {"by": "A. Metrologist", "role": "Technical manager", "approved_utc": "2026-11-27T10:00:00+00:00"}


def environment(tmp_path: Path, db: str) -> dict[str, str]:
    return bench_env(tmp_path, db)


def labcal(tmp_path: Path, *args: str, db: str) -> subprocess.CompletedProcess:
    return at_bench(tmp_path, *args, db=db)


def wait_for(url: str, condition: str, what: str, timeout_s: float = 60.0) -> None:
    """Poll pg_stat_activity until a backend other than ours meets ``condition``."""
    deadline = time.monotonic() + timeout_s
    with psycopg.connect(url, autocommit=True) as conn:
        while time.monotonic() < deadline:
            query = f"SELECT count(*) FROM pg_stat_activity WHERE pid <> pg_backend_pid() AND {condition}"
            if conn.execute(query).fetchone()[0]:
                return
            time.sleep(0.02)
    raise AssertionError(f"the sync never {what}")


@pytest.fixture
def bench(tmp_path, postgres_url):
    """bench-1's role has run a simulated calibration; its draft certificate is in the lab, and the
    journal notes it as sent. (admin URL, bench URL, certificate id, the draft's document.)"""
    assert labcal(tmp_path, "db", "upgrade", "--db", postgres_url, db=postgres_url).returncode == 0
    granted = labcal(tmp_path, "db", "grant-station", "bench-1", "--db", postgres_url, db=postgres_url)
    assert granted.returncode == 0, granted.stderr
    url = granted.stdout.strip().splitlines()[-1]
    done = labcal(tmp_path, "run", "--sim", "--yes", "--plan", "one-mount-16", "--serial", "ACC-0042",
                  "--out", str(tmp_path / "bench-1" / "run"), db=url)
    assert done.returncode == 0, done.stderr
    with psycopg.connect(postgres_url) as conn:
        (certificate_id, draft), = conn.execute("SELECT certificate_id, document FROM certificates"
                                                ).fetchall()
    return postgres_url, url, certificate_id, draft


def journal_certificate(tmp_path: Path, certificate_id: str) -> tuple[str, str]:
    with closing(sqlite3.connect(tmp_path / "bench-1" / "journal.sqlite")) as db:
        return db.execute("SELECT sha256, document FROM certificates WHERE certificate_id = ?",
                          (certificate_id,)).fetchone()


@pytest.mark.slow  # a simulated run and three syncs as processes: about 15 s
def test_a_draft_re_issued_while_sync_receives_the_approval_is_not_overwritten(tmp_path, bench):
    admin, url, certificate_id, draft = bench
    approved = json.dumps({**json.loads(draft), "approval": APPROVAL})
    reissued = json.dumps({**json.loads(draft), "issued_utc": "2026-11-28T09:00:00Z"})
    with psycopg.connect(admin) as conn:  # the lab approved it (as its server does: in place of the draft)
        conn.execute("UPDATE certificates SET document = %s, sha256 = %s WHERE certificate_id = %s",
                     (approved, "a" * 64, certificate_id))
    gate = psycopg.connect(admin)
    journal = sqlite3.connect(tmp_path / "bench-1" / "journal.sqlite", isolation_level=None, timeout=30)
    sync = None
    try:
        gate.execute("LOCK TABLE certificates IN ACCESS EXCLUSIVE MODE")  # the sync's pull waits here
        sync = subprocess.Popen([LABCAL, "sync", "--json"], env=environment(tmp_path, url), text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        wait_for(admin, "wait_event_type = 'Lock' AND query LIKE '%FROM certificates%'", "reached the pull")
        journal.execute("BEGIN IMMEDIATE")  # the bench's other process (labcal report) holds the journal
        gate.commit()
        # the pull has read the journal and fetched the lab's approved copy: it now waits for the journal
        wait_for(admin, "state = 'idle in transaction' AND query LIKE '%certificates.document%'",
                 "fetched the lab's copy")
        journal.execute("UPDATE certificates SET sha256 = ?, document = ? WHERE certificate_id = ?",
                        ("b" * 64, reissued, certificate_id))
        journal.execute("COMMIT")
        out, err = sync.communicate(timeout=120)
    finally:
        if sync is not None and sync.poll() is None:
            sync.kill()
            sync.communicate()
        gate.close()
        journal.close()
    assert sync.returncode == 0, err
    assert json.loads(out)["received"]["certificates"] == 0
    assert journal_certificate(tmp_path, certificate_id) == ("b" * 64, reissued)  # the bench's own, kept

    # sent next time: the lab keeps its approved certificate, and the journal receives it
    done = labcal(tmp_path, "sync", "--json", db=url)
    assert done.returncode == 0, done.stderr
    with psycopg.connect(admin) as conn:
        assert conn.execute("SELECT sha256, document FROM certificates").fetchall() == [("a" * 64, approved)]
    again = labcal(tmp_path, "sync", db=url)
    assert again.returncode == 0, again.stderr
    assert journal_certificate(tmp_path, certificate_id) == ("a" * 64, approved)


def test_the_lab_keeps_one_approved_file_of_each_name_per_revision(postgres_url, tmp_path):
    assert labcal(tmp_path, "db", "upgrade", "--db", postgres_url, db=postgres_url).returncode == 0
    insert = ("INSERT INTO certificate_files (certificate_id, run_uuid, name, sha256, content, stored_utc) "
              "VALUES (%s, 'run-uuid', 'certificate.json', 'x', 'x', '2026-11-28')")
    with psycopg.connect(postgres_url) as conn:
        conn.execute(insert, ("ACC-0042-1",))
    with psycopg.connect(postgres_url) as conn, pytest.raises(psycopg.errors.UniqueViolation):
        conn.execute(insert, ("ACC-0042-1",))  # a second approval of the same revision, by any process
    with psycopg.connect(postgres_url) as conn:  # a later revision of the run: its own approved set
        conn.execute(insert, ("ACC-0042-1-R2",))
    with psycopg.connect(postgres_url) as conn:
        kept = conn.execute("SELECT certificate_id FROM certificate_files ORDER BY certificate_id").fetchall()
        assert kept == [("ACC-0042-1",), ("ACC-0042-1-R2",)]
