"""A run is shown in the same words wherever the lab server lists it: the overview's "Recent runs"
table and the run's own page say what the overview's bench card says — "not heard from" for a run
the journal still calls running whose bench has gone silent (a killed process cannot close its run),
"running" while it is heard — and a finished run by the status it was closed with.

The lab: two dry runs on one bench, the first complete, the second cut from a finished journal at
its second mount (the journal only appends, so deleting what was written after a moment leaves what
the lab read then: a run still running, nothing heard since), and its records moved ten minutes into
the past: its bench silent for ten minutes, ten times the lab server's default allowance of one minute
(a simulated rig journals a point every few milliseconds, so five of its intervals are less). Allowed
an hour's silence instead, the same run is running."""

from __future__ import annotations

import re
import sqlite3
from datetime import datetime, timedelta

import httpx
from lab_server import add_user, served

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.app.overview import lab_overview
from labcal.app.station_state import Silence
from labcal.cli import main

HOUR = Silence(floor_s=3600.0)
AGO = timedelta(minutes=10)


def _earlier(utc: str) -> str:
    return (datetime.fromisoformat(utc) - AGO).isoformat(timespec="milliseconds")


def _lab(tmp_path, monkeypatch) -> str:
    db = str(tmp_path / "lab.sqlite")
    monkeypatch.setenv("LABCAL_STATION", "bench 7")
    for n, seed in ((1, 5), (2, 6)):
        assert main(["run", "--sim", "--yes", "--no-report", "--seed", str(seed), "--db", db,
                     "--out", str(tmp_path / f"run{n}")]) == 0
    with sqlite3.connect(db) as conn:  # run 2 as the lab read it just after its second mount
        event_id, utc = conn.execute(
            "SELECT id, utc FROM events WHERE run_id = 2 AND kind = 'status' "
            "AND message LIKE 'running: 16 of %' ORDER BY id LIMIT 1").fetchone()
        conn.execute("DELETE FROM events WHERE run_id = 2 AND id > ?", (event_id,))
        conn.execute("DELETE FROM points WHERE run_id = 2 AND utc > ?", (utc,))
        conn.execute("UPDATE runs SET status = 'running', ended_utc = NULL, reason = NULL WHERE id = 2")
        conn.create_function("earlier", 1, _earlier)
        for table in ("events", "points"):
            conn.execute(f"UPDATE {table} SET utc = earlier(utc) WHERE run_id = 2")
    return db


def test_the_recent_runs_state_is_the_benchs_not_the_journals_status(tmp_path, monkeypatch):
    db = _lab(tmp_path, monkeypatch)
    lab = open_lab(OpenLab(db))
    try:
        silent, heard = lab_overview(lab), lab_overview(lab, HOUR)
    finally:
        lab.close()
    assert [(r["id"], r["status"], r["state"], r["state_label"]) for r in silent.runs] == [
        (2, "running", "silent", "not heard from"), (1, "complete", "complete", "complete")]
    assert [(s["station"], s["label"]) for s in silent.stations] == [("bench 7", "not heard from")]
    assert [(r["id"], r["state_label"]) for r in heard.runs] == [(2, "running"), (1, "complete")]


def test_the_overview_table_and_the_run_page_say_not_heard_from_for_a_silent_run(tmp_path, monkeypatch):
    db = _lab(tmp_path, monkeypatch)
    add_user(db, "vic", "viewer", "vic's passphrase")
    with served(db) as url, httpx.Client(base_url=url, timeout=15) as page:
        csrf = re.search(r'name="csrf" value="([^"]+)"', page.get("/login").text)
        assert csrf is not None
        page.post("/login", data={"name": "vic", "password": "vic's passphrase", "csrf": csrf[1]})
        overview, run2, run1 = page.get("/").text, page.get("/runs/2").text, page.get("/runs/1").text
    table = overview[overview.index("<h2>Recent runs</h2>"):]
    rows = re.findall(r'<a href="/runs/(\d+)">.*?<span class="badge ([\w-]+)">([^<]+)</span>', table, re.S)
    assert rows == [("2", "state-silent", "not heard from"), ("1", "state-complete", "complete")]
    badge = r'<span class="badge ([\w-]+)" id="status">([^<]+)</span>'
    assert re.findall(badge, run2) == [("state-silent", "not heard from")]
    assert re.findall(badge, run1) == [("state-complete", "complete")]
