"""The approver's desk on a PostgreSQL lab database (tests/services.py's private cluster): a bench
measures a run through the real drivers and syncs it, `labcal serve` runs as the server's own role;
the run waits on the queue until an approver signs it through the API, and then its page names the
approver and the time, and its documents download byte for byte as the lab database keeps them (read
here with psycopg and hashlib, not through labcal); the instrument's page lists the calibration with
the same documents. Each page parses cleanly and has no axe-core violation in Chromium."""

from __future__ import annotations

import hashlib
import re

import httpx
import psycopg
import pytest
from cli import in_process as labcal  # labcal ARGS in this process: code, stdout, stderr
from lab_server import accessible, add_user, parses_cleanly, served
from simulated_runs import bench_run

# A run through the drivers, a sync and a server (about 30 s), built once on one worker (loadgroup)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("desk_postgres")]

SERIAL = "ACC-0042"
PASSWORD = "a long passphrase 1"


@pytest.fixture(scope="module")
def lab(tmp_path_factory, postgres_cluster):
    yield from _desk(tmp_path_factory, postgres_cluster)


@pytest.fixture(scope="module")
def second_lab(tmp_path_factory, postgres_cluster):
    """A lab of its own, so that its run's revisions do not depend on what another test approved."""
    yield from _desk(tmp_path_factory, postgres_cluster)


def _desk(tmp_path_factory, postgres_cluster):
    base = tmp_path_factory.mktemp("pg-desk")
    url = postgres_cluster.url(postgres_cluster.create_database())
    patch = pytest.MonkeyPatch()
    (base / "lab.toml").write_text("")
    env = {"LABCAL_DB": url, "LABCAL_JOURNAL": str(base / "bench" / "journal.sqlite"),
           "LABCAL_STATION": "bench-1", "LABCAL_CONFIG": str(base / "lab.toml"), "LABCAL_NOTIFY": ""}
    for name, value in env.items():
        patch.setenv(name, value)
    try:
        (base / "bench").mkdir()
        bench_run(base / "bench" / "run1", url, SERIAL)  # its draft certificate too
        assert labcal("sync")[0] == 0
        assert labcal("instrument", "add", SERIAL, "--model", "TA-300", "--interval", "12m")[0] == 0
        assert labcal("certificate", "keygen", "--out", str(base / "server"))[0] == 0
        assert labcal("certificate", "approvers", "add", "lab server", "--role", "lab server",
                      "--public-key", str(base / "server.pub"))[0] == 0
        code, out, err = labcal("db", "grant-server", "labserver")
        assert code == 0, err
        server_url = out.strip().splitlines()[-1]
        token = add_user(url, "ada", "approver", PASSWORD)
        with served(server_url, "--key", str(base / "server.key")) as served_at:
            yield {"url": served_at, "db": url, "token": token, "run": base / "bench" / "run1",
                   "env": env}
    finally:
        patch.undo()


def _login(url: str) -> httpx.Client:
    client = httpx.Client(base_url=url, timeout=60)
    token = re.search(r'name="csrf" value="([^"]+)"', client.get("/login").text)
    assert token is not None
    signed = client.post("/login", data={"name": "ada", "password": PASSWORD, "csrf": token[1]})
    assert signed.status_code == 303
    return client


def _kept(db: str) -> dict[str, str]:
    """The approved files the lab database keeps, name → SHA-256 of the bytes, read with psycopg."""
    with psycopg.connect(db) as conn:
        rows = conn.execute("SELECT name, content FROM certificate_files").fetchall()
    return {name: hashlib.sha256(bytes(content)).hexdigest() for name, content in rows}


def test_an_approval_on_postgresql_leaves_the_queue_and_its_kept_documents_download(lab, browser):
    client = _login(lab["url"])
    queue = client.get("/queue").text
    assert 'data-run="1"' in queue and _kept(lab["db"]) == {}
    done = client.post("/api/runs/1/approve", headers={"Authorization": f"Bearer {lab['token']}"})
    assert done.status_code == 200, done.text
    kept = _kept(lab["db"])
    assert {"certificate.json", "certificate.dcc.xml", "report.pdf"} <= set(kept)

    assert 'data-run="1"' not in client.get("/queue").text
    page = client.get("/runs/1").text
    assert "Approved by <b>ada</b>" in page and done.json()["approved_utc"][:19].replace("T", " ") in page
    links = set(re.findall(r'href="(/certificates/[^"]+)"', page))
    names = {link: link.rsplit("/", 1)[1] for link in links}
    assert set(names.values()) == {"certificate.json", "certificate.dcc.xml", "report.pdf"}
    for link, name in names.items():
        got = client.get(link)
        assert got.status_code == 200 and hashlib.sha256(got.content).hexdigest() == kept[name], name
    instrument = client.get(f"/instruments/{SERIAL}").text
    assert links <= set(re.findall(r'href="(/certificates/[^"]+)"', instrument))

    shown = browser.new_page()
    try:
        shown.goto(lab["url"] + "/login")
        shown.fill("input[name=name]", "ada")
        shown.fill("input[name=password]", PASSWORD)
        shown.click("button[type=submit]")
        shown.wait_for_url(lab["url"] + "/")
        for path in ("/queue", "/runs/1", f"/instruments/{SERIAL}", "/instruments", "/due"):
            response = shown.goto(lab["url"] + path)
            assert response is not None and response.status == 200, path
            parses_cleanly(response.text(), path)
            accessible(shown, path)
    finally:
        shown.close()


def test_a_new_revision_of_a_server_approved_certificate_waits_on_the_queue_and_is_approved(second_lab,
                                                                                          monkeypatch):
    lab = second_lab
    client = _login(lab["url"])
    bearer = {"Authorization": f"Bearer {lab['token']}"}
    first = client.post("/api/runs/1/approve", headers=bearer)
    assert first.status_code == 200, first.text
    assert 'data-run="1"' not in client.get("/queue").text
    for name, value in lab["env"].items():  # the bench's, as the lab's setup had them
        monkeypatch.setenv(name, value)
    assert labcal("sync")[0] == 0  # the bench receives revision 1 approved
    code, _, err = labcal("report", str(lab["run"]))  # and issues revision 2
    assert code == 0, err
    assert (lab["run"] / "certificate.rev1.json").is_file()
    assert labcal("sync")[0] == 0

    assert 'data-run="1"' in client.get("/queue").text
    second = client.post("/api/runs/1/approve", headers=bearer)
    assert second.status_code == 200, second.text
    with psycopg.connect(lab["db"]) as conn:  # each revision's approved set kept, under its own id
        kept = conn.execute("SELECT certificate_id, count(*) FROM certificate_files GROUP BY certificate_id"
                            ).fetchall()
    assert len(kept) == 2 and all(count >= 3 for _, count in kept)
    assert 'data-run="1"' not in client.get("/queue").text
