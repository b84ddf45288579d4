"""A station waiting for its technician says so on the lab server: the remount prompt and the pause
prompt of a real `labcal run` (no --yes: the answers typed on its stdin, as at the terminal), as the
API and the lab's overview show them, and nothing once the prompt is answered; and when the lab last
heard from it, as the journal has it."""

from __future__ import annotations

import re
import signal
import sqlite3
import subprocess

import httpx
import pytest
from cli import LABCAL
from lab_server import add_user, ctrl_c, served, wait_for

pytestmark = pytest.mark.long(seconds=20)  # a bench waiting at a prompt, seen by a server: handed out first


def _events(db: str) -> list[tuple[str, str]]:
    with sqlite3.connect(db) as conn:
        try:
            return conn.execute("SELECT kind, message FROM events ORDER BY id").fetchall()
        except sqlite3.OperationalError:  # not created yet
            return []


def _last_journaled(db: str) -> str:
    with sqlite3.connect(db) as conn:
        heard = [conn.execute(f"SELECT max(utc) FROM {t}").fetchone()[0] for t in ("points", "events")]
    return max(h for h in heard if h)


def test_a_run_waiting_at_a_prompt_says_so_until_it_is_answered(tmp_path):
    db = str(tmp_path / "lab.sqlite")
    token = add_user(db, "tom", "technician", "tom's passphrase")
    run = subprocess.Popen([LABCAL, "run", "--sim", "--no-report", "--pace", "20", "--plan", "one-mount-16",
                            "--db", db, "--out", str(tmp_path / "run")],
                           stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           text=True)
    assert run.stdin is not None
    try:
        with served(db) as url, httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"},
                                             timeout=15) as api:
            def waiting() -> dict | None:
                answer = api.get("/api/runs/1")
                return answer.json()["waiting"] if answer.status_code == 200 else None

            def typed(line: str) -> None:
                run.stdin.write(line + "\n")
                run.stdin.flush()

            at = wait_for(waiting, 60, "the remount prompt")
            assert at["text"] == "mount 1 of 1: y=0°, u=0°"
            with httpx.Client(base_url=url, timeout=15) as page:  # the technician's overview in a browser
                form = page.get("/login").text
                csrf = re.search(r'name="csrf" value="([^"]+)"', form)
                assert csrf is not None
                page.post("/login", data={"name": "tom", "password": "tom's passphrase", "csrf": csrf[1]})
                overview = page.get("/").text
                waited = r'Waiting for a person for <span data-since="[^"]+">\d+ (s|min \d\d s)</span>: '
                assert re.search(waited + "mount 1 of 1: y=0°, u=0°", overview), overview
                assert '<span class="badge state-waiting">waiting for a person</span>' in overview
                assert f"<dt>Last heard</dt><dd>{_last_journaled(db)[11:19]} UTC" in overview
            typed("n")  # not yet: the prompt stays open
            wait_for(lambda: ("answer", "mount: 'n' (not yet; the prompt stays open)") in _events(db), 30,
                     "the answer 'n'")
            assert waiting() == at
            with sqlite3.connect(db) as conn:  # another writer's event meanwhile, as the sync writes one
                conn.execute("INSERT INTO events (run_id, utc, kind, message) VALUES (1, ?, 'lab_database', "
                             "'the lab database is unreachable')", (at["utc"],))
            assert waiting() == at  # it answers nothing: the station still waits
            typed("y")
            wait_for(lambda: waiting() is None, 30, "the prompt to close")
            assert ("answer", "mount: confirmed") in _events(db)
            wait_for(lambda: api.get("/api/runs/1").json()["points_done"] >= 2, 60, "two points")
            run.send_signal(signal.SIGINT)  # once: a pause, and the pause prompt
            paused = wait_for(waiting, 30, "the pause prompt")
            assert paused["text"] == "paused: Ctrl-C"
            typed("a")  # abort: the run ends stopped, nothing waits any more
            assert run.wait(timeout=60) != 0
            ended = api.get("/api/runs/1").json()
            assert ended["waiting"] is None and ended["last_heard_utc"] == _last_journaled(db)
    finally:
        ctrl_c(run, 20)
