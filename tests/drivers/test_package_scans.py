"""A package of fewer sensors on the 34970A: the driver configures and scans one channel per sensor
(the bytes the Keysight 34970A/34972A User's Guide documents for a scan list, hardware_protocols.md
§3.1) and files each reading in its sensor's column, NaN in the others; the emulated unit answers a
one- and a two-channel scan list as the manual says: ROUTe:SCAN? as an IEEE 488.2 definite-length
block of the list, and FETCh? as every sweep's readings in scan-list order, one per channel."""

from __future__ import annotations

import math

import numpy as np
import pytest
from transcripts import Transcript, lines

from labcal.config.emulation import InstrumentTruth, RigConfig
from labcal.drivers.keysight_34970a import Keysight34970A
from labcal.drivers.transport import LineTransport
from labcal.sim.dmm_emulator import Keysight34970AEmulator
from labcal.sim.emulated_rig import EmulatedRig

NO_ERROR = ("SYST:ERR?", '+0,"No error"')
STAMP = "2026,01,01,12,00,{:06.3f}"  # FORMat:READing:TIME:TYPE ABSolute: yyyy,mm,dd,hh,mm,ss.sss


def configuration(volts: str, scan: str, block: str, n: int, thermometer: str | None = None) -> list:
    """The driver's configuration of ``n`` volts channels, then its read-back: per-channel queries
    answer one value per channel of the list, ROUT:SCAN? the definite-length block ``block``."""
    ten = ",".join(["+1.00000000E+01"] * n)
    sent = [("*RST", None), ("*CLS", None), (f"CONF:VOLT:DC 10,{volts}", None),
            (f"VOLT:DC:NPLC 10,{volts}", None), (f"INP:IMP:AUTO ON,{volts}", None)]
    if thermometer:
        sent += [(f"CONF:TEMP RTD,85,{thermometer}", None), (f"TEMP:NPLC 10,{thermometer}", None)]
    sent += [(f"ROUT:SCAN {scan}", None), ("FORM:READ:CHAN ON", None), ("FORM:READ:TIME ON", None),
             ("FORM:READ:TIME:TYPE ABS", None), ("FORM:READ:UNIT OFF", None), ("FORM:READ:ALAR OFF", None),
             ("TRIG:SOUR IMM", None), NO_ERROR,
             (f"VOLT:DC:RANG? {volts}", ten), (f"VOLT:DC:NPLC? {volts}", ten),
             (f"INP:IMP:AUTO? {volts}", ",".join(["1"] * n))]
    if thermometer:
        sent += [(f"TEMP:NPLC? {thermometer}", "+1.00000000E+01")]
    return sent + [("ROUT:SCAN?", block), ("FORM:READ:CHAN?", "1"), ("FORM:READ:TIME?", "1"),
                   ("FORM:READ:TIME:TYPE?", "ABS"), ("FORM:READ:UNIT?", "0"), ("FORM:READ:ALAR?", "0")]


def fetched(*readings: tuple[str, float, int]) -> str:
    """FETC?'s reply: each reading, its time stamp (seconds of the minute) and its channel."""
    return ",".join(f"{value},{STAMP.format(second)},{channel}" for value, second, channel in readings)


def meter(transcript: Transcript, **settings) -> Keysight34970A:
    link = LineTransport("transcript", lambda: transcript, eol=b"\n", timeout_s=0.05, reconnect_s=0)
    return Keysight34970A("dmm", link, nplc=10, range_v=10, retries=0, **settings)


def test_a_single_sensor_is_scanned_on_its_channel_and_the_thermometer_and_filed_in_x():
    """Channel 101 (x) and the thermometer on 104: the scan list (@101,104) reads back as the block
    #210(@101,104) (one digit giving the length's two digits, then the 10 characters); two sweeps
    are four readings, x in column 0 and NaN for the y and z the package lacks."""
    readings = fetched(("+1.25000000E+00", 1.1, 101), ("+2.10500000E+01", 1.5, 104),
                       ("+1.25010000E+00", 1.9, 101), ("+2.10510000E+01", 2.3, 104))
    transcript = Transcript(lines(*configuration("(@101)", "(@101,104)", "#210(@101,104)", 1, "(@104)"),
                                  ("TRIG:COUN 2", None), ("INIT", None), ("*OPC?", "1"), ("FETC?", readings),
                                  NO_ERROR, eol="\n"))
    dmm = meter(transcript, channels=(101,), temperature_channel=104, axes=(0,))
    dmm.configure()
    scan = dmm.read(2)
    assert transcript.done()
    assert scan.volts[:, 0].tolist() == [1.25, 1.2501] and np.isnan(scan.volts[:, 1:]).all()
    assert scan.temp_c is not None and scan.temp_c.tolist() == [21.05, 21.051]


def test_an_x_z_package_files_its_second_channel_in_z():
    """Channels 101 and 103 wired to x and z: the block is #210(@101,103); the y column is NaN."""
    readings = fetched(("+1.00000000E+00", 1.1, 101), ("-3.00000000E+00", 1.5, 103))
    transcript = Transcript(lines(*configuration("(@101,103)", "(@101,103)", "#210(@101,103)", 2),
                                  ("TRIG:COUN 1", None), ("INIT", None), ("*OPC?", "1"), ("FETC?", readings),
                                  NO_ERROR, eol="\n"))
    dmm = meter(transcript, channels=(101, 103), axes=(0, 2))
    dmm.configure()
    volts = dmm.read(1).volts
    assert transcript.done()
    assert volts[0, 0] == 1.0 and math.isnan(volts[0, 1]) and volts[0, 2] == -3.0


def test_channels_and_axes_must_pair_one_to_one():
    with pytest.raises(ValueError, match="2 channels for 1 axes"):
        meter(Transcript([]), channels=(101, 102), axes=(0,))


def emulated_unit(package: str, wiring: dict[int, int | str]) -> Keysight34970AEmulator:
    """The emulated 34970A on a rig whose instrument has only ``package``'s sensors (the absent
    ones' outputs are NaN in the rig: reading one would show as nan in a reply)."""
    rig = EmulatedRig(RigConfig(instrument=InstrumentTruth(package=package, noise_v=1e-5)), time_scale=1e4,
                      seed=3)
    return Keysight34970AEmulator(rig, wiring)


@pytest.mark.parametrize(("package", "wiring", "scan", "block"), [
    ("single-axis", {101: 0}, "(@101)", "#16(@101)"),
    ("two-axis-xz", {101: 0, 103: 2}, "(@101,103)", "#210(@101,103)"),
])
def test_the_emulated_unit_answers_a_scan_of_fewer_channels_as_the_manual_says(package, wiring, scan, block):
    """CONFigure defines the scan list as its channels; ROUTe:SCAN? returns it as a definite-length
    block (#, the count of length digits, the length, the list: "(@101)" is 6 characters, so #16);
    three sweeps leave 3 × channels readings in memory (DATA:POINts?), and FETCh? returns them sweep
    by sweep in scan-list order, each with its channel number (FORMat:READing:CHANnel ON), every
    one a finite reading within the 10 V range."""
    unit = emulated_unit(package, wiring)
    channels = list(wiring)
    assert unit.handle(f"CONF:VOLT:DC 10,{scan}") is None
    assert unit.handle("ROUT:SCAN?") == block
    assert unit.handle("FORM:READ:CHAN ON;TRIG:COUN 3;INIT") is None
    assert unit.handle("*OPC?") == "1"
    assert unit.handle("DATA:POIN?") == str(3 * len(channels))
    fields = unit.handle("FETC?").split(",")
    assert [int(c) for c in fields[1::2]] == channels * 3
    values = [float(v) for v in fields[0::2]]
    assert all(math.isfinite(v) and abs(v) <= 10 for v in values), values
    assert unit.handle("SYST:ERR?") == '+0,"No error"'
