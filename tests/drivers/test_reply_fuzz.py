"""Fuzzing every reply path with hypothesis: whatever bytes or lines come back, a driver either
understands them or raises one of its own `DriverError`s (a one-line user error), never anything
else (no IndexError, no UnicodeDecodeError, no pymodbus exception leaking out)."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from modbus_crc import with_crc

from labcal.drivers.errors import DriverError
from labcal.drivers.keysight_34970a import Keysight34970A, parse_error, parse_readings
from labcal.drivers.modbus import ModbusLink
from labcal.drivers.newport_smc100 import Smc100Axis, parse_error_code, parse_number, parse_reply, parse_state
from labcal.drivers.oriental_az import AzAxis, decode_status
from labcal.drivers.transport import LineTransport
from labcal.sim.clock import VirtualClock

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FUZZ_DRIVER = settings(FUZZ, max_examples=60)  # each example may wait out a few (2 ms) timeouts
lines = st.one_of(st.text(max_size=80), st.from_regex(r"1[A-Z]{2}[-+0-9A-F.e@]{0,12}", fullmatch=True),
                  st.from_regex(r"[-+][0-9.]{1,10}E[-+][0-9]{2},10[1-4](,[-+][0-9.E+]{1,12},10[1-4]){0,8}",
                                fullmatch=True))
raw = st.one_of(st.binary(max_size=120), lines.map(lambda t: t.encode("utf-8", "surrogatepass") + b"\r\n"))


class ScriptedStream:
    """A device that answers each request with the next scripted reply (bytes), then is silent."""

    def __init__(self, replies: list[bytes]):
        self.replies, self.pending = list(replies), b""

    def write(self, data: bytes) -> None:
        if self.replies:
            self.pending += self.replies.pop(0)

    def read_some(self) -> bytes:
        data, self.pending = self.pending, b""
        return data

    def close(self) -> None:
        pass


def transport(replies: list[bytes], eol: bytes) -> LineTransport:
    return LineTransport("fuzz", lambda: ScriptedStream(replies), eol=eol, timeout_s=0.002, reconnect_s=0)


def only_driver_errors(call) -> None:
    try:
        call()
    except DriverError as exc:
        assert str(exc) and "\n" not in str(exc)


@FUZZ
@given(lines, st.integers(1, 31), st.sampled_from(["TP", "TS", "TE", "ID?", "VA?"]))
def test_smc100_reply_parsers(line, address, mnemonic):
    only_driver_errors(lambda: parse_number(parse_reply(line, address, mnemonic)))
    only_driver_errors(lambda: parse_state(parse_reply(line, address, mnemonic)))
    only_driver_errors(lambda: parse_error_code(parse_reply(line, address, mnemonic)))


@FUZZ
@given(lines, st.lists(st.sampled_from([101, 102, 103, 104]), min_size=1, max_size=4, unique=True),
       st.integers(1, 4))
def test_scpi_reply_parsers(line, scan_list, sweeps):
    only_driver_errors(lambda: parse_error(line))
    only_driver_errors(lambda: parse_readings(line, scan_list, sweeps))


@FUZZ_DRIVER
@given(st.lists(raw, max_size=6))
def test_smc100_driver_on_any_replies(replies):
    axis = Smc100Axis("roll", transport(replies, b"\r\n"), 1, VirtualClock(), speed_dps=10, accel_dps2=10,
                      retries=1)
    for call in (axis.status, axis.angle, lambda: axis.move_to(45)):
        only_driver_errors(call)


@FUZZ_DRIVER
@given(st.lists(raw, max_size=8), st.integers(1, 3))
def test_keysight_driver_on_any_replies(replies, n):
    meter = Keysight34970A("dmm", transport(replies, b"\n"), temperature_channel=104, nplc=0.02, retries=1)
    only_driver_errors(lambda: meter.read(n))
    only_driver_errors(meter.identify)


registers4 = st.lists(st.integers(0, 0xFFFF), min_size=4, max_size=4)


def signed32(upper: int, lower: int) -> int:
    """Two registers, upper word first, as a two's-complement 32-bit value (§2.1 "Data format")."""
    return int.from_bytes(upper.to_bytes(2, "big") + lower.to_bytes(2, "big"), "big", signed=True)


@FUZZ
@given(registers4)
def test_az_status_decoding(registers):
    """The output bits are the lower word of 007Eh/7Fh (the upper word is not status); the
    alarm is 0080h/81h read as a signed 32-bit pair."""
    bits, alarm = decode_status(registers)
    assert int(bits) == registers[1] and alarm == signed32(registers[2], registers[3])


@pytest.fixture(scope="module")
def modbus_reply():
    """A real pymodbus RTU client on pyserial's loop:// whose incoming bytes are replaced by the
    example's: the driver's whole reply path (framing, CRC, decoding, checks) sees them."""
    reply = {"bytes": b""}

    def replace_replies(sending: bool, data: bytes) -> bytes:
        return data if sending else reply["bytes"]

    link = ModbusLink.serial("loop://", baudrate=115200, bytesize=8, parity="N", stopbits=1, timeout_s=0.005,
                             retries=0, reconnect_s=0, trace=replace_replies)
    yield link, reply
    link.close()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(st.one_of(st.binary(max_size=40), st.binary(max_size=6).map(lambda b: b"\x01\x03\x04" + b)))
def test_modbus_driver_on_any_reply_bytes(modbus_reply, data):
    link, reply = modbus_reply
    reply["bytes"] = data
    axis = AzAxis("pitch", link, 1, VirtualClock(), steps_per_degree=50, speed_dps=10, accel_dps2=10)
    only_driver_errors(axis.angle)
    only_driver_errors(axis.status)
    only_driver_errors(axis.stop)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(registers4)
@example([0, 0x0080, 0, 0])  # ALM-A set, no code yet
@example([0, 0x6020, 0, 0])  # READY, MOVE and IN-POS together: moving, so not in position
@example([0xFFFF, 0x4020, 0, 0x0030])  # upper word all ones (not status); alarm 30h
def test_modbus_driver_status_from_any_registers(modbus_reply, registers):
    """A well-formed FC03 reply with any four registers at 007Eh: the driver's status is what
    hardware_protocols.md §2.1 says the bits mean (READY bit 5, ALM-A bit 7, MOVE bit 13,
    IN-POS bit 14 of the lower word; in position = IN-POS and not MOVE) and a fault exactly when
    an alarm code is present or ALM-A is set, naming the code."""
    link, reply = modbus_reply
    reply["bytes"] = with_crc(bytes([1, 3, 8]) + b"".join(r.to_bytes(2, "big") for r in registers))
    axis = AzAxis("pitch", link, 1, VirtualClock(), steps_per_degree=50, speed_dps=10, accel_dps2=10)
    status = axis.status()
    low, alarm = registers[1], signed32(registers[2], registers[3])
    assert status.ready == bool(low & 1 << 5) and status.moving == bool(low & 1 << 13)
    assert status.in_position == (bool(low & 1 << 14) and not low & 1 << 13)
    if alarm or low & 1 << 7:
        assert status.fault is not None and status.fault.startswith(f"alarm {alarm:02X}h ("), status.fault
    else:
        assert status.fault is None
