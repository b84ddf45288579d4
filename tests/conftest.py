"""Shared helpers for the tests."""

from __future__ import annotations

import gc
import os

import numpy as np
import pytest

from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import Misalignment
from labcal.analysis.plan import Plan
from labcal.config.emulation import InstrumentTruth
from labcal.sim.direct import simulate_readings


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """`-n auto`: two workers per core (at most 16). Much of the suite waits rather than computes:
    tables moved in real time because the timing is the subject (a stop's latency, a reply's
    timeout), servers and a browser answering, a bench killed and watched. One worker per core left
    the cores idle in those waits: tests/drivers and tests/run took 287 s with 2 workers on 2 cores
    and 204-226 s with 4, on the same loaded machine."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return min(2 * cores, 16)


def pytest_collection_finish(session: pytest.Session) -> None:
    """The collected modules, pytest's and the libraries they imported live as long as the worker:
    frozen (`gc.freeze`), a full collection no longer walks them: there are some 320 000 of them once
    the suite is collected, and a full collection of them took 0.2 s."""
    gc.freeze()


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Longest first. pytest-xdist hands out files (the ordinary suite, `--dist loadfile`) or tests
    and groups (CI's slow step, `--dist loadgroup`) in this order (`--no-loadscope-reorder`,
    pyproject.toml), and a long one handed out last runs alone at the end while the other workers
    idle: the browser's 44 s page test, a one-test file, was handed out last by pytest-xdist's own
    order (most tests first), and the ordinary suite's workers finished at 272, 277, 299 and 319 s.
    A file with a test marked `slow(seconds=N)` or `long(seconds=N)` (its time on two cores, module
    fixture included) goes ahead of the rest, longest first; then files with more tests first, as
    pytest-xdist ordered them. The sort is stable: a file stays in one piece, and files alike keep
    pytest-randomly's order."""
    def marked_seconds(item: pytest.Item) -> float:
        return max((float(mark.kwargs.get("seconds", 0)) for name in ("slow", "long")
                    for mark in item.iter_markers(name)), default=0.0)

    file_of = {item.nodeid: item.nodeid.split("::")[0] for item in items}
    seconds: dict[str, float] = {}
    tests: dict[str, int] = {}
    for item in items:
        file = file_of[item.nodeid]
        seconds[file] = max(seconds.get(file, 0.0), marked_seconds(item))
        tests[file] = tests.get(file, 0) + 1
    items.sort(key=lambda item: (-seconds[file_of[item.nodeid]], -tests[file_of[item.nodeid]]))


@pytest.fixture(scope="session", autouse=True)
def neutral_folder(tmp_path_factory):
    """Module and session fixtures (which start before `lab_database` below) work in a folder of
    their own too: a `python -m labcal.cli` they start from the checkout would import the source
    tree's labcal/ rather than the installed one."""
    if "MUTANT_UNDER_TEST" in os.environ:  # mutmut reads its configuration from the checkout
        yield
        return
    before = os.getcwd()
    os.chdir(tmp_path_factory.mktemp("cwd"))
    try:
        yield
    finally:
        os.chdir(before)


@pytest.fixture(autouse=True)
def lab_database(tmp_path, monkeypatch):
    """Every test (and every labcal it starts) journals into its own database, never runs/."""
    monkeypatch.setenv("LABCAL_DB", str(tmp_path / "labcal.sqlite"))
    monkeypatch.setenv("LABCAL_JOURNAL", str(tmp_path / "journal.sqlite"))  # with a lab server: the station's
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "runtime"))  # its station locks are the test's own
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))  # never the developer's own lab file
    monkeypatch.setenv("XDG_CONFIG_DIRS", str(tmp_path / "site-config"))
    monkeypatch.delenv("LABCAL_CONFIG", raising=False)
    monkeypatch.delenv("LABCAL_NOTIFY", raising=False)  # nor the developer's notifications
    monkeypatch.delenv("LABCAL_STATION", raising=False)  # the computer's name, unless a test names one
    # and works in its own folder: a run's default runs/ lands there, and `python -m labcal.cli` finds
    # the installed labcal, not the source tree's labcal/ (which lacks drivers/ and sim/) beside it.
    # Not under mutation testing (tools/mutation.py): mutmut's trampoline reads its configuration
    # from the current folder, and there the tree is laid out as installed anyway.
    if "MUTANT_UNDER_TEST" not in os.environ:
        monkeypatch.chdir(tmp_path)
    return tmp_path / "labcal.sqlite"


@pytest.fixture(autouse=True)
def terminal(monkeypatch):
    """Every test sees one terminal, 80 × 25 and colourless, whatever the developer's, CI's or a
    pipe's: labcal run in-process prints through consoles that may have been made by an earlier
    test (their width is set here), and a labcal started as a subprocess inherits COLUMNS/LINES.
    A test that needs another terminal sets it through this fixture's ``set`` (or a pty of its own)."""
    from labcal.commands import common

    for name in ("FORCE_COLOR", "NO_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE", "JUPYTER_COLUMNS",
                 "JUPYTER_LINES"):
        monkeypatch.delenv(name, raising=False)

    def set_size(columns: int, lines: int = 25) -> None:
        monkeypatch.setenv("COLUMNS", str(columns))
        monkeypatch.setenv("LINES", str(lines))
        for console in (common.out, common.err):
            if not isinstance(console, common._LazyConsole):  # already made: it read COLUMNS then
                console.size = (columns, lines)

    set_size(80)
    return set_size


SOTO_POINTS = [(p, r) for p in (0, 90, 180, 270) for r in (0, 90, 180, 270)]  # Soto Table 2
FOUR_MOUNTS = [(0, 0), (180, 0), (0, 180), (180, 180)]  # Soto Table 3


def soto_plan(mounts: list[tuple[int, int]]) -> Plan:
    return Plan(name="test", mounts=mounts, points=SOTO_POINTS)


def ideal_fit(mounts: list[tuple[int, int]], mis: Misalignment) -> np.ndarray:
    """X fitted to noise-free readings of an ideal instrument (B = 0, S = I) on a misaligned CD."""
    readings = simulate_readings(soto_plan(mounts), InstrumentTruth(), mis)
    return fit_readings(readings).coefficients


def quiet_console():
    import io

    from rich.console import Console

    return Console(file=io.StringIO())


def run_on_rig(rig, plan_name: str, tmp_path, settings=None, events=None, operator=None):
    """A whole calibration of a shipped plan on a SimRig, journaled under tmp_path."""
    from labcal.config.plans import load_plan
    from labcal.config.settings import SequencerSettings
    from labcal.run.operator import AutoOperator
    from labcal.run.runner import calibrate
    from labcal.store.journal import Journal

    plan, text = load_plan(plan_name)
    run_dir = tmp_path / "run"
    run_dir.mkdir(exist_ok=True)
    with Journal(tmp_path / "journal.sqlite") as journal:
        operator = operator or AutoOperator(quiet_console())
        return calibrate(plan, text, rig.station(), "simulated rig", operator,
                         settings or SequencerSettings(), run_dir, journal, events)


pytest_plugins = ["services"]  # postgres_cluster, postgres_url, browser: tests/services.py
