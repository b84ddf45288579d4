"""Modbus RTU frames, byte for byte: the frames the AZ driver puts on a (pty) RS-485 line through
the real pymodbus client, compared with the reference frames of hardware_protocols.md §2.1 and
checked with a CRC-16/MODBUS written from the serial-line spec (tests/modbus_crc.py), never with
pymodbus's own CRC."""

from __future__ import annotations

import pytest
from emulators import emulated, no_leaks  # noqa: F401 - fixture
from modbus_crc import crc16_modbus, crc_ok, with_crc

from labcal.drivers.errors import Rejected
from labcal.drivers.modbus import ModbusLink, int32_words, words_int32
from labcal.drivers.oriental_az import AzAxis

GOLDEN = {
    "read position": "01 03 00 CC 00 02 04 34",
    "read alarm": "01 03 00 80 00 02 C5 E3",
    "stop pulse": "01 06 00 7D 00 20 18 0A",
    "alarm reset": "01 10 01 80 00 02 04 00 00 00 01 37 9F",
    "ddo reply": "01 10 00 58 00 12 C1 D7",
    "exception": "01 83 02 C0 F1",
    "faq -1000": "01 10 18 02 00 02 04 FF FF FC 18 99 58",
    "position 9000": "01 03 04 00 00 23 28 E3 1D",
    "ddo move": "01 10 00 58 00 12 24 00000000 00000001 00002328 000009C4 000F4240 000F4240 000003E8 "
                "00000001 00000000 73 DB",
}


def frame(name: str) -> bytes:
    return bytes.fromhex(GOLDEN[name])


def test_the_test_crc_reproduces_the_documented_vectors():
    """The independent CRC is right before it judges the driver: the check value of the CRC
    catalogue (CRC-16/MODBUS of "123456789" = 4B37h) and every reference frame's last two bytes."""
    assert crc16_modbus(b"123456789") == 0x4B37
    for name in GOLDEN:
        assert crc_ok(frame(name)), name
    assert not crc_ok(frame("read position")[:-2] + bytes.fromhex("34 04"))  # high byte first is wrong


def test_vendor_faq_vector_negative_position():
    """Oriental Motor FAQ 0331: −1000 into 1802h/1803h is FFFF FC18, upper word first."""
    assert int32_words(-1000) == [0xFFFF, 0xFC18]
    assert words_int32(0xFFFF, 0xFC18) == -1000


@pytest.mark.parametrize("value", [0, 1, -1, 9000, 2**31 - 1, -(2**31), 360_000])
def test_int32_words_round_trip(value):
    assert words_int32(*int32_words(value)) == value


def test_int32_words_refuses_what_does_not_fit():
    with pytest.raises(ValueError):
        int32_words(2**31)


def test_driver_frames_on_an_rtu_line(tmp_path, no_leaks):  # noqa: F811
    """The driver's requests and the emulator's replies, as bytes on the pty, for the reference
    example: 50 steps/°, 2500 Hz, 1000 kHz/s, type 1 absolute, 9000 steps = 180°."""
    wire: list[tuple[bool, bytes]] = []
    session: list[tuple[bytes, bytes]] = []  # every exchange of the test

    def trace(sending: bool, data: bytes) -> bytes:
        wire.append((sending, bytes(data)))
        return data

    def exchanges() -> list[tuple[bytes, bytes]]:
        """(request, reply) pairs; a reply may arrive in several reads, so keep the last, whole one."""
        pairs, request = [], None
        for sending, data in wire:
            if sending:
                request = data
            else:
                pairs = [p for p in pairs if p[0] is not request] + [(request, data)]
        wire.clear()
        session.extend(pairs)
        return pairs

    with emulated("az-modbus-rtu", tmp_path) as (emulation, _):
        link = ModbusLink.serial(emulation.station_config.pitch.port, baudrate=115200, bytesize=8, parity="N",
                                 stopbits=1, timeout_s=1.0, retries=0, reconnect_s=1.0, trace=trace)
        axis = AzAxis("pitch", link, 1, emulation.rig.clock, steps_per_degree=50, speed_dps=50,
                      accel_dps2=20000, wrap=False, limits_deg=(0, 359))
        try:
            axis.status()
            # §2.1 "ready check" reads 007Eh ×2; the driver reads the alarm pair 0080h with it
            assert exchanges()[0][0] == with_crc(bytes.fromhex("01 03 00 7E 00 04"))
            axis.angle()
            exchanges()
            axis.move_to(180)
            [(_, _), (request, reply)] = exchanges()  # the position read, then the move
            assert request == frame("ddo move") and reply == frame("ddo reply")
            assert axis.wait_in_position(60) == 180.0
            exchanges()

            assert axis.angle() == 180.0
            assert exchanges() == [(frame("read position"), frame("position 9000"))]
            assert axis.alarm() == 0
            assert exchanges() == [(frame("read alarm"), bytes.fromhex("01 03 04 00 00 00 00 FA 33"))]
            axis.stop()
            # STOP on, STOP off, and the input command read back to see that it is off
            assert [request for request, _ in exchanges()] == [frame("stop pulse"),
                                                               bytes.fromhex("01 06 00 7D 00 00 19 D2"),
                                                               with_crc(bytes.fromhex("01 03 00 7C 00 02"))]
            axis.reset_alarm()
            assert exchanges()[0][0] == frame("alarm reset")
            with pytest.raises(Rejected, match="exception 02h \\(illegal data address\\)"):
                link.read(1, 0x0000, 2)  # nothing is mapped at 0000h
            assert exchanges()[-1][1] == frame("exception")
            with pytest.raises(Rejected, match="exception 02h"):  # the emulator maps no operation data
                link.write(1, 0x1802, int32_words(-1000))
            [(request, _)] = exchanges()
            assert request == frame("faq -1000")  # the vendor's frame, CRC 99 58 included
        finally:
            link.close()
    # every frame on the line, the driver's requests and the emulator's replies, carries the
    # CRC of the serial-line spec, low byte first (the real drive ignores a frame that does not)
    assert len(session) >= 12
    for request, reply in session:
        assert crc_ok(request), request.hex(" ")
        assert crc_ok(reply), reply.hex(" ")
