"""The lab database is the lab's one record: benches with journals of their own, one PostgreSQL lab
database (tests/services.py's private cluster), and what each bench reads.

- Run numbers: the lab numbers a run once, when it first reaches it, without gaps, and every bench's
  `labcal runs --json` and the server's `/api/runs` give each run the same number; a run the lab has
  not seen yet is shown by its provisional label until it is sent.

Every expectation is read independently of the code under test where it can be: the lab database
with psycopg and plain SQL, the journals with sqlite3.
"""

from __future__ import annotations

import io
import json
import sqlite3
from contextlib import closing, redirect_stderr, redirect_stdout
from pathlib import Path

import psycopg
import pytest
from services import free_port

from labcal.cli import main

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

    def labcal(self, *args: str, db: str | None = None) -> tuple[int, str, str]:
        """A labcal command at this bench (in this process: a new Python per command takes seconds)."""
        for name, value in (("LABCAL_DB", db or self.url), ("LABCAL_JOURNAL", str(self.journal)),
                            ("LABCAL_STATION", self.name), ("LABCAL_CONFIG", str(self.config)),
                            ("LABCAL_NOTIFY", "")):
            self.monkeypatch.setenv(name, value)
        out, err = io.StringIO(), io.StringIO()
        with redirect_stdout(out), redirect_stderr(err):
            code = main(list(args))
        return code, out.getvalue(), err.getvalue()

    def run(self, db: str | None = None) -> None:
        self.runs += 1
        code, _, err = self.labcal("run", "--sim", "--yes", "--no-report", "--plan", PLAN, "--seed",
                                   str(self.runs), "--serial", SERIAL, "--out",
                                   str(self.folder / f"run{self.runs}"), db=db)
        assert code == 0, err

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
    one.run()  # number 4: bench 2's run reaches the lab after it, and is numbered after it
    code, out, err = two.labcal("sync")
    assert code == 0, err

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
    finally:
        postgres_cluster.start()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "cannot reach the lab database" in lines[0]
    assert "last in step with the lab" in lines[0] and str(one.journal) in lines[0]
    assert [(r["id"], r["uuid"]) for r in listed] == [(n, u) for n, u, s in lab_numbers(one.url)
                                                       if s == "bench-1"]
