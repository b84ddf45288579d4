"""Secrets and the credential lifecycle of the lab server's users, as the ASVS review asked: no
password on a command line or a page, the lab database owner-only, a password policy (a length
floor, a list of common passwords), `labcal user passwd`, `token` (rotation) and expiry, an audit
trail for approvers; and user values (a serial with Rich markup) printed literally, commands
shell-quoted. `labcal serve` runs in a process of its own, over HTTP; the other commands run in this
process, except where the point is what a process of its own prints or does without a terminal."""

from __future__ import annotations

import io
import re
import shlex
import sqlite3
import stat
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import pytest
from cli import cli, in_process, labcal
from lab_server import add_user, served

PASSWORD = {"ada": "ada's long passphrase", "vic": "vic's passphrase", "tom": "tom's passphrase"}
SERIAL = "ACC[/x] $HOME"  # Rich markup and a shell expansion in one serial


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Iterator[dict]:
    """A lab database made by `labcal run` (a simulated run issuing its certificate, of an instrument
    whose serial is `SERIAL`; its exit code, stdout and stderr) and three users."""
    base = tmp_path_factory.mktemp("cred")
    db = str(base / "lab.sqlite")
    ran = in_process("run", "--sim", "--yes", "--plan", "one-mount-16", "--serial", SERIAL,
                     "--db", db, "--out", str(base / "run"))
    tokens = {name: add_user(db, name, role, PASSWORD[name])
              for name, role in (("ada", "approver"), ("vic", "viewer"), ("tom", "technician"))}
    with served(db) as url:
        yield {"db": db, "url": url, "tokens": tokens, "base": base, "ran": ran}


def _csrf(html: str) -> str:
    return re.search(r'name="csrf" value="([^"]+)"', html)[1]


def _signed_in(url: str, name: str, password: str) -> httpx.Client:
    client = httpx.Client(base_url=url, timeout=15)
    signed = client.post("/login", data={"name": name, "password": password,
                                         "csrf": _csrf(client.get("/login").text)})
    assert signed.status_code == 303, signed.text
    return client


def test_a_serial_with_markup_is_printed_as_it_is_and_the_history_command_is_shell_quoted(lab):
    """`ACC[/x]` crashed `labcal run` after the run (Rich read it as a closing tag); the hint
    `labcal history SERIAL` is printed so that the shell gives the serial back unchanged."""
    code, stdout, stderr = lab["ran"]
    assert code == 0 and "Traceback" not in stderr, stderr[-800:]
    printed = " ".join(stdout.split())  # the console wraps long lines
    hint = re.search(r"\((labcal history .*?)\)$", printed, re.M)
    assert hint, printed[-400:]
    assert shlex.split(hint[1]) == ["labcal", "history", SERIAL]


def test_user_add_without_a_terminal_nor_a_password_says_so_in_one_line(tmp_path):
    done = labcal("user", "add", "hal", "--role", "viewer", "--db", str(tmp_path / "lab.sqlite"), typed="")
    assert done.returncode == 2 and done.stdout == "" and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "--password-stdin" in done.stderr


@pytest.mark.parametrize(("role", "password", "why"), [
    ("approver", "eleven char", "at least 12 characters"),  # every account: 12 (ASVS V2.1.1)
    ("viewer", "eleven char", "at least 12 characters"),
    ("approver", "password1234", "most common"),  # in the shipped list (zxcvbn's, from Xato's corpus)
    ("viewer", "123QWEASDZXC", "most common"),  # compared without case
    ("viewer", "hal-the-user", None),
])
def test_the_password_policy_holds_at_user_add(tmp_path, capsys, monkeypatch, role, password, why):
    name = "hal-the-user" if why is None else "hal"
    monkeypatch.setattr("sys.stdin", io.StringIO(password + "\n"))
    code, _, stderr = cli(capsys, "user", "add", name, "--role", role, "--password-stdin", "--db",
                          str(tmp_path / "lab.sqlite"))
    if why is None:  # the name as the password is refused too
        assert code == 2 and "most common" in stderr
        return
    assert code == 2 and why in stderr and len(stderr.strip().splitlines()) == 1


def test_a_password_on_the_command_line_still_works_with_a_warning(tmp_path, capsys):
    code, _, stderr = cli(capsys, "user", "add", "hal", "--role", "viewer", "--password", "hal's passphrase",
                          "--db", str(tmp_path / "lab.sqlite"))
    assert code == 0 and "visible to every account" in stderr


def test_the_lab_database_is_created_readable_by_its_owner_only(tmp_path, capsys, monkeypatch):
    db = tmp_path / "new" / "lab.sqlite"
    monkeypatch.setattr("sys.stdin", io.StringIO("hal's password\n"))
    assert cli(capsys, "user", "add", "hal", "--role", "viewer", "--password-stdin", "--db", str(db))[0] == 0
    for path in [db, *db.parent.glob("lab.sqlite-*")]:
        assert stat.S_IMODE(path.stat().st_mode) & 0o077 == 0, (path, oct(path.stat().st_mode))


def test_a_new_password_replaces_the_old_one_and_a_new_token_the_old_one(lab, capsys, monkeypatch):
    db, url = lab["db"], lab["url"]

    def passwd(typed: str) -> tuple[int, str, str]:
        monkeypatch.setattr("sys.stdin", io.StringIO(typed))
        return cli(capsys, "user", "passwd", "eve", "--password-stdin", "--db", db)

    add_user(db, "eve", "viewer", "eve's first passphrase")
    code, _, stderr = passwd("eve's second one\n")
    assert code == 0, stderr
    refused = httpx.Client(base_url=url, timeout=15)
    old = refused.post("/login", data={"name": "eve", "password": "eve's first passphrase",
                                       "csrf": _csrf(refused.get("/login").text)})
    assert old.status_code == 401
    _signed_in(url, "eve", "eve's second one").close()
    code, _, stderr = passwd("short\n")
    assert code == 2 and "unchanged" in stderr

    code, stdout, _ = cli(capsys, "user", "token", "tom", "--db", db)
    assert code == 0 and re.fullmatch(r"[A-Za-z0-9_-]{43}\n", stdout)
    new = stdout.strip()
    api = url + "/api/runs"
    assert httpx.get(api, headers={"Authorization": f"Bearer {lab['tokens']['tom']}"}, timeout=10
                     ).status_code == 401
    assert httpx.get(api, headers={"Authorization": f"Bearer {new}"}, timeout=10).status_code == 200
    lab["tokens"]["tom"] = new


def test_a_token_expires_a_year_after_it_was_issued(lab):
    db, url = lab["db"], lab["url"]
    token = add_user(db, "old", "viewer", "old's passphrase")
    headers = {"Authorization": f"Bearer {token}"}
    assert httpx.get(url + "/api/runs", headers=headers, timeout=10).status_code == 200
    issued = (datetime.now(UTC) - timedelta(days=366)).isoformat(timespec="seconds")
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE users SET token_utc = ? WHERE name = 'old'", (issued,))
    assert httpx.get(url + "/api/runs", headers=headers, timeout=10).status_code == 401


def test_viewers_and_anonymous_visitors_are_not_told_where_anything_is(lab):
    """The footer named the lab database (a PostgreSQL URL with its password, on the sign-in page
    too); the API gave viewers the runs' folders."""
    url, db = lab["url"], lab["db"]
    folder = str(Path(db).parent)
    assert folder not in httpx.get(url + "/login", timeout=10).text
    viewer = _signed_in(url, "vic", PASSWORD["vic"])
    assert folder not in viewer.get("/").text and folder not in viewer.get("/runs/1").text
    runs = httpx.get(url + "/api/runs", headers={"Authorization": f"Bearer {lab['tokens']['vic']}"},
                     timeout=10)
    assert folder not in runs.text and "run_dir" not in runs.text
    staff = httpx.get(url + "/api/runs/1", headers={"Authorization": f"Bearer {lab['tokens']['ada']}"},
                      timeout=10)
    assert staff.json()["run_dir"]  # the lab's staff still see where a run's folder is


def test_a_database_password_is_never_printed(tmp_path):
    """Neither the password of the URL's user part nor a ``?password=`` parameter reaches a message."""
    url = "postgresql://lab:s3cret-one@127.0.0.1:1/lab?password=s3cret-two&sslpassword=s3cret-three"
    done = labcal("serve", "--port", "0", "--db", url)
    assert done.returncode == 2 and "s3cret" not in done.stderr + done.stdout, done.stderr
    assert "127.0.0.1:1" in done.stderr  # the rest of the location is still said
    assert "visible to every account" in done.stderr.splitlines()[0]  # and the command line is warned of


def test_the_audit_trail_page_is_for_approvers_and_its_chain_is_checked(lab, capsys):
    url, db = lab["url"], lab["db"]
    viewer = _signed_in(url, "vic", PASSWORD["vic"])
    assert viewer.get("/audit").status_code == 403
    approver = _signed_in(url, "ada", PASSWORD["ada"])
    page = approver.get("/audit")
    assert page.status_code == 200 and "The chain of digests holds" in page.text
    assert "signed in" in page.text and "user added" in page.text and "refused" in page.text
    with sqlite3.connect(db) as conn:  # someone edits a row in the file
        conn.execute("UPDATE audit SET account = 'nobody' WHERE id = 2")
    altered = approver.get("/audit")
    assert "row 2 does not follow" in altered.text
    code, _, stderr = cli(capsys, "user", "audit", "--db", db)
    assert code == 2 and "row 2 does not follow" in stderr


def test_changes_to_the_register_of_approvers_are_in_the_audit_trail(tmp_path, capsys):
    db = str(tmp_path / "lab.sqlite")
    add_user(db, "ada", "approver", PASSWORD["ada"])
    assert cli(capsys, "certificate", "keygen", "--out", str(tmp_path / "ada"))[0] == 0
    code, _, stderr = cli(capsys, "certificate", "approvers", "add", "ada", "--role", "Technical manager",
                          "--public-key", str(tmp_path / "ada.pub"), "--db", db)
    assert code == 0, stderr
    assert cli(capsys, "certificate", "approvers", "revoke", "ada", "--db", db)[0] == 0
    with sqlite3.connect(db) as conn:
        rows = conn.execute("SELECT account, detail FROM audit WHERE kind = 'approver changed' ORDER BY id"
                            ).fetchall()
    assert [r[0] for r in rows] == ["ada", "ada"]
    assert "Technical manager" in rows[0][1] and "revoked" in rows[1][1]
