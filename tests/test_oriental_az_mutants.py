"""The AZ driver's words and registers against the register map, alarm table and reference frames of
hardware_protocols.md §2.1 (issue 21, docs/mutation.md): each expected value is transcribed from there."""

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
