"""Defects the vendor-document emulators showed in the AZ driver and the Modbus link,
each against the emulator written from the manuals: a STOP input left on, busy devices and
gateways, the RTU silent interval, and why a port does not open."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest
from cli import cli
from emulators import bench_fixtures, emulated, no_leaks, private_file  # noqa: F401 - fixture

from labcal.bench.hardware import Bench
from labcal.config.emulation import FaultKind
from labcal.config.station import load_station
from labcal.drivers.errors import DeviceFault, LinkLost, Rejected
from labcal.drivers.modbus import ModbusLink
from labcal.sim.emulation import Emulation
from labcal.sim.faults import Fault

QUICK = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}
STOP_BIT = 1 << 5  # driver input command bit 5 (HM-60262E; hardware_protocols.md §2.1)
STOP_WRITE = "fc06 007D"  # how the emulator describes an FC 06 write to 007Dh

station, az, az_slow = bench_fixtures(["az-modbus-tcp", "az-modbus-rtu"], pitch=QUICK, roll=QUICK)
# For tests where every reply is an answer (exceptions included) and none is meant to be lost: a
# reply late by more than QUICK's 0.1 s on a loaded machine would otherwise use up a retry.
PATIENT = {**QUICK, "timeout_s": 1.0}
_, az_patient, _ = bench_fixtures(["az-modbus-tcp", "az-modbus-rtu"], pitch=PATIENT, roll=PATIENT)


def test_a_lost_stop_release_is_repeated_until_the_drive_reports_it_off(az_slow):
    """Three release writes lost on the way (more than the link's own retries): the driver reads
    the input back and releases again, so the table moves afterwards."""
    emulation, bench = az_slow
    pitch, table = bench.pitch, emulation.rig.axis("pitch")
    pitch.move_to(170)
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match=STOP_WRITE, after=1, count=3))
    pitch.stop()
    assert emulation.faults["pitch"].count(FaultKind.LOST_REQUEST) == 3
    assert not pitch.stop_input_on()
    now = emulation.rig.clock.now()
    assert 0 < float(table.angle_at(now)) < 169  # it stopped mid-move ...
    pitch.move_to(90)
    assert pitch.wait_in_position(60) == pytest.approx(90.0)  # ... and moves again


def test_a_stop_release_that_never_lands_says_so(az):
    emulation, bench = az
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match=STOP_WRITE, after=1, count=100))
    with pytest.raises(DeviceFault, match="pitch table .*STOP input may still be on after 5 attempts"):
        bench.pitch.stop()


def test_a_stop_input_found_on_at_start_is_one_line_and_check_releases_it(az):
    emulation, bench = az
    bench.pitch.link.write_one(bench.pitch.unit, 0x007D, STOP_BIT)  # as a lost release leaves it
    with pytest.raises(DeviceFault, match="pitch table .*STOP input is on .*--reset-alarms"):
        bench.pitch.prepare()
    report = bench.check(reset_alarms=True)[0]
    assert report["stop_released"] and report["problem"] is None
    bench.pitch.prepare()
    bench.pitch.move_to(10)
    assert bench.pitch.wait_in_position(60) == pytest.approx(10.0)


def test_the_emulated_drive_starts_nothing_while_stop_is_on(az):
    """The emulator, from the manual: STOP on inhibits operation and READY is off meanwhile."""
    emulation, bench = az
    bench.pitch.link.write_one(bench.pitch.unit, 0x007D, STOP_BIT)
    assert not bench.pitch.status().ready
    bench.pitch._go(45.0)  # the DDO write is acknowledged ...
    assert emulation.rig.axis("pitch").travel_deg == 0.0  # ... and nothing moves


@pytest.mark.parametrize("code", [0x06, 0x0A, 0x0B])
def test_busy_and_gateway_exceptions_are_retried_like_a_lost_reply(az_patient, code):
    emulation, bench = az_patient
    emulation.faults["pitch"].add(Fault(FaultKind.EXCEPTION, code=code, count=2))
    assert bench.pitch.angle() == 0.0
    assert emulation.faults["pitch"].count(FaultKind.EXCEPTION) == 2


def test_a_busy_device_that_stays_busy_is_one_line(az_patient):
    emulation, bench = az_patient
    emulation.faults["pitch"].add(Fault(FaultKind.EXCEPTION, code=0x06, count=3))
    with pytest.raises(Rejected, match="exception 06h \\(slave device busy\\).*stayed busy"):
        bench.pitch.angle()


def test_requests_keep_the_rtu_silent_interval(tmp_path, no_leaks):  # noqa: F811
    """Modbus over Serial Line V1.02 §2.5.1.1: at least t3.5 (1.75 ms above 19200 Bd) of silence
    before every frame. Measured by the emulator (our reply leaving → the next request arriving),
    so the driver's own clock is not the judge; a frame inside t3.5 is dropped there."""
    with emulated("az-modbus-rtu", tmp_path, pitch=QUICK, roll=QUICK) as (emulation, bench):
        server = next(s for names, _, s in emulation.servers.values() if "pitch" in names)
        for _ in range(150):
            bench.pitch.status()
            bench.roll.angle()
        gaps = np.array(server.gaps)
        print(f"RTU silence before a request: min {gaps.min() * 1e3:.3f} ms, "
              f"1st percentile {np.percentile(gaps, 1) * 1e3:.3f} ms over {len(gaps)} requests")
        assert len(gaps) >= 299 and server.dropped == 0
        assert gaps.min() >= 1.75e-3


def test_a_serial_port_that_does_not_open_says_why(tmp_path):
    link = ModbusLink.serial(str(tmp_path / "ttyUSB9"), baudrate=115200, bytesize=8, parity="E",
                             stopbits=1, timeout_s=0.1, retries=0, reconnect_s=0)
    with pytest.raises(LinkLost, match="cannot open .*ttyUSB9 \\(.*(No such file|could not open port)"):
        link.read(1, 0x00CC, 2)
    assert "connection refused" not in str(pytest.raises(LinkLost, link.read, 1, 0x00CC, 2).value)


def test_station_check_shows_an_identity_only_for_a_drive_that_answered(tmp_path, no_leaks):  # noqa: F811
    with emulated("az-modbus-tcp", tmp_path, pitch=QUICK, roll=QUICK) as (emulation, _):
        config = emulation.station_config
        wrong = config.model_copy(update={"roll": config.roll.model_copy(update={"unit": 9, "retries": 0})})
        with Bench(wrong, emulation.rig.clock) as bench:
            pitch, roll, dmm = bench.check()
        assert pitch["identity"].startswith("Oriental Motor AZ unit 1 on tcp 127.0.0.1:")
        assert "identity" not in roll and "no reply" in roll["problem"]
        assert dmm["identity"].startswith("Keysight Technologies,34970A,")


def test_a_run_on_a_drive_with_stop_on_is_refused_in_one_line(tmp_path, capsys, lab_database, no_leaks):  # noqa: F811
    """`labcal run` on a bench (here served by emulators the test starts) whose pitch drive still
    has STOP on: one line naming the drive and what to do, exit 2, no run journaled."""
    path = private_file("az-modbus-tcp", tmp_path, link="timeout_s = 0.2")
    config, _ = load_station(path)
    with Emulation(config) as emulation, Bench(emulation.station_config, emulation.rig.clock) as bench:
        bench.pitch.link.write_one(1, 0x007D, STOP_BIT)
        code, out, err = cli(capsys, "run", "--station", str(path), "--no-report", "--yes",
                             "--out", str(tmp_path / "run"))
    assert code == 2 and out == "" and "Traceback" not in err, err
    [error] = [line for line in err.splitlines() if line.startswith("labcal: error:")]  # after the checklist
    assert error.startswith("labcal: error: pre-run checklist: tables homed: pitch: ")
    assert "; its STOP input is on" in error
    assert "--reset-alarms" in error and error.endswith("; nothing was moved")
    with sqlite3.connect(lab_database) as db:  # no run started (the checklist opened the lab database)
        assert db.execute("SELECT count(*) FROM runs").fetchall() == [(0,)]
