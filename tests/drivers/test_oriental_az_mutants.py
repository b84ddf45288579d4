"""The AZ driver's words and registers against the register map, alarm table and reference frames of
hardware_protocols.md §2.1 (docs/mutation.md): each expected value is transcribed from there."""

from __future__ import annotations

import pytest

from labcal.drivers.oriental_az import Output, alarm_text, ddo_registers, decode_status, status_words

RESET = "clear the cause, then `labcal station check STATION --reset-alarms`"
POWER = "cannot be reset by command: clear the cause and cycle the drive's power"


def _words(hex_longs: str) -> list[int]:
    """'000F4240 …' (the manual's 32-bit fields) as 16-bit registers, upper word first."""
    return [int(h[i:i + 4], 16) for h in hex_longs.split() for i in (0, 4)]


def test_the_manuals_absolute_move_frame():
    """§2.1 "Move absolute": type 1, 9000 steps, 2500 Hz, acc = dec = 1 000 000, current 1000,
    trigger 1, destination 0 is `… 24 00000000 00000001 00002328 000009C4 000F4240 000F4240 000003E8
    00000001 00000000 …`."""
    assert ddo_registers(1, 9000, 2500, 1_000_000) == _words(
        "00000000 00000001 00002328 000009C4 000F4240 000F4240 000003E8 00000001 00000000")


def test_a_negative_position_and_the_optional_fields():
    """Oriental Motor FAQ 0331 (§2.1): −1000 is FFFF FC18; wrap proximity is type 9 (§2.1 map)."""
    assert ddo_registers(9, -1000, 1, 2, current_permille=500, trigger=-5) == _words(
        "00000000 00000009 FFFFFC18 00000001 00000002 00000002 000001F4 FFFFFFFB 00000000")


@pytest.mark.parametrize("code, meaning, resettable", [
    (0x10, "excessive position deviation", True),
    (0x20, "overcurrent", False),  # "20h, 28h, 33h and 41h cannot be reset by command"
    (0x28, "sensor error", False),
    (0x33, "absolute position error (needs P-PRESET or homing)", False),
    (0x41, "EEPROM error", False),
    (0x4A, "return-to-home incomplete", True),
    (0x70, "operation data error", True),
    (0x85, "RS-485 communication timeout", True),
    (0xF0, "CPU error", True),
])
def test_alarm_text_names_the_alarm_and_whether_a_command_can_reset_it(code, meaning, resettable):
    assert alarm_text(code) == f"alarm {code:02X}h ({meaning}); {RESET if resettable else POWER}"


def test_an_undocumented_alarm_is_named_unknown():
    assert alarm_text(0x0B) == f"alarm 0Bh (unknown alarm); {RESET}"


def test_status_bits_are_the_low_word_at_7eh_and_the_alarm_follows():
    """0x007E/7F output status (READY bit 5, ALM-A 7, SYS-BSY 8, MOVE 13, IN-POS 14), then 0x0080/81
    the present alarm: four registers, upper words first; the upper status word carries no bit."""
    bits, alarm = decode_status([0x0001, 0x6020, 0x0000, 0x0033])
    assert bits == Output(0x6020) and alarm == 0x33
    assert Output.READY in bits and Output.MOVE in bits and Output.IN_POS in bits
    assert Output.ALM_A not in bits
    bits, alarm = decode_status([0xFFFF, 0x0180, 0x0000, 0x0000])
    assert bits == Output.ALM_A | Output.SYS_BSY and alarm == 0
    assert decode_status([0, 0, 0x0001, 0x0000])[1] == 0x10000  # the alarm is all 32 bits


def test_status_words_list_the_bits_in_a_fixed_order():
    assert status_words(Output(0), 0) == "not ready"
    assert status_words(Output.READY | Output.IN_POS, 0) == "READY IN-POS"
    assert status_words(Output.SYS_BSY | Output.MOVE | Output.READY, 0) == "READY MOVE SYS-BSY"
    assert status_words(Output.ALM_A, 0x33) == "ALM-A 33h"
    assert status_words(Output.READY | Output.HOME_END | Output.INFO, 0x0A) == "READY ALM-A 0Ah"


# --- the axis: its arithmetic, and on its emulator (Modbus TCP) -------------------------------------
import logging  # noqa: E402

from emulators import bench_fixtures, no_leaks  # noqa: E402, F401 - fixture

from labcal.config.emulation import FaultKind  # noqa: E402
from labcal.drivers.errors import DeviceFault  # noqa: E402
from labcal.drivers.modbus import ModbusLink  # noqa: E402
from labcal.drivers.oriental_az import AzAxis  # noqa: E402
from labcal.sim.faults import Fault  # noqa: E402

QUICK = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}
STOP_WRITE = "fc06 007D"  # how the emulator names an FC 06 write to 007Dh
station, az, az_slow = bench_fixtures(["az-modbus-tcp"], pitch=QUICK, roll=QUICK)


def _axis(**kw: object) -> AzAxis:
    link = ModbusLink.tcp("127.0.0.1", 9, timeout_s=0.1, retries=0, reconnect_s=0.0)
    settings = {"steps_per_degree": 50.0, "speed_dps": 50.0, "accel_dps2": 20_000.0, **kw}
    return AzAxis("pitch", link, 1, None, **settings)


def test_steps_speeds_and_rates_from_degrees():
    """§2.1 "Units": a DGII table of ratio 18 is 18 000 steps a turn, 50 steps/°; the reference move
    runs at 2500 Hz (= 50°/s) with a rate of 1 000 000 (0.001 kHz/s units = steps/s²: 20 000°/s²)."""
    axis = _axis()
    assert (axis.steps_per_turn, axis.speed_hz, axis.rate, axis.wrap) == (18_000, 2500, 1_000_000, True)
    slow = _axis(speed_dps=0.001, accel_dps2=0.001, wrap=False)  # 0.05 steps/s rounds to 0: at least 1
    assert (slow.speed_hz, slow.rate, slow.wrap) == (1, 1, False)


def test_an_alarm_is_the_status_fault_and_word(az):
    """Alarm 10h (the emulator's default, excessive position deviation) read from 0x0080."""
    emulation, bench = az
    emulation.faults["pitch"].add(Fault(FaultKind.ALARM))
    bench.pitch.status()  # the request the alarm strikes on
    s = bench.pitch.status()
    assert s.fault == ("alarm 10h (excessive position deviation); clear the cause, then `labcal station "
                       "check STATION --reset-alarms`")
    assert "ALM-A 10h" in s.words and not s.ready and not s.in_position


def test_a_stop_release_that_never_lands_names_each_attempt_and_the_last_error(az, caplog):
    emulation, bench = az
    caplog.set_level(logging.WARNING, logger="labcal.drivers.oriental_az")
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match=STOP_WRITE, after=1, count=100))
    with pytest.raises(DeviceFault) as err:
        bench.pitch.stop()
    device = bench.pitch.device
    text = str(err.value)
    assert text.startswith(f"{device}: the STOP input may still be on after 5 attempts to release it (")
    assert "read back on" not in text  # the writes failed: the last failure is named
    assert text.endswith("): the table will not move until it is off; check the line, then `labcal station "
                         "check STATION --reset-alarms`")
    attempts = [r.getMessage() for r in caplog.records if "STOP input still on" in r.getMessage()]
    assert [m.split(" of ")[0] for m in attempts] == [
        f"{device}: STOP input still on after release attempt {k}" for k in range(1, 6)]
    assert all(m.split(" of ")[1].startswith("5 (") and m.endswith(")") for m in attempts)


def test_a_stop_input_left_on_is_refused_before_anything_moves(az):
    emulation, bench = az
    bench.pitch.link.write_one(bench.pitch.unit, 0x007D, 1 << 5)  # STOP, as a lost release leaves it
    with pytest.raises(DeviceFault) as err:
        bench.pitch.prepare()
    assert str(err.value) == (f"{bench.pitch.device}: its STOP input is on (left on by an interrupted "
                              "stop?), so no move can start; release it with `labcal station check STATION "
                              "--reset-alarms`, then run or resume again")
