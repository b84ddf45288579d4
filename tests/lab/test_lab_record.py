"""The lab database is the lab's one record: benches with journals of their own, one PostgreSQL lab
database (tests/services.py's private cluster), and what each bench reads.

- Run numbers: the lab numbers a run once, when it first reaches it, without gaps, and every bench's
  `labcal runs --json` and the server's `/api/runs` give each run the same number; a run the lab has
  not seen yet is shown by its provisional label until it is sent.
- Everything reaches the lab exactly once: an approver registered at bench 3 approves and verifies a
  certificate of bench 1's, the approved certificate replaces the draft in the lab, and repeated and
  interrupted syncs store each run, point, event, certificate, estimate, approver and pool once.
- Every bench reads the lab: ACC-0042 calibrated at two benches shows both calibrations, its drift
  flagged, in `labcal history` at either; bench 2's device estimates drive `plan optimize --device`
  after its journal is deleted.

Every expectation is read independently of the code under test where it can be: the lab database
with psycopg and plain SQL, the journals with sqlite3.
"""

from __future__ import annotations

import io
import json
import re
import sqlite3
from contextlib import closing, redirect_stdout
from pathlib import Path

import psycopg
import pytest
from cli import in_process
from services import free_port
from simulated_runs import days_ago

from labcal.cli import main
from labcal.store.labquery import lab_number_of

PLAN = "one-mount-16"
SERIAL = "ACC-0042"


class Bench:
    """One bench: its name, its journal, the lab database it is configured with (by the environment,
    as a bench's lab file would)."""

    def __init__(self, tmp_path: Path, name: str, url: str, monkeypatch: pytest.MonkeyPatch):
        self.name, self.url, self.monkeypatch = name, url, monkeypatch
        self.journal = tmp_path / name / "journal.sqlite"
        self.folder = tmp_path / name
        self.runs = 0
        (tmp_path / "lab.toml").write_text("")
        self.config = tmp_path / "lab.toml"

    def here(self, db: str | None = None) -> None:
        """The environment of this bench (its lab file would say the same)."""
        for name, value in (("LABCAL_DB", db or self.url), ("LABCAL_JOURNAL", str(self.journal)),
                            ("LABCAL_STATION", self.name), ("LABCAL_CONFIG", str(self.config)),
                            ("LABCAL_NOTIFY", "")):
            self.monkeypatch.setenv(name, value)

    def labcal(self, *args: str, db: str | None = None) -> tuple[int, str, str]:
        """A labcal command at this bench (in this process: a new Python per command takes seconds)."""
        self.here(db)
        return in_process(*args)

    def run(self, db: str | None = None, *extra: str, report: bool = False, seed: int | None = None) -> Path:
        """A dry run of ACC-0042 at this bench (one mount, no report unless asked); its folder."""
        self.runs += 1
        folder = self.folder / f"run{self.runs}"
        options = ("--plan", PLAN, "--no-report") if not report else ()
        code, _, err = self.labcal("run", "--sim", "--yes", *options, "--seed", str(seed or self.runs),
                                   "--serial", SERIAL, "--out", str(folder), *extra, db=db)
        assert code == 0, err
        return folder

    def listed(self) -> tuple[list[dict], str]:
        code, out, err = self.labcal("runs", "--json", "--db", self.url)
        assert code == 0, err
        return json.loads(out)["runs"], err


@pytest.fixture
def benches(tmp_path, postgres_url, monkeypatch) -> tuple[Bench, Bench]:
    return Bench(tmp_path, "bench-1", postgres_url, monkeypatch), Bench(tmp_path, "bench-2", postgres_url,
                                                                        monkeypatch)


def lab_numbers(url: str) -> list[tuple[int, str, str]]:
    """(number, uuid, station) of every run in the lab database, read with plain SQL."""
    with psycopg.connect(url) as conn:
        return [tuple(row) for row in conn.execute("SELECT id, uuid, station FROM runs ORDER BY id")]


def journal_uuids(journal: Path) -> list[str]:
    with closing(sqlite3.connect(journal)) as db:
        return [row[0] for row in db.execute("SELECT uuid FROM runs ORDER BY id")]


def api_runs(url: str) -> list[dict]:
    """`GET /api/runs` of a lab server on the lab database (FastAPI's test client: the app itself)."""
    from fastapi.testclient import TestClient

    from labcal.app.labdatabase import OpenLab, open_lab
    from labcal.server.app import ServerSettings, create_app

    printed = io.StringIO()
    with redirect_stdout(printed):
        assert main(["user", "add", "viewer", "--role", "viewer", "--password", "a long passphrase 1",
                     "--db", url, "--json"]) == 0
    token = json.loads(printed.getvalue())["token"]
    lab = open_lab(OpenLab(url))
    try:
        with TestClient(create_app(ServerSettings(lab))) as client:
            response = client.get("/api/runs", headers={"Authorization": f"Bearer {token}"})
    finally:
        lab.close()
    assert response.status_code == 200, response.text
    return response.json()["runs"]


@pytest.mark.slow  # five dry runs at two benches: about 20 s
def test_two_benches_show_the_same_gap_free_run_numbers_as_the_api(benches):
    one, two = benches
    offline = f"postgresql://labcal@127.0.0.1:{free_port()}/lab"  # nothing listens: bench 2 cut off
    one.run()
    two.run()
    one.run()
    two.run(db=offline)  # journaled at bench 2 only: the lab has not numbered it
    listed, err = two.listed()
    unsent = journal_uuids(two.journal)[-1]
    assert [r["id"] for r in listed] == [1, 2, 3, None] and not err
    assert listed[-1]["uuid"] == unsent and listed[-1]["label"] == f"{unsent[:8]} (provisional)"
    # how a notification names it: by the same label (bench 2's journal row 2)
    assert lab_number_of(two.journal, 2, two.url) == f"{unsent[:8]} (provisional)"
    one.run()  # number 4: bench 2's run reaches the lab after it, and is numbered after it
    code, out, err = two.labcal("sync")
    assert code == 0, err
    assert lab_number_of(two.journal, 2, two.url) == "5" and lab_number_of(two.journal, 1, two.url) == "2"

    lab = lab_numbers(one.url)
    assert [n for n, _, _ in lab] == [1, 2, 3, 4, 5]  # without a gap, though each status was sent many times
    assert lab[4][1:] == (unsent, "bench-2")
    expected = [{"id": n, "uuid": u, "station": s} for n, u, s in lab]
    for bench in (one, two):
        listed, _ = bench.listed()
        assert [{k: r[k] for k in ("id", "uuid", "station")} for r in listed] == expected
        assert all(r["serial"] == SERIAL and r["points_ok"] == 16 and r["label"] == str(r["id"])
                   for r in listed)
    served = api_runs(one.url)
    assert [{k: r[k] for k in ("id", "uuid", "station")} for r in reversed(served)] == expected
    assert all(r["serial"] == SERIAL and r["points_ok"] == 16 for r in served)

    # its folder is bench 2's: exported there by its lab number, refused at bench 1 naming bench 2
    code, out, err = two.labcal("export", "5", "--out", str(two.folder / "copy"), "--json")
    assert code == 0 and (json.loads(out)["id"], json.loads(out)["uuid"]) == (5, unsent), err
    code, out, err = one.labcal("export", "5", "--out", str(one.folder / "copy"))
    assert code == 2 and "measured at bench-2" in err and len(err.strip().splitlines()) == 1, err

    code, out, err = one.labcal("log", "5", "--json")  # bench 2's run, read at bench 1 from the lab
    log = json.loads(out)
    assert code == 0 and log["id"] == 5 and log["uuid"] == unsent and log["station"] == "bench-2"
    with closing(sqlite3.connect(two.journal)) as db:
        journaled = db.execute("SELECT kind, message FROM events WHERE run_id = (SELECT max(id) FROM runs) "
                               "ORDER BY id").fetchall()
    assert [(e["kind"], e["message"]) for e in log["events"]] == journaled


def test_a_bench_that_cannot_reach_the_lab_lists_its_own_runs_by_their_lab_numbers(benches,
                                                                                       postgres_cluster):
    one, two = benches
    one.run()
    two.run()
    one.run()
    postgres_cluster.pause()
    try:
        listed, err = one.listed()
        code, approvers, approvers_err = one.labcal("certificate", "approvers", "list", "--json")
    finally:
        postgres_cluster.start()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "cannot reach the lab database" in lines[0]
    # the registry read from the journal's copy says so too, in the same one line
    assert code == 0 and approvers_err.strip().splitlines() == lines, approvers_err
    assert json.loads(approvers)["approvers"] == []
    assert "last in step with the lab" in lines[0] and str(one.journal) in lines[0]
    assert [(r["id"], r["uuid"]) for r in listed] == [(n, u) for n, u, s in lab_numbers(one.url)
                                                       if s == "bench-1"]


def lab_count(url: str, table: str) -> int:
    with psycopg.connect(url) as conn:
        return int(conn.execute(f"SELECT count(*) FROM {table}").fetchone()[0])


def journal_count(journals: list[Path], table: str) -> int:
    total = 0
    for journal in journals:
        with closing(sqlite3.connect(journal)) as db:
            total += int(db.execute(f"SELECT count(*) FROM {table}").fetchone()[0])
    return total


KEYS = {"runs": "uuid", "certificates": "certificate_id", "device_estimates": "device_id || '/' || source",
        "approvers": "key_id", "settle_pools": "pool_key"}


def journal_records(journals: list[Path], table: str) -> int:
    """Distinct records of ``table`` in the journals (a bench also keeps copies of other benches'
    records it received from the lab: counted once, by their key); points and events are each
    bench's own."""
    if table not in KEYS:
        return journal_count(journals, table)
    keys = set()
    for journal in journals:
        with closing(sqlite3.connect(journal)) as db:
            keys |= {row[0] for row in db.execute(f"SELECT {KEYS[table]} FROM {table}")}
    return len(keys)


TABLES = ("runs", "points", "events", "certificates", "device_estimates", "approvers", "settle_pools")
NAME, ROLE = "A. Metrologist", "Technical manager"


@pytest.mark.slow
def test_an_approver_registered_at_bench_3_approves_at_bench_1_and_everything_is_in_the_lab_once(
        tmp_path, postgres_url, monkeypatch):
    from simulated_runs import bench_run

    one = Bench(tmp_path, "bench-1", postgres_url, monkeypatch)
    three = Bench(tmp_path, "bench-3", postgres_url, monkeypatch)
    code, _, err = three.labcal("certificate", "keygen", "--out", str(tmp_path / "approver"))
    assert code == 0, err
    code, _, err = three.labcal("certificate", "approvers", "add", NAME, "--role", ROLE, "--public-key",
                                str(tmp_path / "approver.pub"))
    assert code == 0 and err == "", err  # in the lab at once: nothing left for labcal sync
    assert lab_count(postgres_url, "approvers") == 1

    one.here()
    one.folder.mkdir(parents=True, exist_ok=True)
    run = bench_run(tmp_path / "bench-1" / "run", postgres_url, SERIAL)  # through the drivers: signable
    code, _, err = one.labcal("certificate", "approvers", "list", "--json")
    assert code == 0 and NAME in _, err  # bench 1 knows bench 3's registration
    code, _, err = one.labcal("certificate", "approve", str(run), "--by", NAME, "--role", ROLE, "--key",
                              str(tmp_path / "approver.key"))
    assert code == 0 and err == "", err
    code, out, err = one.labcal("certificate", "verify", str(run / "certificate.json"), "--json")
    assert code == 0 and json.loads(out)["verified_against"] == "the registered key", err
    signed = json.loads((run / "certificate.json").read_text())
    with psycopg.connect(postgres_url) as conn:
        stored = conn.execute("SELECT document FROM certificates WHERE certificate_id = %s",
                              (signed["certificate_id"],)).fetchone()[0]
    assert json.loads(stored)["approval"] == signed["approval"]  # the approved one, not the draft

    journals = [one.journal, three.journal]
    expected = {t: journal_records(journals, t) for t in TABLES}
    assert expected["approvers"] == 1 and expected["certificates"] == 1 and expected["runs"] == 1
    for _ in range(2):
        code, out, err = one.labcal("sync")
        assert code == 0 and "nothing to send" in out, err
    # the lab committed every batch but the journal lost what it noted of them (a kill between the
    # two commits): everything is offered again, and nothing is stored twice
    with closing(sqlite3.connect(one.journal)) as db, db:
        for table in ("sync_sent", "sync_cursors", "sync_runs", "sync_targets"):
            db.execute(f"DELETE FROM {table}")
    code, out, err = one.labcal("sync", "--json")
    sent = json.loads(out)
    assert code == 0 and sent["sent"]["points"] == journal_count([one.journal], "points"), err
    assert sum(sent["new"].values()) == 0
    assert {t: lab_count(postgres_url, t) for t in TABLES} == expected
    assert lab_numbers(postgres_url)[0][0] == 1

    # the lab server's page says who approved the run and when, and offers no form that would only
    # be refused
    from fastapi.testclient import TestClient

    from labcal.app.labdatabase import OpenLab, open_lab
    from labcal.server.app import ServerSettings, create_app

    assert main(["user", "add", "ada", "--role", "approver", "--password", "a long passphrase 2", "--db",
                 postgres_url]) == 0
    lab = open_lab(OpenLab(postgres_url))
    try:
        with TestClient(create_app(ServerSettings(lab, key=tmp_path / "approver.key"))) as client:
            form = client.get("/login")
            csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)[1]
            client.post("/login", data={"name": "ada", "password": "a long passphrase 2", "csrf": csrf})
            page = client.get("/runs/1")
    finally:
        lab.close()
    assert page.status_code == 200 and "Approve the certificate" not in page.text
    assert 'action="/runs/1/approve"' not in page.text
    assert f"approved by {NAME} ({ROLE}) at {signed['approval']['approved_utc']}" in page.text


@pytest.mark.slow
def test_acc_0042_calibrated_at_two_benches_shows_both_calibrations_and_its_drift_at_either(
        benches, tmp_path, postgres_cluster):
    from simulated_runs import rig_with_bias_shift

    one, two = benches
    one.run(report=True, seed=3)
    shifted = rig_with_bias_shift(tmp_path / "shifted.toml", (0.005, 0.0, 0.0))  # 5 mV on x: far beyond U
    two.run(None, "--rig", str(shifted), report=True, seed=4)
    documents = []
    for bench in (one, two):
        code, out, err = bench.labcal("history", SERIAL, "--include-simulated", "--json")
        assert code == 0, err
        documents.append(json.loads(out))
    assert documents[0] == documents[1]
    history = documents[0]
    assert len(history["calibrations"]) == 2
    flagged = {(f["coefficient"], f["sensor"]) for f in history["flagged"]}
    assert ("B", "x") in flagged
    bias_x = [c["coefficients"][0][0] for c in history["calibrations"]]
    assert abs(bias_x[1] - bias_x[0] - 0.005) < 0.001  # the shift, as both calibrations measured it

    # bench 2 has received bench 1's certificate (before its own run, and at each sync), then loses
    # the lab: it works from what it had
    code, out, err = two.labcal("sync")
    assert code == 0, err
    assert journal_count([two.journal], "certificates") == 2
    postgres_cluster.pause()
    try:
        code, out, err = two.labcal("history", SERIAL, "--include-simulated", "--json")
    finally:
        postgres_cluster.start()
    assert code == 0 and json.loads(out) == history
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "cannot reach the lab database" in lines[0] and "ago" in lines[0]


@pytest.mark.slow
def test_bench_2s_device_estimates_drive_plan_optimize_after_its_journal_is_deleted(benches):
    from labcal.app.planning import device_correction

    _, two = benches
    two.run(report=True, seed=1)
    last = two.run(report=True, seed=2)
    with psycopg.connect(two.url) as conn:
        sources = [r[0] for r in conn.execute("SELECT source FROM device_estimates "
                                              "WHERE device_id = 'SIMULATED' ORDER BY calibrated_utc")]
    assert sources == ["run1", last.name]
    earlier = days_ago(3)  # two estimates of one day are one sitting: the first from three days before
    with psycopg.connect(two.url) as conn:
        conn.execute("UPDATE device_estimates SET calibrated_utc = %s, document = "
                     "jsonb_set(document::jsonb, '{calibrated_utc}', to_jsonb(%s::text))::text "
                     "WHERE source = 'run1'", (earlier, earlier))
    two.journal.unlink()
    for wal in two.journal.parent.glob("journal.sqlite-*"):
        wal.unlink()
    two.here()
    correction, why = device_correction("SIMULATED", None)
    assert correction is not None, why
    assert correction.source == last.name
    # a loose target: the quickest plan, which leaves the misalignments to the lab's estimate
    code, out, err = two.labcal("plan", "optimize", "--device", "SIMULATED", "--target-attitude-u95-deg", "1",
                                "--json")
    assert code == 0, err
    assert json.loads(out)["device_correction"]["source"] == last.name


@pytest.mark.slow  # two dry runs with model settling: about 15 s
def test_a_run_at_bench_2_starts_from_the_settle_pool_bench_1_left_in_the_lab(benches):
    """The same simulated station and instrument at both benches share one settle pool: bench 1's
    run keeps its step records in the lab, and bench 2's next run starts with them."""
    one, two = benches
    one.run(None, "--settle", "model")
    with psycopg.connect(one.url) as conn:
        records = conn.execute("SELECT records FROM settle_pools").fetchall()
    assert len(records) == 1 and records[0][0] > 0
    two.run(None, "--settle", "model", seed=2)  # another noise realisation
    with closing(sqlite3.connect(two.journal)) as db:
        note = db.execute("SELECT message FROM events WHERE kind = 'settle_pool'").fetchone()[0]
    assert note.startswith(f"model settling starts with {records[0][0]} step records of 1 earlier run"), note
