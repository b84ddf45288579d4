"""The lab server while runs go on: the event stream of a paced run (each point as it is journaled,
resumed after a reconnection with Last-Event-ID), the run page counting up in a real browser without a
reload, and the same API on PostgreSQL.

Every run is a real `labcal run --sim --pace` process journaling into the database the server reads
(`labcal serve` in a process of its own, tests/lab_server.py); the values are compared with the journal
as sqlite3 reads it."""

from __future__ import annotations

import json
import re
import sqlite3
import time

import httpx
import pytest
from lab_server import add_user, paced_run, served, wait_for

from labcal.cli import main

pytestmark = pytest.mark.long(seconds=25)  # live pages in a browser while runs journal: handed out first

PACE = 120.0  # four-mount-64 at 120 × real time: a point about every quarter second, some 16 s in all
PLAN, TOTAL = "four-mount-64", 64


def _journaled(db: str, run_id: int = 1) -> int:
    """Points the run has journaled, as sqlite3 reads the file (0 before the run exists)."""
    try:
        with sqlite3.connect(db) as conn:
            return int(conn.execute("SELECT count(*) FROM points WHERE run_id = ?", (run_id,)).fetchone()[0])
    except sqlite3.OperationalError:  # not created yet
        return 0


def _run_exists(db: str) -> bool:
    try:
        with sqlite3.connect(db) as conn:
            return conn.execute("SELECT count(*) FROM runs").fetchone()[0] > 0
    except sqlite3.OperationalError:
        return False


def _sse(response: httpx.Response, deadline: float):
    """(id, event, data) of each server-sent event, until ``deadline`` (monotonic)."""
    fields: dict[str, str] = {}
    for line in response.iter_lines():
        if time.monotonic() > deadline:
            raise AssertionError("the stream sent too little before the deadline")
        if line == "":
            if "data" in fields:
                yield fields.get("id"), fields.get("event", "message"), json.loads(fields["data"])
            fields = {}
        elif not line.startswith(":") and ":" in line:
            key, _, value = line.partition(":")
            fields[key] = value.removeprefix(" ")


def _points(url: str, token: str, want: int, last_event_id: str | None = None,
            timeout_s: float = 25.0, run_id: int = 1) -> list[tuple[str, dict]]:
    """The first ``want`` point events of the run's stream, with their ids."""
    return [(i, data) for i, kind, data in _messages(url, token, want, last_event_id, timeout_s, run_id)
            if kind == "point"][:want]


def _messages(url: str, token: str, want: int, last_event_id: str | None = None,
              timeout_s: float = 25.0, run_id: int = 1) -> list[tuple[str, str, dict]]:
    """Every event of the run's stream until ``want`` points and the progress after them have come."""
    headers = {"Authorization": f"Bearer {token}"}
    if last_event_id:
        headers["Last-Event-ID"] = last_event_id
    found: list[tuple[str, str, dict]] = []
    points = 0
    deadline = time.monotonic() + timeout_s
    stream = f"{url}/api/runs/{run_id}/stream"
    with httpx.stream("GET", stream, headers=headers, timeout=timeout_s) as response:
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        for event_id, kind, data in _sse(response, deadline):
            found.append((event_id, kind, data))
            points += kind == "point"
            if points >= want and kind == "progress":  # the batch's summary closes it
                break
    return found


def test_the_stream_sends_each_point_as_it_is_journaled_and_resumes(tmp_path):
    db = str(tmp_path / "lab.sqlite")
    token = add_user(db, "vic", "viewer", "vic's passphrase")
    with served(db) as url, paced_run(db, tmp_path / "run", PACE, PLAN):
        wait_for(lambda: _journaled(db) >= 1, 30, "the run's first point")
        at_connect = _journaled(db)
        messages = _messages(url, token, want=at_connect + 3)
        first = [(i, data) for i, kind, data in messages if kind == "point"]
        seqs = [data["seq"] for _, data in first]
        assert seqs == list(range(len(seqs)))  # every point once, in order, none missing
        assert seqs[-1] >= at_connect + 2  # and points journaled after the client connected came too
        with sqlite3.connect(db) as conn:
            rows = dict(conn.execute("SELECT seq, vx FROM points WHERE run_id = 1").fetchall())
        assert all(data["vx"] == rows[data["seq"]] for _, data in first)  # the journal's values
        _progress_is_the_journals(messages)
        # A client that reconnects with the last id it saw gets the points after it, none again.
        resumed = _points(url, token, want=2, last_event_id=first[-1][0])
        assert [data["seq"] for _, data in resumed] == [seqs[-1] + 1, seqs[-1] + 2]


def _progress_is_the_journals(messages: list[tuple[str, str, dict]]) -> None:
    """Each `progress` event states the points sent before it, and the next remount as the run's own
    status event (journaled at the mount) gave it, less the rig time since: worked out here from the
    stream's own point and status events (the journal's rows)."""
    done, last_end, status, checked = 0, 0.0, None, 0
    for _, kind, data in messages:
        if kind == "point":
            done, last_end = data["seq"] + 1, data["t_end"]
        elif kind == "status":
            status = data
        elif kind == "progress" and data["status"] == "running" and done:
            assert data["points_done"] == done
            assert status is not None and data["estimate"] == "status"
            remount = status["data"]["next_remount_in_s"]
            expected = None if remount is None else max(0.0, remount - (last_end - status["station_time"]))
            assert data["next_remount_in_s"] == pytest.approx(expected, abs=1e-9)
            checked += 1
    assert checked >= 1


def test_the_run_page_counts_up_without_a_reload(browser, tmp_path):
    db = str(tmp_path / "lab.sqlite")
    add_user(db, "ada", "approver", "ada's passphrase")
    with served(db) as url, paced_run(db, tmp_path / "run", PACE, PLAN):
        page = browser.new_page()
        try:
            page.goto(url + "/login")
            page.fill("input[name=name]", "ada")
            page.fill("input[name=password]", "ada's passphrase")
            page.click("button[type=submit]")
            page.wait_for_url(url + "/")
            wait_for(lambda: _run_exists(db), 30, "the run to start")
            page.goto(url + "/runs/1")
            page.evaluate("window.notReloaded = true")
            shown = page.text_content("#count") or ""
            assert re.fullmatch(rf"\s*\d+ / {TOTAL}\s*", shown), shown
            before = int(page.text_content("#done") or "-1")
            page.wait_for_timeout(3000)  # seconds apart: six points or so at this pace
            page.wait_for_function("n => Number(document.getElementById('done').textContent) > n", arg=before,
                                   timeout=20_000)
            after = int(page.text_content("#done") or "-1")
            assert after > before
            assert page.evaluate("window.notReloaded") is True  # the same page, updated in place
            assert after <= _journaled(db) <= TOTAL  # it shows what the journal holds, never more
        finally:
            page.close()


def test_the_api_on_postgresql(postgres_url, tmp_path, monkeypatch):
    """A station journaling into the lab's PostgreSQL (its local journal sent by labcal's sync), users
    added by `labcal user add --db postgresql://…`: /api/runs and the stream say what the station's
    journal says, read with sqlite3."""
    journal = tmp_path / "station" / "journal.sqlite"
    (tmp_path / "lab.toml").write_text("")
    station = {"LABCAL_JOURNAL": str(journal), "LABCAL_STATION": "bench-2",
               "LABCAL_CONFIG": str(tmp_path / "lab.toml"), "XDG_DATA_HOME": str(tmp_path / "data")}
    for name, value in station.items():
        monkeypatch.setenv(name, value)
    token = add_user(postgres_url, "vic", "viewer", "vic's passphrase")
    assert main(["run", "--sim", "--yes", "--no-report", "--seed", "4", "--serial", "ACC-7",
                 "--db", postgres_url, "--out", str(tmp_path / "run")]) == 0
    with sqlite3.connect(journal) as conn:
        row = conn.execute("SELECT status, instrument_serial FROM runs").fetchone()
        done = conn.execute("SELECT count(*) FROM points").fetchone()[0]
        kinds = [k for (k,) in conn.execute("SELECT kind FROM events ORDER BY id")]
    with served(postgres_url) as url:
        auth = {"Authorization": f"Bearer {token}"}
        assert httpx.get(url + "/api/runs", timeout=10).status_code == 401

        def listed() -> list[dict]:
            runs = httpx.get(url + "/api/runs", headers=auth, timeout=10).json()["runs"]
            return runs if runs and runs[0]["points_done"] == done else []
        runs = wait_for(listed, 30, "the station's points on the server")
        got = [(r["status"], r["serial"], r["station"], r["points_done"], r["points_total"]) for r in runs]
        assert got == [(row[0], row[1], "bench-2", done, TOTAL)]
        run_id = runs[0]["id"]
        detail = httpx.get(f"{url}/api/runs/{run_id}", headers=auth, timeout=10).json()
        assert [e["kind"] for e in detail["events"]] == kinds
        streamed = _points(url, token, want=3, run_id=run_id)
        assert [data["seq"] for _, data in streamed] == [0, 1, 2]
