"""The lab server as the lab runs it, for the server's tests: `labcal serve` in a process of its own
on a free port of 127.0.0.1 (it prints its URL), users added by `labcal user add`, simulated runs by
`labcal run --sim` (paced: `--pace`), each a real process writing the same lab database."""

from __future__ import annotations

import io
import json
import re
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

import pytest
from cli import LABCAL


def add_user(db: str, name: str, role: str, password: str) -> str:
    """Add a user through the command line (in this process: a labcal process takes seconds to start
    on a loaded machine), the password in $LABCAL_PASSWORD; their API token."""
    from labcal.cli import main

    printed = io.StringIO()
    with redirect_stdout(printed), pytest.MonkeyPatch.context() as env:
        env.setenv("LABCAL_PASSWORD", password)
        assert main(["user", "add", name, "--role", role, "--db", db, "--json"]) == 0
    return json.loads(printed.getvalue())["token"]


def ctrl_c(process: subprocess.Popen, timeout_s: float) -> None:
    """Stop a labcal process as a user would (Ctrl-C; nothing if it has ended), killed if it has not
    ended within ``timeout_s``."""
    process.send_signal(signal.SIGINT)  # nothing once it has ended (Popen knows)
    try:
        process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()


@contextmanager
def served(db: str, *extra: str) -> Iterator[str]:
    """`labcal serve --port 0` on ``db``; yields its URL, stops it (Ctrl-C) at the end."""
    with serving(db, *extra) as (url, _):
        yield url


@contextmanager
def serving(db: str, *extra: str, files: int | None = None, log: Path | None = None
            ) -> Iterator[tuple[str, subprocess.Popen]]:
    """`labcal serve --port 0` on ``db``: its URL and its process. ``files``: the process's open-file
    limit (soft and hard), as on a machine that allows no more; ``log``: a file for its stderr."""
    def limited() -> None:
        if files is not None:
            import resource

            resource.setrlimit(resource.RLIMIT_NOFILE, (files, files))

    stderr = open(log, "w") if log is not None else subprocess.PIPE  # noqa: SIM115 (closed below)
    server = subprocess.Popen([LABCAL, "serve", "--port", "0", "--db", db, "--poll", "0.2", *extra],
                              stdout=subprocess.PIPE, stderr=stderr, text=True, preexec_fn=limited)
    try:
        assert server.stdout is not None
        line = server.stdout.readline()
        found = re.search(r"https?://127\.0\.0\.1:\d+", line)
        assert found, f"labcal serve printed {line!r}; stderr: {server.stderr and server.stderr.read()}"
        yield found[0], server
    finally:
        ctrl_c(server, 15)
        if log is not None:
            stderr.close()  # type: ignore[union-attr]


@contextmanager
def paced_run(db: str, out: Path, pace: float, plan: str = "one-mount-16", serial: str = "ACC-0107"
              ) -> Iterator[subprocess.Popen]:
    """A simulated run at ``pace`` × real time, journaling into ``db`` while the test watches."""
    run = subprocess.Popen([LABCAL, "run", "--sim", "--yes", "--no-report", "--pace", str(pace),
                            "--plan", plan, "--serial", serial, "--db", db, "--out", str(out)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        yield run
    finally:
        ctrl_c(run, 20)


WCAG = {"runOnly": {"type": "tag", "values": ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa"]},
        "resultTypes": ["violations"]}


def parses_cleanly(text: str, where: str) -> None:
    """The HTML as the server sent it, parsed by html5lib in strict mode: the WHATWG parsing
    algorithm reports no parse error (unclosed or misnested elements, bad attributes, stray text);
    content rules such as unique ids are axe-core's to check."""
    import html5lib

    try:
        html5lib.HTMLParser(strict=True).parse(text)
    except html5lib.html5parser.ParseError as exc:
        raise AssertionError(f"{where}: an HTML parse error ({exc})") from None


def accessible(page, where: str) -> None:
    """No WCAG 2.1 A or AA violation that axe-core finds in the page as the browser shows it."""
    from axe_playwright_python.sync_playwright import Axe

    results = Axe().run(page, options=WCAG)
    assert results.violations_count == 0, f"{where}:\n{results.generate_report()}"


def wait_for(condition: Callable[[], object], timeout_s: float, what: str, every_s: float = 0.2) -> object:
    """Poll ``condition`` until it is truthy (returned) or ``timeout_s`` passes (fails, saying what)."""
    deadline = time.monotonic() + timeout_s
    while True:
        found = condition()
        if found:
            return found
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {timeout_s:g} s for {what}")
        time.sleep(every_s)
