"""The Modbus link's arithmetic and reply checks against the specifications (docs/mutation.md):
t3.5 from Modbus over Serial Line V1.02 §2.5.1.1 (3.5 character times, 1.75 ms above 19200 Bd), the
exception codes of the Modbus Application Protocol V1.1b3 §7, two's complement by hand. The clock of
the silent interval is a fake one, so nothing here depends on how busy the machine is; late bytes sit
in real sockets and a real pyserial loop port."""

from __future__ import annotations

import logging
import socket

import pytest
import serial
from pymodbus.pdu import ExceptionResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterResponse,
)

from labcal.drivers import modbus
from labcal.drivers.errors import BadReply, Busy, Rejected
from labcal.drivers.modbus import (
    ModbusLink,
    SilentInterval,
    checked,
    int32_words,
    silent_interval_s,
    trace_frame,
    words_int32,
)


@pytest.mark.parametrize("baudrate, bits, seconds", [
    (9600, 11, 3.5 * 11 / 9600),  # 4.0104 ms
    (9600, 10, 3.5 * 10 / 9600),  # 8N1: 10 bits a character
    (19200, 11, 3.5 * 11 / 19200),  # 2.0052 ms: 19200 itself still counts characters
    (19201, 11, 1.75e-3),
    (115200, 11, 1.75e-3),
])
def test_t35_is_three_and_a_half_characters_or_1_75_ms_above_19200_bd(baudrate, bits, seconds):
    assert silent_interval_s(baudrate, bits) == pytest.approx(seconds, rel=1e-12)


def test_t35_counts_eleven_bits_a_character_unless_told():
    assert silent_interval_s(9600) == pytest.approx(3.5 * 11 / 9600, rel=1e-12)


class FakeTime:
    """A monotonic clock that moves only when slept on."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def test_a_request_waits_for_t35_after_the_last_byte_on_the_line(monkeypatch):
    """9600 Bd, 11 bits: a character lasts 11/9600 s, t3.5 = 3.5 of them. An 8-byte request sent at
    t ends on the line at t + 8 characters; the next request may start t3.5 after that, and a reply
    received later pushes the silence on from its arrival."""
    clock = FakeTime()
    monkeypatch.setattr(modbus, "time", clock)
    char, t35 = 11 / 9600, 3.5 * 11 / 9600
    seen: list[tuple[bool, bytes]] = []
    line = SilentInterval(9600, 11,
                          then=lambda sending, packet: seen.append((sending, packet)) or packet[::-1])
    assert (line.t35, line.char_s) == (pytest.approx(t35), pytest.approx(char))
    assert line(True, b"\x01\x03\x00\xcc\x00\x02\x04\x34") == b"\x34\x04\x02\x00\xcc\x00\x03\x01"
    assert clock.sleeps == []  # the line has been silent since long before t = 100 s
    sent_at = clock.now
    assert line.quiet_from == pytest.approx(sent_at + 8 * char)
    line(True, b"\x01")  # at once: waits for the first to end and t3.5 after it
    assert sum(clock.sleeps) == pytest.approx(8 * char + t35)
    clock.now += 1.0  # a reply arrives a second later
    line(False, b"\x01\x03\x04")
    assert line.quiet_from == pytest.approx(clock.now)
    clock.sleeps.clear()
    line(True, b"\x01")
    assert sum(clock.sleeps) == pytest.approx(t35)
    assert [s for s, _ in seen] == [True, True, False, True]


def test_a_received_frame_never_moves_the_silence_back(monkeypatch):
    clock = FakeTime()
    monkeypatch.setattr(modbus, "time", clock)
    line = SilentInterval(9600, 11)
    line(True, bytes(100))  # on the line until 100 characters from now
    end = line.quiet_from
    line(False, b"\x01")  # received while our request is still going out (a daisy chain's echo)
    assert line.quiet_from == end


def test_frames_are_logged_in_hex_with_their_direction(caplog):
    caplog.set_level(logging.DEBUG, logger="labcal.drivers.modbus")
    assert trace_frame(True, b"\x01\x03\x00\xcc", None) == b"\x01\x03\x00\xcc"
    assert trace_frame(False, b"\x01\x83\x02", None) == b"\x01\x83\x02"
    assert trace_frame(True, b"", None) == b""  # nothing on the line: nothing logged
    assert [r.getMessage() for r in caplog.records] == ["> 01 03 00 cc", "< 01 83 02"]
    assert trace_frame(False, b"\x01", lambda sending, packet: packet + bytes([sending])) == b"\x01\x00"


def test_frames_are_not_formatted_unless_debug_is_on(caplog):
    caplog.set_level(logging.INFO, logger="labcal.drivers.modbus")
    trace_frame(True, b"\x01", None)
    assert caplog.records == []


def test_int32_limits_by_hand():
    assert int32_words(2**31 - 1) == [0x7FFF, 0xFFFF]
    assert int32_words(-(2**31)) == [0x8000, 0x0000]
    assert int32_words(-1) == [0xFFFF, 0xFFFF]
    assert int32_words(65536) == [0x0001, 0x0000]
    assert words_int32(0x8000, 0x0000) == -(2**31)
    assert words_int32(0x7FFF, 0xFFFF) == 2**31 - 1
    assert words_int32(0x0001, 0x0000) == 65536
    with pytest.raises(ValueError) as err:
        int32_words(-(2**31) - 1)
    assert str(err.value) == "-2147483649 does not fit in 32 bits"


def _exception(function_code: int, code: int) -> ExceptionResponse:
    return ExceptionResponse(function_code, code)


@pytest.mark.parametrize("code, name, kind", [
    (1, "illegal function", Rejected), (2, "illegal data address", Rejected),
    (3, "illegal data value", Rejected), (4, "slave device failure", Rejected), (5, "acknowledge", Rejected),
    (6, "slave device busy", Busy), (8, "memory parity error", Rejected),
    (10, "gateway path unavailable", Busy), (11, "gateway target failed to respond", Busy),
    (7, "unknown code", Rejected),
])
def test_an_exception_reply_is_named_and_a_busy_one_may_be_asked_again(code, name, kind):
    with pytest.raises(Rejected) as err:
        checked(_exception(0x03, code), 0x03, 0x00CC, 2)
    assert type(err.value) is kind
    assert str(err.value) == f"exception {code:02X}h ({name}) to function 03h at 00CCh"


def test_a_reply_flagged_as_an_error_without_a_code_is_refused():
    reply = ReadHoldingRegistersResponse(registers=[1, 2])
    reply.function_code = 0x83  # exception bit set, no exception code
    with pytest.raises(Rejected) as err:
        checked(reply, 0x03, 0x0080, 2)
    assert type(err.value) is Rejected
    assert str(err.value) == "exception 00h (unknown code) to function 03h at 0080h"


def test_replies_of_the_right_shape_give_their_registers():
    assert checked(ReadHoldingRegistersResponse(registers=[0, 9000]), 0x03, 0x00CC, 2) == [0, 9000]
    assert checked(WriteSingleRegisterResponse(address=0x7D, registers=[0x20]), 0x06, 0x7D, 1) == [0x20]
    assert checked(WriteMultipleRegistersResponse(address=0x58, count=18), 0x10, 0x58, 18) == []


def test_replies_of_the_wrong_shape_are_bad_replies():
    cases = [
        (ReadHoldingRegistersResponse(registers=[9000]), 0x03, 0xCC, 2,
         "1 registers in the reply, 2 asked for"),
        (ReadHoldingRegistersResponse(registers=[]), 0x03, 0xCC, 2, "0 registers in the reply, 2 asked for"),
        (WriteSingleRegisterResponse(address=0x7E, registers=[0x20]), 0x06, 0x7D, 1,
         "write acknowledged at 126, not 007Dh"),
        (WriteMultipleRegistersResponse(address=0x5A, count=18), 0x10, 0x58, 18,
         "write acknowledged at 90, not 0058h"),
        (WriteMultipleRegistersResponse(address=0x58, count=17), 0x10, 0x58, 18,
         "write of 18 registers acknowledged as 17"),
    ]
    for reply, function_code, address, count, message in cases:
        with pytest.raises(BadReply) as err:
            checked(reply, function_code, address, count)
        assert str(err.value) == message
    for reply in (WriteSingleRegisterResponse(address=0xCC), None, b"\x01\x03"):
        with pytest.raises(BadReply) as err:
            checked(reply, 0x03, 0xCC, 2)
        assert str(err.value).endswith("does not answer function 03h")


def _link(timeout_s: float = 0.01) -> ModbusLink:
    return ModbusLink.tcp("127.0.0.1", 9, timeout_s=timeout_s, retries=0, reconnect_s=0.0)


def test_late_bytes_are_counted_without_being_read():
    link = _link()
    ours, theirs = socket.socketpair()
    try:
        link.client.socket = ours
        assert link._waiting() == 0
        theirs.sendall(b"\x01\x03\x04\x00")
        for _ in range(100):  # a local socket pair delivers at once; allow the kernel a moment
            if link._waiting() == 4:
                break
        assert link._waiting() == 4
        assert ours.recv(16) == b"\x01\x03\x04\x00"  # still there: peeked, not read
    finally:
        ours.close()
        theirs.close()
    port = serial.serial_for_url("loop://", timeout=0)
    try:
        port.write(b"\x01\x83\x02")
        link.client.socket = port
        assert link._waiting() == 3
        port.close()
        assert link._waiting() == 0  # a port that closed under us: nothing to count
    finally:
        port.close()
    link.client.socket = None
    assert link._waiting() == 0


def test_recovery_says_how_many_late_bytes_go_with_the_reopened_port(caplog):
    caplog.set_level(logging.WARNING, logger="labcal.drivers.modbus")
    link = _link()
    ours, theirs = socket.socketpair()
    try:
        link.client.socket = ours
        theirs.sendall(b"\x01\x03\x04\x00\x00")
        link._recover()
        assert link.client.socket is None  # closed: the next exchange reopens it
        link.client.socket = None
        link._recover()
    finally:
        ours.close()
        theirs.close()
    assert [r.getMessage() for r in caplog.records] == [
        "tcp 127.0.0.1:9: reopening the port (5 late byte(s) discarded with it)",
        "tcp 127.0.0.1:9: reopening the port before the next try"]


def test_a_serial_link_frames_characters_as_the_line_settings_say():
    """8E1: 1 start + 8 data + 1 parity + 1 stop = 11 bits; 8N1: 10."""
    even = ModbusLink.serial("loop://", baudrate=9600, bytesize=8, parity="E", stopbits=1, timeout_s=0.1,
                             retries=2, reconnect_s=0.0)
    none = ModbusLink.serial("loop://", baudrate=9600, bytesize=8, parity="N", stopbits=1, timeout_s=0.1,
                             retries=2, reconnect_s=0.0)
    assert even.client.comm_params.baudrate == 9600 and even.where == "loop://"
    assert (even.tries, even.timeout_s, even.reconnect_s) == (3, 0.1, 0.0)
    trace_even, trace_none = even.client.transaction.trace_packet, none.client.transaction.trace_packet
    assert trace_even.char_s == pytest.approx(11 / 9600) and trace_none.char_s == pytest.approx(10 / 9600)


def test_t35_follows_the_character_size_it_is_given():
    assert SilentInterval(9600, 10).t35 == pytest.approx(3.5 * 10 / 9600, rel=1e-12)  # 8N1
    assert SilentInterval(9600, 10).char_s == pytest.approx(10 / 9600, rel=1e-12)


def test_a_line_never_used_has_been_silent_since_the_clock_began(monkeypatch):
    """The first request waits for nothing, even a moment after the monotonic clock's origin."""
    clock = FakeTime()
    clock.now = 0.5
    monkeypatch.setattr(modbus, "time", clock)
    SilentInterval(9600, 11)(True, b"\x01")
    assert clock.sleeps == []


def test_recovery_waits_for_a_late_reply_at_most_half_a_second(monkeypatch):
    clock = FakeTime()
    monkeypatch.setattr(modbus, "time", clock)
    _link(timeout_s=2.0)._recover()
    _link(timeout_s=0.2)._recover()
    assert clock.sleeps == [0.5, 0.2]


def test_a_serial_link_opens_its_port_with_the_stations_settings():
    """Every setting of the station reaches the client (pymodbus retries none itself, reconnects at
    once, frames RTU) and the port labcal opens itself."""
    link = ModbusLink.serial("loop://", baudrate=19200, bytesize=7, parity="O", stopbits=2, timeout_s=0.3,
                             retries=1, reconnect_s=0.0)
    params = link.client.comm_params
    assert (params.baudrate, params.bytesize, params.parity, params.stopbits) == (19200, 7, "O", 2)
    assert (params.timeout_connect, params.reconnect_delay, link.client.retries) == (0.3, 0, 0)
    assert type(link.client.framer).__name__ == "FramerRTU"
    link.open_port()
    port = link.client.socket
    try:
        assert (port.baudrate, port.bytesize, port.parity, port.stopbits) == (19200, 7, "O", 2)
        assert (port.timeout, port.write_timeout, port.exclusive) == (0.3, 0.3, True)
        # pymodbus's inter-character timeout (1.5 character times) reaches the port labcal opened
        assert port.inter_byte_timeout == link.client.inter_byte_timeout
        assert 0 < port.inter_byte_timeout < 1.5 * 12 / 19200
    finally:
        link.close()


def test_a_tcp_link_opens_its_socket_and_traces_every_frame():
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    seen: list[tuple[bool, bytes]] = []
    link = ModbusLink.tcp("127.0.0.1", port, timeout_s=0.7, retries=3, reconnect_s=0.0,
                          trace=lambda sending, packet: seen.append((sending, packet)) or packet + b"!")
    try:
        params = link.client.comm_params
        assert (params.host, params.port, params.timeout_connect, params.reconnect_delay) == (
            "127.0.0.1", port, 0.7, 0)
        assert (link.client.retries, link.tries, link.where) == (0, 4, f"tcp 127.0.0.1:{port}")
        assert link.client.transaction.trace_packet(True, b"\x00\x01") == b"\x00\x01!"
        assert seen == [(True, b"\x00\x01")]
        link.open_port()
        assert link.client.socket.gettimeout() == 0.7
        assert link.client.socket.getpeername() == ("127.0.0.1", port)
    finally:
        link.close()
        server.close()
