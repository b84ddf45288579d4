"""The servers some tests need: a private PostgreSQL cluster and the system's Chromium.

Both come from Debian's packages (`postgresql`, `chromium`), never from a download at test time.
On a developer's machine without them the tests that need them skip, with a line saying what to
install; CI sets ``LABCAL_TEST_SERVICES=required`` (`.ci/run`), where a missing one fails instead,
so CI never skips them.

The cluster is per pytest worker (xdist): initdb into a private folder, listening on 127.0.0.1 at a
free port and on a socket in that folder, trust authentication for its one user, stopped at the end.
initdb refuses to run as root, so as root the folder belongs to the ``postgres`` user and the
server runs as that user (``runuser``). Each test gets a database of its own (`postgres_url`).
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

REQUIRED = os.environ.get("LABCAL_TEST_SERVICES") == "required"
PG_USER = "labcal"


def missing(what: str, how: str) -> None:
    """Skip (a developer's machine) or fail (CI) for a service that is not installed."""
    message = f"{what} is not installed: {how}"
    if REQUIRED:
        pytest.fail(message)
    pytest.skip(message)


_GIVEN: set[int] = set()  # the ports this process has handed out


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now and that this process has not handed out
    before. The system may offer a port it has just freed again: two calls for one station file once
    gave its DMM and its tables the same port, a file labcal refuses."""
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _GIVEN:
            _GIVEN.add(port)
            return port


def _pg_bin(name: str) -> str | None:
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    return found[-1] if found else shutil.which(name)


class Cluster:
    """A running private PostgreSQL server; `url` names a fresh database in it."""

    def __init__(self) -> None:
        initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
        if not initdb or not pg_ctl:
            missing("PostgreSQL", "apt-get install postgresql (Debian), or skip these tests")
        assert initdb and pg_ctl
        self.pg_ctl = pg_ctl
        self.as_user: list[str] = []
        self.folder = Path(tempfile.mkdtemp(prefix="labcal-pg-"))
        if os.geteuid() == 0:
            self.as_user = ["runuser", "-u", "postgres", "--"]
            os.chmod(self.folder, 0o755)
            shutil.chown(self.folder, "postgres", "postgres")
        self.data = self.folder / "data"
        self.port = free_port()
        self._run([initdb, "-D", str(self.data), "-U", PG_USER, "-A", "trust", "-E", "UTF8", "--no-sync"])
        options = f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.folder} -c fsync=off"
        self._run([pg_ctl, "-D", str(self.data), "-o", options, "-l", str(self.folder / "log"), "-w",
                   "-t", "60", "start"])

    def _run(self, command: list[str]) -> None:
        done = subprocess.run(self.as_user + command, capture_output=True, text=True, timeout=120)
        if done.returncode:
            raise RuntimeError(f"{command[0]} failed: {done.stderr.strip() or done.stdout.strip()}")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{PG_USER}@127.0.0.1:{self.port}/{database}"

    def create_database(self) -> str:
        import psycopg

        name = "t_" + uuid.uuid4().hex[:12]
        with psycopg.connect(f"host=127.0.0.1 port={self.port} user={PG_USER} dbname=postgres",
                             autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return name

    def stop(self) -> None:
        """Stop the server (fast: its connections are cut) and remove its folder."""
        subprocess.run(self.as_user + [self.pg_ctl, "-D", str(self.data), "-m", "fast", "-w", "stop"],
                       capture_output=True, timeout=60)
        shutil.rmtree(self.folder, ignore_errors=True)

    def start(self) -> None:
        """Start it again after `pause` (the outage tests)."""
        options = f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.folder} -c fsync=off"
        self._run([self.pg_ctl, "-D", str(self.data), "-o", options, "-l", str(self.folder / "log"),
                   "-w", "-t", "60", "start"])

    def pause(self) -> None:
        """Stop the server but keep its data: the lab's database server goes away."""
        self._run([self.pg_ctl, "-D", str(self.data), "-m", "fast", "-w", "stop"])


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[Cluster]:
    try:
        import psycopg  # noqa: F401
    except ImportError:
        missing("psycopg", "pip install 'psycopg[binary]'")
    cluster = Cluster()
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def postgres_url(postgres_cluster: Cluster) -> str:
    """A new, empty PostgreSQL database of its own for this test, as a `LABCAL_DB` URL."""
    return postgres_cluster.url(postgres_cluster.create_database())


CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="session")
def browser():
    """Debian's Chromium, driven by Playwright (its own browser download cannot work here)."""
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if not executable:
        missing("Chromium", "apt-get install chromium (Debian)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing("Playwright", "pip install playwright")
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=executable, args=CHROMIUM_FLAGS)
        try:
            yield chromium
        finally:
            chromium.close()
