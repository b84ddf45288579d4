"""Every page of the lab server checked by two tools we did not write: its HTML as the server sends
it parsed by html5lib in strict mode (the WHATWG parsing algorithm: a parse error fails), and the
page as Chromium shows it checked by axe-core (Deque's accessibility engine, WCAG 2.1 A and AA
rules, unique ids among them): no violation.

The pages: the sign-in form, the lab's overview with a finished, a stopped and a running
station (each status in its colours), the overview again after it has updated itself in place, a
finished run (its residual plot; a dry run has no approval form), a running run (updating live), a
run that does not exist (the error page) and the audit trail."""

from __future__ import annotations

import sqlite3
from datetime import UTC, datetime, timedelta

import pytest
from lab_server import accessible, add_user, ctrl_c, paced_run, parses_cleanly, served, wait_for

from labcal.cli import main

pytestmark = pytest.mark.long(seconds=45)  # a server and a browser over every page: handed out first


def _points(db: str, run_id: int) -> int:
    with sqlite3.connect(db) as conn:
        return conn.execute("SELECT count(*) FROM points WHERE run_id = ?", (run_id,)).fetchone()[0]


def test_every_page_parses_cleanly_and_has_no_accessibility_violation(browser, tmp_path):
    db = str(tmp_path / "lab.sqlite")
    add_user(db, "ada", "approver", "ada's passphrase")
    assert main(["run", "--sim", "--yes", "--plan", "one-mount-16", "--serial", "ACC-0107", "--db", db,
                 "--out", str(tmp_path / "finished")]) == 0
    with paced_run(db, tmp_path / "stopped", 20.0, "one-mount-16", "ACC-0108") as stopped:
        wait_for(lambda: _points(db, 2) >= 1, 30, "the second run's first point")
        ctrl_c(stopped, 20)
    with served(db) as url, paced_run(db, tmp_path / "running", 20.0, "four-mount-64", "ACC-0109"):
        def sign_in(page) -> None:
            page.goto(url + "/login")
            page.fill("input[name=name]", "ada")
            page.fill("input[name=password]", "ada's passphrase")
            page.click("button[type=submit]")
            page.wait_for_url(url + "/")

        page = browser.new_page()
        try:
            def check(path: str, status: int = 200) -> None:
                response = page.goto(url + path)
                assert response is not None and response.status == status, (path, response)
                parses_cleanly(response.text(), path)
                accessible(page, path)

            check("/login")
            sign_in(page)
            wait_for(lambda: _points(db, 3) >= 1, 30, "the running station's first point")
            check("/")
            badges = {page.text_content(f"table.runs tr:has(a[href='/runs/{n}']) .badge") for n in (1, 2, 3)}
            assert badges == {"complete", "stopped", "running"}  # Ctrl-C stops a run
            check("/runs/1")  # finished: its residual plot
            assert page.is_visible("img.plot")
            check("/runs/3")  # running: the count, the mount, the next remount, updated in place
            shown = int(page.text_content("#done") or "-1")
            wait_for(lambda: _points(db, 3) > shown, 30, "another point of the running station")
            page.wait_for_function("n => Number(document.getElementById('done').textContent) > n",
                                   arg=shown, timeout=20_000)
            accessible(page, "/runs/3 after updates")
            check("/runs/99", 404)
            check("/audit")  # the approver's audit trail: the sign-in above is its newest row
        finally:
            page.close()

        page = browser.new_page()  # the overview updating itself, on a clock the test moves
        try:
            page.clock.install()
            sign_in(page)
            page.clock.pause_at(datetime.now(UTC) + timedelta(seconds=1))  # no update until run_for
            card = "a.card[href='/runs/3']"
            before = int(page.text_content(f"{card} .count span") or "-1")
            page.evaluate("window.notReloaded = true")
            page.focus(card)
            wait_for(lambda: _points(db, 3) > before, 30, "another point of the running station")
            page.clock.run_for(16_000)
            page.wait_for_function("([sel, n]) => Number(document.querySelector(sel).textContent) > n",
                                   arg=[f"{card} .count span", before], timeout=20_000)
            assert page.evaluate("window.notReloaded") is True  # updated in place, not reloaded
            assert page.evaluate("document.activeElement.getAttribute('href')") == "/runs/3"  # focus kept
            page.clock.resume()  # axe-core waits on timers of its own; the next update is 14 s away
            accessible(page, "/ after it updated itself")
        finally:
            page.close()
