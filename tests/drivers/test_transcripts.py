"""Each driver replays, byte for byte, what the vendor's document shows for an operation (PyMeasure's
expected-protocol style, tests/transcripts.py): no emulator, so the test and the driver share no
understanding of the protocol but the document's.

Sources: Oriental Motor AZ series Modbus RTU (HM-60262E and FAQ 0331, as transcribed with CRCs in
reference/hardware_protocols.md §2.1 "Command sequences" and §6 "Golden frames"; CRCs here from
tests/modbus_crc.py, written from Modbus over Serial Line V1.02 §6.2.2); Newport SMC100CC/PP
User's Manual (command syntax ``nnAAxx`` CR LF, replies echo address and command, TS/TE/ID?/VE
pages; hardware_protocols.md §2.2); Keysight 34970A/34972A User's Guide (SCPI scan sequence,
FORMat:READing with channel numbers, *IDN?, SYSTem:ERRor?, SYSTem:REMote; §3.1 there)."""

from __future__ import annotations

import pytest
from modbus_crc import with_crc
from transcripts import Transcript, lines

from labcal.devices.station import SystemClock
from labcal.drivers.errors import DeviceFault, NoReply, Rejected
from labcal.drivers.keysight_34970a import Keysight34970A
from labcal.drivers.modbus import ModbusLink
from labcal.drivers.newport_smc100 import Smc100Axis
from labcal.drivers.oriental_az import AzAxis
from labcal.drivers.transport import LineTransport


def hexes(text: str) -> bytes:
    return bytes.fromhex(text)


def crc(text: str) -> bytes:
    return with_crc(hexes(text))


# --- Oriental Motor AZ over Modbus RTU ----------------------------------------------------------

def az_on(transcript: Transcript, **settings) -> AzAxis:
    """Slave 1, 50 steps/° (a DGII table with gear 18), the manual's example move: 2500 Hz and a
    rate of 1 000 000 (× 0.001 kHz/s), i.e. 50 °/s and 20 000 °/s²."""
    link = ModbusLink.serial("transcript", baudrate=115200, bytesize=8, parity="E", stopbits=1,
                             timeout_s=0.05, retries=settings.pop("retries", 0), reconnect_s=0)
    link.open_port = lambda: setattr(link.client, "socket", transcript)
    return AzAxis("pitch", link, 1, SystemClock(), steps_per_degree=50, speed_dps=50, accel_dps2=20000,
                  wrap=False, limits_deg=(0, 359), **settings)


def test_az_read_position():
    """Read 00CCh ×2 → 00002328h = 9000 steps = 180° at 50 steps/°."""
    transcript = Transcript([(hexes("01 03 00 CC 00 02 04 34"), hexes("01 03 04 00 00 23 28 E3 1D"))])
    assert az_on(transcript).angle() == 180.0 and transcript.done()


def test_az_absolute_move_is_one_fc10_write_of_the_ddo_block():
    """Type 1 (absolute), 9000 steps, 2500 Hz, rate = stop rate 1 000 000, current 1000, trigger 1."""
    move = ("01 10 00 58 00 12 24 00000000 00000001 00002328 000009C4 000F4240 000F4240 000003E8 "
            "00000001 00000000 73 DB")
    transcript = Transcript([(hexes("01 03 00 CC 00 02 04 34"), crc("01 03 04 00 00 00 00")),  # at 0 steps
                             (hexes(move), hexes("01 10 00 58 00 12 C1 D7"))])
    az_on(transcript).move_to(180)
    assert transcript.done()


def test_az_status_bits_and_present_alarm():
    """007Eh/007Fh output status (READY bit 5, IN-POS bit 14) and 0080h/0081h present alarm."""
    ready = Transcript([(crc("01 03 00 7E 00 04"), crc("01 03 08 0000 4020 0000 0000"))])
    status = az_on(ready).status()
    assert status.ready and status.in_position and not status.moving and status.fault is None
    alarm = Transcript([(crc("01 03 00 7E 00 04"), crc("01 03 08 0000 2080 0000 0030"))])  # MOVE, ALM-A, 30h
    status = az_on(alarm).status()
    assert status.moving and "alarm 30h (overload)" in status.fault


def test_az_read_alarm():
    transcript = Transcript([(hexes("01 03 00 80 00 02 C5 E3"), crc("01 03 04 0000 0010"))])
    assert az_on(transcript).alarm() == 0x10


def test_az_stop_is_stop_on_then_off_read_back():
    """STOP pulse on bit 5 of 007Dh (FC 06: the reply echoes the request), then off, then the
    reference input command read back to see that STOP is off."""
    transcript = Transcript([(hexes("01 06 00 7D 00 20 18 0A"), hexes("01 06 00 7D 00 20 18 0A")),
                             (crc("01 06 00 7D 00 00"), crc("01 06 00 7D 00 00")),
                             (crc("01 03 00 7C 00 02"), crc("01 03 04 0000 0000"))])
    az_on(transcript).stop()
    assert transcript.done()


def test_az_alarm_reset_is_a_0_to_1_edge():
    transcript = Transcript([(hexes("01 10 01 80 00 02 04 00 00 00 01 37 9F"), crc("01 10 01 80 00 02")),
                             (crc("01 10 01 80 00 02 04 00 00 00 00"), crc("01 10 01 80 00 02"))])
    az_on(transcript).reset_alarm()
    assert transcript.done()


def test_az_exception_response_and_busy_retry():
    """Exception 02h (illegal data address) is refused at once; 06h (busy) is asked again."""
    illegal = Transcript([(hexes("01 03 00 CC 00 02 04 34"), hexes("01 83 02 C0 F1"))])
    with pytest.raises(Rejected, match="exception 02h \\(illegal data address\\)"):
        az_on(illegal, retries=2).angle()
    assert illegal.done()
    busy = Transcript([(hexes("01 03 00 CC 00 02 04 34"), crc("01 83 06")),
                       (hexes("01 03 00 CC 00 02 04 34"), hexes("01 03 04 00 00 23 28 E3 1D"))])
    assert az_on(busy, retries=2).angle() == 180.0 and busy.done()


# --- Newport SMC100 -----------------------------------------------------------------------------

def smc_on(transcript: Transcript) -> Smc100Axis:
    link = LineTransport("transcript", lambda: transcript, eol=b"\r\n", timeout_s=0.05, reconnect_s=0)
    return Smc100Axis("pitch", link, 1, SystemClock(), speed_dps=20, accel_dps2=80, retries=0)


def smc(*pairs: tuple[str, str | None]) -> Transcript:
    return Transcript(lines(*pairs, eol="\r\n"))


def test_smc100_position_and_state():
    """``1TP`` → ``1TP45.00012``; ``1TS`` → ``1TS000033`` (no positioner error, READY from MOVING)."""
    transcript = smc(("1TP", "1TP45.00012"), ("1TS", "1TS000033"))
    axis = smc_on(transcript)
    assert axis.angle() == pytest.approx(45.00012)
    status = axis.status()
    assert status.ready and status.in_position and status.words == "READY from MOVING (33h)"
    assert transcript.done()


def test_smc100_move_is_pa_then_te():
    transcript = smc(("1TP", "1TP0.000000"), ("1PA45.000000", None), ("1TE", "1TE@"))
    smc_on(transcript).move_to(45)
    assert transcript.done()


def test_smc100_a_refused_move_is_the_te_code():
    transcript = smc(("1TP", "1TP0.000000"), ("1PA45.000000", None), ("1TE", "1TEH"))
    with pytest.raises(Rejected, match="refused PA45.000000: error H \\(not allowed in NOT REFERENCED\\)"):
        smc_on(transcript).move_to(45)


def test_smc100_a_lost_te_after_pa_asks_the_state_not_pa_again():
    transcript = smc(("1TP", "1TP0.000000"), ("1PA90.000000", None), ("1TE", None), ("1TS", "1TS000028"))
    smc_on(transcript).move_to(90)
    assert transcript.done()


def test_smc100_stop_only_when_moving():
    moving = smc(("1TS", "1TS000028"), ("1ST", None), ("1TE", "1TE@"))
    smc_on(moving).stop()
    assert moving.done()
    not_referenced = smc(("1TS", "1TS00000A"))
    smc_on(not_referenced).stop()
    assert not_referenced.done()


def test_smc100_stop_refused_because_homing_just_ended_is_a_stopped_stage():
    """TS says HOMING (1Eh), the homing ends before ST arrives, the controller refuses ST with error
    H (NOT REFERENCED, 0Bh from HOMING): nothing moves, so the stop has done its job. Seen when a
    SIGTERM came during homing."""
    raced = smc(("1TS", "1TS00001E"), ("1ST", None), ("1TE", "1TEH"), ("1TS", "1TS00000B"))
    smc_on(raced).stop()
    assert raced.done()
    still_moving = smc(("1TS", "1TS000028"), ("1ST", None), ("1TE", "1TEH"), ("1TS", "1TS000028"))
    with pytest.raises(Rejected, match="refused ST"):
        smc_on(still_moving).stop()


def test_smc100_identity():
    transcript = smc(("1ID?", "1IDURS100BCC"), ("1VE", "1VE SMC_CC - Controller-driver version 2.0.0"))
    assert smc_on(transcript).identify() == ("Newport SMC100 address 1: stage URS100BCC, "
                                             "SMC_CC - Controller-driver version 2.0.0")


def test_smc100_silence_after_a_query_is_explained_by_te():
    transcript = smc(("1TP", None), ("1TE", "1TE@"))
    with pytest.raises(NoReply, match="no reply"):
        smc_on(transcript).angle()


# --- Keysight 34970A ----------------------------------------------------------------------------

def dmm_on(transcript: Transcript, **settings) -> Keysight34970A:
    link = LineTransport("transcript", lambda: transcript, eol=b"\n", timeout_s=0.05, reconnect_s=0)
    return Keysight34970A("dmm", link, nplc=10, range_v=10, retries=0, **settings)


def scpi(*pairs: tuple[str, str | None]) -> Transcript:
    return Transcript(lines(*pairs, eol="\n"))


NO_ERROR = ("SYST:ERR?", '+0,"No error"')
VOLTS = "(@101,102,103)"
# the configuration as the manual's command sequence sends it (hardware_protocols.md §3.1), then
# read back by its queries: range and NPLC per channel as numbers, INP:IMP:AUTO? as 0/1, the
# scan list as a definite-length block, the FORMat:READing switches as 0/1
CONFIGURE = [("*RST", None), ("*CLS", None), (f"CONF:VOLT:DC 10,{VOLTS}", None),
             (f"VOLT:DC:NPLC 10,{VOLTS}", None), (f"INP:IMP:AUTO ON,{VOLTS}", None),
             ("ROUT:SCAN (@101,102,103)", None), ("FORM:READ:CHAN ON", None), ("FORM:READ:TIME ON", None),
             ("FORM:READ:TIME:TYPE ABS", None), ("FORM:READ:UNIT OFF", None),
             ("FORM:READ:ALAR OFF", None), ("TRIG:SOUR IMM", None), NO_ERROR,
             (f"VOLT:DC:RANG? {VOLTS}", "+1.00000000E+01,+1.00000000E+01,+1.00000000E+01"),
             (f"VOLT:DC:NPLC? {VOLTS}", "+1.00000000E+01,+1.00000000E+01,+1.00000000E+01"),
             (f"INP:IMP:AUTO? {VOLTS}", "1,1,1"), ("ROUT:SCAN?", "#214(@101,102,103)"),
             ("FORM:READ:CHAN?", "1"), ("FORM:READ:TIME?", "1"), ("FORM:READ:TIME:TYPE?", "ABS"),
             ("FORM:READ:UNIT?", "0"), ("FORM:READ:ALAR?", "0")]


def test_34970a_identity():
    transcript = scpi(("*IDN?", "HEWLETT-PACKARD,34970A,0,13-2-2"))
    assert dmm_on(transcript).identify() == "HEWLETT-PACKARD,34970A,0,13-2-2"


def test_34970a_configure_and_one_scan_of_two_sweeps():
    readings = ("+1.00000000E+00,2026,01,01,12,00,01.100,101,-2.50000000E-01,2026,01,01,12,00,01.500,102,"
                "+4.99990000E+00,2026,01,01,12,00,01.900,103,+1.00001000E+00,2026,01,01,12,00,02.300,101,"
                "-2.50010000E-01,2026,01,01,12,00,02.700,102,+4.99980000E+00,2026,01,01,12,00,03.100,103")
    transcript = scpi(*CONFIGURE, ("TRIG:COUN 2", None), ("INIT", None), ("*OPC?", "1"),
                      ("FETC?", readings), NO_ERROR)
    meter = dmm_on(transcript)
    meter.configure()
    scan = meter.read(2)
    assert scan.volts.tolist() == [[1.0, -0.25, 4.9999], [1.00001, -0.25001, 4.9998]] and scan.temp_c is None
    assert transcript.done()


def test_34970a_on_rs232_starts_with_syst_rem():
    transcript = scpi(("SYST:REM", None), *CONFIGURE)
    dmm_on(transcript, serial_line=True, baudrate=57600).configure()
    assert transcript.done()


def test_34970a_a_reset_unit_is_configured_again_before_the_scan_is_repeated():
    """The unit refuses the scan (-221: a reset left it no scan list): the next try asks *ESR?,
    sees the power-on bit (128), sends the configuration, reads it back, and scans again."""
    readings = ("+1.00000000E+00,2026,01,01,12,00,01.100,101,-2.50000000E-01,2026,01,01,12,00,01.500,102,"
                "+4.99990000E+00,2026,01,01,12,00,01.900,103")
    scan = [("TRIG:COUN 1", None), ("INIT", None), ("*OPC?", "1")]
    transcript = scpi(*CONFIGURE, *scan, ("FETC?", None), ("SYST:ERR?", '-221,"Settings conflict"'),
                      ("SYST:ERR?", '-230,"Data corrupt or stale"'), NO_ERROR,
                      ("*ESR?", "+148"), *CONFIGURE, *scan, ("FETC?", readings), NO_ERROR)
    meter = Keysight34970A("dmm", LineTransport("transcript", lambda: transcript, eol=b"\n", timeout_s=0.05,
                                                reconnect_s=0), nplc=10, range_v=10, retries=1)
    meter.configure()
    assert meter.read(1).volts.tolist() == [[1.0, -0.25, 4.9999]]
    assert transcript.done()


def test_34970a_overload_and_error_queue():
    overload = ("+9.90000000E+37,2026,01,01,12,00,01.100,101,-2.50000000E-01,2026,01,01,12,00,01.500,102,"
                "+4.99990000E+00,2026,01,01,12,00,01.900,103")
    transcript = scpi(*CONFIGURE, ("TRIG:COUN 1", None), ("INIT", None), ("*OPC?", "1"),
                      ("FETC?", overload), NO_ERROR)
    meter = dmm_on(transcript)
    meter.configure()
    with pytest.raises(DeviceFault, match="channel 101 overloaded"):
        meter.read(1)
    refused = scpi(*CONFIGURE[:12], ("SYST:ERR?", '-222,"Data out of range"'), NO_ERROR)
    with pytest.raises(Rejected, match='SCPI error -222 "Data out of range" after configuration'):
        dmm_on(refused).configure()
