"""Shared by the driver, emulator and station tests: example stations made private to one test,
emulators that are always stopped, and a check that nothing is left running."""

from __future__ import annotations

import os
import re
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from services import free_port

from labcal.bench.hardware import Bench
from labcal.config.station import StationFile, load_station, shipped_stations
from labcal.sim.emulation import Emulation

TIME_SCALE = 1000.0  # the default test time scale: a 30-minute calibration takes ~2 s of emulated motion
MOTION_SCALE = 20.0  # slow enough to catch a table mid-move: a 90° move lasts 250 ms of wall time


def private(config: StationFile, tmp_path: Path, **changes: dict) -> StationFile:
    """The station with free TCP ports and its ptys under ``tmp_path``, so that tests never meet
    (devices that shared a port still do); ``changes`` per device (e.g. ``pitch={"timeout_s":
    0.1}``) override any link setting."""
    ports: dict[str, int] = {}
    updates = {}
    for name, link in config.devices().items():
        change = dict(changes.get(name, {}))
        if link.tcp or str(link.port).startswith("socket://"):
            port = ports.setdefault(link.bus, free_port())  # on port 0, the bus names the driver
            change.setdefault(*(("tcp", f"127.0.0.1:{port}") if link.tcp else ("port", f"socket://127.0.0.1:{port}")))
        else:  # a pty path, or pty:NAME
            change.setdefault("port", str(tmp_path / Path(str(link.port).removeprefix("pty:")).name))
        updates[name] = link.model_copy(update=change)
    return config.model_copy(update=updates)


def private_file(station: str, tmp_path: Path, extra: str = "", link: str = "") -> Path:
    """A shipped example station rewritten for one test (its ptys under ``tmp_path``, free TCP
    ports), ``link`` settings added to every device (e.g. ``timeout_s = 0.1``) and ``extra`` TOML
    (e.g. ``[[emulation.faults]]`` tables) appended; returns the file."""
    text = shipped_stations()[station].read_text(encoding="utf-8").replace("/tmp/labcal-sim/", f"{tmp_path}/")
    text = text.replace('"pty:', f'"{tmp_path}/')  # an emulator's own pty: here, at a fixed path
    for device in ("[pitch]", "[roll]", "[dmm]"):
        text = text.replace(f"{device}\n", f"{device}\n{link}\n" if link else f"{device}\n")
    # the example's port → a free one; devices that shared a port still do, and on port 0 (any free
    # one) the devices of one driver do, as the emulators have them
    ports: dict[tuple[str, str], int] = {}
    sections = re.split(r"(?m)^(?=\[)", text)
    for i, section in enumerate(sections):
        driver = m[1] if (m := re.search(r'(?m)^driver = "([^"]+)"', section)) else ""
        sections[i] = re.sub(r"127\.0\.0\.1:(\d+)", lambda m, driver=driver: "127.0.0.1:" + str(
            ports.setdefault((m[1], driver if m[1] == "0" else ""), free_port())), section)
    text = "".join(sections)
    path = tmp_path / f"{station}.toml"
    path.write_text(text + extra, encoding="utf-8")
    return path


@contextmanager
def emulated(station: str | StationFile, tmp_path: Path, time_scale: float = TIME_SCALE,
             **changes: dict) -> Iterator[tuple[Emulation, Bench]]:
    """Emulators for a (private copy of a) station, and the real drivers talking to them."""
    config = load_station(station)[0] if isinstance(station, str) else station
    with Emulation(private(config, tmp_path, **changes), time_scale=time_scale) as emulation, \
            Bench(emulation.station_config, emulation.rig.clock) as bench:
        yield emulation, bench


def bench_fixtures(stations: list[str], **changes: dict):
    """Three fixtures for a module's tests: ``station`` (each of ``stations`` in turn), and the
    emulators with the drivers on them, at the test time scale and slow enough to catch a table
    moving. Use: ``station, rig, slow_rig = bench_fixtures([...], pitch=QUICK)``."""
    @pytest.fixture(params=stations)
    def station(request):
        return request.param

    def at(time_scale: float):
        @pytest.fixture
        def emulators_and_drivers(station, tmp_path, no_leaks):
            with emulated(station, tmp_path, time_scale, **changes) as pair:
                yield pair
        return emulators_and_drivers

    return station, at(TIME_SCALE), at(MOTION_SCALE)


def until_still(axis, within_s: float = 30.0) -> None:
    """Wait until the controller says the table no longer moves: a stop decelerates first."""
    deadline = time.monotonic() + within_s
    while axis.status().moving:
        assert time.monotonic() < deadline, f"{axis.name} still moving {within_s:g} s after its stop"
        time.sleep(0.005)


def _ptys() -> set[str]:
    found = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("/dev/pts/") or target == "/dev/ptmx":
            found.add(f"{fd}->{target}")
    return found


def _apprise_pool_threads() -> set[threading.Thread]:
    """The workers of apprise's process-wide pools. apprise 2.x makes one pool per process on its first
    notification and keeps it, idle, for every later one (apprise/apprise.py, get_shared_executor and
    get_coordinator_executor); which test sends the first notification depends on the random test
    order, so its idle workers are not a leak of that test (CI once failed on exactly that)."""
    core = sys.modules.get("apprise.apprise")
    pools = [getattr(core, name, None) for name in ("_shared_executor", "_coordinator_executor")]
    return {thread for pool in pools if pool is not None for thread in getattr(pool, "_threads", ())}


@pytest.fixture
def no_leaks():
    """Fails the test if it leaves a thread or a pty open behind it."""
    threads, ptys = set(threading.enumerate()), _ptys()
    yield
    # Every thread is told to stop when its context ends; on a loaded CI machine one took longer than
    # 5 s to notice once (which one was not said then: the message names them now). A leak never ends.
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and (set(threading.enumerate()) - threads - _apprise_pool_threads()
                                           or _ptys() - ptys):
        time.sleep(0.05)
    left = set(threading.enumerate()) - threads - _apprise_pool_threads()
    assert not left, f"threads left running: {', '.join(sorted(t.name for t in left))}"
    assert not _ptys() - ptys, "ptys left open"
