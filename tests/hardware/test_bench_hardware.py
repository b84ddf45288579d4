"""The real bench, when there is one: skipped unless ``LABCAL_HARDWARE_STATION`` names a station
file. Run it when bringing up a new bench (README, "Bringing up a new bench"), with the instrument
unmounted or the plate clear to turn: each table moves 1° and back, and once a few degrees before
being stopped. Nothing here is emulated; every check is what the devices themselves report.

    LABCAL_HARDWARE_STATION=my-bench.toml python -m pytest tests/hardware -v -s
"""

from __future__ import annotations

import os
import time

import pytest

from labcal.bench.hardware import Bench
from labcal.config.station import load_station
from labcal.drivers.axis import wrapped

STATION = os.environ.get("LABCAL_HARDWARE_STATION")
pytestmark = pytest.mark.skipif(not STATION, reason="no bench: set LABCAL_HARDWARE_STATION=STATION.toml")
STEP_DEG = 1.0
STOP_RUN_DEG = 20.0  # long enough at the station's speed that a stop lands mid-move


@pytest.fixture(scope="module")
def bench():
    config, _ = load_station(STATION)
    with Bench(config) as bench:
        yield bench


def test_every_device_identifies_itself(bench):
    bench.prepare(say=print)  # homes a table that is not referenced, enables it, configures the DMM
    print(bench.identities)
    assert set(bench.identities) == {"pitch", "roll", "dmm"}
    assert all(identity.identity for identity in bench.identities.values())


def test_status_and_one_scan(bench):
    reports = bench.check()
    for report in reports:
        print(report)
    assert [r["problem"] for r in reports] == [None, None, None]
    assert len(reports[2]["volts"]) == 3


@pytest.mark.parametrize("table", ["pitch", "roll"])
def test_one_degree_and_back(bench, table):
    axis = getattr(bench, table)
    start = axis.position()
    timeout_s = bench.config.sequencer.move_timeout_s
    for target in (start + STEP_DEG, start):
        axis.move_to(target % 360.0)
        here = axis.wait_in_position(timeout_s)
        assert abs(wrapped(here - target)) * 3600 <= getattr(bench.config, table).in_position_arcsec


@pytest.mark.parametrize("table", ["pitch", "roll"])
def test_a_stop_during_a_move(bench, table):
    axis = getattr(bench, table)
    settings = getattr(bench.config, table)
    start = axis.position()
    axis.move_to((start + STOP_RUN_DEG) % 360.0)
    time.sleep(min(0.5, STOP_RUN_DEG / settings.speed_dps / 4))
    assert axis.status().moving, "the table finished before the stop: lower its speed_dps for this test"
    axis.stop()
    deadline = time.monotonic() + bench.config.sequencer.move_timeout_s
    while axis.status().moving:
        assert time.monotonic() < deadline, "still moving after the stop"
        time.sleep(settings.poll_s)
    stopped = axis.position()
    assert 0 < wrapped(stopped - start) < STOP_RUN_DEG  # stopped part way
    axis.move_to(start)  # and it moves again (an AZ STOP input was released)
    axis.wait_in_position(bench.config.sequencer.move_timeout_s)
