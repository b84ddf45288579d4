"""Driver logging (loggers under ``labcal.drivers``): DEBUG every exchange (Modbus frames in hex,
ASCII and SCPI lines), WARNING every retry, reopened port, late reply and failed stop."""

from __future__ import annotations

import logging

import pytest
from emulators import emulated, no_leaks  # noqa: F401 - fixture
from test_transcripts import az_on, hexes, smc, smc_on
from transcripts import Transcript

from labcal.config.emulation import FaultKind
from labcal.drivers.errors import NoReply
from labcal.sim.faults import Fault


def records(caplog, level: int) -> list[tuple[str, str]]:
    return [(r.name, r.getMessage()) for r in caplog.records if r.levelno == level]


def test_modbus_frames_in_hex_at_debug(caplog):
    caplog.set_level(logging.DEBUG, logger="labcal.drivers")
    az_on(Transcript([(hexes("01 03 00 CC 00 02 04 34"), hexes("01 03 04 00 00 23 28 E3 1D"))])).angle()
    debug = records(caplog, logging.DEBUG)
    assert ("labcal.drivers.modbus", "> 01 03 00 cc 00 02 04 34") in debug
    assert ("labcal.drivers.modbus", "< 01 03 04 00 00 23 28 e3 1d") in debug


def test_ascii_lines_at_debug_and_a_failed_stop_at_warning(caplog):
    caplog.set_level(logging.DEBUG, logger="labcal.drivers")
    axis = smc_on(smc(("1TS", None), ("1TE", None), ("1ST", None), ("1TE", None)))
    with pytest.raises(NoReply):
        axis.stop()
    assert ("labcal.drivers.transport", "transcript > 1TS") in records(caplog, logging.DEBUG)
    warnings = [message for name, message in records(caplog, logging.WARNING)]
    assert any("state unreadable before stopping" in m for m in warnings)
    failed = "pitch table (Newport SMC100, address 1 on transcript): STOP FAILED"
    assert any(m.startswith(failed) for m in warnings)


def test_a_retry_and_a_reopened_port_are_warnings(tmp_path, caplog, no_leaks):  # noqa: F811
    caplog.set_level(logging.WARNING, logger="labcal.drivers")
    quick = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}
    with emulated("az-modbus-tcp", tmp_path, pitch=quick, roll=quick) as (emulation, bench):
        emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY))
        bench.pitch.angle()
    warnings = records(caplog, logging.WARNING)
    retry = ": retry 1 of 2 after: no reply within 0.1 s"
    assert any(name == "labcal.drivers.transport" and retry in message for name, message in warnings)
    assert any(name == "labcal.drivers.modbus" and "reopening the port" in text for name, text in warnings)
    assert all(name.startswith("labcal.drivers.") for name, _ in warnings)
