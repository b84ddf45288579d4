"""A bench's role writes only its own station's draft certificates: against a real PostgreSQL server
(tests/services.py), PostgreSQL itself refuses a bench's role an approved certificate (even of its
own run: replacing, re-storing or deleting it), a certificate of another station's run, and the
approved files; its own drafts it appends and re-issues, and `labcal sync` passes over what the lab
refuses it in one line while the rest of its journal reaches the lab.

Which certificate is approved and which run it states is written here by hand into the documents
(the "approval" member, data.journal.run_uuid), as plain SQL and JSON, not by labcal.
"""

from __future__ import annotations

import json
import sqlite3
import uuid
from contextlib import closing

import psycopg
import pytest
from cli import here_at_bench as here

APPROVAL = {"by": "A. Metrologist", "role": "Technical manager", "approved_utc": "2026-11-27T10:00:00+00:00"}


def refused(url: str, sql: str, args: tuple = ()) -> str:
    """PostgreSQL's refusal of ``sql`` as the role of ``url`` (fails the test if it is allowed)."""
    with psycopg.connect(url) as conn, pytest.raises(psycopg.errors.InsufficientPrivilege) as caught:
        conn.execute(sql, args)
    return str(caught.value).splitlines()[0]


def document(draft: str, certificate_id: str, run_uuid: str | None = None, approved: bool = False) -> str:
    """A copy of ``draft`` under another id, stating another run (None: no journal chain, as a run
    journaled before digests), approved or not."""
    doc = json.loads(draft)
    doc["certificate_id"] = certificate_id
    if run_uuid is None:
        doc["data"].pop("journal")
    else:
        doc["data"]["journal"]["run_uuid"] = run_uuid
    if approved:
        doc["approval"] = APPROVAL
    return json.dumps(doc)


INSERT = ("INSERT INTO certificates (certificate_id, serial, calibrated_utc, issued_utc, sha256, document) "
          "VALUES (%s, 'ACC-0042', '2026-11-27', '2026-11-27', %s, %s)")


@pytest.fixture(scope="module")
def lab(tmp_path_factory, postgres_cluster):
    """A lab database set up by its administrator; bench-1's role has run a simulated calibration
    whose draft certificate reached the lab; the administrator has stored an approved copy of it
    (``approved``) and a run of bench-2. (admin URL, bench-1's URL, bench-1's draft, bench-2's run uuid,
    the folder.)"""
    tmp_path = tmp_path_factory.mktemp("certificate-roles")
    admin = postgres_cluster.url(postgres_cluster.create_database())
    with pytest.MonkeyPatch.context() as env:
        assert here(env, tmp_path, "db", "upgrade", "--db", admin, db=admin)[0] == 0
        code, out, err = here(env, tmp_path, "db", "grant-station", "bench-1", "--db", admin, db=admin)
        assert code == 0, err
        bench = out.strip().splitlines()[-1]
        code, _, err = here(env, tmp_path, "run", "--sim", "--yes", "--plan", "one-mount-16", "--serial",
                            "ACC-0042", "--out", str(tmp_path / "bench-1" / "run"), db=bench)
    assert code == 0, err
    other = str(uuid.uuid4())
    with psycopg.connect(admin) as conn:
        run_uuid, = conn.execute("SELECT uuid FROM runs WHERE station = 'bench-1'").fetchone()
        drafts = conn.execute("SELECT document FROM certificates").fetchall()
        assert len(drafts) == 1 and json.loads(drafts[0][0])["data"]["journal"]["run_uuid"] == run_uuid
        draft = drafts[0][0]
        conn.execute(INSERT, ("approved", "a" * 64, document(draft, "approved", run_uuid, approved=True)))
        conn.execute("INSERT INTO runs (id, run_dir, plan_name, plan_text, plan_hash, station_text, "
                     "station_hash, software_version, settings, metadata, started_utc, status, uuid, "
                     "station) VALUES (1000, 'x', 'p', 'p', 'h', 's', 'h', 'v', '{}', '{}', '2026-11-27', "
                     "'complete', %s, 'bench-2')", (other,))
    return admin, bench, draft, run_uuid, other, tmp_path


def test_a_bench_role_cannot_replace_re_store_or_delete_an_approved_certificate_of_its_own_run(lab):
    admin, bench, draft, run_uuid, _, _ = lab
    with psycopg.connect(admin) as conn:
        before = conn.execute("SELECT sha256, document FROM certificates WHERE certificate_id = 'approved'"
                              ).fetchone()
    with psycopg.connect(bench) as conn:  # row-level security hides the row from its UPDATE: nothing changes
        changed = conn.execute("UPDATE certificates SET document = %s, sha256 = %s "
                               "WHERE certificate_id = 'approved'",
                               (document(draft, "approved", run_uuid), "b" * 64)).rowcount
    assert changed == 0
    # re-stored over it, as a sync sends a certificate: refused outright
    assert "row-level security" in refused(
        bench, INSERT + " ON CONFLICT (certificate_id) DO UPDATE SET document = excluded.document, "
                        "sha256 = excluded.sha256",
        ("approved", "b" * 64, document(draft, "approved", run_uuid)))
    assert "permission denied for table certificates" in refused(
        bench, "DELETE FROM certificates WHERE certificate_id = 'approved'")
    assert "permission denied for table certificate_files" in refused(
        bench, "INSERT INTO certificate_files (certificate_id, run_uuid, name, sha256, content, stored_utc) "
               "VALUES ('approved', %s, 'certificate.json', 'x', 'x', '2026-11-27')", (run_uuid,))
    assert "permission denied for table certificate_files" in refused(bench, "DELETE FROM certificate_files")
    with psycopg.connect(admin) as conn:
        assert conn.execute("SELECT sha256, document FROM certificates WHERE certificate_id = 'approved'"
                            ).fetchone() == before


def test_a_bench_role_appends_and_re_issues_only_its_own_stations_drafts(lab):
    admin, bench, draft, run_uuid, other, _ = lab
    for forged in (document(draft, "for-bench-2", other),  # another station's run
                   document(draft, "approved-at-the-bench", run_uuid, approved=True),  # its own, approved
                   document(draft, "no-run", None),  # a draft that names no run
                   document(draft, "no-such-run", str(uuid.uuid4()))):  # a run the lab does not hold
        assert "row-level security" in refused(bench, INSERT, (json.loads(forged)["certificate_id"], "c" * 64,
                                                               forged))
    # its own station's draft it appends, and re-issues under its id; approving it is refused
    with psycopg.connect(bench) as conn:
        conn.execute(INSERT, ("own-draft", "d" * 64, document(draft, "own-draft", run_uuid)))
        assert conn.execute("UPDATE certificates SET sha256 = %s WHERE certificate_id = 'own-draft'",
                            ("e" * 64,)).rowcount == 1
    assert "row-level security" in refused(
        bench, "UPDATE certificates SET document = %s WHERE certificate_id = 'own-draft'",
        (document(draft, "own-draft", run_uuid, True),))
    with psycopg.connect(admin) as conn:
        own = conn.execute("SELECT sha256 FROM certificates WHERE certificate_id = 'own-draft'").fetchone()
        assert own == ("e" * 64,)
        held = {r[0] for r in conn.execute("SELECT certificate_id FROM certificates")}
    # (the module's lab is shared: another test's syncs may have sent drafts of their own meanwhile)
    assert {json.loads(draft)["certificate_id"], "approved", "own-draft"} <= held
    assert not held & {"for-bench-2", "approved-at-the-bench", "no-run", "no-such-run"}


def test_sync_passes_over_an_approved_certificate_in_one_line_and_sends_the_rest(lab, monkeypatch, capsys):
    """A bench's journal holding a certificate approved there (its role may not store it in the lab)
    and a new draft of its own run: `labcal sync` stores the draft, says in one line what the lab
    refused, ends, and offers it again next time (it stays in the journal)."""
    admin, bench, draft, run_uuid, _, tmp_path = lab
    journal = tmp_path / "bench-1" / "journal.sqlite"
    with closing(sqlite3.connect(journal)) as db, db:
        db.execute("INSERT INTO certificates (certificate_id, serial, calibrated_utc, issued_utc, sha256, "
                   "document) VALUES ('approved-here', 'ACC-0042', '2026-11-27', '2026-11-27', ?, ?)",
                   ("f" * 64, document(draft, "approved-here", run_uuid, approved=True)))
        db.execute("INSERT INTO certificates (certificate_id, serial, calibrated_utc, issued_utc, sha256, "
                   "document) VALUES ('second-draft', 'ACC-0042', '2026-11-27', '2026-11-27', ?, ?)",
                   ("0" * 64, document(draft, "second-draft", run_uuid)))
    for _ in range(2):
        code, out, err = here(monkeypatch, tmp_path, "sync", "--json", db=bench, capture=capsys)
        assert code == 0, err
        said = json.loads(out)
        assert said["refused"] == {"certificates": 1}
    assert said["sent"]["certificates"] == 0  # the draft went the first time
    code, out, _ = here(monkeypatch, tmp_path, "sync", db=bench, capture=capsys)
    said = " ".join(out.split())  # the console wraps its lines
    assert code == 0 and said.count("refused") == 1, out
    assert "refused this bench's role 1 certificates (new row violates row-level security" in said
    with psycopg.connect(admin) as conn:
        held = {r[0] for r in conn.execute("SELECT certificate_id FROM certificates")}
    assert "second-draft" in held and "approved-here" not in held
