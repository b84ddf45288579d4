"""The lab overview in Chromium while real benches run: a bench whose process is killed (SIGKILL,
as a power cut or the OOM killer would) shows as "not heard from", without an ETA, within two
minutes; a bench at a remount prompt shows in its own state with how long it has waited, counted
from the prompt's time in the journal.

Every bench is a real `labcal run --sim --pace` process journaling into the SQLite lab database
that `labcal serve` (a process of its own) reads. The server is told a short least silence
(``--silent-after``) so that the test is quick; it polls with a bound and never sleeps on a guess."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import time
from datetime import datetime, timedelta

import pytest
from lab_server import LABCAL, accessible, add_user, ctrl_c, parses_cleanly, served, wait_for

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


@pytest.mark.slow
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
