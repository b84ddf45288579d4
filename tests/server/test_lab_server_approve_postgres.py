"""Approving on a PostgreSQL lab database (tests/services.py's private cluster): a bench measures a run
through the real drivers and syncs it; `labcal serve`, connected as the server's own role, approves it
through `POST /api/runs/{id}/approve` from the lab's own copy of the run, keeps the signed certificate,
DCC and report in the lab database, serves the certificate, and `labcal certificate verify` says it is
valid; the bench's folder receives them on `labcal sync`. A point edited in the lab database as its
superuser makes the approval refuse, naming the point, and signs nothing.

What is expected is read independently of the code under test: the lab database with psycopg and
plain SQL, the files with hashlib, the certificate by `labcal certificate verify`."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import sqlite3
from contextlib import closing

import httpx
import psycopg
import pytest
from cli import LABCAL
from cli import in_process as labcal
from lab_server import accessible, add_user, parses_cleanly, served
from simulated_runs import bench_run

# Four runs through the drivers and a server (about 40 s), built once: the group keeps this module's
# tests on one worker of the slow step (`--dist loadgroup`), which otherwise hands out test by test.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("approve_postgres")]

SERIAL = "ACC-0042"
FILES = {"certificate.json", "certificate.dcc.xml", "report.pdf", "report.html"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory, postgres_cluster):
    """One bench (its journal, its folder) that measured and synced four runs, and `labcal serve` on the
    lab database as the server's role, with the lab server's key registered. Each test approves a run
of its own (1, 2, 3, 4), so that they hold in any order."""
    base = tmp_path_factory.mktemp("pg-approve")
    url = postgres_cluster.url(postgres_cluster.create_database())
    patch = pytest.MonkeyPatch()
    (base / "lab.toml").write_text("")
    environment = {"LABCAL_DB": url, "LABCAL_JOURNAL": str(base / "bench" / "journal.sqlite"),
                   "LABCAL_STATION": "bench-1", "LABCAL_CONFIG": str(base / "lab.toml"), "LABCAL_NOTIFY": ""}
    for name, value in environment.items():
        patch.setenv(name, value)
    (base / "bench").mkdir()
    runs = [bench_run(base / "bench" / f"run{n}", url, SERIAL) for n in (1, 2, 3, 4)]  # with drafts
    assert labcal("sync")[0] == 0
    assert labcal("certificate", "keygen", "--out", str(base / "server"))[0] == 0
    code, _, err = labcal("certificate", "approvers", "add", "lab server", "--role", "lab server",
                          "--public-key", str(base / "server.pub"))
    assert code == 0, err
    code, out, err = labcal("db", "grant-server", "labserver")
    assert code == 0, err
    server_url = out.strip().splitlines()[-1]
    assert server_url.startswith("postgresql://labcal_server_labserver@")
    tokens = {"ada": add_user(url, "ada", "approver", "a long passphrase 1")}
    try:
        with served(server_url, "--key", str(base / "server.key")) as served_at:
            yield {"url": served_at, "db": url, "runs": runs, "tokens": tokens, "base": base,
                   "environment": environment}
    finally:
        patch.undo()


@pytest.fixture
def bench(lab, monkeypatch):
    """The bench's environment for a test (each test's own is set afresh by conftest)."""
    for name, value in lab["environment"].items():
        monkeypatch.setenv(name, value)
    return lab


def approve(lab, run_id: int) -> httpx.Response:
    return httpx.post(f"{lab['url']}/api/runs/{run_id}/approve",
                      headers={"Authorization": f"Bearer {lab['tokens']['ada']}"}, timeout=180)


def kept(url: str, run_id: int) -> dict[str, tuple[str, bytes]]:
    """The files the lab database keeps of run ``run_id``'s approved certificate, read with plain SQL."""
    with psycopg.connect(url) as conn:
        return {name: (sha, bytes(content)) for name, sha, content in conn.execute(
            "SELECT name, sha256, content FROM certificate_files WHERE run_uuid = "
            "(SELECT uuid FROM runs WHERE id = %s)", (run_id,))}


def test_the_server_signs_the_labs_own_copy_and_the_bench_receives_it_on_sync(bench):
    lab = bench
    assert kept(lab["db"], 1) == {}
    done = approve(lab, 1)
    assert done.status_code == 200, done.text
    assert done.json()["by"] == "ada"
    files = kept(lab["db"], 1)
    assert set(files) == FILES
    assert all(hashlib.sha256(content).hexdigest() == sha for sha, content in files.values())
    signed = json.loads(files["certificate.json"][1])
    assert signed["approval"]["by"] == "ada" and signed["approval"]["server"]["authentication"] == "API token"

    with psycopg.connect(lab["db"]) as conn:  # the approved certificate in place of the draft
        stored = conn.execute("SELECT document FROM certificates WHERE certificate_id = %s",
                              (signed["certificate_id"],)).fetchone()[0]
    assert json.loads(stored)["approval"] == signed["approval"]
    downloads = lab["base"] / "downloads"
    downloads.mkdir()
    for name in FILES:  # as a customer downloads them from the server
        got = httpx.get(f"{lab['url']}/api/runs/1/approved/{name}",
                        headers={"Authorization": f"Bearer {lab['tokens']['ada']}"}, timeout=30)
        assert got.status_code == 200 and got.content == files[name][1], name
        (downloads / name).write_bytes(got.content)
    downloaded = downloads / "certificate.json"
    code, out, err = labcal("certificate", "verify", str(downloaded), "--json")
    assert code == 0 and json.loads(out)["valid"] is True, err

    folder = lab["runs"][0]
    assert json.loads((folder / "certificate.json").read_text()).get("approval") is None  # a draft still
    code, out, err = labcal("sync", "--json")
    # this run's four files at least (the module's lab is shared: another test may have approved a run)
    assert code == 0 and json.loads(out)["received"]["approved certificate files"] >= len(FILES), err
    for name in FILES:
        assert (folder / name).read_bytes() == files[name][1], name
    with closing(sqlite3.connect(lab["environment"]["LABCAL_JOURNAL"])) as journal:  # its history too
        copied = journal.execute("SELECT document FROM certificates WHERE certificate_id = ?",
                                 (signed["certificate_id"],)).fetchone()[0]
    assert json.loads(copied)["approval"] == signed["approval"]
    code, out, err = labcal("certificate", "verify", str(folder / "certificate.json"), "--json")
    assert code == 0 and json.loads(out)["approved_by"] == "ada", err

    shutil.rmtree(folder)  # the folder lost: `labcal export RUN` makes it again, the approval with it
    code, _, err = labcal("export", "1")
    assert code == 0, err
    assert all((folder / name).read_bytes() == files[name][1] for name in FILES)
    code, out, err = labcal("certificate", "verify", str(folder / "certificate.json"), "--json")
    assert code == 0 and json.loads(out)["valid"] is True, err

    with httpx.Client(base_url=lab["url"], timeout=30) as browser:  # the run page, signed in
        csrf = re.search(r'name="csrf" value="([^"]+)"', browser.get("/login").text)[1]
        browser.post("/login", data={"name": "ada", "password": "a long passphrase 1", "csrf": csrf})
        page = browser.get("/runs/1").text
    assert f"approved by ada (approver) at {signed['approval']['approved_utc']}" in page
    assert 'action="/runs/1/approve"' not in page

    again = approve(lab, 1)
    assert again.status_code == 409 and "already approved by ada" in again.json()["detail"]
    assert kept(lab["db"], 1).keys() == FILES  # nothing added by the refusal


def test_a_point_edited_in_the_lab_database_is_named_and_nothing_is_signed(lab):
    run = 3
    with psycopg.connect(lab["db"]) as conn:
        seq, vx = conn.execute("SELECT seq, vx FROM points WHERE run_id = %s ORDER BY seq OFFSET 3 LIMIT 1",
                               (run,)).fetchone()
        conn.execute("UPDATE points SET vx = %s WHERE run_id = %s AND seq = %s", (vx + 0.0005, run, seq))
    try:
        refused = approve(lab, run)
    finally:  # as it was (a float read back exactly: both are IEEE doubles)
        with psycopg.connect(lab["db"]) as conn:
            conn.execute("UPDATE points SET vx = %s WHERE run_id = %s AND seq = %s", (vx, run, seq))
    assert refused.status_code == 409
    detail = refused.json()["detail"]
    assert len(detail.splitlines()) == 1 and f"point {seq} of run {run} of the lab" in detail, detail
    assert kept(lab["db"], run) == {}


def test_a_server_killed_mid_approval_leaves_no_half_approved_certificate(bench):
    """`labcal serve` killed (SIGKILL) while it holds the approval's transaction open: the lab keeps
    nothing of the approval, and the approval made again afterwards is whole."""
    import os
    import signal
    import subprocess
    import threading
    import time


    lab, run = bench, 2
    server = subprocess.Popen([LABCAL, "serve", "--port", "0", "--db", lab["db"], "--poll", "0.2", "--key",
                               str(lab["base"] / "server.key")], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        assert server.stdout is not None
        url = re.search(r"http://127\.0\.0\.1:\d+", server.stdout.readline())[0]
        answers: list = []

        def ask() -> None:
            try:
                answers.append(approve({**lab, "url": url}, run))
            except httpx.HTTPError as exc:
                answers.append(exc)

        asking = threading.Thread(target=ask)
        asking.start()
        held = False
        with psycopg.connect(lab["db"], autocommit=True) as conn:
            for _ in range(3000):  # the approval's advisory lock: its transaction is open
                locks = conn.execute("SELECT count(*) FROM pg_locks WHERE locktype = 'advisory'").fetchone()
                held = locks[0] > 0
                if held or answers:
                    break
                time.sleep(0.01)
        os.kill(server.pid, signal.SIGKILL)
        asking.join(60)
    finally:
        server.kill()
        server.communicate(timeout=20)
    assert held, f"the approval ended before it could be interrupted: {answers}"
    assert isinstance(answers[0], httpx.HTTPError)  # no answer: the server died
    assert kept(lab["db"], run) == {}
    with psycopg.connect(lab["db"]) as conn:
        drafts = conn.execute("SELECT document FROM certificates WHERE document LIKE "
                              "'%%' || (SELECT uuid FROM runs WHERE id = %s) || '%%'", (run,)).fetchall()
    assert len(drafts) == 1 and json.loads(drafts[0][0]).get("approval") is None  # the bench's draft
    done = approve(lab, run)  # the module's server, still up
    assert done.status_code == 200, done.text
    assert set(kept(lab["db"], run)) == FILES


def test_an_approver_approves_in_chromium_and_downloads_a_certificate_that_verifies(bench, browser):
    lab, run = bench, 4
    page = browser.new_page(accept_downloads=True)
    try:
        page.goto(lab["url"] + "/login")
        page.fill("input[name=name]", "ada")
        page.fill("input[name=password]", "a long passphrase 1")
        page.click("button[type=submit]")
        page.wait_for_url(lab["url"] + "/")
        page.goto(f"{lab['url']}/runs/{run}")
        page.fill(f"form[action='/runs/{run}/approve'] input[name=password]", "a long passphrase 1")
        page.click(f"form[action='/runs/{run}/approve'] button[type=submit]")
        page.wait_for_selector("#message")
        assert "approved by ada" in (page.text_content("#message") or "")
        shown = page.goto(f"{lab['url']}/runs/{run}")  # the page as anyone sees it afterwards
        assert shown is not None
        parses_cleanly(shown.text(), "an approved run's page")
        accessible(page, "an approved run's page")
        assert page.query_selector(f"form[action='/runs/{run}/approve']") is None
        assert "approved by ada (approver)" in (page.text_content("#approved") or "")
        downloads = lab["base"] / "chromium"
        downloads.mkdir()
        for name in FILES:
            with page.expect_download() as waiting:
                page.click(f"#approved a[href='/runs/{run}/approved/{name}']")
            waiting.value.save_as(downloads / name)
    finally:
        page.close()
    files = kept(lab["db"], run)
    assert all((downloads / name).read_bytes() == files[name][1] for name in FILES)
    code, out, err = labcal("certificate", "verify", str(downloads / "certificate.json"), "--json")
    assert code == 0 and json.loads(out)["approved_by"] == "ada", err
    assert labcal("sync")[0] == 0
    folder = lab["runs"][3]
    code, out, err = labcal("certificate", "verify", str(folder / "certificate.json"), "--json")
    assert code == 0 and json.loads(out)["valid"] is True, err


def test_only_the_servers_role_writes_the_approved_files(bench):
    """A bench's role reads the lab's approved files (its sync writes them into its folders) and can
    neither add nor change one; the server's role adds them."""
    code, out, err = labcal("db", "grant-station", "bench-9")
    assert code == 0, err
    bench_url = out.strip().splitlines()[-1]
    row = ("ACC-FORGED-1", "00000000-0000-0000-0000-000000000000", "certificate.json", "0" * 64, b"{}", "now")
    with psycopg.connect(bench_url) as conn:
        conn.execute("SELECT count(*) FROM certificate_files").fetchone()
        with pytest.raises(psycopg.errors.InsufficientPrivilege):
            conn.execute("INSERT INTO certificate_files (certificate_id, run_uuid, name, sha256, content, "
                         "stored_utc) VALUES (%s, %s, %s, %s, %s, %s)", row)
    with psycopg.connect(bench_url) as conn, pytest.raises(psycopg.errors.InsufficientPrivilege):
        conn.execute("UPDATE certificate_files SET content = %s", (b"{}",))
