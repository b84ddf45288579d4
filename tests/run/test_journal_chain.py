"""The journal is tamper-evident: every point and event of a run carries a SHA-256 digest chained
to the run's previous record, the certificate states the chain's head and its approval signs it,
and `certificate verify` and `certificate approve` recompute the chain and name the first record
that differs — edited with sqlite3 directly, or as PostgreSQL's superuser in the lab database.

The chain's form is re-derived here from its written definition (docs/design/journal-integrity.md)
with hashlib and json, not with labcal's own functions; the records are read with plain sqlite3.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import stat
from contextlib import closing
from pathlib import Path

import httpx
import psycopg
import pytest
from lab_server import add_user, served
from simulated_runs import bench_run

from labcal.app.run_documents import write_run_outputs
from labcal.cli import main

pytestmark = pytest.mark.long(seconds=33)  # runs approved on SQLite and PostgreSQL: handed out first

SERIAL = "ACC-0042"
APPROVER = ["--by", "A. Metrologist", "--role", "Technical manager"]


@pytest.fixture(scope="module")
def issued(tmp_path_factory) -> Path:
    """A run on a bench (a dry run is never approved), its draft certificate, and a key pair
    registered to the approver, in one folder copied by each test."""
    base = tmp_path_factory.mktemp("chain")
    bench_run(base / "run", base / "lab.sqlite", SERIAL, report=False)  # its documents written just below
    write_run_outputs(base / "run", db=base / "lab.sqlite")
    assert main(["certificate", "keygen", "--out", str(base / "approver")]) == 0
    assert main(["certificate", "approvers", "add", "A. Metrologist", "--role", "Technical manager",
                 "--public-key", str(base / "approver.pub"), "--db", str(base / "lab.sqlite")]) == 0
    return base


def copy_of(issued: Path, tmp_path: Path) -> Path:
    """The issued lab copied, its run folder naming the copy's journal."""
    base = tmp_path / "lab"
    shutil.copytree(issued, base)
    info = json.loads((base / "run" / "run.json").read_text())
    (base / "run" / "run.json").write_text(json.dumps({**info, "journal": str(base / "lab.sqlite")}))
    return base


def approve(base: Path, *extra: str) -> list[str]:
    return ["certificate", "approve", str(base / "run"), *APPROVER, "--key", str(base / "approver.key"),
            "--db", str(base / "lab.sqlite"), *extra]


def verify(base: Path, *extra: str) -> list[str]:
    return ["certificate", "verify", str(base / "run" / "certificate.json"), "--db", str(base / "lab.sqlite"),
            *extra]


def one_line(capsys, args: list[str]) -> str:
    assert main(args) == 2
    captured = capsys.readouterr()
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    return " ".join(captured.err.split())


def run_id(base: Path) -> int:
    return json.loads((base / "run" / "run.json").read_text())["run_id"]


def edit(base: Path, sql: str, *args: object) -> None:
    with closing(sqlite3.connect(base / "lab.sqlite")) as db:
        assert db.execute(sql, args).rowcount == 1
        db.commit()


# --- the form, re-derived from its definition ------------------------------------------------------
POINT_FLOATS = ("y_deg", "u_deg", "pitch_deg", "roll_deg", "pitch_read", "roll_read", "t_start", "t_end",
                "vx", "vy", "vz", "sd_vx", "sd_vy", "sd_vz", "temp_c", "settle_s")
POINT_INTS = ("seq", "replicate", "attempt", "n_samples")
POINT_TEXTS = ("status", "settle_verdict", "utc")


def by_hand(run_uuid: str, kind: str, link: int, previous: str, fields: dict) -> str:
    doc = {"form": "labcal.journal-chain/1", "run": run_uuid, "record": kind, "link": link,
           "previous": previous, "fields": fields}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def test_the_manifest_and_the_first_point_carry_the_digests_the_written_form_gives(issued):
    with closing(sqlite3.connect(issued / "lab.sqlite")) as db:
        db.row_factory = sqlite3.Row
        run = db.execute("SELECT * FROM runs WHERE id=?", (run_id(issued),)).fetchone()
        sha = lambda text: hashlib.sha256(text.encode("utf-8")).hexdigest()  # noqa: E731
        manifest = {"uuid": run["uuid"], "plan_name": run["plan_name"], "plan_text": sha(run["plan_text"]),
                    "station_text": sha(run["station_text"]), "software_version": run["software_version"],
                    "instrument_serial": run["instrument_serial"], "device_id": run["device_id"],
                    "operator": run["operator"], "settings": run["settings"], "metadata": run["metadata"],
                    "started_utc": run["started_utc"], "station": run["station"]}
        assert run["digest"] == by_hand(run["uuid"], "run", 0, "", manifest)

        first = db.execute("SELECT * FROM points WHERE run_id=? ORDER BY link LIMIT 1",
                           (run["id"],)).fetchone()
        events_before = db.execute("SELECT * FROM events WHERE run_id=? AND link < ? ORDER BY link",
                                   (run["id"], first["link"])).fetchall()
        previous, link = run["digest"], 0
        for event in events_before:  # the events of the start (checklist, prompts) come first
            link += 1
            fields = {"utc": event["utc"], "kind": event["kind"], "message": event["message"],
                      "data": event["data"],
                      "station_time": None if event["station_time"] is None else float(event["station_time"])}
            assert event["link"] == link and event["digest"] == by_hand(run["uuid"], "event", link, previous,
                                                                        fields)
            previous = event["digest"]
        fields = {**{k: None if first[k] is None else float(first[k]) for k in POINT_FLOATS},
                  **{k: int(first[k]) for k in POINT_INTS}, **{k: first[k] for k in POINT_TEXTS},
                  "samples": hashlib.sha256(first["samples"]).hexdigest()}
        assert first["link"] == link + 1
        assert first["digest"] == by_hand(run["uuid"], "point", link + 1, previous, fields)
        links = sorted(r[0] for r in db.execute("SELECT link FROM points WHERE run_id=:r UNION ALL "
                                                "SELECT link FROM events WHERE run_id=:r", {"r": run["id"]}))
        assert links == list(range(1, len(links) + 1))  # every record of the run, in one chain


# --- verify and approve -------------------------------------------------------------------------------
def test_an_untouched_run_is_approved_and_its_certificate_verifies_with_the_chain_it_states(issued, tmp_path,
                                                                                            capsys):
    base = copy_of(issued, tmp_path)
    assert main(approve(base)) == 0
    capsys.readouterr()
    doc = json.loads((base / "run" / "certificate.json").read_text())
    with closing(sqlite3.connect(base / "lab.sqlite")) as db:
        uuid = db.execute("SELECT uuid FROM runs WHERE id=?", (run_id(base),)).fetchone()[0]
        records = db.execute("SELECT (SELECT count(*) FROM points WHERE run_id=:r) + (SELECT count(*)"
                             " FROM events WHERE run_id=:r)", {"r": run_id(base)}).fetchone()[0]
        last = db.execute("SELECT digest FROM (SELECT link, digest FROM points WHERE run_id=:r UNION ALL"
                          " SELECT link, digest FROM events WHERE run_id=:r) WHERE link=:n",
                          {"r": run_id(base), "n": doc["data"]["journal"]["records"]}).fetchone()[0]
    stated = doc["data"]["journal"]
    assert stated["run_uuid"] == uuid and stated["head"] == last and 0 < stated["records"] <= records
    assert main(verify(base, "--json")) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["valid"] and "holds up to the signed head" in result["journal"]


def test_a_point_edited_with_sqlite3_is_named_by_verify_and_approve_refuses_it(issued, tmp_path, capsys):
    approved = copy_of(issued, tmp_path / "approved")
    assert main(approve(approved)) == 0
    capsys.readouterr()
    edit(approved, "UPDATE points SET vx = vx + 0.0005 WHERE run_id=? AND seq=5", run_id(approved))
    said = one_line(capsys, verify(approved))
    assert f"point 5 of run {run_id(approved)} differs from the journal's chain: its digest" in said

    draft = copy_of(issued, tmp_path / "draft")
    edit(draft, "UPDATE points SET vx = vx + 0.0005 WHERE run_id=? AND seq=5", run_id(draft))
    said = one_line(capsys, approve(draft))
    assert "not approved" in said
    assert f"point 5 of run {run_id(draft)} differs from the journal's chain" in said
    # issued again from the edited journal: still refused, the edit still named
    assert main(["report", str(draft / "run"), "--db", str(draft / "lab.sqlite")]) == 0
    capsys.readouterr()
    said = one_line(capsys, approve(draft))
    assert f"point 5 of run {run_id(draft)} differs from the journal's chain" in said
    assert json.loads((draft / "run" / "certificate.json").read_text()).get("approval") is None


def test_an_event_deleted_from_the_journal_is_named_as_missing(issued, tmp_path, capsys):
    base = copy_of(issued, tmp_path)
    assert main(approve(base)) == 0
    capsys.readouterr()
    edit(base, "DELETE FROM events WHERE run_id=? AND link=3", run_id(base))
    said = one_line(capsys, verify(base))
    assert f"record 3 of run {run_id(base)}'s chain is missing" in said


def test_every_digest_recomputed_after_an_edit_still_fails_against_the_signed_head(issued, tmp_path, capsys):
    """A forger who recomputes the whole chain after editing a point: each record holds, but the chain
    no longer ends in the head the approval signed."""
    from labcal.store import chain  # the forger's tool: labcal's own writer of digests

    base = copy_of(issued, tmp_path)
    assert main(approve(base)) == 0
    capsys.readouterr()
    edit(base, "UPDATE points SET vx = vx + 0.0005 WHERE run_id=? AND seq=5", run_id(base))
    with closing(sqlite3.connect(base / "lab.sqlite")) as db:
        check = chain.check_sqlite(db, run_id(base))
        while check.problem is not None:  # rewrite the named record's digest, then the next, …
            rows = db.execute("SELECT 'point', link, rowid FROM points WHERE run_id=:r UNION ALL SELECT"
                              " 'event', link, id FROM events WHERE run_id=:r ORDER BY 2",
                              {"r": run_id(base)}).fetchall()
            uuid, previous = db.execute("SELECT uuid, digest FROM runs WHERE id=?",
                                        (run_id(base),)).fetchone()
            for kind, link, key in rows:
                table, columns, where = (("points", chain.POINT_COLUMNS, "rowid") if kind == "point"
                                         else ("events", chain.EVENT_COLUMNS, "id"))
                row = db.execute(f"SELECT {', '.join(columns)} FROM {table} WHERE {where}=?",
                                 (key,)).fetchone()
                values = dict(zip(columns, row, strict=True))
                previous = chain.digest(kind, uuid, link, previous, values)
                db.execute(f"UPDATE {table} SET digest=? WHERE {where}=?", (previous, key))
            db.commit()
            check = chain.check_sqlite(db, run_id(base))
    said = one_line(capsys, verify(base))
    assert "not the head" in said and "the journal was changed after it was issued" in said


def test_a_run_journaled_before_digests_is_said_to_be_so_and_approved_only_when_told(issued, tmp_path,
                                                                                      capsys):
    base = copy_of(issued, tmp_path)
    with closing(sqlite3.connect(base / "lab.sqlite")) as db:  # as a journal of the labcal before the chain
        db.execute("UPDATE runs SET digest=NULL")
        db.execute("UPDATE points SET link=NULL, digest=NULL")
        db.execute("UPDATE events SET link=NULL, digest=NULL")
        db.commit()
    assert main(["report", str(base / "run"), "--db", str(base / "lab.sqlite")]) == 0
    capsys.readouterr()
    assert "journal" not in json.loads((base / "run" / "certificate.json").read_text())["data"]
    said = one_line(capsys, approve(base))
    assert "journaled before digests; not tamper-evident" in said and "--unchained" in said
    assert main(approve(base, "--unchained")) == 0
    capsys.readouterr()
    assert main(verify(base)) == 0
    said = " ".join(capsys.readouterr().out.split())
    assert "its run was journaled before digests; not tamper-evident" in said


def test_digests_stripped_after_approval_do_not_pass_for_a_run_journaled_before_them(issued, tmp_path,
                                                                                     capsys):
    base = copy_of(issued, tmp_path)
    assert main(approve(base)) == 0
    capsys.readouterr()
    edit(base, "UPDATE runs SET digest=NULL WHERE id=?", run_id(base))
    said = one_line(capsys, verify(base))
    assert "journaled before digests" in said and "yet the certificate states a chain" in said


# --- the lab database on PostgreSQL --------------------------------------------------------------------
def test_a_point_edited_by_postgresqls_superuser_is_named_by_verify_and_approve_refuses(
        issued, tmp_path, postgres_url, monkeypatch, capsys):
    from labcal.config.lab import ServerDatabase
    from labcal.store.sync import Sender

    base = copy_of(issued, tmp_path)
    journal = base / "lab.sqlite"
    monkeypatch.setenv("LABCAL_JOURNAL", str(journal))  # the bench's journal; the lab is the server
    (tmp_path / "lab.toml").write_text("")
    monkeypatch.setenv("LABCAL_CONFIG", str(tmp_path / "lab.toml"))
    monkeypatch.setenv("LABCAL_STATION", "bench-1")
    sender = Sender(journal, ServerDatabase(postgres_url, "test"))
    try:
        sender.push()
    finally:
        sender.close()
    with psycopg.connect(postgres_url) as conn:  # the digests travelled unchanged
        server = conn.execute("SELECT p.seq, p.link, p.digest FROM points p JOIN runs r ON r.id = p.run_id "
                              "ORDER BY p.seq").fetchall()
        lab_run = conn.execute("SELECT id FROM runs").fetchone()[0]
    with closing(sqlite3.connect(journal)) as db:
        assert server == db.execute("SELECT seq, link, digest FROM points ORDER BY seq").fetchall()

    draft = base / "draft"
    shutil.copytree(base / "run", draft)
    assert main(approve(base)[:-2] + ["--db", postgres_url]) == 0
    capsys.readouterr()
    assert main(["certificate", "verify", str(base / "run" / "certificate.json"), "--db", postgres_url]) == 0
    assert "of the lab's journal holds up to the signed head" in " ".join(capsys.readouterr().out.split())

    with psycopg.connect(postgres_url) as conn:  # the test cluster's user is its superuser
        edited = conn.execute("UPDATE points SET vx = vx + 0.0005 WHERE run_id=%s AND seq=5", (lab_run,))
        assert edited.rowcount == 1
    said = one_line(capsys, ["certificate", "verify", str(base / "run" / "certificate.json"),
                             "--db", postgres_url])
    assert f"point 5 of run {lab_run} of the lab differs from the journal's chain" in said

    shutil.rmtree(base / "run")
    shutil.copytree(draft, base / "run")
    said = one_line(capsys, approve(base)[:-2] + ["--db", postgres_url])
    assert "not approved" in said and f"point 5 of run {lab_run} of the lab differs" in said


# --- the lab server --------------------------------------------------------------------------------------
def server_approves(base: Path, user: str = "A. Metrologist") -> httpx.Response:
    """The approver, signed in to `labcal serve` on the copy's lab file with their own key as the
    server's, approves the copy's run through the API."""
    token = add_user(str(base / "lab.sqlite"), user, "approver", "a long passphrase")
    with served(str(base / "lab.sqlite"), "--key", str(base / "approver.key")) as url:
        return httpx.post(f"{url}/api/runs/{run_id(base)}/approve",
                          headers={"Authorization": f"Bearer {token}"}, timeout=120)


def test_the_server_refuses_to_sign_a_run_whose_point_was_edited(issued, tmp_path):
    base = copy_of(issued, tmp_path)
    edit(base, "UPDATE points SET vx = vx + 0.0005 WHERE run_id=? AND seq=5", run_id(base))
    refused = server_approves(base)
    assert refused.status_code == 409
    assert f"point 5 of run {run_id(base)} differs from the journal's chain" in refused.json()["detail"]
    assert json.loads((base / "run" / "certificate.json").read_text()).get("approval") is None


@pytest.mark.parametrize("loose", ["lab.sqlite", "."])
def test_the_server_signs_nothing_from_a_sqlite_lab_database_others_may_write(issued, tmp_path, loose):
    base = copy_of(issued, tmp_path)
    (base / loose).chmod(0o664 if loose != "." else 0o775)
    refused = server_approves(base)
    assert refused.status_code == 409
    detail = refused.json()["detail"]
    assert len(detail.splitlines()) == 1 and "others may write this SQLite lab database" in detail
    assert detail.endswith(f"chmod go-w {base / 'lab.sqlite' if loose != '.' else base}")
    assert json.loads((base / "run" / "certificate.json").read_text()).get("approval") is None


def test_a_new_lab_database_and_its_folder_are_its_owners_only(tmp_path):
    from labcal.store.journal import Journal

    folder = tmp_path / "new" / "lab"
    with Journal(folder / "lab.sqlite") as journal:
        journal.db.execute("CREATE TABLE scratch (x)")  # a write: the -wal file exists now
        files = [folder / "lab.sqlite", folder / "lab.sqlite-wal"]
        assert all(f.exists() for f in files)
        assert {f.name: stat.S_IMODE(f.stat().st_mode) for f in files} == dict.fromkeys(
            (f.name for f in files), 0o600)
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700


# --- the writer -------------------------------------------------------------------------------------------
def test_records_written_through_two_connections_and_a_reopened_journal_form_one_unbroken_chain(tmp_path):
    """The run's writer and the sync thread's outage event (another connection), then a resume in
    a new process, all append to one chain; integers written into REAL columns hash as the floats
    they read back as."""
    import numpy as np

    from labcal.store.chain import check_sqlite
    from labcal.store.journal import Journal, Manifest, PointRecord

    def point(seq: int) -> PointRecord:
        return PointRecord(seq, 1, 0, 90, 0, 0, None, None, 1, "ok", float(seq), seq + 0.5, 2, 1, 0, -1,
                           None, None, None, 21.5, 1.5, "settled")

    path = tmp_path / "journal.sqlite"
    with Journal(path) as writer, Journal(path) as sender:
        run = writer.start_run(Manifest("run", "p", "plan", "{}", "1", {"a": 1}, {}, station="bench-1"))
        writer.record_point(run, point(0), np.ones((2, 4)))
        sender.event(run, "lab_database", "the lab database is unreachable")
        writer.record_point(run, point(1), None)
        writer.event(run, "pause", "operator paused", {"why": "coffee"}, 12.0)
    with Journal(path) as resumed:
        resumed.reopen(run)
        resumed.event(run, "resume", "resumed")
        resumed.record_point(run, point(2), np.zeros((2, 4)))
    with closing(sqlite3.connect(path)) as db:
        check = check_sqlite(db, run)
        links = db.execute("SELECT link FROM points WHERE run_id=:r UNION ALL SELECT link FROM events "
                           "WHERE run_id=:r ORDER BY 1", {"r": run}).fetchall()
    assert check.intact and check.records == 6 and links == [(n,) for n in range(1, 7)]
