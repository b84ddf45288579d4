"""Screenshots of the lab server's pages during a live run: docs/screenshots/lab.png and run.png.

    .venv/bin/python tools/screenshots.py [--out docs/screenshots]

Everything is real and local: a lab database in a temporary folder, a finished simulated run, a
paced one in progress (`labcal run --sim --pace`), one waiting at its first remount prompt (no
--yes: nobody answers it) and one killed (SIGKILL) after a few points, shown as not heard from
(`labcal serve --silent-after 10`), `labcal serve` on a free port of 127.0.0.1, and
Debian's Chromium driven by Playwright, signed in through the login form as an approver. Needs the
test extra (`pip install -e '.[test]'`) and `apt-get install chromium`.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LABCAL = str(Path(sys.executable).with_name("labcal"))
PASSWORD = "screenshot-only passphrase"


def labcal(*args: str, station: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([LABCAL, *args], check=True, capture_output=True, text=True, timeout=300,
                          env=at(station))


def at(station: str | None) -> dict[str, str]:
    """The environment of a labcal started at ``station`` (its name in the lab database)."""
    return {**os.environ, **({"LABCAL_STATION": station} if station else {})}


def points_of(db: str, station: str, at_least: int, within_s: float) -> int:
    """Wait (bounded) until the station's runs have journaled ``at_least`` points; how many they have."""
    deadline = time.monotonic() + within_s
    while True:
        try:
            with sqlite3.connect(db) as conn:
                found = conn.execute("SELECT count(*) FROM points p JOIN runs r ON r.id = p.run_id "
                                     "WHERE r.station = ?", (station,)).fetchone()[0]
        except sqlite3.OperationalError:
            found = 0
        if found >= at_least or time.monotonic() > deadline:
            return int(found)
        time.sleep(0.2)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "screenshots"))
    parser.add_argument("--pace", type=float, default=12.0, help="the live run's pace (rig × wall time)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("Chromium is not installed: apt-get install chromium")
    with tempfile.TemporaryDirectory(prefix="labcal-shots-") as tmp:
        base = Path(tmp)
        db = str(base / "lab.sqlite")
        labcal("run", "--sim", "--yes", "--no-report", "--seed", "3", "--serial", "ACC-0042",
               "--operator", "J. Doe", "--plan", "one-mount-16", "--db", db, "--out", str(base / "done"),
               station="bench 1 (east)")
        labcal("user", "add", "A. Metrologist", "--role", "approver", "--password", PASSWORD, "--db", db)
        live = subprocess.Popen([LABCAL, "run", "--sim", "--yes", "--no-report", "--pace", str(args.pace),
                                 "--serial", "ACC-0107", "--operator", "R. Tech", "--db", db,
                                 "--out", str(base / "live")],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                env=at("bench 2 (west)"))
        points_of(db, "bench 2 (west)", at_least=1, within_s=120)  # run 2 is the live one (run.png)
        killed = subprocess.Popen([LABCAL, "run", "--sim", "--yes", "--no-report", "--pace", str(args.pace),
                                   "--serial", "ACC-0310", "--operator", "J. Doe", "--db", db,
                                   "--out", str(base / "killed")], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, env=at("bench 4 (annex)"))
        points_of(db, "bench 4 (annex)", at_least=5, within_s=120)
        killed.send_signal(signal.SIGKILL)  # its run stays "running" in the journal: only silence tells
        waiting = subprocess.Popen([LABCAL, "run", "--sim", "--no-report", "--pace", str(args.pace),
                                    "--serial", "ACC-0211", "--operator", "M. Ops", "--db", db,
                                    "--out", str(base / "waiting")], stdin=subprocess.PIPE,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   env=at("bench 3 (mezzanine)"))
        server = subprocess.Popen([LABCAL, "serve", "--port", "0", "--db", db, "--silent-after", "10"],
                                  stdout=subprocess.PIPE, text=True,
                                  env={**os.environ, "TZ": "Europe/Berlin"})  # a lab's local time beside UTC
        try:
            assert server.stdout is not None
            url = re.search(r"http://[\d.]+:\d+", server.stdout.readline())
            assert url is not None, "labcal serve printed no URL"
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium, args=["--headless", "--no-sandbox"])
                page = browser.new_page(viewport={"width": 1200, "height": 820})
                page.goto(url[0] + "/login")
                page.fill("input[name=name]", "A. Metrologist")
                page.fill("input[name=password]", PASSWORD)
                page.click("button[type=submit]")
                page.wait_for_url(url[0] + "/")
                points_of(db, "bench 2 (west)", at_least=6, within_s=120)  # some points and journal lines
                page.wait_for_timeout(12_000)  # the killed bench silent past --silent-after
                page.reload()
                page.screenshot(path=str(out / "lab.png"), full_page=True)
                page.goto(url[0] + "/runs/2")
                page.wait_for_timeout(4000)  # the live count has moved on since the page came
                page.screenshot(path=str(out / "run.png"), full_page=True)
                browser.close()
        finally:
            for process in (server, live, waiting, killed):
                process.terminate()
                process.wait(timeout=30)
    print(f"{out / 'lab.png'}\n{out / 'run.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
