"""The lab server against a lab database of real simulated runs: tokens (401), roles (403),
the runs the API lists compared with the journal as sqlite3 reads it, the web login's session
cookie and CSRF checks, and what the users table keeps (hashes only).

`labcal serve` runs in a process of its own on a free port of 127.0.0.1 (tests/lab_server.py); every
request is real HTTP through httpx; the database is the SQLite file the runs journaled into."""

from __future__ import annotations

import hashlib
import io
import json
import re
import sqlite3
import tomllib

import httpx
import pytest
from cli import cli, labcal
from lab_server import add_user, served

from labcal.cli import main

STATIONS = {1: "bench 1", 2: "bench 2 (west)"}  # run id: the LABCAL_STATION it ran under
PASSWORD = {"ada": "ada's long passphrase", "tom": "tom's passphrase 1", "vic": "vic's passphrase 2",
            "dan": "dan's passphrase 3"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """Two complete simulated runs (the four-mount and the one-mount plan) of two stations
    (LABCAL_STATION) in one SQLite lab database, four users (approver, technician, viewer, and one to
    disable), and the server on it."""
    base = tmp_path_factory.mktemp("lab")
    db = str(base / "lab.sqlite")
    with pytest.MonkeyPatch.context() as env:
        env.setenv("LABCAL_STATION", STATIONS[1])
        assert main(["run", "--sim", "--yes", "--no-report", "--seed", "1", "--serial", "ACC-1", "--db", db,
                     "--out", str(base / "four")]) == 0
        env.setenv("LABCAL_STATION", STATIONS[2])
        assert main(["run", "--sim", "--yes", "--no-report", "--seed", "2", "--plan", "one-mount-16",
                     "--operator", "R. Tech", "--db", db, "--out", str(base / "one")]) == 0
    roles = {"ada": "approver", "tom": "technician", "vic": "viewer", "dan": "viewer"}
    tokens = {name: add_user(db, name, role, PASSWORD[name]) for name, role in roles.items()}
    with served(db) as url:
        yield {"db": db, "url": url, "tokens": tokens, "base": base}


def _get(lab, path: str, token: str | None) -> httpx.Response:
    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    return httpx.get(lab["url"] + path, headers=headers, timeout=10)


API = ["/api/runs", "/api/runs/1", "/api/runs/1/stream", "/api/runs/1/residuals.png", "/api/stations"]


@pytest.mark.parametrize("path", API)
def test_the_api_refuses_a_request_without_a_valid_token(lab, path):
    assert _get(lab, path, None).status_code == 401
    assert _get(lab, path, "not-a-token").status_code == 401
    assert _get(lab, path, lab["tokens"]["vic"][:-1]).status_code == 401  # one character short
    basic = httpx.get(lab["url"] + path, headers={"Authorization": f"Basic {lab['tokens']['vic']}"},
                      timeout=10)
    assert basic.status_code == 401
    assert _get(lab, path, None).headers["www-authenticate"] == "Bearer"


def test_approving_needs_a_token_and_the_approver_role(lab):
    url = lab["url"] + "/api/runs/1/approve"
    assert httpx.post(url, timeout=10).status_code == 401
    for name in ("vic", "tom"):
        refused = httpx.post(url, headers={"Authorization": f"Bearer {lab['tokens'][name]}"}, timeout=10)
        assert refused.status_code == 403, refused.text
        assert "only an approver" in refused.json()["detail"]


def test_api_runs_are_the_journals_runs(lab):
    """Every run's id, status, serial and points done against the journal read by sqlite3, its
    station as LABCAL_STATION named it when it ran, and points_total against the plan's TOML read by
    tomllib (replicates × mounts × points) — on a SQLite lab database, which no sync fills in."""
    found = _get(lab, "/api/runs", lab["tokens"]["vic"])
    assert found.status_code == 200
    listed = {r["id"]: r for r in found.json()["runs"]}
    with sqlite3.connect(lab["db"]) as conn:
        rows = conn.execute("SELECT id, status, instrument_serial, plan_text, operator FROM runs").fetchall()
        done = dict(conn.execute("SELECT run_id, count(*) FROM points GROUP BY run_id").fetchall())
    assert sorted(listed) == sorted(r[0] for r in rows) == [1, 2]
    for run_id, status, serial, plan_text, operator in rows:
        plan = tomllib.loads(plan_text)
        total = plan.get("replicates", 1) * len(plan["mounts"]) * len(plan["points"])
        got = listed[run_id]
        assert (got["status"], got["serial"], got["operator"]) == (status, serial, operator)
        assert got["station"] == STATIONS[run_id]
        assert got["simulated"] is True  # `labcal run --sim`: said on every run it concerns
        assert (got["points_done"], got["points_total"]) == (done[run_id], total)
    assert (listed[1]["points_total"], listed[2]["points_total"]) == (64, 16)  # four-mount-64, one-mount-16


def test_two_stations_show_as_two_cards_on_the_lab_page(lab):
    """`/` shows each station that journaled a run, under the name it ran with, with its run's
    "done / total" (the plans' sizes: 64 and 16 points)."""
    with httpx.Client(base_url=lab["url"], timeout=10) as client:
        form = client.get("/login")
        csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)[1]
        client.post("/login", data={"name": "vic", "password": PASSWORD["vic"], "csrf": csrf})
        page = client.get("/")
    assert page.status_code == 200
    cards = re.findall(r'<h2>([^<]+?)(?: <small|</h2>).*?<div class="count"><span>(\d+)</span> / (\d+)</div>',
                       page.text, re.S)
    assert sorted(cards) == [("bench 1", "64", "64"), ("bench 2 (west)", "16", "16")]


def test_a_runs_detail_holds_its_journal_events(lab):
    detail = _get(lab, "/api/runs/2", lab["tokens"]["tom"]).json()
    with sqlite3.connect(lab["db"]) as conn:
        events = conn.execute("SELECT id, kind, message FROM events WHERE run_id = 2 ORDER BY id").fetchall()
        last = conn.execute("SELECT y_deg, u_deg FROM points WHERE run_id = 2 "
                            "ORDER BY seq DESC LIMIT 1").fetchone()
    assert [(e["id"], e["kind"], e["message"]) for e in detail["events"]] == events
    assert detail["next_remount_in_s"] is None  # finished: no remount ahead
    assert detail["mount"] == {"y_deg": last[0], "u_deg": last[1]}
    assert _get(lab, "/api/runs/99", lab["tokens"]["tom"]).status_code == 404


def test_a_finished_runs_residual_plot_is_a_png(lab):
    png = _get(lab, "/api/runs/1/residuals.png", lab["tokens"]["vic"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.content[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_users_table_keeps_no_password_nor_token_in_clear(lab):
    with sqlite3.connect(lab["db"]) as conn:
        rows = {r[0]: r[1:] for r in conn.execute("SELECT name, role, password_hash, token_hash FROM users")}
        everything = "\n".join(str(v) for row in conn.execute("SELECT * FROM users") for v in row)
    for name, token in lab["tokens"].items():
        assert PASSWORD[name] not in everything and token not in everything
        role, password_hash, stored_token = rows[name]
        assert stored_token == hashlib.sha256(token.encode()).hexdigest()  # SHA-256, by hashlib
        assert password_hash.startswith("$argon2id$")  # argon2id's PHC string
    from argon2 import PasswordHasher

    assert PasswordHasher().verify(rows["ada"][1], PASSWORD["ada"])


def test_user_add_prints_the_token_alone_on_its_line_and_refuses_an_empty_password(lab, capsys, monkeypatch):
    def add(name: str, role: str, password: str) -> tuple[int, str, str]:
        monkeypatch.setattr("sys.stdin", io.StringIO(password + "\n"))
        return cli(capsys, "user", "add", name, "--role", role, "--password-stdin", "--db", lab["db"])

    code, stdout, stderr = add("eve", "viewer", "eve's password")
    assert code == 0, stderr
    assert re.fullmatch(r"[A-Za-z0-9_-]{43}\n", stdout)  # 32 bytes, URL-safe base64, alone
    assert _get(lab, "/api/runs", stdout.strip()).status_code == 200
    for code, stdout, stderr in (add("eve", "viewer", "eve's password"), add("fay", "viewer", ""),
                                 add("gus", "boss", "gus's password")):
        assert code == 2 and stdout == ""
        assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr
    listed = json.loads(cli(capsys, "user", "list", "--json", "--db", lab["db"])[1])["users"]
    assert "fay" not in {u["name"] for u in listed} and {"eve", "ada"} <= {u["name"] for u in listed}


def test_a_user_refused_creates_no_lab_database(tmp_path, capsys, monkeypatch):
    """`user add` may create the lab database, but not for a request it refuses."""
    db = tmp_path / "new.sqlite"
    for name, role, password in (("", "viewer", "a password"), ("hal", "boss", "a password"),
                                 ("hal", "viewer", "")):
        monkeypatch.setattr("sys.stdin", io.StringIO(password + "\n"))
        code, _, stderr = cli(capsys, "user", "add", name, "--role", role, "--password-stdin",
                              "--db", str(db))
        assert code == 2 and len(stderr.strip().splitlines()) == 1, stderr
        assert not db.exists(), (name, role, password)


def test_a_disabled_user_is_out(lab, capsys):
    token = lab["tokens"]["dan"]
    assert _get(lab, "/api/runs", token).status_code == 200
    client = _signed_in(lab, "dan")
    assert client.get("/").status_code == 200
    assert cli(capsys, "user", "disable", "dan", "--db", lab["db"])[0] == 0
    assert _get(lab, "/api/runs", token).status_code == 401
    assert client.get("/", follow_redirects=False).status_code == 303  # back to the login form
    assert client.post("/login", data={"name": "dan", "password": PASSWORD["dan"],
                                       "csrf": _csrf(client.get("/login").text)}).status_code == 401


# --- the web login, its cookie and CSRF ------------------------------------------------------------
def _csrf(html: str) -> str:
    found = re.search(r'name="csrf" value="([^"]+)"', html)
    assert found, "no CSRF field in the form"
    return found[1]


def _signed_in(lab, name: str) -> httpx.Client:
    client = httpx.Client(base_url=lab["url"], timeout=15)
    form = client.get("/login")
    signed = client.post("/login", data={"name": name, "password": PASSWORD[name], "csrf": _csrf(form.text)})
    assert signed.status_code == 303, signed.text
    return client


def test_pages_need_a_sign_in(lab):
    for path in ("/", "/runs/1"):
        page = httpx.get(lab["url"] + path, timeout=10)
        assert page.status_code == 303 and page.headers["location"].startswith("/login")
    assert httpx.get(lab["url"] + "/runs/1/stream", timeout=10).status_code == 401


def test_the_session_cookie_is_httponly_strict_and_renewed_at_sign_in(lab):
    """No session before sign-in (the form's CSRF token is a cookie of its own); a new session id at
    every sign-in; a forged one is refused."""
    client = httpx.Client(base_url=lab["url"], timeout=15)
    form = client.get("/login")
    assert "labcal_session" not in client.cookies and "labcal_login" in client.cookies
    signed = client.post("/login", data={"name": "vic", "password": PASSWORD["vic"],
                                         "csrf": _csrf(form.text)})
    cookie = signed.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie.replace("Strict", "strict")
    before = client.cookies["labcal_session"]
    again = client.post("/login", data={"name": "vic", "password": PASSWORD["vic"],
                                        "csrf": _csrf(client.get("/login").text)})
    assert again.status_code == 303 and client.cookies["labcal_session"] != before  # renewed
    assert client.get("/").status_code == 200 and STATIONS[1] in client.get("/").text
    forged = httpx.get(lab["url"] + "/", cookies={"labcal_session": before[:-1] + "0"}, timeout=10)
    assert forged.status_code == 303


@pytest.mark.parametrize("csrf", [None, "", "wrong-token"])
def test_every_form_refuses_a_post_without_its_csrf_token(lab, csrf):
    client = _signed_in(lab, "ada")
    good = _csrf(client.get("/runs/1").text)
    data = {} if csrf is None else {"csrf": csrf}
    assert client.post("/logout", data=data).status_code == 403
    assert client.post("/runs/1/approve", data={**data, "password": PASSWORD["ada"]}).status_code == 403
    assert client.get("/").status_code == 200  # still signed in: nothing happened
    stranger = httpx.Client(base_url=lab["url"], timeout=15)
    stranger.get("/login")
    tried = stranger.post("/login", data={**data, "name": "ada", "password": PASSWORD["ada"]})
    assert tried.status_code == 403
    assert client.post("/logout", data={"csrf": good}).status_code == 303
    assert client.get("/", follow_redirects=False).status_code == 303  # signed out on the server


def test_a_wrong_password_signs_nobody_in(lab):
    client = httpx.Client(base_url=lab["url"], timeout=15)
    csrf = _csrf(client.get("/login").text)
    refused = client.post("/login", data={"name": "ada", "password": "guess", "csrf": csrf})
    assert refused.status_code == 401 and "Wrong name or password" in refused.text
    assert client.get("/", follow_redirects=False).status_code == 303


def test_a_viewer_reads_the_pages_but_may_not_approve(lab):
    client = _signed_in(lab, "vic")
    page = client.get("/runs/1")
    assert page.status_code == 200 and "64</span> / <span id=\"total\">64" in page.text
    assert "Approve the certificate" not in page.text
    refused = client.post("/runs/1/approve", data={"csrf": _csrf(page.text), "password": PASSWORD["vic"]})
    assert refused.status_code == 403
    assert "residuals.png" in page.text and client.get("/runs/1/residuals.png").status_code == 200


def test_the_approver_signs_with_the_password_again(lab):
    client = _signed_in(lab, "ada")
    page = client.get("/runs/1")
    assert "never approved" in page.text and "Approve the certificate" not in page.text  # a dry run
    wrong = client.post("/runs/1/approve", data={"csrf": _csrf(page.text), "password": "not hers"})
    assert wrong.status_code == 401 and "nothing was signed" in wrong.text
    # a simulated run without a certificate: the server has no key and the folder holds no draft
    tried = client.post("/runs/1/approve", data={"csrf": _csrf(page.text), "password": PASSWORD["ada"]})
    assert tried.status_code == 409 and "Not approved" in tried.text


def test_serve_refuses_a_database_behind_its_schema_in_one_line(tmp_path):
    from sqlalchemy import create_engine

    from labcal.store import migrations

    db = str(tmp_path / "lab.sqlite")
    old = create_engine(f"sqlite:///{db}")
    with old.begin() as conn:
        migrations.upgrade(conn, "0006")  # the lab's first revision with users, one behind this labcal
    old.dispose()
    done = labcal("serve", "--port", "0", "--db", db)
    assert done.returncode == 2 and done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1 and "labcal db upgrade" in done.stderr
    missing = labcal("serve", "--port", "0", "--db", str(tmp_path / "none.sqlite"))
    assert missing.returncode == 2 and "no lab database there" in missing.stderr
    assert not (tmp_path / "none.sqlite").exists()  # the server creates nothing


def test_serve_refuses_a_key_it_cannot_sign_with_and_a_port_in_use(lab, tmp_path):
    key = tmp_path / "lab.key"
    key.write_text("not a key")
    key.chmod(0o600)
    for args, why in ((["--key", str(tmp_path / "absent.key")], "no such private key"),
                      (["--key", str(key)], "not an unencrypted PEM private key"),
                      (["--port", lab["url"].rsplit(":", 1)[1]], "cannot listen there"),
                      (["--port", "99999"], "argument --port: 99999 is out of range"),
                      (["--poll", "0"], "argument --poll: 0 is out of range"),
                      (["--host", "no-such-host.invalid"], "no-such-host.invalid:8024: cannot listen there")):
        done = labcal("serve", "--db", lab["db"], *args)
        assert done.returncode == 2 and done.stdout == "", done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and why in done.stderr


def test_user_add_asks_for_the_password_when_none_is_given(lab, capsys):
    """Without --password it is asked for twice (getpass: without echo on a terminal; here, in a process
    of its own with no terminal, from stdin) and refused when empty or when the two differ, adding nobody."""
    def add(name: str, typed: str):
        return labcal("user", "add", name, "--role", "viewer", "--db", lab["db"], typed=typed, timeout=60)

    asked = add("hal", "hal's passphrase\nhal's passphrase\n")
    assert asked.returncode == 0, asked.stderr
    assert re.fullmatch(r"[A-Za-z0-9_-]{43}\n", asked.stdout) and "hal's passphrase" not in asked.stdout
    client = httpx.Client(base_url=lab["url"], timeout=15)
    csrf = _csrf(client.get("/login").text)
    signed = client.post("/login", data={"name": "hal", "password": "hal's passphrase", "csrf": csrf})
    assert signed.status_code == 303
    for name, typed, why in (("ian", "\n", "may not be empty"),
                             ("jo", "one passphrase\ntwo passphrase\n", "differ")):
        refused = add(name, typed)
        assert refused.returncode == 2 and refused.stdout == "" and why in refused.stderr
    shown = cli(capsys, "user", "list", "--json", "--db", lab["db"])[1]
    listed = {u["name"] for u in json.loads(shown)["users"]}
    assert "hal" in listed and not {"ian", "jo"} & listed
