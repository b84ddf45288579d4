"""The Keysight 34970A driver against its SCPI emulator (pty and TCP): readings are the emulated
instrument's physics, the error queue behaves as SCPI says, and faults are handled."""

from __future__ import annotations

import numpy as np
import pytest
from emulators import MOTION_SCALE, bench_fixtures, emulated, no_leaks  # noqa: F401 - fixture

from labcal.analysis.kinematics import Mount
from labcal.config.emulation import FaultKind
from labcal.drivers.errors import BadReply, DeviceFault, NoReply, Rejected
from labcal.sim.faults import Fault

QUICK = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}


# the DMM on a pty, and on TCP with a thermometer
station, rig, slow_rig = bench_fixtures(["smc100-serial", "az-modbus-tcp"], dmm=QUICK)


def unit(emulation):
    """The emulated 34970A itself, for what only its front panel would show."""
    return next(server.device for _, protocol, server in emulation.servers.values() if "34970A" in protocol)


@pytest.fixture
def dmm(rig):
    emulation, bench = rig
    bench.dmm.configure()
    return emulation, bench.dmm


def test_identity_and_a_clean_error_queue(dmm):
    _, meter = dmm
    assert meter.identify().startswith("Keysight Technologies,34970A,")
    assert meter.errors() == []


def test_readings_are_the_instruments_outputs_at_the_tables_angles(dmm):
    """Tables at pitch 30°, roll 60°, mount (180, 0), settled: the mean of 20 sweeps is the truth's
    output there (temperature and drift included) within 5 standard errors of the noise."""
    emulation, meter = dmm
    rig = emulation.rig.rig
    with emulation.rig.lock:
        rig.pitch.move_to(30.0)
        rig.roll.move_to(60.0)
    emulation.rig.set_mount(Mount(180, 0))
    emulation.rig.clock.sleep(30)  # the moves, then 60 output time constants
    t0 = emulation.rig.clock.now()
    scan = meter.read(20)
    t = emulation.rig.clock.now()
    with emulation.rig.lock:
        expected = rig.instrument.static_volts(rig.true_gravity(30.0, 60.0), t, rig.lab_temperature(t))
    noise = rig.instrument.noise_v
    assert scan.volts.shape == (20, 3)
    assert np.max(np.abs(scan.volts.mean(axis=0) - expected)) < 5 * noise / np.sqrt(20)
    assert np.std(scan.volts - scan.volts.mean(axis=0), ddof=1) == pytest.approx(noise, rel=0.3)
    if meter.measures_temperature:
        # the lab swings ±0.3 °C over 6 h, smoothly: each reading lies between the lab's temperature
        # before and after the read (whatever wall time a loaded machine added to the rig's clock),
        # within 0.001 °C (the curvature over minutes is below 1e-6 °C)
        low, high = sorted((rig.lab_temperature(t0), rig.lab_temperature(t)))
        assert scan.temp_c.shape == (20,) and np.all((low - 1e-3 < scan.temp_c) & (scan.temp_c < high + 1e-3))
    else:
        assert scan.temp_c is None


def test_a_scan_takes_the_units_integration_time(slow_rig):
    emulation, bench = slow_rig
    meter = bench.dmm
    meter.configure()
    n = 5
    t0 = emulation.rig.clock.now()
    meter.read(n)
    took = emulation.rig.clock.now() - t0
    # hardware_protocols.md §3.1 timing model: per channel, the integration twice (autozero on)
    # plus a few ms of relay switching and settling (5 ms here): NPLC 10 at 50 Hz is ~0.4 s
    per_channel = 2 * meter.nplc / meter.line_hz + 0.005
    expected = n * len(meter.scan_list) * per_channel  # 6 or 8 s of rig time
    assert expected <= took < expected + 0.2 * MOTION_SCALE  # plus at most 0.2 s of wall time for the bytes


def test_the_error_queue(dmm):
    _, meter = dmm
    link = meter.link
    link.write_line("VOLT:DC:NPLC 7,(@101)")  # not an NPLC the unit has
    link.write_line("FROB 1")
    link.write_line("SENSe:VOLTage:DC:NPLCycles 1,(@101)")  # long forms are fine
    assert meter.errors() == [(-222, "Data out of range"), (-113, "Undefined header")]
    link.write_line("*RST")
    with pytest.raises(NoReply):
        link.query("FETC?")  # nothing measured since the reset: no reply, error -230
    assert meter.errors() == [(-230, "Data corrupt or stale")]
    assert link.query("ROUT:SCAN?") == "#13(@)"  # a definite-length block: 1 digit, 3 bytes


def test_an_overload_is_reported_not_averaged(dmm):
    emulation, meter = dmm
    emulation.faults["dmm"].add(Fault(FaultKind.ALARM))
    with pytest.raises(DeviceFault, match="dmm .*channel 101 overloaded \\(\\+9.9E\\+37\\): check the range"):
        meter.read(3)
    assert meter.read(3).volts.shape == (3, 3)


def test_a_refused_command_is_reported_with_the_units_words(dmm):
    """Refused once, the scan is taken again after the configuration was verified; refused every
    time, the unit's words. About words, not timing: the link waits 0.5 s, not the module's 0.1 s,
    since with both cores busy a reply later than 0.1 s (read as the error queue's by the next query)
    turned the third refusal into a lost scan, a true report without the unit's words."""
    emulation, meter = dmm
    meter.link.timeout_s = 0.5
    emulation.faults["dmm"].add(Fault(FaultKind.EXCEPTION, code=-221, match="^INIT"))
    assert meter.read(2).volts.shape == (2, 3)
    emulation.faults["dmm"].add(Fault(FaultKind.EXCEPTION, code=-221, match="^INIT", count=3))
    with pytest.raises(Rejected, match="SCPI error -221 \"Settings conflict\" after .*; verifying the unit"):
        meter.read(2)


@pytest.mark.parametrize("kind", [FaultKind.NO_REPLY, FaultKind.GARBLED, FaultKind.LATE_REPLY])
def test_a_lost_garbled_or_late_scan_is_taken_again(dmm, kind):
    emulation, meter = dmm
    emulation.faults["dmm"].add(Fault(kind, match="FETC", delay_s=0.5))  # beyond the FETC? deadline (0.29 s)
    scan = meter.read(4)
    assert scan.volts.shape == (4, 3) and emulation.faults["dmm"].count(kind) == 1
    assert list(emulation.faults["dmm"].recent).count("INIT") >= 2


def test_a_reply_later_than_the_timeout_is_drained_not_read_as_the_error_queues_answer(dmm, caplog):
    """A reply that comes after the query's timeout (a loaded computer, a slow link): the driver asks
    the error queue why the unit was silent, and the late reply must not be taken for its answer.
    It was: the error queue's ``SYST:ERR?`` read the late ranges and the try ended as a BadReply
    ('+1.00000000E+01,... is not an error-queue entry') instead of the silence it was."""
    emulation, meter = dmm
    # just past the 0.1 s timeout, as on a loaded machine; the drain listens until the line has been
    # quiet for one timeout (a reply later still is the next try's to recognise: a BadReply)
    emulation.faults["dmm"].add(Fault(FaultKind.LATE_REPLY, match="^VOLT:DC:RANG", delay_s=0.12))
    with pytest.raises(NoReply, match="no reply within 0.1 s"):
        meter._ask("VOLT:DC:RANG? (@101,102,103)")
    assert "late reply discarded" in caplog.text and emulation.faults["dmm"].count(FaultKind.LATE_REPLY) == 1
    assert meter.errors() == []  # the queue read after it is the queue's, and the line is clean
    assert meter.differences() == []


def test_bounded_retries(dmm):
    emulation, meter = dmm
    emulation.faults["dmm"].add(Fault(FaultKind.GARBLED, count=3, match="FETC"))
    with pytest.raises(BadReply, match="dmm \\(Keysight 34970A, .*garbled reply"):
        meter.read(2)


def test_the_port_comes_back(dmm):
    emulation, meter = dmm
    emulation.faults["dmm"].add(Fault(FaultKind.CLOSE_PORT, reopen_s=0.2, match="FETC"))
    meter.configure()  # a reopened serial unit may have lost its setup; configuring again is safe
    assert meter.read(2).volts.shape == (2, 3)


def test_a_slow_scan_on_a_slow_serial_line_is_waited_for(tmp_path, no_leaks):  # noqa: F811
    """At 2400 Bd the readings of 2 sweeps × 4 channels take 1.5 s to arrive (45 characters
    each with its time stamp and channel, "+1.23456789E+00,2026,01,01,12,00,01.234,101,"; 10 bits
    a character), more than twice the link's 0.5 s timeout: the FETC? deadline scales
    with the reply's length at the line's rate (the emulator paces its replies in rig time, here
    real time)."""
    slow_line = {"timeout_s": 0.5, "retries": 0, "baudrate": 2400, "nplc": 0.2}
    with emulated("smc100-serial", tmp_path, time_scale=1.0, dmm=slow_line) as (emulation, bench):
        bench.dmm.configure()
        assert bench.dmm.scan_list == (101, 102, 103, 104)
        scan_s, fetch_s = bench.dmm.deadlines_s(2)
        assert fetch_s == pytest.approx(0.5 + 1.5 * 2 * 4 * (45 * 10 / 2400 + 0.002))
        assert scan_s == pytest.approx(0.5 + 1.5 * 2 * 4 * (2 * 0.2 / 50 + 0.005))
        assert bench.dmm.read(2).volts.shape == (2, 3)


def test_on_rs232_nothing_is_obeyed_before_syst_rem(tmp_path, no_leaks):  # noqa: F811
    """The emulator, from the User's Guide: on RS-232, SYST:REM first; the driver sends it first."""
    with emulated("smc100-serial", tmp_path, dmm=QUICK) as (emulation, bench):
        link = bench.dmm.link
        with pytest.raises(NoReply):
            link.query("*IDN?")  # in local: ignored
        assert bench.dmm.identify().startswith("Keysight Technologies,34970A,")
        bench.dmm.configure()
        assert bench.dmm.read(1).volts.shape == (1, 3)


def test_another_instrument_at_the_dmm_address_is_one_line(tmp_path, no_leaks, monkeypatch):  # noqa: F811
    from labcal.sim import dmm_emulator

    monkeypatch.setattr(dmm_emulator, "IDN", "Keysight Technologies,34465A,MY12345678,A.02.14")
    with emulated("az-modbus-tcp", tmp_path, dmm=QUICK) as (_, bench):
        with pytest.raises(DeviceFault, match="dmm .*answers \\*IDN\\? with '.*34465A.*', not a 34970A/"):
            bench.dmm.identify()
        [report] = [r for r in bench.check() if r["device"] == "dmm"]
        assert "identity" not in report and "34465A" in report["problem"]


def _loading(emulation, meter, n: int = 20) -> float:
    """The DMM's reading of a change of the instrument's outputs over the change itself: tables from
    pitch 0°, roll 0° to pitch 180°, roll 90° (each output swings by up to 2 g × 5 V/g), each
    attitude settled, 20 sweeps averaged; one least-squares ratio over the three channels."""
    rig = emulation.rig.rig
    read, true = [], []
    for pitch, roll in ((0.0, 0.0), (180.0, 90.0)):
        with emulation.rig.lock:
            rig.pitch.move_to(pitch)
            rig.roll.move_to(roll)
        emulation.rig.clock.sleep(30)  # the moves, then 60 output time constants
        read.append(meter.read(n).volts.mean(axis=0))
        t = emulation.rig.clock.now()
        with emulation.rig.lock:
            true.append(rig.instrument.static_volts(rig.true_gravity(pitch, roll), t, rig.lab_temperature(t)))
    d_read, d_true = read[1] - read[0], true[1] - true[0]
    return float(d_read @ d_true / (d_true @ d_true))


def test_the_high_impedance_input_is_declared_and_a_10_megohm_input_reads_500_ppm_low(dmm):
    """Issue 22 item 4. The instrument's outputs have a 5 kΩ source resistance (the emulation's
    default); the 34970A's DC volts input is 10 MΩ unless INP:IMP:AUTO ON gives the ≤10 V ranges
    >10 GΩ. By hand: a 10 MΩ input reads 10e6/(10e6 + 5e3) = 0.99950025 of the output (500 ppm
    low), a 10 GΩ one 10e9/(10e9 + 5e3) = 0.9999995. The ratio's noise: 20 µV/√20 per mean over a
    change of ~10 V, under 1 ppm; the tolerance, 20 ppm, is 25 times smaller than the effect."""
    emulation, meter = dmm
    assert emulation.station_config.emulation.rig.output_ohm == 5000.0
    volts = "(@101,102,103)"
    assert meter.link.query(f"INP:IMP:AUTO? {volts}") == "1,1,1"  # the driver's configuration sent it
    assert _loading(emulation, meter) == pytest.approx(10e9 / (10e9 + 5e3), abs=20e-6)
    meter.link.write_line(f"INP:IMP:AUTO OFF,{volts}")  # labcal once did: the reset default
    assert _loading(emulation, meter) == pytest.approx(10e6 / (10e6 + 5e3), abs=20e-6)
    assert 10e6 / (10e6 + 5e3) == pytest.approx(1 - 500e-6, abs=1e-6)


def test_no_high_impedance_input_above_10_volts(tmp_path, no_leaks):  # noqa: F811
    """The 100 V range has no >10 GΩ input (User's Guide, DC input resistance): the driver does not
    ask for one there, and the unit keeps its 10 MΩ."""
    with emulated("az-modbus-tcp", tmp_path, dmm={**QUICK, "range_v": 100.0}) as (emulation, bench):
        bench.dmm.configure()
        assert bench.dmm.link.query("INP:IMP:AUTO? (@101:103)") == "0,0,0"
        assert "INP:IMP:AUTO ON" not in " ".join(emulation.faults["dmm"].recent)


def test_a_lost_init_does_not_fetch_the_previous_scan(dmm):
    """Issue 22 item 6: the INIT of a scan never reaches the unit (noise on the line). *OPC?
    answers at once and FETC? returns the previous scan, taken at the tables' previous attitude.
    The driver sees that the fetched scan began when the last one did (the readings' time stamps),
    discards it and scans again: the readings are those of the new attitude, taken after the move.
    Before, the previous attitude's readings came back for the new point (volts off by up to 2 g)."""
    emulation, meter = dmm
    rig = emulation.rig.rig
    first = meter.read(3)
    with emulation.rig.lock:
        rig.pitch.move_to(180.0)  # every output that sees gravity changes by up to 2 g × 5 V/g
    emulation.rig.clock.sleep(30)
    emulation.faults["dmm"].add(Fault(FaultKind.LOST_REQUEST, match="^INIT"))
    t0 = emulation.rig.clock.now()
    second = meter.read(3)
    t = emulation.rig.clock.now()
    assert emulation.faults["dmm"].count(FaultKind.LOST_REQUEST) == 1
    assert list(emulation.faults["dmm"].recent).count("INIT") == 3  # the first scan, the lost one, again
    with emulation.rig.lock:
        expected = rig.instrument.static_volts(rig.true_gravity(180.0, 0.0), t, rig.lab_temperature(t))
    noise = rig.instrument.noise_v
    assert np.max(np.abs(second.volts.mean(axis=0) - expected)) < 5 * noise / np.sqrt(3) + 10e-6  # + loading
    assert np.max(np.abs(second.volts.mean(axis=0) - first.volts.mean(axis=0))) > 1.0
    assert t - t0 >= 3 * len(meter.scan_list) * 2 * meter.nplc / meter.line_hz  # a scan was taken after


def test_a_lost_first_init_is_measured_again(dmm):
    """A lost INIT right after the configuration (*RST emptied the memory): FETC? has nothing to
    give and the unit says -230 "Data corrupt or stale" — a scan to take again, not a refusal."""
    emulation, meter = dmm
    emulation.faults["dmm"].add(Fault(FaultKind.LOST_REQUEST, match="^INIT"))
    assert meter.read(2).volts.shape == (2, 3)
    assert meter.errors() == []


def test_the_declared_configuration_is_read_back_and_restored(dmm, caplog):
    """Issue 22 item 5: range, NPLC, input impedance, scan list and reading format are a declared
    state. Someone sets NPLC 1 at the front panel between mounts (the unit would then integrate
    20 ms instead of 200 ms, with 10 times less mains rejection): the check at the mount names it
    and configures the unit again."""
    emulation, meter = dmm
    assert meter.differences() == [] and meter.verify() == []
    meter.link.write_line("VOLT:DC:NPLC 1,(@102)")
    found = meter.verify("at the mount")
    assert found == ["VOLT:DC:NPLC? (@101,102,103) answers 10,1,10, declared 10,10,10"], found
    assert "at the mount: VOLT:DC:NPLC?" in caplog.text and "configuring it again" in caplog.text
    assert [unit(emulation).state.channels[c].nplc for c in (101, 102, 103)] == [10.0, 10.0, 10.0]
    assert meter.differences() == []


@pytest.mark.parametrize("when", ["TRIG:COUN", "FETC"])
def test_a_power_cycled_dmm_is_configured_again_and_the_scan_taken(dmm, when, caplog):
    """Issue 22 item 5: the unit is switched off and on as a scan begins or is fetched. It comes
    back with its power-on defaults (no scan list, NPLC 1... here none configured at all, 10 MΩ
    input) and, on RS-232, deaf until SYST:REM; on TCP the connection is gone. The driver's next
    try sends SYST:REM, sees the power-on bit of *ESR?, sends the configuration, reads it back and
    takes the scan. Before, the scan failed with "no reply" again and again."""
    emulation, meter = dmm
    meter.read(2)
    emulation.faults["dmm"].add(Fault(FaultKind.POWER_CYCLE, match=when))
    scan = meter.read(3)
    assert scan.volts.shape == (3, 3) and emulation.faults["dmm"].count(FaultKind.POWER_CYCLE) == 1
    assert "it was powered off and on (*ESR? power-on bit); configuring it again" in caplog.text
    state = unit(emulation).state
    assert state.scan_list == list(meter.scan_list)
    assert all(state.channels[c].impedance_auto and state.channels[c].nplc == 10.0 for c in meter.channels)
    assert meter.differences() == []


def test_a_dmm_reset_between_scans_is_seen_by_its_power_on_bit(dmm, caplog):
    """A power cycle between two scans that leaves the link as it was (GPIB, or a LAN connection
    that survived it): the unit, with no scan list, refuses the scan (-221); the next try verifies
    the unit, finds its power-on bit, and configures it again."""
    emulation, meter = dmm
    meter.read(2)
    unit(emulation).power_cycle()
    unit(emulation).remote = True  # as a GPIB or LAN unit would be
    assert meter.read(2).volts.shape == (2, 3)
    assert "after a failed exchange: it was powered off and on" in caplog.text
    assert meter.differences() == []


def test_a_long_fast_scan_is_waited_for_on_a_network_link(tmp_path, no_leaks):  # noqa: F811
    """Issue 22 item 9: 3000 sweeps of 4 channels at NPLC 0.02 on TCP, 12000 readings and ~540 kB
    of reply, which the unit takes time to send from its memory (the emulator, to format: tenths of
    a second of wall time), far more than the link's 0.1 s timeout. The FETC? deadline allows 2 ms
    a reading on any link; by hand: 0.1 + 1.5 × 12000 × 0.002 = 36.1 s. Before, it was the link's
    0.1 s on a network link, and the scan was lost and taken again until the retries ran out."""
    quick = {"timeout_s": 0.1, "retries": 0, "nplc": 0.02}
    with emulated("az-modbus-tcp", tmp_path, dmm=quick) as (_, bench):
        bench.dmm.configure()
        assert bench.dmm.deadlines_s(3000)[1] == pytest.approx(0.1 + 1.5 * 12000 * 0.002)
        assert bench.dmm.read(3000).volts.shape == (3000, 3)


def test_a_reading_that_lost_a_byte_but_still_parses_is_scanned_again(dmm, caplog):
    """One byte of the FETC? reply is lost on the line: the first reading's 8th significant digit
    ("+5.01318258E+00" arriving as "+5.0131828E+00": still a number, off by up to 1.6 standard
    errors of a point's mean where the lost digit is the 4th or 5th decimal). Every reading is checked
    against the width the unit writes it in (SD.DDDDDDDDESDD, yyyy,mm,dd,hh,mm,ss.sss, ccc: User's
    Guide, "Reading format"), so the reply is refused and the scan taken again; the scan returned
    is the second one, whole."""
    emulation, meter = dmm
    meter.read(2)
    fault = emulation.faults["dmm"].add(Fault(FaultKind.DROPPED_BYTE, match="FETC"))
    scan = meter.read(3)
    assert emulation.faults["dmm"].count(FaultKind.DROPPED_BYTE) == 1 and fault.seen == 1
    assert scan.volts.shape == (3, 3)
    assert "reading 1 " in caplog.text and "is not as the unit writes it" in caplog.text, caplog.text
    reply = unit(emulation).handle("FETC?")  # the scan as the unit sent it: its first reading, short a byte
    first = reply.split(",")[0]
    shortened = first[:8] + first[9:]
    assert float(shortened) != float(first)  # a number still: only its width gives it away
    assert scan.volts[0, 0] == float(first)  # the scan taken again, as the unit sent it


def test_readings_stamped_out_of_order_are_refused():
    """Each reading is stamped after the one before it (the unit takes them one after another):
    a reply whose second reading is stamped before its first is not the unit's, whatever parses."""
    from labcal.drivers.keysight_34970a import parse_readings

    swapped = ("+1.00000000E+00,2026,01,01,12,00,01.500,101,-2.50000000E-01,2026,01,01,12,00,01.100,102,"
               "+4.99990000E+00,2026,01,01,12,00,01.900,103")
    with pytest.raises(BadReply, match="reading 2 is stamped 12:00:01.100000, not after the one before it"):
        parse_readings(swapped, [101, 102, 103], 1)


def test_a_reset_from_another_controller_during_a_scan_is_named_as_one(dmm, caplog):
    """Another controller sends *RST between a scan's INIT and its FETC?: the memory and the scan list are
    emptied (User's Guide, *RST), so FETC? finds no scan (-230), as after a lost INIT. The unit's
    empty scan list tells the two apart: the first report says it was reset, not that the INIT
    was lost; its configuration is restored and the scan taken again."""
    emulation, meter = dmm
    meter.read(2)
    another = unit(emulation)
    resets: list[str] = []

    def reset_then_fetch(line: str, handle=another.handle) -> str | None:
        if line.startswith("FETC") and not resets:  # once, as the scan is fetched
            resets.append(line)
            handle("*RST")
        return handle(line)
    another.handle = reset_then_fetch  # type: ignore[method-assign]
    try:
        scan = meter.read(2)
    finally:
        del another.handle
    assert scan.volts.shape == (2, 3) and resets == ["FETC?"]
    assert "the unit was reset during the scan (*RST from another controller" in caplog.text, caplog.text
    assert "the INIT was lost" not in caplog.text
    assert meter.differences() == []
