"""An approver registered or revoked at a bench that cannot reach the lab is journaled there, audit
row included; `labcal sync` appends those rows to the lab's audit trail (which the lab server's
/audit page reads) exactly once — synced twice, and synced again after the journal lost its note
of what it had sent — each chained after the lab's newest row, so the trail's chain still holds.

The chain is recomputed here from its published form (SHA-256 of the JSON list of the previous
digest and the row's fields), with hashlib, not by labcal's own verifier.
"""

from __future__ import annotations

import hashlib
import json
import re
import sqlite3
from contextlib import closing
from pathlib import Path

import psycopg
import pytest
from cli import in_process
from services import free_port

from labcal.cli import main

NAME, ROLE = "A. Metrologist", "Technical manager"
CHANGED = "approver changed"


def labcal(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, *args: str, db: str) -> tuple[int, str, str]:
    """A labcal command at bench-3 (in this process), with ``db`` as its lab database."""
    (tmp_path / "lab.toml").touch()
    for name, value in (("LABCAL_DB", db), ("LABCAL_JOURNAL", str(tmp_path / "bench-3" / "journal.sqlite")),
                        ("LABCAL_STATION", "bench-3"), ("LABCAL_CONFIG", str(tmp_path / "lab.toml")),
                        ("LABCAL_NOTIFY", "")):
        monkeypatch.setenv(name, value)
    return in_process(*args)


def lab_trail(url: str) -> list[tuple]:
    with psycopg.connect(url) as conn:
        return conn.execute("SELECT utc, kind, account, actor, client, detail, prev, digest FROM audit "
                            "ORDER BY id").fetchall()


def chain_holds(rows: list[tuple]) -> bool:
    prev = ""
    for utc, kind, account, actor, client, detail, stated_prev, digest in rows:
        fields = [prev, utc, kind, account, actor, client, detail]
        canonical = json.dumps(fields, separators=(",", ":"), ensure_ascii=False).encode()
        expected = hashlib.sha256(canonical).hexdigest()
        if stated_prev != prev or digest != expected:
            return False
        prev = digest
    return True


def test_approver_changes_made_offline_reach_the_labs_audit_trail_once(tmp_path, postgres_url, monkeypatch):
    offline = f"postgresql://labcal@127.0.0.1:{free_port()}/lab"  # nothing listens there
    (tmp_path / "bench-3").mkdir()
    assert labcal(monkeypatch, tmp_path, "db", "upgrade", "--db", postgres_url, db=postgres_url)[0] == 0
    code, _, err = labcal(monkeypatch, tmp_path, "certificate", "keygen", "--out", str(tmp_path / "approver"),
                          db=offline)
    assert code == 0, err
    code, _, err = labcal(monkeypatch, tmp_path, "certificate", "approvers", "add", NAME, "--role", ROLE,
                          "--public-key", str(tmp_path / "approver.pub"), db=offline)
    assert code == 0 and "labcal sync" in err, err  # kept in the journal for labcal sync
    code, _, err = labcal(monkeypatch, tmp_path, "certificate", "approvers", "revoke", NAME, db=offline)
    assert code == 0, err
    journal = tmp_path / "bench-3" / "journal.sqlite"
    with closing(sqlite3.connect(journal)) as db:
        journaled = db.execute("SELECT utc, kind, account, actor, client, detail FROM audit ORDER BY id"
                               ).fetchall()
    assert [(kind, account) for _, kind, account, *_ in journaled] == [(CHANGED, NAME)] * 2
    # the lab's trail already has a row of its own (an administrator's change made there)
    assert main(["user", "add", "ada", "--role", "approver", "--password", "a long passphrase 3", "--db",
                 postgres_url]) == 0
    assert [r[1] for r in lab_trail(postgres_url)] == ["user added"]

    for _ in range(2):
        code, out, err = labcal(monkeypatch, tmp_path, "sync", "--json", db=postgres_url)
        assert code == 0, err
    assert json.loads(out)["sent"]["audit"] == 0  # all went the first time
    with closing(sqlite3.connect(journal)) as db, db:  # the journal forgets what it sent (a kill, a restore)
        for table in ("sync_sent", "sync_cursors", "sync_runs", "sync_targets"):
            db.execute(f"DELETE FROM {table}")
    code, out, err = labcal(monkeypatch, tmp_path, "sync", "--json", db=postgres_url)
    assert code == 0 and json.loads(out)["sent"]["audit"] == 2 and json.loads(out)["new"]["audit"] == 0, err

    trail = lab_trail(postgres_url)
    assert [r[:6] for r in trail[1:]] == journaled  # as journaled, once each, after the lab's own row
    assert chain_holds(trail)

    # the lab server's audit page shows them, and says the chain holds
    from fastapi.testclient import TestClient

    from labcal.app.labdatabase import OpenLab, open_lab
    from labcal.server.app import ServerSettings, create_app

    lab = open_lab(OpenLab(postgres_url))
    try:
        with TestClient(create_app(ServerSettings(lab))) as client:
            form = client.get("/login")
            csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)[1]
            client.post("/login", data={"name": "ada", "password": "a long passphrase 3", "csrf": csrf})
            page = client.get("/audit")
    finally:
        lab.close()
    assert page.status_code == 200 and "The chain of digests holds" in page.text
    for detail in (row[5] for row in journaled):
        assert page.text.count(detail) == 1, detail


def test_an_approver_registered_with_the_lab_reachable_is_audited_there_once(tmp_path, postgres_url,
                                                                              monkeypatch):
    (tmp_path / "bench-3").mkdir()
    code, _, err = labcal(monkeypatch, tmp_path, "certificate", "keygen", "--out", str(tmp_path / "approver"),
                          db=postgres_url)
    assert code == 0, err
    code, _, err = labcal(monkeypatch, tmp_path, "certificate", "approvers", "add", NAME, "--role", ROLE,
                          "--public-key", str(tmp_path / "approver.pub"), db=postgres_url)
    assert code == 0 and err == "", err  # sent at once
    assert [(r[1], r[2]) for r in lab_trail(postgres_url)] == [(CHANGED, NAME)]
    code, out, err = labcal(monkeypatch, tmp_path, "sync", db=postgres_url)
    assert code == 0 and "nothing to send" in out, err
    assert len(lab_trail(postgres_url)) == 1 and chain_holds(lab_trail(postgres_url))
