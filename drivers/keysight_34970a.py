"""Keysight (Agilent) 34970A / 34972A / DAQ970A data acquisition units over SCPI.

A DC-volts channel per sensor of the instrument's package (x, y, z of a three-axis one; fewer of a
single- or two-axis one, whose absent outputs a `Scan` carries as NaN) and optionally a temperature
channel in one scan list; each `read` is
``TRIG:COUN n``, ``INIT``, ``*OPC?`` (answers when the sweeps are done), ``FETC?`` (readings stay
in memory, so fetching again is safe) and ``SYST:ERR?``. Every reading carries its time of day
(``FORM:READ:TIME ON``, ``TYPE ABS``), so a fetched scan is known to be the one just started: a
lost ``INIT`` leaves the previous scan in memory, which ``FETC?`` would return again. Lines end in
LF; over RS-232 the unit needs ``SYST:REM`` first. A query the unit cannot answer gets no reply
and leaves an error in the queue, so silence is explained by reading the queue. Dialect:
hardware_protocols.md §3.1.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import TypeVar

import numpy as np

from labcal.devices.station import Scan
from labcal.drivers.errors import (
    TRANSIENT,
    BadReply,
    Busy,
    DeviceFault,
    NoReply,
    Overloaded,
    Rejected,
    on_device,
)
from labcal.drivers.transport import Lines, retried

T = TypeVar("T")
log = logging.getLogger(__name__)
EOL = b"\n"
OVERLOAD = 9.9e37
CHANNEL_S = 0.005  # relay switching and settling per channel, on top of integration
MAX_ERRORS = 20  # the 34970A's error queue holds 10; never loop for ever on a chatty device
# one reading with its time of day and channel number in a FETC? reply:
# "+1.23456789E+00,2026,01,01,12,00,01.234,101,"
READING_CHARS = 45
STAMP_FIELDS = 6  # an absolute time stamp is yyyy,mm,dd,hh,mm,ss.sss (FORMat:READing:TIME:TYPE ABS)
# Each reading exactly as the unit writes it, with the fields `commands` turns on (User's Guide,
# FORMat:READing and "Reading format": the reading SD.DDDDDDDDESDD, an overload +9.90000000E+37; the
# absolute time stamp yyyy,mm,dd,hh,mm,ss.sss; the channel number ccc; hardware_protocols.md §3.1
# "Reply formats"). A byte lost on the line may leave a number that still parses (+5.01318258E+00
# read as +5.0131828E+00): only the fixed width of every field tells it from the one sent.
READING_FORMAT = re.compile(r"[+-]\d\.\d{8}E[+-]\d{2},\d{4},\d{2},\d{2},\d{2},\d{2},\d{2}\.\d{3},\d{3}")
PON = 128  # *ESR? bit 7, power on: set when the unit powers up, cleared by *CLS or by reading it
# (IEEE 488.2 standard event register; 34970A User's Guide, status system, *ESR?)
POWERED_ON = "it was powered off and on (*ESR? power-on bit)"
NO_DATA = -230  # "Data corrupt or stale": FETC? with no scan in memory (after *RST, or before any INIT)
BITS_PER_CHAR = 10  # start, 8 data, stop (8N1; a parity bit makes it 11, within the margin)
MARGIN = 1.5  # deadlines allow half as long again as the estimate
# The unit's own time to take a reading from memory, format it and hand it to the interface, on
# top of the line's rate: what sizes a long FETC? on LAN or GPIB, where the line is fast. An
# allowance, generous against the ~3 ms a reading takes on RS-232 at 57600 Bd (hardware_protocols.md
# §3.1), most of which is the line's
OUTPUT_S = 0.002
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


class ScpiError(Rejected):
    """The unit refused a command: the first entry of its error queue, with its code."""

    def __init__(self, code: int, message: str, device: str | None = None):
        super().__init__(message, device)
        self.code = code


class ScanRefused(Busy):
    """The unit refused a scan (an error in its queue): repeated, once its configuration has been
    verified (a unit that was reset has no scan list); after every try, the unit's words."""


class StaleScan(BadReply):
    """``FETC?`` gave a scan other than the one just started (its ``INIT`` never arrived): discarded,
    and the scan is taken again like any reply that is not the answer."""


def parse_readings(line: str, scan_list: Sequence[int], sweeps: int, previous: datetime | None = None
                   ) -> tuple[np.ndarray, list[datetime]]:
    """``FETC?`` with absolute time stamps and channel numbers on (``+1.23E+00,2026,01,01,12,00,
    01.234,101,...``) → (sweeps, channels) array and each reading's time of day; the channels must
    come in scan-list order, sweep after sweep. A scan whose first reading is stamped ``previous``
    (when the last scan fetched began) is that scan again: `StaleScan`, whatever its length."""
    fields = line.split(",")
    width = 2 + STAMP_FIELDS
    expected = width * sweeps * len(scan_list)
    if len(fields) % width:
        raise BadReply(f"reply {line[:60]!r} is not readings, time stamps and channel numbers")
    for k in range(0, len(fields), width):
        if not READING_FORMAT.fullmatch(text := ",".join(fields[k:k + width])):
            raise BadReply(f"reading {k // width + 1} {text[:60]!r} is not as the unit writes it (a byte "
                           "lost or changed on the line?)")
    try:
        values = [float(f) for f in fields[0::width]]
        channels = [int(f) for f in fields[width - 1::width]]
        stamps = [stamp(fields[i + 1:i + 1 + STAMP_FIELDS]) for i in range(0, len(fields), width)]
    except ValueError:
        raise BadReply(f"reply {line[:60]!r} is not readings, time stamps and channel numbers") from None
    if previous is not None and stamps[0] == previous:
        raise StaleScan(f"FETC? returned the previous scan again (begun {previous:%H:%M:%S.%f}): the INIT "
                        "was lost; discarded")
    if len(fields) != expected:
        raise BadReply(f"{len(fields) // width} readings in the reply, {expected // width} expected")
    if channels != list(scan_list) * sweeps:
        raise BadReply(f"readings from channels {sorted(set(channels))[:8]}, scan list {list(scan_list)}")
    for k in range(1, len(stamps)):  # the unit takes its readings one after another, each ≥ 1 ms apart
        if stamps[k] <= stamps[k - 1]:
            raise BadReply(f"reading {k + 1} is stamped {stamps[k]:%H:%M:%S.%f}, not after the one before "
                           f"it ({stamps[k - 1]:%H:%M:%S.%f})")
    if not all(math.isfinite(v) for v in values):
        raise BadReply("a reading is not a finite number")
    return np.array(values).reshape(sweeps, len(scan_list)), stamps


def definite_block(reply: str) -> str:
    """An IEEE 488.2 definite-length block (``#213(@101,102,103)``) → its bytes as text."""
    match = re.fullmatch(r"#([1-9])(\d+)(.*)", reply.strip())
    if not match or int(match.group(1)) > len(match.group(2)):
        raise BadReply(f"{reply[:40]!r} is not a definite-length block")
    digits = int(match.group(1))
    length, text = int(match.group(2)[:digits]), match.group(2)[digits:] + match.group(3)
    if len(text) != length:
        raise BadReply(f"{reply[:40]!r} is not a definite-length block of {length} bytes")
    return text


def channels_of(text: str) -> list[int]:
    """``(@101:103,105)`` → [101, 102, 103, 105]; BadReply if it is not a channel list."""
    match = re.fullmatch(r"\(@([\d,: ]*)\)", text.strip())
    if not match:
        raise BadReply(f"{text[:40]!r} is not a channel list")
    channels: list[int] = []
    for part in filter(None, (p.strip() for p in match.group(1).split(","))):
        first, _, last = part.partition(":")
        channels += range(int(first), int(last or first) + 1)
    return channels


def spell(values: list[float]) -> str:
    """Numbers for a message: ``10,1,10``."""
    return ",".join(f"{v:g}" for v in values)


def stamp(fields: Sequence[str]) -> datetime:
    """``2026,01,01,12,00,01.234`` → that time of day; ValueError if it is not one."""
    year, month, day, hour, minute = (int(f) for f in fields[:5])
    seconds = float(fields[5])
    if not 0 <= seconds < 61:
        raise ValueError(fields[5])
    return datetime(year, month, day, hour, minute, int(seconds), round((seconds % 1) * 1e6) % 1000000)


class Keysight34970A:
    """A scanning DMM behind `labcal.devices.station.Voltmeter`."""

    model = "Keysight 34970A"

    def __init__(self, name: str, link: Lines, *, channels: Sequence[int] = (101, 102, 103),
                 temperature_channel: int | None = None, temperature_probe: str = "RTD,85",
                 nplc: float = 10.0, range_v: float = 10.0, line_hz: float = 50.0, retries: int = 2,
                 serial_line: bool = False, baudrate: int | None = None, axes: Sequence[int] = (0, 1, 2)):
        """``axes``: the output columns (0 x, 1 y, 2 z) ``channels`` are wired to, one each: a
        package without a sensor has no channel for it, and its column of every scan is NaN."""
        if len(axes) != len(channels):
            raise ValueError(f"{len(channels)} channels for {len(axes)} axes")
        self.name, self.link = name, link
        self.axes = tuple(axes)
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
        self.last_scan: datetime | None = None  # when the last scan fetched began, by the unit's clock
        self._verified_at: int | None = None  # the link's open count when the state was last verified
        self._suspect = False  # an exchange failed: the unit may have been reset, verify before using it

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
            code, text = found[0]
            raise ScpiError(code, f"SCPI error {code} \"{text}\" after {after}", self.device)

    def _ask(self, query: str, timeout_s: float | None = None) -> str:
        try:
            return self.link.query(query, timeout_s)
        except NoReply:
            # silence because the query failed, or just silence; a reply that comes late is drained
            # first, not read as the error queue's answer (it was, on a loaded machine: one try lost)
            self.link.drain()
            self._check(query)
            raise

    def _exchange(self, exchange: Callable[[], T]) -> T:
        with on_device(self.device):
            try:
                return retried(exchange, self.tries, self._recover, self.link.critical, self.device)
            except TRANSIENT:
                self.link.drop_connection()  # whoever asks next (a resumed run) asks on a new one
                self._suspect = True
                raise

    def _recover(self) -> None:
        """Between tries: a network connection is dropped (the next try opens a new one: a
        half-open connection would swallow every try), late replies are drained, and the next try
        verifies the unit first (silence may be a unit that was powered off and on: back to its
        defaults, and on RS-232 deaf until ``SYST:REM``)."""
        self.link.drop_connection()
        self.link.drain()
        self._suspect = True

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

    def commands(self) -> list[str]:
        """The configuration, from a reset: DC volts at a fixed range and NPLC on the sensors'
        channels with the high-impedance input where the range has it, the temperature channel,
        the scan list, each reading's time of day and channel number."""
        volts = channel_list(self.channels)
        commands = ["*RST", "*CLS", f"CONF:VOLT:DC {self.range_v:g},{volts}",
                    f"VOLT:DC:NPLC {self.nplc:g},{volts}"]
        commands += [f"INP:IMP:AUTO ON,{volts}"] if self.impedance_auto else []
        if self.temperature_channel:
            thermometer = channel_list([self.temperature_channel])
            commands += [f"CONF:TEMP {self.temperature_probe},{thermometer}",
                         f"TEMP:NPLC {self.nplc:g},{thermometer}"]  # the same mains rejection
        return commands + [f"ROUT:SCAN {channel_list(self.scan_list)}", "FORM:READ:CHAN ON",
                           "FORM:READ:TIME ON", "FORM:READ:TIME:TYPE ABS", "FORM:READ:UNIT OFF",
                           "FORM:READ:ALAR OFF", "TRIG:SOUR IMM"]

    def declared(self) -> dict[str, list[float] | str]:
        """The configuration as the unit reports it when it holds it: each query and its answer
        (numbers per channel, or text)."""
        volts, n = channel_list(self.channels), len(self.channels)
        state: dict[str, list[float] | str] = {
            f"VOLT:DC:RANG? {volts}": [self.range_v] * n, f"VOLT:DC:NPLC? {volts}": [self.nplc] * n,
            f"INP:IMP:AUTO? {volts}": [float(self.impedance_auto)] * n}
        if self.temperature_channel:
            state[f"TEMP:NPLC? {channel_list([self.temperature_channel])}"] = [self.nplc]
        return {**state, "ROUT:SCAN?": channel_list(self.scan_list), "FORM:READ:CHAN?": [1.0],
                "FORM:READ:TIME?": [1.0], "FORM:READ:TIME:TYPE?": "ABS", "FORM:READ:UNIT?": [0.0],
                "FORM:READ:ALAR?": [0.0]}

    def differences(self) -> list[str]:
        """Each declared setting the unit does not hold, as ``VOLT:DC:NPLC? (@101,102,103) answers
        1,1,1, declared 10,10,10`` (a query it cannot answer counts as a difference)."""
        found = []
        for query, want in self.declared().items():
            try:
                answer = self._ask(query)
            except (NoReply, Rejected) as exc:
                found.append(f"{query} unanswered ({exc})")
                continue
            if isinstance(want, str):
                text = answer.strip().upper()
                if query == "ROUT:SCAN?":
                    text = channel_list(channels_of(definite_block(answer)))
                if text != want:
                    found.append(f"{query} answers {text}, declared {want}")
                continue
            try:
                numbers = [float(f) for f in answer.split(",")]
            except ValueError:
                raise BadReply(f"{query} answered {answer[:40]!r}") from None
            if len(numbers) != len(want) or not all(
                    math.isclose(a, b, rel_tol=1e-6) for a, b in zip(numbers, want, strict=True)):
                found.append(f"{query} answers {spell(numbers)}, declared {spell(want)}")
        return found

    def _configure(self) -> None:
        """Send the configuration and read it back (inside an exchange)."""
        self._remote()
        for command in self.commands():
            self.link.write_line(command)
        self._check("configuration")
        if found := self.differences():
            raise DeviceFault(f"does not hold the configuration just sent ({'; '.join(found)}); check the "
                              "multiplexer card and the station's channels", self.device)
        self._verified_at, self._suspect = self.link.opens, False

    def configure(self) -> None:
        """Put the unit in the declared state (`commands`) and verify it by reading it back."""
        self._exchange(self._configure)

    def _inspect(self) -> list[str]:
        """What says the unit is not in the declared state: the power-on bit of ``*ESR?`` (it was
        reset), errors in its queue, or a setting that differs (inside an exchange)."""
        self._remote()
        if self._status() & PON:
            return [POWERED_ON]
        if errors := self.errors():
            return [f"errors in its queue: {', '.join(f'{c} {t!r}' for c, t in errors)}"]
        return self.differences()

    def _status(self) -> int:
        """``*ESR?``: the standard event register (reading it clears it)."""
        try:
            return int(self._ask("*ESR?"))
        except ValueError:
            raise BadReply("*ESR? did not answer a number") from None

    def _ensure(self, why: str, found: list[str] | None = None) -> list[str]:
        """Verify the declared state (unless ``found`` already says what is wrong); configure again
        if the unit lost it. Returns what was found."""
        found = self._inspect() if found is None else found
        if found:
            log.warning("%s: %s: %s; configuring it again", self.device, why, "; ".join(found))
            self._configure()
        self._verified_at, self._suspect = self.link.opens, False
        return found

    def verify(self, why: str = "verifying its configuration") -> list[str]:
        """Read the declared configuration back (at every mount, and whenever asked); a unit that
        was reset or changed is configured again. Returns what was found wrong (empty: nothing)."""
        return self._exchange(lambda: self._ensure(why))

    def _no_scan(self) -> StaleScan | ScanRefused:
        """What ``FETC?`` finding no scan (-230) after ``INIT`` means: the ``INIT`` was lost, or the
        unit was reset since it arrived (``*RST`` from another controller, or a power cycle: the
        reset empties the memory and the scan list, User's Guide, *RST and "Power-on and reset
        state"). Its scan list tells the two apart; either way the scan is taken again, the
        unit's configuration verified first."""
        try:
            listed = channels_of(definite_block(self._ask("ROUT:SCAN?")))
        except (NoReply, BadReply):
            listed = None  # unreadable: the retry's verification finds out
        if listed == []:
            return ScanRefused("no scan in memory after INIT (error -230) and no scan list: the unit was "
                               "reset during the scan (*RST from another controller, or a power cycle); "
                               "verifying its configuration", self.device)
        return StaleScan("no scan in memory after INIT (error -230): the INIT was lost")

    def scan_time_s(self, sweeps: int) -> float:
        """How long the unit needs for ``sweeps`` sweeps of the scan list."""
        return sweeps * len(self.scan_list) * channel_time_s(self.nplc, self.line_hz)

    def deadlines_s(self, sweeps: int) -> tuple[float, float]:
        """How long to wait for ``*OPC?`` (the scan: NPLC × channels × sweeps) and for ``FETC?``
        (its reply: every reading with its time stamp and channel number, each taken from memory by
        the unit and sent at the serial line's rate), each the link's own timeout plus half as long
        again as the estimate: a long fast scan is waited for, on any link."""
        transfer_s = sweeps * len(self.scan_list) * (READING_CHARS * self.char_s + OUTPUT_S)
        timeout = self.link.timeout_s
        return timeout + MARGIN * self.scan_time_s(sweeps), timeout + MARGIN * transfer_s

    def read(self, n_samples: int) -> Scan:
        """n sweeps of the scan list; a lost or garbled reply repeats the whole scan, and so does a
        stale one: a scan whose first reading is stamped as the last scan's was (its ``INIT`` was
        lost, so ``FETC?`` returned the previous scan), or no scan at all (error -230)."""
        scan_s, fetch_s = self.deadlines_s(n_samples)

        def once() -> np.ndarray:
            if self._suspect or self.link.opens != self._verified_at:
                self._ensure("after a failed exchange" if self._suspect else "after the link was reopened")
            try:
                self.link.write_line(f"TRIG:COUN {n_samples}")
                self.link.write_line("INIT")
                done = self._ask("*OPC?", scan_s)
                if done.strip() != "1":
                    raise BadReply(f"*OPC? answered {done[:40]!r}")
                reply = self._ask("FETC?", fetch_s)
                readings, stamps = parse_readings(reply, self.scan_list, n_samples, self.last_scan)
                self._check("the scan")
            except ScpiError as exc:
                if exc.code == NO_DATA:
                    raise self._no_scan() from None
                # a unit reset since the last scan (no scan list, another format) refuses it: the
                # next try verifies its configuration first
                raise ScanRefused(f"{exc.args[0].removeprefix(f'{self.device}: ')}; verifying the unit's "
                                  "configuration", self.device) from None
            self.last_scan = stamps[0]
            return readings

        readings = self._exchange(once)
        for column, channel in enumerate(self.scan_list):
            if np.any(np.abs(readings[:, column]) >= OVERLOAD):
                raise Overloaded(f"channel {channel} overloaded (+9.9E+37): check the range "
                                 f"({self.range_v:g} V) and the wiring", self.device, readings)
        n = len(self.channels)
        volts = np.full((len(readings), 3), np.nan)
        volts[:, list(self.axes)] = readings[:, :n]
        return Scan(volts=volts, temp_c=readings[:, n] if self.measures_temperature else None)
