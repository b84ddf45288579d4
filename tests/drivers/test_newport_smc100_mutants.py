"""The SMC100's replies decoded as the manual documents them (docs/mutation.md).

Every expected value is transcribed from hardware_protocols.md §2.2 ("Controller states", "Positioner
error bits", "Command error codes", reply syntax `1TP` → `1TP45.00012`); where the driver spells out an
abbreviation of that table ("SW" → "software", "comm" → "communication", "/" → "or") the test says so.
"""

from __future__ import annotations

import pytest

from labcal.drivers.errors import BadReply, Rejected
from labcal.drivers.newport_smc100 import (
    COMMAND_ERRORS,
    DISABLE,
    HOMING,
    MOVING,
    NOT_REFERENCED,
    POSITIONER_ERRORS,
    READY,
    STATES,
    describe_state,
    parse_error_code,
    parse_number,
    parse_reply,
    parse_state,
)

# §2.2 "Controller states (TS last 2 hex digits)"; 1E/1F are "HOMING (RS-232)" and "HOMING (SMC-RC)",
# the keypad's, which the driver names so.
MANUAL_STATES = {
    "0A": "NOT REFERENCED from reset", "0B": "NOT REFERENCED from HOMING",
    "0C": "NOT REFERENCED from CONFIGURATION", "0D": "NOT REFERENCED from DISABLE",
    "0E": "NOT REFERENCED from READY", "0F": "NOT REFERENCED from MOVING",
    "10": "NOT REFERENCED, ESP stage error", "11": "NOT REFERENCED from JOGGING", "14": "CONFIGURATION",
    "1E": "HOMING", "1F": "HOMING from the keypad", "28": "MOVING", "32": "READY from HOMING",
    "33": "READY from MOVING", "34": "READY from DISABLE", "35": "READY from JOGGING",
    "3C": "DISABLE from READY", "3D": "DISABLE from MOVING", "3E": "DISABLE from JOGGING",
    "46": "JOGGING from READY", "47": "JOGGING from DISABLE",
}
# §2.2 "Positioner error bits (TS first 4 hex digits)"
MANUAL_BITS = {
    "0200": "80 W output power exceeded", "0100": "DC voltage too low", "0080": "wrong ESP stage",
    "0040": "homing time-out", "0020": "following error", "0010": "short circuit",
    "0008": "RMS current limit",
    "0004": "peak current limit", "0002": "positive end of run", "0001": "negative end of run",
}
# §2.2 "Command error codes (TE)"
MANUAL_ERRORS = {
    "A": "unknown message code", "B": "bad address", "C": "parameter missing or out of range",  # "/"
    "D": "command not allowed", "E": "home sequence already started",  # "home already started"
    "F": "ESP stage name unknown", "G": "displacement out of limits", "H": "not allowed in NOT REFERENCED",
    "I": "not allowed in CONFIGURATION", "J": "not allowed in DISABLE", "K": "not allowed in READY",
    "L": "not allowed in HOMING", "M": "not allowed in MOVING",
    "N": "position out of software limits",  # "position out of SW limit"
    "S": "communication time-out",  # "comm time-out"
    "U": "EEPROM error", "V": "error during execution", "W": "not allowed for PP", "X": "not allowed for CC",
}


@pytest.mark.parametrize("code, text", MANUAL_STATES.items())
def test_every_controller_state_is_described_as_the_manual_names_it(code, text):
    assert describe_state(0, int(code, 16)) == f"{text} ({code}h)"
    assert parse_state(f"0000{code}") == (0, int(code, 16))


def test_the_state_families_are_the_manuals_code_ranges():
    """READY 32–35, MOVING 28, HOMING 1E–1F, DISABLE 3C–3E, NOT REFERENCED 0A–11 (§2.2 table)."""
    assert set(STATES) == {int(c, 16) for c in MANUAL_STATES}
    assert READY == {0x32, 0x33, 0x34, 0x35}
    assert MOVING == {0x28}
    assert HOMING == {0x1E, 0x1F}
    assert DISABLE == {0x3C, 0x3D, 0x3E}
    assert NOT_REFERENCED == {0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11}


def test_an_undocumented_state_is_named_unknown_with_its_code():
    assert describe_state(0, 0x29) == "unknown state (29h)"
    assert describe_state(0, 0x05) == "unknown state (05h)"


@pytest.mark.parametrize("mask, text", MANUAL_BITS.items())
def test_each_positioner_error_bit_is_named(mask, text):
    assert POSITIONER_ERRORS[int(mask, 16)] == text
    assert describe_state(int(mask, 16), 0x33) == f"READY from MOVING (33h), positioner error: {text}"
    assert parse_state(f"{mask}33") == (int(mask, 16), 0x33)


def test_several_error_bits_are_listed_from_the_highest():
    """0x0221 = 80 W exceeded + following error + negative end of run."""
    assert describe_state(0x0221, 0x3D) == ("DISABLE from MOVING (3Dh), positioner error: 80 W output power "
                                            "exceeded, following error, negative end of run")
    assert describe_state(0x8000, 0x3D) == "DISABLE from MOVING (3Dh)"  # an undocumented bit: no word


def test_command_errors_are_the_manuals_letters():
    assert COMMAND_ERRORS == MANUAL_ERRORS
    for code in [*MANUAL_ERRORS, "@"]:
        assert parse_error_code(code) == code


@pytest.mark.parametrize("value", ["", "@@", "Y", "O", "a", "1"])
def test_an_error_code_outside_the_table_is_a_bad_reply(value):
    with pytest.raises(BadReply) as err:
        parse_error_code(value)
    assert str(err.value).startswith(f"error code {value!r} is not one of @, A..X")


def test_status_is_exactly_six_hex_digits():
    assert parse_state("02210A") == (0x0221, 0x0A)
    assert parse_state("0000ff") == (0, 0xFF)  # hex digits in either case
    for bad in ("00033", "0000033", "00003G", " 00033", "0x0033"):
        with pytest.raises(BadReply) as err:
            parse_state(bad)
        assert str(err.value) == f"status {bad!r} is not six hex digits"


def test_a_reply_echoes_address_and_mnemonic():
    """`1TP` → `1TP45.00012` (§2.2 syntax); a query's `?` is not echoed (`1ID?` → `1ID<stage>`)."""
    assert parse_reply("1TP45.00012", 1, "TP") == "45.00012"
    assert parse_reply("12TS00000A", 12, "TS") == "00000A"
    assert parse_reply("1IDURS75BCC ", 1, "ID?") == "URS75BCC"
    assert parse_reply("1TP 45.0", 1, "tp") == "45.0"  # blanks around the value are ignored
    for line, address in (("2TP45.0", 1), ("1TH45.0", 1), ("TP45.0", 1), ("1T", 1), ("1TP45", 11)):
        with pytest.raises(BadReply) as err:
            parse_reply(line, address, "TP")
        assert str(err.value) == f"reply {line!r} does not echo '{address}TP'"


def test_a_long_reply_is_quoted_shortened_in_the_error():
    with pytest.raises(BadReply) as err:
        parse_reply("9" * 100, 1, "TP")
    assert str(err.value) == f"reply {'9' * 40!r} does not echo '1TP'"
    with pytest.raises(BadReply) as err:
        parse_number("x" * 100)
    assert str(err.value) == f"{'x' * 40!r} is not a number"


def test_numbers_are_finite_decimals():
    assert parse_number("45.00012") == 45.00012
    assert parse_number("-0.5") == -0.5
    for bad in ("nan", "inf", "-inf", "1e999"):
        with pytest.raises(BadReply) as err:
            parse_number(bad)
        assert str(err.value) == f"{bad!r} is not a finite number"
    with pytest.raises(BadReply, match="is not a number"):
        parse_number("45,0")


# --- the axis on its emulator (the SMC100 state machine of §2.2, through pyserial on a pty) --------
import logging  # noqa: E402

from emulators import bench_fixtures, no_leaks, until_still  # noqa: E402, F401 - fixture

from labcal.config.emulation import FaultKind  # noqa: E402
from labcal.drivers.errors import DeviceFault  # noqa: E402
from labcal.sim.faults import Fault  # noqa: E402

QUICK = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}
station, smc, smc_slow = bench_fixtures(["smc100-serial"], pitch=QUICK, roll=QUICK)


def test_status_flags_through_power_up_homing_and_a_move(smc_slow):
    """§2.2: 0A at power-up (home it), 1E HOMING → 32 READY; 28 MOVING during PA."""
    emulation, bench = smc_slow
    s = bench.pitch.status()
    assert (s.ready, s.moving, s.in_position, s.needs_homing) == (False, False, False, True)
    assert s.fault == "NOT REFERENCED from reset (0Ah); home it (a run homes it first)"
    bench.pitch.prepare()
    s = bench.pitch.status()
    assert (s.ready, s.moving, s.in_position, s.needs_homing, s.fault) == (True, False, True, False, None)
    bench.pitch.move_to(90)
    s = bench.pitch.status()
    assert (s.ready, s.moving, s.in_position, s.needs_homing, s.fault) == (False, True, False, False, None)
    bench.pitch.stop()


def test_a_following_error_is_a_fault_to_clear_not_a_homing(smc_slow):
    emulation, bench = smc_slow
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].add(Fault(FaultKind.ALARM))
    with pytest.raises(DeviceFault):
        bench.roll.wait_in_position(60)
    s = bench.roll.status()
    # §2.2: "reading TS clears the positioner error", which the wait already read: DISABLE remains
    assert s.fault == "DISABLE from MOVING (3Dh); clear the cause, then re-enable it (MM1) or home it"
    assert (s.ready, s.moving, s.needs_homing) == (False, False, False)


def test_a_move_that_never_arrived_is_logged_and_sent_once_more(smc, caplog):
    emulation, bench = smc
    caplog.set_level(logging.WARNING, logger="labcal.drivers.newport_smc100")
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match="PA"))
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))
    bench.pitch.move_to(30)
    assert bench.pitch.wait_in_position(60) == pytest.approx(30.0)
    device = bench.pitch.device
    messages = [r.getMessage() for r in caplog.records]
    assert f"{device}: PA30.000000 did not arrive; sending it again (READY)" in messages
    lost = [m for m in messages if m.startswith(f"{device}: the reply to TE after PA30.000000 was lost (")]
    assert len(lost) == 1 and lost[0].endswith("); asking the state instead")


def test_nothing_is_sent_to_stop_a_stage_that_cannot_move(smc, caplog):
    emulation, bench = smc
    caplog.set_level(logging.DEBUG, logger="labcal.drivers.newport_smc100")
    bench.pitch.stop()
    assert f"{bench.pitch.device}: not moving (NOT REFERENCED from reset (0Ah)): nothing to stop" in [
        r.getMessage() for r in caplog.records]


def test_replies_of_any_length_are_quoted_to_forty_characters():
    with pytest.raises(BadReply) as err:
        parse_number("inf" + " " * 60)  # float() takes the blanks: infinite
    assert str(err.value) == f"{('inf' + ' ' * 37)!r} is not a finite number"
    with pytest.raises(BadReply) as err:
        parse_state("0" * 60)
    assert str(err.value) == f"status {'0' * 40!r} is not six hex digits"
    with pytest.raises(BadReply) as err:
        parse_error_code("@" * 60)
    assert str(err.value) == f"error code {'@' * 40!r} is not one of @, A..X"


def test_only_the_query_mark_is_stripped_from_a_mnemonic():
    """`ZX` (stage auto-configuration) ends in X: the echo is `1ZX`, not `1Z`."""
    assert parse_reply("1ZX2", 1, "ZX") == "2"
    assert parse_reply("1ZX2", 1, "ZX?") == "2"


def test_a_stop_is_sent_even_when_the_state_cannot_be_read(smc_slow, caplog):
    """A stop must be tried: with every TS reply lost, ST goes out anyway, and the log says why."""
    emulation, bench = smc_slow
    caplog.set_level(logging.WARNING, logger="labcal.drivers.newport_smc100")
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].add(Fault(FaultKind.NO_REPLY, count=3, match="TS"))
    bench.roll.stop()
    assert f"{bench.roll.address}ST" in list(emulation.faults["roll"].recent)
    device = bench.roll.device
    warning = [r.getMessage() for r in caplog.records if "state unreadable" in r.getMessage()]
    assert len(warning) == 1 and warning[0].startswith(f"{device}: state unreadable before stopping (")
    assert warning[0].endswith("); sending ST anyway")
    until_still(bench.roll)  # ST decelerates the stage (MOVING until still, §2.2), then READY
    assert bench.roll.status().words == "READY from MOVING (33h)"  # it stopped


def test_a_refusal_names_the_table_the_command_and_the_manuals_reason(smc):
    emulation, bench = smc
    with pytest.raises(Rejected) as err:  # §2.2: ST is not allowed in NOT REFERENCED (error H)
        bench.pitch.do("ST")
    assert str(err.value) == f"{bench.pitch.device}: refused ST: error H (not allowed in NOT REFERENCED)"


def test_retries_of_queries_and_commands_name_the_table(smc, caplog):
    emulation, bench = smc
    caplog.set_level(logging.WARNING, logger="labcal.drivers.transport")
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.GARBLED, count=1, match="TP"))
    assert bench.pitch.angle() == 0.0
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, count=1, match="TE"))
    bench.pitch.do("VA10")  # safe to repeat: retried after the lost TE
    assert bench.pitch.ask("VA?") == "10"
    retries = [r.getMessage() for r in caplog.records if "retry" in r.getMessage()]
    assert len(retries) == 2
    assert all(m.startswith(f"{bench.pitch.device}: retry 1 of 2 after: ") for m in retries)


def test_prepare_refuses_a_stage_with_a_positioner_error(smc_slow):
    emulation, bench = smc_slow
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].add(Fault(FaultKind.ALARM))
    with pytest.raises(DeviceFault) as err:
        bench.roll.prepare()
    device = bench.roll.device
    assert str(err.value) == f"{device}: DISABLE from MOVING (3Dh), positioner error: following error"


# --- software limits, stops to every table, a lost PA acknowledgement --
import re  # noqa: E402
import time  # noqa: E402

from emulators import emulated  # noqa: E402

from labcal.drivers.errors import DriverError, NoReply  # noqa: E402


def spelled_as_the_manual(sent):
    """Every request as §2.2 writes it: address, the upper-case two-letter mnemonic, value or `?`."""
    for request in sent:
        assert re.fullmatch(r"[12][A-Z]{2}(\?|-?[0-9.]*)", request), request


def _controller(emulation, table):
    """The emulated SMC100 (its SL/SR) driving ``table``."""
    server = next(s for _, _, s in emulation.servers.values() if getattr(s.device, "positioners", None))
    return next(p for p in server.device.positioners.values() if p.name == table)


def _software_limits_refusal(tmp_path, table, sl_sr):
    """prepare() on ``table`` with the controller's SL/SR set to ``sl_sr``: the DeviceFault's text,
    or None when accepted; and whether an OR (homing) went out."""
    with emulated("smc100-serial", tmp_path, pitch=QUICK, roll=QUICK) as (emulation, bench):
        _controller(emulation, table).limits = sl_sr
        axis = getattr(bench, table)
        try:
            axis.prepare()
        except DeviceFault as exc:
            return str(exc), list(emulation.faults[table].recent)
        return None, list(emulation.faults[table].recent)


# smc100-serial: pitch limits_deg [-100, 280] at address 1; roll none at address 2 (the station file)
PITCH_DEVICE_PREFIX = "pitch table (Newport SMC100, address 1 on "


@pytest.mark.parametrize("sl_sr", [(-100.0, 280.0), (-100.5, 280.5), (-1e9, 1e9)])
def test_controller_limits_reaching_the_stations_are_accepted(sl_sr, tmp_path, no_leaks):  # noqa: F811
    """Equal limits are within (the station may go to -100° and 280°, the controller takes PA there)."""
    refusal, sent = _software_limits_refusal(tmp_path, "pitch", sl_sr)
    assert refusal is None
    assert sent[:2] == ["1SL?", "1SR?"]  # §2.2 "Limits": SL, SR; queried with `?` — before anything else


@pytest.mark.parametrize(("sl_sr", "shown"), [
    ((-99.0, 280.0), "[-99°, 280°]"), ((-100.0, 279.5), "[-100°, 279.5°]"), ((-50.0, 200.0), "[-50°, 200°]")])
def test_controller_limits_narrower_on_either_side_are_refused_word_for_word(sl_sr, shown, tmp_path,
                                                                             no_leaks):  # noqa: F811
    refusal, sent = _software_limits_refusal(tmp_path, "pitch", sl_sr)
    assert refusal is not None and refusal.startswith(PITCH_DEVICE_PREFIX)
    assert refusal.split("): ", 1)[1] == (
        f"the station's limits_deg [-100°, 280°] exceed the controller's software limits {shown} (SL, SR); "
        "narrow limits_deg in the station file, or widen SL and SR on the controller")
    assert not any(line.endswith("OR") for line in sent)  # refused before homing: nothing moved


@pytest.mark.parametrize("sl_sr", [(-1e6, 1e6), (-1e9, 1e6), (-1e6, 1e9)])
def test_a_free_table_takes_controller_limits_a_million_degrees_out(sl_sr, tmp_path, no_leaks):  # noqa: F811
    """1e6° is thousands of turns: as good as none (the driver's documented threshold, inclusive)."""
    refusal, sent = _software_limits_refusal(tmp_path, "roll", sl_sr)
    assert refusal is None
    assert sent[:2] == ["2SL?", "2SR?"]


@pytest.mark.parametrize(("sl_sr", "shown"), [
    ((-999999.0, 1e9), "[-999999°, 1e+09°]"), ((-1e9, 999999.0), "[-1e+09°, 999999°]"),
    ((-170.0, 170.0), "[-170°, 170°]")])
def test_a_free_table_with_controller_limits_is_refused_word_for_word(sl_sr, shown, tmp_path,
                                                                      no_leaks):  # noqa: F811
    refusal, sent = _software_limits_refusal(tmp_path, "roll", sl_sr)
    assert refusal is not None and refusal.startswith("roll table (Newport SMC100, address 2 on ")
    assert refusal.split("): ", 1)[1] == (
        f"the controller's software limits are {shown} (SL, SR) but the station file gives no limits_deg "
        "(a free table, moved the shortest way round); set limits_deg within the controller's, or widen "
        "SL and SR")
    assert not any(line.endswith("OR") for line in sent)


def test_software_limits_are_sl_then_sr(smc):
    emulation, bench = smc
    _controller(emulation, "pitch").limits = (-12.5, 345.25)
    assert bench.pitch.software_limits() == (-12.5, 345.25)


def test_the_axis_keeps_the_station_files_settings(tmp_path, no_leaks):  # noqa: F811
    settings = {**QUICK, "poll_s": 0.07, "in_position_arcsec": 3.0, "home_timeout_s": 7.0, "retries": 4,
                "cable_wrap_deg": 500.0}
    roll = {**QUICK, "slip_ring": True}
    with emulated("smc100-serial", tmp_path, pitch=settings, roll=roll) as (emulation, bench):
        pitch = bench.pitch
        assert (pitch.name, pitch.address, pitch.limits) == ("pitch", 1, (-100.0, 280.0))
        assert pitch.device.startswith(PITCH_DEVICE_PREFIX) and pitch.device.endswith(")")
        assert (pitch.poll_s, pitch.tolerance_arcsec) == (0.07, 3.0)
        assert (pitch.home_timeout_s, pitch.tries) == (7.0, 5)  # retries 4: five tries
        assert (pitch.speed_dps, pitch.accel_dps2) == (20, 80)
        assert pitch.clock is emulation.rig.clock
        assert (pitch.cable_wrap_deg, bench.roll.cable_wrap_deg) == (500.0, None)
        assert bench.roll.limits is None


def test_prepare_sets_the_station_files_speed_and_acceleration(tmp_path, no_leaks):  # noqa: F811
    """§2.2: `1VA<u/s>`, `1AC<u/s²>`, queried with `?`; 15 and 60 differ from the emulator's power-up
    20, 80."""
    with emulated("smc100-serial", tmp_path, pitch={**QUICK, "speed_dps": 15, "accel_dps2": 60},
                  roll=QUICK) as (emulation, bench):
        bench.pitch.prepare()
        assert (bench.pitch.ask("VA?"), bench.pitch.ask("AC?")) == ("15", "60")
        sent = list(emulation.faults["pitch"].recent)
        assert "1OR" in sent and "1VA15" in sent and "1AC60" in sent
        assert sent[:5] == ["1SL?", "1SR?", "1TS", "1OR", "1TE"]
        spelled_as_the_manual(sent)
        assert bench.pitch.status().words == "READY from HOMING (32h)"


def test_prepare_enables_a_disabled_stage_without_homing_it(smc):
    """§2.2: `1MM1` leaves DISABLE (→ READY, 34h READY from DISABLE); a referenced stage is not homed
    again."""
    emulation, bench = smc
    bench.pitch.prepare()
    bench.pitch.do("MM0")
    assert bench.pitch.status().words == "DISABLE from READY (3Ch)"
    emulation.faults["pitch"].recent.clear()
    bench.pitch.prepare()
    sent = list(emulation.faults["pitch"].recent)
    assert "1MM1" in sent and "1OR" not in sent
    spelled_as_the_manual(sent)
    assert bench.pitch.status().words == "READY from DISABLE (34h)"


def test_prepare_homes_a_stage_not_referenced_even_with_an_error_bit(smc):
    """A positioner error with NOT REFERENCED is what homing clears (§2.2: 1OR from NOT REFERENCED)."""
    emulation, bench = smc
    _controller(emulation, "pitch").errors = 0x0001  # negative end of run, at power-up (0Ah)
    bench.pitch.prepare()
    assert "1OR" in list(emulation.faults["pitch"].recent)
    assert bench.pitch.status().words == "READY from HOMING (32h)"


def test_the_homing_timeout_message_word_for_word(tmp_path, no_leaks):  # noqa: F811
    """Homing from 90° at 20°/s takes 4.5 s; with home_timeout_s = 0.5 the stage is stopped on its way:
    ST during HOMING leaves NOT REFERENCED from HOMING (0Bh, §2.2 state table)."""
    with emulated("smc100-serial", tmp_path, 10.0, pitch={**QUICK, "home_timeout_s": 0.5},
                  roll=QUICK) as (emulation, bench):
        table = emulation.rig.axis("pitch")
        table.move_to(90.0, "direct")
        emulation.rig.clock.advance_to(table.motion_end)
        with pytest.raises(DeviceFault) as fault:
            bench.pitch.prepare()
        message = str(fault.value)
        assert message.startswith(PITCH_DEVICE_PREFIX)
        found = re.fullmatch(
            r"homing \(OR\) did not find home within home_timeout_s = 0\.5 s; the stage was stopped "
            r"\(ST\) at (\d+\.\d{3})°, now NOT REFERENCED from HOMING \(0Bh\); check that nothing blocks "
            r"the stage and that its home switch is cabled, or raise home_timeout_s in the station file if "
            r"homing from there takes longer", message.split("): ", 1)[1])
        assert found is not None, message
        assert 0.0 < float(found[1]) < 90.0  # on its way home from 90°
        sent = list(emulation.faults["pitch"].recent)
        assert "1ST" in sent
        spelled_as_the_manual(sent)
        after_stop = sent[sent.index("1ST"):]
        assert after_stop[:4] == ["1ST", "1TE", "1TP", "1TS"]  # stopped, then where and in which state


def test_a_stop_sent_without_te_has_its_refusal_read_by_the_stop(smc, caplog):
    """§2.2: ST is refused in NOT REFERENCED (error H), kept for TE. `send_stop` leaves that TE;
    `stop` must read it, so that the next command's TE is its own (@ for VA10)."""
    emulation, bench = smc
    caplog.set_level(logging.DEBUG, logger="labcal.drivers.newport_smc100")
    bench.pitch.send_stop()
    deadline = time.monotonic() + 5.0  # the line to the emulator's thread: until it has read it
    while not emulation.faults["pitch"].recent and time.monotonic() < deadline:
        time.sleep(0.005)
    assert list(emulation.faults["pitch"].recent) == ["1ST"]  # nothing else: no TE waited for
    bench.pitch.stop()
    messages = [r.getMessage() for r in caplog.records]
    device = bench.pitch.device
    assert f"{device}: the ST sent without TE left H" in messages
    assert f"{device}: not moving (NOT REFERENCED from reset (0Ah)): nothing to stop" in messages
    bench.pitch.do("VA10")  # its own TE: @
    emulation.faults["pitch"].recent.clear()
    bench.pitch.stop()  # the TE was read once: not asked again
    assert list(emulation.faults["pitch"].recent) == ["1TS"]


def test_a_stop_sent_without_te_then_stop_a_moving_stage(smc_slow):
    emulation, bench = smc_slow
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].recent.clear()
    bench.roll.send_stop()
    bench.roll.stop()
    assert list(emulation.faults["roll"].recent)[:3] == ["2ST", "2TE", "2TS"]
    until_still(bench.roll)
    assert bench.roll.status().words == "READY from MOVING (33h)"


def test_a_refused_stop_of_a_moving_stage_fails_loudly(smc_slow, caplog):
    """ST refused (error M injected) while TS still says MOVING (28h): the stop failed and says so."""
    emulation, bench = smc_slow
    caplog.set_level(logging.WARNING)
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].add(Fault(FaultKind.EXCEPTION, match="ST$", code="M"))
    with pytest.raises(Rejected) as err:
        bench.roll.stop()
    assert str(err.value) == f"{bench.roll.device}: refused ST: error M (not allowed in MOVING)"
    assert f"{bench.roll.device}: STOP FAILED, the table may still be moving: {err.value}" in [
        r.getMessage() for r in caplog.records]
    bench.roll.stop()
    until_still(bench.roll)


def test_a_refused_stop_of_a_stage_no_longer_moving_is_logged_not_raised(smc_slow, caplog):
    """ST refused, and the next TS finds the stage stopped (a following error disabled it: 3Dh, bit
    0x0020): nothing moves, which is what the stop is for."""
    emulation, bench = smc_slow
    caplog.set_level(logging.INFO, logger="labcal.drivers.newport_smc100")
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].add(Fault(FaultKind.EXCEPTION, match="ST$", code="M"))
    emulation.faults["roll"].add(Fault(FaultKind.ALARM, match="TS", after=1))
    bench.roll.stop()
    assert (f"{bench.roll.device}: ST refused in DISABLE from MOVING (3Dh): the stage is not moving"
            in [r.getMessage() for r in caplog.records])


def test_a_move_whose_acknowledgement_was_lost_is_not_sent_twice(smc, caplog):
    """PA arrived, its TE reply was lost: READY on the set-point (TH = 30.000000) means taken."""
    emulation, bench = smc
    caplog.set_level(logging.WARNING, logger="labcal.drivers.newport_smc100")
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))
    bench.pitch.move_to(30)
    assert bench.pitch.wait_in_position(60) == pytest.approx(30.0)
    assert list(emulation.faults["pitch"].recent).count("1PA30.000000") == 1
    assert not [r for r in caplog.records if "did not arrive" in r.getMessage()]


def test_a_moving_stage_after_a_lost_acknowledgement_is_taken_as_moving(smc_slow, caplog):
    emulation, bench = smc_slow
    caplog.set_level(logging.WARNING, logger="labcal.drivers.newport_smc100")
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))
    # 270° at 20°/s: 13.5 s, 0.7 s here; still MOVING after the lost TE (0.1 s) and the drain (0.1 s)
    bench.pitch.move_to(270, travel_deg=270)
    sent = list(emulation.faults["pitch"].recent)
    assert sent.count("1PA270.000000") == 1 and "1TH" not in sent  # MOVING: no set-point needed
    assert not [r for r in caplog.records if "did not arrive" in r.getMessage()]
    bench.pitch.stop()
    until_still(bench.pitch)


def test_a_move_sent_again_is_not_retried(smc):
    """The PA sent again after a lost one is not repeated when its TE is lost too (a repeat would be
    refused with M while moving, or move twice): the lost reply is raised."""
    emulation, bench = smc
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match="PA"))
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE", count=2))
    with pytest.raises(NoReply):
        bench.pitch.move_to(30)
    assert list(emulation.faults["pitch"].recent).count("1PA30.000000") == 2


def test_a_lost_move_on_a_disabled_stage_is_a_fault_word_for_word(smc):
    """After the PA's acknowledgement was lost, DISABLE from READY (3Ch) is neither moving nor READY."""
    emulation, bench = smc
    bench.pitch.prepare()
    bench.pitch.do("MM0")
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match="PA"))
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))
    with pytest.raises(DeviceFault) as err:
        bench.pitch.move_to(30)
    assert str(err.value) == f"{bench.pitch.device}: after PA30.000000: DISABLE from READY (3Ch)"


def test_the_lost_acknowledgement_warning_names_the_failure(smc, caplog):
    """The reply to TE lost once: the warning quotes the link's failure ("no reply within 0.1 s",
    0.1 s being QUICK's timeout_s) word for word, and the controller is asked TS, then TH (§2.2)."""
    emulation, bench = smc
    bench.pitch.prepare()
    emulation.faults["pitch"].recent.clear()
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))
    caplog.set_level(logging.WARNING, logger="labcal.drivers.newport_smc100")
    bench.pitch.move_to(30)
    assert [r.getMessage() for r in caplog.records if r.name == "labcal.drivers.newport_smc100"] == [
        f"{bench.pitch.device}: the reply to TE after PA30.000000 was lost (no reply within 0.1 s); "
        "asking the state instead"]
    sent = list(emulation.faults["pitch"].recent)
    assert sent[sent.index("1PA30.000000"):][:4] == ["1PA30.000000", "1TE", "1TS", "1TH"]
    spelled_as_the_manual(sent)


def test_a_stop_with_the_state_unreadable_quotes_why(smc_slow, caplog):
    emulation, bench = smc_slow
    caplog.set_level(logging.WARNING, logger="labcal.drivers.newport_smc100")
    bench.roll.prepare()
    bench.roll.move_to(150)
    emulation.faults["roll"].add(Fault(FaultKind.NO_REPLY, count=3, match="TS"))  # every try of TS
    bench.roll.stop()
    device = bench.roll.device
    hint = "check that it is powered and cabled, and its address and line settings in the station file"
    assert [r.getMessage() for r in caplog.records if "state unreadable" in r.getMessage()] == [
        f"{device}: state unreadable before stopping ({device}: no reply within 0.1 s; {hint}); "
        "sending ST anyway"]
    until_still(bench.roll)


def test_homing_again_forgets_the_last_target(smc):
    """After a reset (`1RS`, §2.2: back to NOT REFERENCED) prepare homes the stage to 0°; waiting then
    expects no earlier move's target (30°) but where homing left the stage."""
    emulation, bench = smc
    bench.pitch.prepare()
    bench.pitch.move_to(30)
    assert bench.pitch.wait_in_position(60) == pytest.approx(30.0)
    bench.pitch.do("RS")
    assert bench.pitch.status().words == "NOT REFERENCED from reset (0Ah)"
    bench.pitch.prepare()
    assert bench.pitch.wait_in_position(60) == pytest.approx(0.0, abs=1e-6)


def test_exchanges_are_critical_sections_of_a_run(smc):
    """A run hands its links its critical section: each query and each command with its TE runs
    inside one (a Ctrl-C waits for the exchange to end)."""
    from contextlib import contextmanager

    emulation, bench = smc
    entered: list[int] = []
    waits: list[int] = []  # the waits for a reply, which a stop may cut short

    @contextmanager
    def section(awaiting_reply: bool = False):
        (waits if awaiting_reply else entered).append(len(emulation.faults["pitch"].recent))
        yield

    bench.pitch.link.critical = section
    try:
        assert bench.pitch.ask("VA?") == "20"  # the emulator's power-up speed
        assert len(entered) == 1 and len(waits) >= 1
        bench.pitch.do("VA10")
        assert len(entered) == 2
    finally:
        bench.pitch.link.critical = None


def test_link_failures_on_a_stop_or_a_move_name_the_table(smc):
    """The port gone (emulators closed): the error names the table and says what to check."""
    emulation, bench = smc
    bench.pitch.prepare()
    emulation.close()
    device = bench.pitch.device
    with pytest.raises(DriverError) as err:  # a link error (PortClosed)
        bench.pitch.send_stop()
    assert str(err.value).startswith(f"{device}: ")
    assert str(err.value).endswith("; check the cable and the port")
    with pytest.raises(DriverError) as err:  # LinkLost
        bench.pitch._go(30.0)  # PA's own exchange (move_to would fail first at TP)
    assert str(err.value).startswith(f"{device}: cannot open ")
    hint = "check the cable, the port name, and that no other program holds the port"
    assert str(err.value).endswith(f"; {hint}")


def test_retries_default_to_two(smc):
    """The station file's default (retries = 2: three tries) is also the driver's."""
    from labcal.drivers.newport_smc100 import Smc100Axis

    emulation, bench = smc
    axis = Smc100Axis("pitch", bench.pitch.link, 1, emulation.rig.clock, speed_dps=20, accel_dps2=80)
    assert axis.tries == 3


def test_a_set_point_one_unit_of_the_sixth_decimal_off_counts_as_taken(smc):
    """TH answers with six decimals as PA was sent (§2.2 `1TH` → set-point): one unit of the last
    decimal (1e-6°, 0.0036″) is within the set-point tolerance, inclusive; the PA is not sent again.
    Homed, the set-point is 0.000000; PA0.000001 is lost with its acknowledgement."""
    emulation, bench = smc
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match="PA"))
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))
    bench.pitch.move_to(0.000001)
    sent = list(emulation.faults["pitch"].recent)
    assert sent.count("1PA0.000001") == 1 and "1TH" in sent
    assert bench.pitch.wait_in_position(60) == pytest.approx(0.0, abs=1e-5)
