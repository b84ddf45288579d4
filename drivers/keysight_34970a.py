"""Keysight (Agilent) 34970A / 34972A / DAQ970A data acquisition units over SCPI.

Three DC-volts channels (and optionally a temperature channel) in one scan list; each `read` is
``TRIG:COUN n``, ``INIT``, ``*OPC?`` (answers when the sweeps are done), ``FETC?`` (readings stay
in memory, so fetching again is safe) and ``SYST:ERR?``. Lines end in LF; over RS-232 the unit
needs ``SYST:REM`` first. A query the unit cannot answer gets no reply and leaves an error in the
queue, so silence is explained by reading the queue. Dialect: hardware_protocols.md §3.1.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np

from labcal.drivers.errors import BadReply, DeviceFault, NoReply, Rejected, on_device
from labcal.drivers.transport import Lines, retried
from labcal.run.station import Scan

T = TypeVar("T")
log = logging.getLogger(__name__)
EOL = b"\n"
OVERLOAD = 9.9e37
CHANNEL_S = 0.005  # relay switching and settling per channel, on top of integration
MAX_ERRORS = 20  # the 34970A's error queue holds 10; never loop for ever on a chatty device
READING_CHARS = 20  # one reading with its channel number in a FETC? reply: "+1.23456789E+00,101,"
BITS_PER_CHAR = 10  # start, 8 data, stop (8N1; a parity bit makes it 11, within the margin)
MARGIN = 1.5  # deadlines allow half as long again as the estimate
# DC volts ranges with a >10 GΩ input under INPut:IMPedance:AUTO ON; above them, and on every range
# with AUTO OFF (the *RST and CONFigure default), the input is 10 MΩ, which a ~5 kΩ source output
# pulls ~500 ppm low (User's Guide, "DC input resistance"; hardware_protocols.md §3.1)
HIGH_Z_RANGES_V = (0.1, 1.0, 10.0)
FAMILY = ("34970A", "34972A", "DAQ970A", "DAQ973A")  # the models that speak this scan-list dialect


def channel_time_s(nplc: float, line_hz: float) -> float:
    """Time per channel: the integration twice (autozero is on), plus relay switching."""
    return 2 * nplc / line_hz + CHANNEL_S


def channel_list(channels: Sequence[int]) -> str:
    return "(@" + ",".join(str(c) for c in channels) + ")"


def parse_error(line: str) -> tuple[int, str]:
    """``-113,"Undefined header"`` → (-113, 'Undefined header')."""
    match = re.fullmatch(r'\s*([+-]?\d+)\s*,\s*"([^"]*)"\s*', line)
    if not match:
        raise BadReply(f"{line[:60]!r} is not an error-queue entry")
    return int(match.group(1)), match.group(2)


def parse_readings(line: str, scan_list: Sequence[int], sweeps: int) -> np.ndarray:
    """``FETC?`` with channel numbers on (``+1.23E+00,101,...``) → (sweeps, channels) array; the
    channels must come in scan-list order, sweep after sweep."""
    fields = line.split(",")
    expected = 2 * sweeps * len(scan_list)
    if len(fields) != expected:
        raise BadReply(f"{len(fields) // 2} readings in the reply, {expected // 2} expected")
    try:
        values = [float(f) for f in fields[0::2]]
        channels = [int(f) for f in fields[1::2]]
    except ValueError:
        raise BadReply(f"reply {line[:60]!r} is not readings and channel numbers") from None
    if channels != list(scan_list) * sweeps:
        raise BadReply(f"readings from channels {sorted(set(channels))[:8]}, scan list {list(scan_list)}")
    if not all(math.isfinite(v) for v in values):
        raise BadReply("a reading is not a finite number")
    return np.array(values).reshape(sweeps, len(scan_list))


class Keysight34970A:
    """A scanning DMM behind `labcal.station.Voltmeter`."""

    model = "Keysight 34970A"

    def __init__(self, name: str, link: Lines, *, channels: Sequence[int] = (101, 102, 103),
                 temperature_channel: int | None = None, temperature_probe: str = "RTD,85",
                 nplc: float = 10.0, range_v: float = 10.0, line_hz: float = 50.0, retries: int = 2,
                 serial_line: bool = False, baudrate: int | None = None):
        self.name, self.link = name, link
        self.device = f"{name} ({self.model}, {link.where})"
        self.channels = tuple(channels)
        self.temperature_channel = temperature_channel
        self.temperature_probe = temperature_probe
        self.scan_list = self.channels + ((temperature_channel,) if temperature_channel else ())
        self.nplc, self.range_v, self.line_hz = nplc, range_v, line_hz
        self.tries = retries + 1
        self.serial_line = serial_line
        self.char_s = BITS_PER_CHAR / baudrate if serial_line and baudrate else 0.0  # 0: network speed
        self.measures_temperature = temperature_channel is not None
        # declared: the >10 GΩ input wherever the range has one (CONFigure turns it off again)
        self.impedance_auto = range_v in HIGH_Z_RANGES_V

    # --- exchanges --------------------------------------------------------------------------
    def errors(self) -> list[tuple[int, str]]:
        """Empty the error queue."""
        found: list[tuple[int, str]] = []
        for _ in range(MAX_ERRORS):
            code, text = parse_error(self.link.query("SYST:ERR?"))
            if code == 0:
                return found
            found.append((code, text))
        raise BadReply(f"the error queue does not empty ({found[-1]})")

    def _check(self, after: str) -> None:
        if found := self.errors():
            raise Rejected(f"SCPI error {found[0][0]} \"{found[0][1]}\" after {after}", self.device)

    def _ask(self, query: str, timeout_s: float | None = None) -> str:
        try:
            return self.link.query(query, timeout_s)
        except NoReply:
            self._check(query)  # silence because the query failed, or just silence
            raise

    def _exchange(self, exchange: Callable[[], T]) -> T:
        with on_device(self.device):
            return retried(exchange, self.tries, self.link.drain, self.link.critical, self.device)

    # --- the voltmeter ----------------------------------------------------------------------
    def _remote(self) -> None:
        """On RS-232 the unit obeys nothing before ``SYST:REM`` (User's Guide, SYSTem:REMote)."""
        if self.serial_line:
            self.link.write_line("SYST:REM")

    def identify(self) -> str:
        """``*IDN?``: maker, model, serial number, firmware. A unit that answers as another model
        is refused: this driver's scan-list dialect is the 34970A family's."""
        def once() -> str:
            self._remote()
            return self._ask("*IDN?")

        identity = self._exchange(once)
        fields = [f.strip() for f in identity.split(",")]
        if len(fields) != 4 or not any(model in fields[1].upper() for model in FAMILY):
            raise DeviceFault(f"answers *IDN? with {identity[:80]!r}, not a {'/'.join(FAMILY)}; check the "
                              "station file's dmm link (is another instrument at that address?)", self.device)
        return identity

    def configure(self) -> None:
        """Put the unit in a known state: DC volts at a fixed range and NPLC on the three
        channels with the high-impedance input where the range has it, the temperature channel,
        the scan list, channel numbers in the readings."""
        volts = channel_list(self.channels)
        commands = (["SYST:REM"] if self.serial_line else []) + ["*RST", "*CLS"] + [
            f"CONF:VOLT:DC {self.range_v:g},{volts}", f"VOLT:DC:NPLC {self.nplc:g},{volts}"] + (
            [f"INP:IMP:AUTO ON,{volts}"] if self.impedance_auto else [])
        if self.temperature_channel:
            thermometer = channel_list([self.temperature_channel])
            commands += [f"CONF:TEMP {self.temperature_probe},{thermometer}",
                         f"TEMP:NPLC {self.nplc:g},{thermometer}"]  # the same mains rejection
        commands += [f"ROUT:SCAN {channel_list(self.scan_list)}", "FORM:READ:CHAN ON", "FORM:READ:TIME OFF",
                     "FORM:READ:UNIT OFF", "FORM:READ:ALAR OFF", "TRIG:SOUR IMM"]

        def once() -> None:
            for command in commands:
                self.link.write_line(command)
            self._check("configuration")

        self._exchange(once)

    def scan_time_s(self, sweeps: int) -> float:
        """How long the unit needs for ``sweeps`` sweeps of the scan list."""
        return sweeps * len(self.scan_list) * channel_time_s(self.nplc, self.line_hz)

    def deadlines_s(self, sweeps: int) -> tuple[float, float]:
        """How long to wait for ``*OPC?`` (the scan: NPLC × channels × sweeps) and for ``FETC?``
        (its reply: every reading with its channel number, at the serial line's rate), each the
        link's own timeout plus half as long again as the estimate."""
        transfer_s = sweeps * len(self.scan_list) * READING_CHARS * self.char_s
        timeout = self.link.timeout_s
        return timeout + MARGIN * self.scan_time_s(sweeps), timeout + MARGIN * transfer_s

    def read(self, n_samples: int) -> Scan:
        """n sweeps of the scan list; a lost or garbled reply repeats the whole scan."""
        scan_s, fetch_s = self.deadlines_s(n_samples)

        def once() -> np.ndarray:
            self.link.write_line(f"TRIG:COUN {n_samples}")
            self.link.write_line("INIT")
            done = self._ask("*OPC?", scan_s)
            if done.strip() != "1":
                raise BadReply(f"*OPC? answered {done[:40]!r}")
            readings = parse_readings(self._ask("FETC?", fetch_s), self.scan_list, n_samples)
            self._check("the scan")
            return readings

        readings = self._exchange(once)
        for column, channel in enumerate(self.scan_list):
            if np.any(np.abs(readings[:, column]) >= OVERLOAD):
                raise DeviceFault(f"channel {channel} overloaded (+9.9E+37): check the range "
                                  f"({self.range_v:g} V) and the wiring", self.device)
        volts = readings[:, :3]
        return Scan(volts=volts, temp_c=readings[:, 3] if self.measures_temperature else None)
