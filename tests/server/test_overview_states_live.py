"""The lab overview in Chromium while real benches run: a bench whose process is killed (SIGKILL,
as a power cut or the OOM killer would) shows as "not heard from", without an ETA, within two
minutes; a bench at a remount prompt shows in its own state with how long it has waited, counted
from the prompt's time in the journal; an emulated station paused on its drive's alarm shows
"paused on a fault" until the technician aborts it.

Every bench is a real `labcal run --sim --pace` process journaling into the SQLite lab database
that `labcal serve` (a process of its own) reads. The server is told a short least silence
(``--silent-after``) so that the test is quick; it polls with a bound and never sleeps on a guess."""

from __future__ import annotations

import os
import re
import signal
import sqlite3
import subprocess
import time
from datetime import datetime, timedelta

import pytest
from cli import LABCAL
from lab_server import accessible, add_user, ctrl_c, parses_cleanly, served, wait_for

SILENT_AFTER_S = 8.0  # the server's least silence: a paced run journals a point every second or so
CARD = "a.card[href='/runs/1']"


def _points(db: str) -> int:
    try:
        with sqlite3.connect(db) as conn:
            return int(conn.execute("SELECT count(*) FROM points").fetchone()[0])
    except sqlite3.OperationalError:  # not created yet
        return 0


def _prompt_utc(db: str) -> str | None:
    try:
        with sqlite3.connect(db) as conn:
            row = conn.execute("SELECT utc FROM events WHERE kind = 'prompt' ORDER BY id LIMIT 1").fetchone()
    except sqlite3.OperationalError:
        return None
    return None if row is None else row[0]


def _bench(db: str, out: str, station: str, *extra: str, stdin: int | None = None) -> subprocess.Popen:
    return subprocess.Popen([LABCAL, "run", "--sim", "--no-report", "--pace", "20", "--serial", "ACC-0110",
                             "--db", db, "--out", out, *extra], stdin=stdin, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, text=True,
                            env={**os.environ, "LABCAL_STATION": station})


def _sign_in(page, url: str) -> None:
    page.goto(url + "/login")
    page.fill("input[name=name]", "ada")
    page.fill("input[name=password]", "ada's passphrase")
    page.click("button[type=submit]")
    page.wait_for_url(url + "/")


def _badge(page) -> str:
    page.reload()
    return (page.text_content(f"{CARD} .badge") or "").strip()


@pytest.mark.slow(seconds=33)
def test_a_killed_bench_is_shown_not_heard_from_within_two_minutes(browser, tmp_path):
    db = str(tmp_path / "lab.sqlite")
    add_user(db, "ada", "approver", "ada's passphrase")
    bench = _bench(db, str(tmp_path / "run"), "bench 3", "--yes", "--plan", "four-mount-64")
    try:
        with served(db, "--silent-after", str(SILENT_AFTER_S)) as url:
            page = browser.new_page()
            try:
                _sign_in(page, url)
                wait_for(lambda: _points(db) >= 3, 60, "the bench's first points")
                wait_for(lambda: _badge(page) == "running", 60, "the bench shown running")
                assert "Done at" in (page.text_content(CARD) or "")
                bench.send_signal(signal.SIGKILL)
                bench.wait(timeout=10)
                killed = time.monotonic()
                wait_for(lambda: _badge(page) == "not heard from", 120, "the killed bench not heard from",
                         every_s=1.0)
                assert time.monotonic() - killed < 120
                card = page.text_content(CARD) or ""
                assert "Not heard from for" in card and "No ETA" in card
                assert "Done at" not in card and "Next remount" not in card
                with sqlite3.connect(db) as conn:  # the journal still says running: only silence tells
                    assert conn.execute("SELECT status FROM runs").fetchone()[0] == "running"
                parses_cleanly(page.content(), "/ with a bench not heard from")
                accessible(page, "/ with a bench not heard from")
            finally:
                page.close()
    finally:
        ctrl_c(bench, 10)


@pytest.mark.slow
def test_a_bench_at_a_remount_prompt_is_waiting_for_a_person_with_the_minutes_waited(browser, tmp_path):
    """No --yes: the run asks for mount 1 at once and waits for someone to confirm it. The page's clock
    is then moved seven minutes on (Playwright's clock, the page's alone): the time waited it shows is
    that clock's now less the prompt's time as the journal has it, and the bench is still waiting,
    never "not heard from" — a bench at a prompt is silent by design."""
    db = str(tmp_path / "lab.sqlite")
    add_user(db, "ada", "approver", "ada's passphrase")
    bench = _bench(db, str(tmp_path / "run"), "bench 2", "--plan", "one-mount-16", stdin=subprocess.PIPE)
    try:
        with served(db, "--silent-after", str(SILENT_AFTER_S)) as url:
            prompt = datetime.fromisoformat(str(wait_for(lambda: _prompt_utc(db), 60, "the remount prompt")))
            page = browser.new_page()
            try:
                page.clock.install()
                _sign_in(page, url)
                assert (page.text_content(f"{CARD} .badge") or "").strip() == "waiting for a person"
                page.clock.pause_at(prompt + timedelta(minutes=7, seconds=12))
                page.clock.run_for(5000)  # the page counts the time waited again every 5 s
                now_ms = page.evaluate("Date.now()")
                waited = round((now_ms - prompt.timestamp() * 1000) / 1000)  # 7 min 12 s, then 5 s run
                expected = f"{waited // 60} min {waited % 60:02d} s"
                assert waited // 60 == 7
                line = page.text_content(f"{CARD} .alert.waiting") or ""
                assert line.startswith(f"Waiting for a person for {expected}: mount 1 of 1: "), line
                page.clock.resume()
                assert _badge(page) == "waiting for a person"  # the server's own count: still waiting
                accessible(page, "/ with a bench waiting")
            finally:
                page.close()
    finally:
        ctrl_c(bench, 20)


@pytest.mark.slow
def test_a_bench_paused_on_a_fault_shows_the_fault_until_it_is_stopped(tmp_path):
    """An emulated AZ station whose roll drive raises alarm 10h mid-run (AZ manual: excessive position
    deviation): the run pauses, and the overview says "paused on a fault" with the alarm, as the API
    does; the technician aborts at the station, and the bench is idle, its run stopped, the fault
    still shown as not cleared (nothing went past it)."""
    import httpx
    from emulators import private_file

    alarm = '\n[[emulation.faults]]\ndevice = "roll"\nkind = "alarm"\ncode = 16\nafter = 150\n'
    station = private_file("az-modbus-rtu", tmp_path, alarm, "timeout_s = 0.1\nreconnect_s = 1")
    db = str(tmp_path / "lab.sqlite")
    token = add_user(db, "ada", "approver", "ada's passphrase")
    bench = subprocess.Popen([LABCAL, "run", "--station", str(station), "--emulate", "--time-scale", "1000",
                              "--no-report", "--db", db, "--out", str(tmp_path / "run")],
                             stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             text=True, env={**os.environ, "LABCAL_STATION": "bench 6"})
    assert bench.stdin is not None
    bench.stdin.write("y\ny\ny\ny\n")  # every mount confirmed; what is left over is not an answer to a pause
    bench.stdin.flush()
    try:
        with served(db, "--silent-after", str(SILENT_AFTER_S)) as url, \
                httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=15) as api:
            def bench_in(state: str) -> dict | None:
                found = api.get("/api/stations").json()["stations"]
                return found[0] if found and found[0]["state"] == state else None

            paused = wait_for(lambda: bench_in("fault"), 120, "the bench paused on the alarm")
            assert isinstance(paused, dict) and paused["label"] == "paused on a fault"
            assert "alarm 10h (excessive position deviation)" in paused["fault"]["message"]
            assert paused["fault"]["cleared_utc"] is None and paused["done_at_utc"] is None
            with httpx.Client(base_url=url, timeout=15) as page:
                csrf = re.search(r'name="csrf" value="([^"]+)"', page.get("/login").text)
                assert csrf is not None
                page.post("/login", data={"name": "ada", "password": "ada's passphrase", "csrf": csrf[1]})
                shown = page.get("/").text
            assert '<span class="badge state-fault">paused on a fault</span>' in shown
            waited = r'Paused on a fault for <span data-since="[^"]+">[^<]+</span>: roll table'
            assert re.search(waited, shown), shown
            bench.stdin.write("a\n")  # abort at the station
            bench.stdin.flush()
            assert bench.wait(timeout=60) != 0
            stopped = wait_for(lambda: bench_in("idle"), 30, "the bench idle after the abort")
            assert isinstance(stopped, dict) and stopped["run"]["status"] == "stopped"
            assert stopped["fault"]["cleared_utc"] is None
    finally:
        ctrl_c(bench, 20)
