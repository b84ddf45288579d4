"""A bench that syncs while the lab server is approving its run receives either nothing of the approval
or all of it, never part, and never a file twice: against a real PostgreSQL server (tests/services.py),
a bench measures a run through the real drivers as its own role, `labcal serve` on the server's role
approves it, and the test holds the approval inside its transaction (a lock on certificate_files) while
the bench's `labcal sync` runs; then lets it commit, and two `labcal sync` processes of the bench run at
once.

Expected values are read independently: the lab's files with plain SQL and hashlib, the folder's bytes,
the signature by `labcal certificate verify`.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import threading
import time
from pathlib import Path

import httpx
import psycopg
import pytest
from cli import LABCAL, bench_env
from lab_server import add_user, served
from simulated_runs import bench_run

SERIAL = "ACC-0042"
FILES = {"certificate.json", "certificate.dcc.xml", "report.pdf", "report.html"}
pytestmark = pytest.mark.slow(seconds=45)  # a run through the drivers, a server, four syncs


def environment(tmp_path: Path, station: str, db: str) -> dict[str, str]:
    return bench_env(tmp_path, db, station)


def at(tmp_path: Path, station: str, db: str, *args: str) -> subprocess.CompletedProcess:
    done = subprocess.run([LABCAL, *args], capture_output=True, text=True,
                          env=environment(tmp_path, station, db), timeout=240)
    assert done.returncode == 0, f"{station}: labcal {' '.join(args)}: {done.stderr}"
    return done


def lab_files(admin: str) -> dict[str, bytes]:
    with psycopg.connect(admin) as conn:
        rows = conn.execute("SELECT name, sha256, content FROM certificate_files").fetchall()
    assert all(hashlib.sha256(bytes(content)).hexdigest() == sha for _, sha, content in rows)
    assert len(rows) == len({name for name, _, _ in rows})  # each file once
    return {name: bytes(content) for name, _, content in rows}


def test_a_bench_syncing_mid_approval_receives_all_of_it_or_nothing(tmp_path, postgres_url, monkeypatch):
    admin = postgres_url
    at(tmp_path, "admin", admin, "db", "upgrade", "--db", admin)
    bench = at(tmp_path, "admin", admin, "db", "grant-station", "bench-1", "--db", admin).stdout.split()[-1]
    server = at(tmp_path, "admin", admin, "db", "grant-server", "web", "--db", admin).stdout.split()[-1]
    at(tmp_path, "admin", admin, "certificate", "keygen", "--out", str(tmp_path / "server"))
    at(tmp_path, "admin", admin, "certificate", "approvers", "add", "lab server", "--role", "lab server",
       "--public-key", str(tmp_path / "server.pub"))
    token = add_user(admin, "ada", "approver", "a long passphrase 1")
    for name, value in environment(tmp_path, "bench-1", bench).items():
        if name.startswith("LABCAL_"):
            monkeypatch.setenv(name, value)
    (tmp_path / "bench-1").mkdir()
    run = bench_run(tmp_path / "bench-1" / "run", bench, SERIAL)  # its draft sent by the bench's role
    at(tmp_path, "bench-1", bench, "sync")
    draft = (run / "certificate.json").read_bytes()
    assert json.loads(draft).get("approval") is None

    answers: list = []
    with served(server, "--key", str(tmp_path / "server.key")) as url:
        with psycopg.connect(admin) as gate:
            # the approval waits to store its files, its transaction open
            gate.execute("LOCK TABLE certificate_files IN SHARE MODE")

            def approve() -> None:
                answers.append(httpx.post(f"{url}/api/runs/1/approve", timeout=240,
                                          headers={"Authorization": f"Bearer {token}"}))

            approving = threading.Thread(target=approve)
            approving.start()
            try:
                with psycopg.connect(admin, autocommit=True) as watch:
                    for _ in range(6000):
                        if watch.execute("SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = "
                                         "'Lock' AND query LIKE '%INSERT INTO certificate_files%'"
                                         ).fetchone()[0]:
                            break
                        time.sleep(0.02)
                    else:
                        raise AssertionError(f"the approval never reached its files: {answers}")
                mid = json.loads(at(tmp_path, "bench-1", bench, "sync", "--json").stdout)
            finally:
                gate.rollback()  # the approval goes on
                approving.join(240)
    assert mid["received"]["approved certificate files"] == 0
    assert (run / "certificate.json").read_bytes() == draft  # nothing of the approval yet
    assert answers and answers[0].status_code == 200, answers

    files = lab_files(admin)
    assert set(files) == FILES
    syncs = [subprocess.Popen([LABCAL, "sync", "--json"], env=environment(tmp_path, "bench-1", bench),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [sync.communicate(timeout=240) for sync in syncs]
    assert all(sync.returncode == 0 for sync in syncs), results
    received = [json.loads(out)["received"]["approved certificate files"] for out, _ in results]
    assert 4 <= sum(received) <= 8  # each wrote the four, or found some already there
    assert {p.name for p in run.iterdir() if p.name.startswith(".")} == set()  # no temporary file left
    assert all((run / name).read_bytes() == files[name] for name in FILES)
    assert lab_files(admin) == files
    verified = json.loads(at(tmp_path, "bench-1", bench, "certificate", "verify",
                             str(run / "certificate.json"), "--json").stdout)
    assert verified["valid"] is True and verified["approved_by"] == "ada"
