"""The overview and a run's progress read from real journals: the mount a confirmed remount put on
the plate before its first point, and a bench registered in the lab's PostgreSQL before its first
run.

The journal "just after mount 2 was confirmed" is a finished dry run's journal cut at that moment:
the journal only ever appends, so deleting every row written after the status it journaled then
leaves exactly what the lab read at that moment (the run still running)."""

from __future__ import annotations

import re
import sqlite3

import httpx
import pytest
from lab_server import add_user, served

from labcal.app.lab import run_progress
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.app.overview import lab_overview
from labcal.app.station_state import Silence
from labcal.cli import main

HOUR = Silence(floor_s=3600.0)  # the journal was written seconds ago: never "not heard from" here


def _cut_after_second_mount(db: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """Cut run 1's journal just after its second mount was confirmed; the mount of its latest point
    then and of the first point it measured next (y°, u°), as the journal has them."""
    with sqlite3.connect(db) as conn:
        event_id, utc = conn.execute(
            "SELECT id, utc FROM events WHERE run_id = 1 AND kind = 'status' "
            "AND message LIKE 'running: 16 of %' ORDER BY id LIMIT 1").fetchone()
        before = conn.execute("SELECT y_deg, u_deg FROM points WHERE utc <= ? ORDER BY seq DESC LIMIT 1",
                              (utc,)).fetchone()
        after = conn.execute("SELECT y_deg, u_deg FROM points WHERE utc > ? ORDER BY seq LIMIT 1",
                             (utc,)).fetchone()
        conn.execute("DELETE FROM events WHERE id > ?", (event_id,))
        conn.execute("DELETE FROM points WHERE utc > ?", (utc,))
        conn.execute("UPDATE runs SET status = 'running', ended_utc = NULL, reason = NULL")
    return tuple(before), tuple(after)


def test_a_confirmed_remount_is_the_mount_shown_before_its_first_point(tmp_path, monkeypatch):
    db = str(tmp_path / "lab.sqlite")
    monkeypatch.setenv("LABCAL_STATION", "bench 5")
    assert main(["run", "--sim", "--yes", "--no-report", "--seed", "5", "--serial", "ACC-0005", "--db", db,
                 "--out", str(tmp_path / "run")]) == 0
    before, after = _cut_after_second_mount(db)
    assert before != after  # four-mount-64: the second mount is another orientation
    lab = open_lab(OpenLab(db))
    try:
        progress = run_progress(lab, 1)
        assert progress is not None and progress["points_done"] == 16
        assert (progress["mount"]["y_deg"], progress["mount"]["u_deg"]) == after
        (station,) = lab_overview(lab, HOUR).stations
    finally:
        lab.close()
    assert station["station"] == "bench 5" and station["state"] == "running"
    # Soto Table 3's numbering: 1 (0°, 0°), 2 (180°, 0°), 3 (0°, 180°), 4 (180°, 180°)
    number = {(0.0, 0.0): 1, (180.0, 0.0): 2, (0.0, 180.0): 3, (180.0, 180.0): 4}[after]
    assert station["mount"] == {"number": number, "y_deg": after[0], "u_deg": after[1]}


def test_a_bench_registered_in_the_lab_database_shows_idle_before_its_first_run(postgres_url, tmp_path,
                                                                               monkeypatch):
    """`labcal db grant-station 'bench 9'` on the lab's PostgreSQL: the overview lists bench 9, idle,
    with no run, beside bench 2, whose run is complete."""
    (tmp_path / "lab.toml").write_text("")
    for name, value in {"LABCAL_JOURNAL": str(tmp_path / "journal.sqlite"), "LABCAL_STATION": "bench 2",
                        "LABCAL_CONFIG": str(tmp_path / "lab.toml"),
                        "XDG_DATA_HOME": str(tmp_path / "data")}.items():
        monkeypatch.setenv(name, value)
    assert main(["db", "grant-station", "bench 9", "--db", postgres_url, "--json"]) == 0
    token = add_user(postgres_url, "vic", "viewer", "vic's passphrase")
    assert main(["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--db", postgres_url,
                 "--out", str(tmp_path / "run")]) == 0
    with served(postgres_url) as url, httpx.Client(base_url=url, timeout=15) as page:
        csrf = re.search(r'name="csrf" value="([^"]+)"', page.get("/login").text)
        assert csrf is not None
        page.post("/login", data={"name": "vic", "password": "vic's passphrase", "csrf": csrf[1]})
        shown = page.get("/").text
        stations = httpx.get(url + "/api/stations", headers={"Authorization": f"Bearer {token}"},
                             timeout=15).json()["stations"]
    assert [(s["station"], s["state"], s["label"]) for s in stations] == [
        ("bench 2", "complete", "complete"), ("bench 9", "idle", "idle")]
    assert stations[1]["run"] is None and "run_dir" not in stations[0]["run"]  # a viewer's: no folder
    card = r'<h2>([^<]+?)(?: <small[^>]*>simulated</small>)?</h2><span class="badge state-(\w+)">'
    cards = re.findall(card, shown)
    assert cards == [("bench 2", "complete"), ("bench 9", "idle")], shown
    assert "Registered; no run yet." in shown


@pytest.mark.parametrize(("utc", "shown"), [
    ("2026-11-27T09:41:07.250+00:00", "2026-11-27 09:41 UTC (10:41 CET)"),  # winter: UTC+1
    ("2026-07-01T23:30:00.000+00:00", "2026-07-01 23:30 UTC (01:30 CEST)"),  # summer: UTC+2, the next day
    (None, "—")])
def test_times_are_shown_in_utc_and_in_the_labs_local_time_beside_it(utc, shown, monkeypatch):
    """The server's zone is the lab's (TZ); Berlin's offsets are the EU's summer-time rule's."""
    import time

    from labcal.server.app import clock

    monkeypatch.setenv("TZ", "Europe/Berlin")
    time.tzset()
    try:
        assert clock(utc) == shown
    finally:
        monkeypatch.undo()
        time.tzset()


def test_a_lab_on_utc_is_shown_in_utc_alone(monkeypatch):
    import time

    from labcal.server.app import clock

    monkeypatch.setenv("TZ", "UTC")
    time.tzset()
    try:
        assert clock("2026-11-27T09:41:07.250+00:00", seconds=True) == "2026-11-27 09:41:07 UTC"
    finally:
        monkeypatch.undo()
        time.tzset()


@pytest.mark.slow
def test_a_paced_runs_done_at_is_its_eta_at_the_pace_it_keeps(tmp_path):
    """A simulated run paced at 20 × real time: the rig's clock runs 20 times faster than the wall's,
    so the run is done eta_s / 20 wall seconds after its latest point, not eta_s (the rig's clock).
    The tolerance (25 %) allows for the process's own time per point on a busy machine, which the pace
    does not include; the rig's clock taken as the wall's would be 1900 % off."""
    from datetime import datetime

    from lab_server import paced_run, wait_for

    db = str(tmp_path / "lab.sqlite")

    def points() -> int:
        try:
            with sqlite3.connect(db) as conn:
                return int(conn.execute("SELECT count(*) FROM points").fetchone()[0])
        except sqlite3.OperationalError:
            return 0

    with paced_run(db, tmp_path / "run", 20.0, "four-mount-64"):
        wait_for(lambda: points() >= 6, 60, "six points")
        lab = open_lab(OpenLab(db))
        try:
            progress = run_progress(lab, 1)
        finally:
            lab.close()
    assert progress is not None and progress["status"] == "running" and progress["eta_s"] > 0
    with sqlite3.connect(db) as conn:
        (last,) = conn.execute("SELECT utc FROM points ORDER BY seq LIMIT 1 OFFSET ?",
                               (progress["points_done"] - 1,)).fetchone()  # the latest when it was read
    wall_s = (datetime.fromisoformat(progress["done_at_utc"]) - datetime.fromisoformat(last)).total_seconds()
    assert wall_s == pytest.approx(progress["eta_s"] / 20.0, rel=0.25)
