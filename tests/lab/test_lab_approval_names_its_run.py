"""An approval on a PostgreSQL lab database can only ever sign the run it names: against a real PostgreSQL
server (tests/services.py), a bench measures two runs through the real drivers as its own role; its
folder of run 1 is then replaced by a copy of run 2's, with run.json edited to name another journal,
and `POST /api/runs/1/approve` to `labcal serve` on the server's role signs run 1 as the lab holds it —
its uuid, its readings — not what the folder says.

What run 1 and run 2 are is read from the lab with plain SQL; the signed certificate from the lab's
certificate_files and checked by `labcal certificate verify`.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import httpx
import psycopg
import pytest
from cli import LABCAL, bench_env
from lab_server import add_user, served
from simulated_runs import bench_run

pytestmark = pytest.mark.slow(seconds=36)  # two runs through the drivers and a server


def environment(tmp_path: Path, station: str, db: str) -> dict[str, str]:
    return bench_env(tmp_path, db, station)


def at(tmp_path: Path, station: str, db: str, *args: str) -> subprocess.CompletedProcess:
    done = subprocess.run([LABCAL, *args], capture_output=True, text=True,
                          env=environment(tmp_path, station, db), timeout=240)
    assert done.returncode == 0, f"{station}: labcal {' '.join(args)}: {done.stderr}"
    return done


def test_a_folder_copied_over_another_and_renamed_journal_do_not_change_what_is_signed(
        tmp_path, postgres_url, monkeypatch):
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
    one = bench_run(tmp_path / "bench-1" / "run1", bench, "ACC-0042")
    two = bench_run(tmp_path / "bench-1" / "run2", bench, "ACC-0043")
    at(tmp_path, "bench-1", bench, "sync")
    with psycopg.connect(admin) as conn:
        uuids = dict(conn.execute("SELECT id, uuid FROM runs").fetchall())
        drafts = {json.loads(d)["data"]["journal"]["run_uuid"]: json.loads(d)
                  for d, in conn.execute("SELECT document FROM certificates").fetchall()}
    assert set(uuids) == {1, 2} and set(drafts) == set(uuids.values())

    # run 1's folder becomes a copy of run 2's, its run.json naming another journal
    shutil.rmtree(one)
    shutil.copytree(two, one)
    info = json.loads((one / "run.json").read_text())
    info["journal"] = str(tmp_path / "elsewhere.sqlite")
    (one / "run.json").write_text(json.dumps(info))

    with served(server, "--key", str(tmp_path / "server.key")) as url:
        done = httpx.post(f"{url}/api/runs/1/approve", headers={"Authorization": f"Bearer {token}"},
                          timeout=240)
    assert done.status_code == 200, done.text
    with psycopg.connect(admin) as conn:
        files = conn.execute("SELECT name, content, run_uuid FROM certificate_files").fetchall()
    folder = tmp_path / "signed"  # as the customer downloads them
    folder.mkdir()
    for name, content, _ in files:
        (folder / name).write_bytes(bytes(content))
    runs = {run_uuid for _, _, run_uuid in files}
    signed = json.loads((folder / "certificate.json").read_text())
    assert runs == {uuids[1]}
    assert signed["data"]["journal"]["run_uuid"] == uuids[1]
    assert signed["instrument"]["serial"] == "ACC-0042"
    assert signed["data"]["readings_sha256"] == drafts[uuids[1]]["data"]["readings_sha256"]
    assert signed["data"]["readings_sha256"] != drafts[uuids[2]]["data"]["readings_sha256"]
    verified = json.loads(at(tmp_path, "bench-1", bench, "certificate", "verify",
                             str(folder / "certificate.json"), "--json").stdout)
    assert verified["valid"] is True and verified["approved_by"] == "ada"
