"""A Keysight 34970A with a multiplexer card, wired to the emulated instrument's outputs.

Speaks the SCPI subset a scanning DMM needs (CONF, NPLC, ROUT:SCAN, FORM:READ, TRIG, INIT,
*OPC?, FETC?, DATA:POIN?, ABOR, SYST:ERR?) with short and long mnemonics, ``;``-joined commands,
and a SCPI error queue. Each channel is measured at its own moment of the scan, from the rig's
physics at the tables' current angles and the current mount; a sweep takes as long as the real
unit's integration (scaled with the rig's clock). On RS-232 the unit obeys nothing until
``SYST:REM`` (User's Guide, "RS-232 interface configuration" / SYSTem:REMote): until then a
command is ignored and answered by nothing. Written from the Keysight 34970A/34972A User's Guide,
not from labcal's driver; each constant below cites its place.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timedelta

import numpy as np

from labcal.sim.emulated_rig import EmulatedRig

# *IDN?: manufacturer, model, serial number, firmware revisions (User's Guide, "*IDN?": the
# 34970A answers e.g. "HEWLETT-PACKARD,34970A,0,13-2-2"; later units say Agilent/Keysight)
IDN = "Keysight Technologies,34970A,MY00000001,13-2-2"
OVERLOAD = 9.9e37  # an overload reads +9.90000000E+37 (User's Guide, "Overload" readings)
# Settable integration times in PLC and DC volts ranges (User's Guide, DC voltage: "Integration
# time" and "Ranges" tables); others get -222 "Data out of range"
NPLC_VALUES = (0.02, 0.2, 1.0, 2.0, 10.0, 20.0, 100.0, 200.0)
RANGES_V = (0.1, 1.0, 10.0, 100.0, 300.0)
SWITCH_AND_DELAY_S = 0.005  # relay closure and automatic channel delay per channel (User's Guide,
# "Channel delay": automatic delay for DC volts; 34901A relay operate time)
ERRORS = {-102: "Syntax error", -113: "Undefined header", -221: "Settings conflict",
          -222: "Data out of range", -230: "Data corrupt or stale", -350: "Queue overflow"}
QUEUE_SIZE = 10
# The standard event register (*ESR?, IEEE 488.2; User's Guide, "Status System"): bit 7 power on,
# 5 command error (-1xx), 4 execution error (-2xx), 3 device-dependent error (-3xx), 2 query error
# (-4xx); reading it or *CLS clears it
PON = 128
ERROR_BITS = {1: 32, 2: 16, 3: 8, 4: 4}
# DC volts input resistance (User's Guide, "DC input resistance" / INPut:IMPedance:AUTO): fixed at
# 10 MΩ on every range with AUTO OFF, the *RST and CONFigure default; with AUTO ON, >10 GΩ on the
# 100 mV, 1 V and 10 V ranges (10 GΩ here, the bound the manual gives) and still 10 MΩ above
INPUT_OHM = 10e6
HIGH_Z_OHM = 10e9
HIGH_Z_RANGES_V = (0.1, 1.0, 10.0)
OVER_RANGE = 1.2  # readings beyond 120 % of the range are overloads
FORM_FIELDS = ("CHAN", "TIME", "UNIT", "ALAR")  # FORMat:READing fields, in reply order after the value
# The unit's real-time clock at rig time 0 (an emulation choice: the battery-backed clock is set by
# SYSTem:DATE/TIME); absolute time stamps are "yyyy,mm,dd,hh,mm,ss.sss", 1 ms resolution (User's
# Guide, FORMat:READing:TIME:TYPE ABSolute; the 34980A's reading format shows "2004,11,21,15,30,23.000")
CLOCK_AT_ZERO = datetime(2026, 1, 1)


def _regex(spec: str) -> re.Pattern:
    """SCPI header spec (``[SENSe:]VOLTage[:DC]:NPLCycles``) → regex accepting short and long forms."""
    def mnemonic(m: re.Match) -> str:
        word = m.group(0)
        short = "".join(c for c in word if c.isupper() or c.isdigit())
        return f"(?:{word.upper()}|{short})" if short != word.upper() else word.upper()

    optional = re.escape(spec).replace(r"\[", "(?:").replace(r"\]", ")?")
    return re.compile(re.sub(r"[A-Za-z][A-Za-z0-9]*", mnemonic, optional), re.IGNORECASE)


def parse_channels(text: str) -> list[int]:
    """``(@101:103,105)`` → [101, 102, 103, 105]; ValueError if malformed."""
    match = re.fullmatch(r"\(@([\d,: ]+)\)", text.strip())
    if not match:
        raise ValueError(text)
    channels: list[int] = []
    for part in match.group(1).split(","):
        first, _, last = part.strip().partition(":")
        channels += range(int(first), int(last or first) + 1)
    return channels


@dataclass
class Channel:
    function: str  # "VOLT" or "TEMP"
    range_v: float = 10.0
    nplc: float = 1.0
    impedance_auto: bool = False  # INPut:IMPedance:AUTO; CONFigure and *RST turn it off

    def input_ohm(self) -> float:
        """The input resistance the channel presents to its source."""
        return HIGH_Z_OHM if self.impedance_auto and self.range_v in HIGH_Z_RANGES_V else INPUT_OHM


@dataclass
class ScanRun:
    """One INIT: when it began, the sweeps it takes, and the readings once measured."""

    start: float
    channels: list[int]
    durations: list[float]
    sweeps: int
    readings: np.ndarray | None = None
    aborted_at: float | None = None

    @property
    def sweep_s(self) -> float:
        return sum(self.durations)

    @property
    def end(self) -> float:
        return self.start + self.sweeps * self.sweep_s if self.aborted_at is None else self.aborted_at

    def times(self) -> np.ndarray:
        """Mid-integration time of every reading, sweep after sweep."""
        offsets = np.cumsum([0.0, *self.durations[:-1]]) + 0.5 * np.asarray(self.durations)
        return (self.start + np.arange(self.sweeps)[:, None] * self.sweep_s + offsets[None, :]).ravel()

    def done_by(self, t: float) -> int:
        return int(np.sum(self.times() <= t))


@dataclass
class State:
    channels: dict[int, Channel] = field(default_factory=dict)
    scan_list: list[int] = field(default_factory=list)
    form: dict[str, bool] = field(default_factory=lambda: dict.fromkeys(FORM_FIELDS, False))
    time_absolute: bool = False  # FORMat:READing:TIME:TYPE ABSolute (*RST: RELative)
    trigger_count: int = 1
    scan: ScanRun | None = None


def channel_s(nplc: float, line_hz: float) -> float:
    """One channel of a sweep: the integration, once more for autozero (on by default: the offset
    is measured after every reading, User's Guide "Autozero"), and the switch/delay time."""
    return 2 * nplc / line_hz + SWITCH_AND_DELAY_S


class Keysight34970AEmulator:
    eol = b"\n"
    networked = True  # a 34972A on the LAN: a power cycle drops its connections

    def __init__(self, rig: EmulatedRig, wiring: dict[int, int | str], name: str = "dmm",
                 serial_line: bool = False):
        """``wiring``: channel → instrument output 0, 1, 2 (x, y, z) or "temp" for the thermometer;
        ``serial_line``: on RS-232, where ``SYST:REM`` must come first."""
        self.rig, self.wiring, self.name = rig, wiring, name
        self.serial_line = serial_line
        self.remote = not serial_line
        self.state = State()
        self.errors: list[int] = []
        self.event_status = PON  # the unit has just been switched on
        self.overload_next = False
        self.commands: list[tuple[re.Pattern, Callable[[str], str | None]]] = [
            (_regex(spec), handler) for spec, handler in (
                ("*IDN?", lambda a: IDN), ("*RST", self._reset), ("*CLS", self._clear_status),
                ("*ESR?", self._event_status),
                ("*OPC?", self._opc), ("*WAI", self._wait), ("SYSTem:ERRor[:NEXT]?", self._next_error),
                ("SYSTem:REMote", lambda a: None), ("SYSTem:VERSion?", lambda a: "1994.0"),
                ("CONFigure[:VOLTage][:DC]", self._conf_volts), ("CONFigure:TEMPerature", self._conf_temp),
                ("[SENSe:]VOLTage[:DC]:NPLCycles", self._nplc), ("[SENSe:]TEMPerature:NPLCycles", self._nplc),
                ("[SENSe:]VOLTage[:DC]:RANGe", self._range),
                ("[SENSe:]VOLTage[:DC]:RANGe?", self._per_channel("VOLT", lambda c: f"{c.range_v:+.8E}")),
                ("[SENSe:]VOLTage[:DC]:NPLCycles?", self._per_channel("VOLT", lambda c: f"{c.nplc:+.8E}")),
                ("[SENSe:]TEMPerature:NPLCycles?", self._per_channel("TEMP", lambda c: f"{c.nplc:+.8E}")),
                ("INPut:IMPedance:AUTO", self._impedance),
                ("INPut:IMPedance:AUTO?", self._per_channel("VOLT", lambda c: str(int(c.impedance_auto)))),
                ("ROUTe:SCAN", self._scan_list),
                ("ROUTe:SCAN?", self._scan_list_query), ("FORMat:READing:CHANnel", self._form("CHAN")),
                ("FORMat:READing:TIME", self._form("TIME")), ("FORMat:READing:UNIT", self._form("UNIT")),
                ("FORMat:READing:ALARm", self._form("ALAR")),
                ("FORMat:READing:TIME:TYPE", self._time_type),
                ("FORMat:READing:TIME:TYPE?", lambda a: "ABS" if self.state.time_absolute else "REL"),
                ("FORMat:READing:CHANnel?", self._form_query("CHAN")),
                ("FORMat:READing:TIME?", self._form_query("TIME")),
                ("FORMat:READing:UNIT?", self._form_query("UNIT")),
                ("FORMat:READing:ALARm?", self._form_query("ALAR")), ("TRIGger:SOURce", self._trigger_source),
                ("TRIGger:COUNt", self._trigger_count), ("TRIGger:TIMer", lambda a: None),
                ("INITiate", self._init), ("ABORt", self._abort), ("FETCh?", self._fetch),
                ("DATA:POINts?", self._points))]

    # --- LineDevice -------------------------------------------------------------------------
    def route(self, line: str) -> str:
        return self.name

    def refuse(self, line: str, code: int | str | None) -> None:
        self._error(int(code) if isinstance(code, int) else -221)

    def alarm(self, name: str, code: int | str | None) -> None:
        self.overload_next = True

    def power_cycle(self, name: str = "dmm") -> None:
        """Switched off and on: the power-on state (User's Guide, "Power-on and reset state": the
        *RST defaults, no scan list), the error queue empty, the power-on bit set, and on RS-232
        back in local until SYST:REM. The reading memory is cleared too (a simplification: the
        unit keeps a scan in non-volatile memory; the driver's time stamps would refuse it anyway)."""
        self.state = State()
        self.errors.clear()
        self.event_status = PON
        self.remote = not self.serial_line
        self.overload_next = False

    def handle(self, line: str) -> str | None:
        replies = []
        for part in filter(None, (p.strip() for p in line.split(";"))):
            header, _, argument = part.lstrip(":").partition(" ")
            if not self.remote:
                self.remote = bool(re.fullmatch(r"SYST(EM)?:REM(OTE)?", header, re.IGNORECASE))
                continue  # in local, RS-232 commands are not obeyed
            handler = next((h for pattern, h in self.commands if pattern.fullmatch(header)), None)
            if handler is None:
                self._error(-113)
                continue
            try:
                reply = handler(argument.strip())
            except ValueError:
                self._error(-102)
                continue
            if reply is not None:
                replies.append(reply)
        return ";".join(replies) if replies else None

    # --- commands ---------------------------------------------------------------------------
    def _error(self, code: int) -> None:
        self.event_status |= ERROR_BITS.get(-code // 100, 0)
        if len(self.errors) < QUEUE_SIZE:
            self.errors.append(code)
        else:
            self.errors[-1] = -350

    def _next_error(self, _: str) -> str:
        code = self.errors.pop(0) if self.errors else 0
        return f'{code:+d},"{ERRORS.get(code, "No error")}"'

    def _reset(self, _: str) -> None:
        self.state = State()

    def _clear_status(self, _: str) -> None:
        self.errors.clear()
        self.event_status = 0

    def _event_status(self, _: str) -> str:
        status, self.event_status = self.event_status, 0
        return f"{status:+d}"

    def _per_channel(self, function: str, value: Callable[[Channel], str]) -> Callable[[str], str | None]:
        """A query with a channel list (``VOLT:DC:NPLC? (@101:103)``): one value per channel, in
        the list's order; -221 if a channel is not configured for the function."""
        def query(argument: str) -> str | None:
            _, channels = self._split(argument)
            if not channels or any(self.state.channels.get(c, Channel("")).function != function
                                   for c in channels):
                self._error(-221)
                return None
            return ",".join(value(self.state.channels[c]) for c in channels)
        return query

    def _form_query(self, field_name: str) -> Callable[[str], str]:
        return lambda _: "1" if self.state.form[field_name] else "0"

    @staticmethod
    def _split(argument: str) -> tuple[list[str], list[int]]:
        """``10,(@101:103)`` → (["10"], [101, 102, 103])."""
        head, at, channels = argument.partition("(@")
        values = [v.strip() for v in head.split(",") if v.strip()]
        return values, parse_channels(at + channels) if at else []

    def _configure(self, channels: list[int], channel: Callable[[], Channel]) -> None:
        if not channels or any(c not in self.wiring and not 101 <= c <= 340 for c in channels):
            self._error(-222)
            return
        for c in channels:
            self.state.channels[c] = channel()
        self.state.scan_list = list(channels)  # CONFigure redefines the scan list ...
        self.state.form = dict.fromkeys(self.state.form, False)  # ... and the reading format

    def _conf_volts(self, argument: str) -> None:
        values, channels = self._split(argument)
        range_v = 10.0 if not values or values[0].upper() in ("AUTO", "DEF") else float(values[0])
        if range_v not in RANGES_V:
            self._error(-222)
            return
        self._configure(channels, lambda: Channel("VOLT", range_v))

    def _conf_temp(self, argument: str) -> None:
        values, channels = self._split(argument)
        if not values:
            self._error(-102)
            return
        self._configure(channels, lambda: Channel("TEMP"))

    def _nplc(self, argument: str) -> None:
        values, channels = self._split(argument)
        if len(values) != 1 or float(values[0]) not in NPLC_VALUES:
            self._error(-222)
            return
        if any(c not in self.state.channels for c in channels):
            self._error(-221)
            return
        for c in channels:
            self.state.channels[c].nplc = float(values[0])

    def _range(self, argument: str) -> None:
        values, channels = self._split(argument)
        if len(values) != 1 or float(values[0]) not in RANGES_V or any(
                self.state.channels.get(c, Channel("")).function != "VOLT" for c in channels):
            self._error(-222)
            return
        for c in channels:
            self.state.channels[c].range_v = float(values[0])

    def _impedance(self, argument: str) -> None:
        values, channels = self._split(argument)
        if len(values) != 1 or values[0].upper() not in ("ON", "OFF", "1", "0"):
            self._error(-222)
            return
        if not channels or any(self.state.channels.get(c, Channel("")).function != "VOLT" for c in channels):
            self._error(-221)
            return
        for c in channels:
            self.state.channels[c].impedance_auto = values[0].upper() in ("ON", "1")

    def _scan_list(self, argument: str) -> None:
        channels = parse_channels(argument)
        if any(c not in self.state.channels for c in channels):
            self._error(-221)
            return
        self.state.scan_list = channels

    def _scan_list_query(self, _: str) -> str:
        text = "(@" + ",".join(map(str, self.state.scan_list)) + ")"
        return f"#{len(str(len(text)))}{len(text)}{text}"

    def _form(self, field_name: str) -> Callable[[str], None]:
        def set_form(argument: str) -> None:
            if argument.upper() not in ("ON", "OFF", "1", "0"):
                self._error(-222)
                return
            self.state.form[field_name] = argument.upper() in ("ON", "1")
        return set_form

    def _time_type(self, argument: str) -> None:
        if argument.upper() not in ("ABS", "ABSOLUTE", "REL", "RELATIVE"):
            self._error(-222)
            return
        self.state.time_absolute = argument.upper().startswith("ABS")

    def _trigger_source(self, argument: str) -> None:
        if argument.upper() not in ("IMM", "IMMEDIATE", "TIM", "TIMER", "BUS", "EXT", "EXTERNAL"):
            self._error(-222)

    def _trigger_count(self, argument: str) -> None:
        count = int(float(argument))
        if not 1 <= count <= 50000:
            self._error(-222)
            return
        self.state.trigger_count = count

    def _init(self, _: str) -> None:
        state = self.state
        if not state.scan_list:
            self._error(-221)
            return
        line_hz = self.rig.rig.config.line_hz
        durations = [channel_s(state.channels[c].nplc, line_hz) for c in state.scan_list]
        state.scan = ScanRun(self.rig.clock.now(), list(state.scan_list), durations, state.trigger_count)

    def _abort(self, _: str) -> None:
        if self.state.scan is not None and self.state.scan.end > self.rig.clock.now():
            self.state.scan.aborted_at = self.rig.clock.now()

    def _wait(self, _: str) -> None:
        if self.state.scan is not None:
            self.rig.clock.advance_to(self.state.scan.end)

    def _opc(self, _: str) -> str:
        self._wait("")
        return "1"

    def _points(self, _: str) -> str:
        scan = self.state.scan
        return "0" if scan is None else str(scan.done_by(min(self.rig.clock.now(), scan.end)))

    def _fetch(self, _: str) -> str | None:
        scan = self.state.scan
        if scan is None:
            self._error(-230)
            return None
        self._wait("")
        if scan.readings is None:
            scan.readings = self._measure(scan)
        n = scan.done_by(scan.end)
        return ",".join(self._format(value, scan.channels[i % len(scan.channels)], t, scan.start)
                        for i, (value, t) in enumerate(zip(scan.readings[:n], scan.times()[:n], strict=True)))

    # --- measurement ------------------------------------------------------------------------
    def _measure(self, scan: ScanRun) -> np.ndarray:
        """Every reading of the scan, each channel at its own time."""
        times = scan.times()
        with self.rig.lock:
            sample = self.rig.rig.sample_at(times)
        assert sample.temp_c is not None  # SimRig.sample_at always reads the lab thermometer
        readings = np.empty(len(times))
        for i, channel in enumerate(scan.channels * scan.sweeps):
            wired = self.wiring.get(channel)
            if wired == "temp":
                readings[i] = sample.temp_c[i]
            elif isinstance(wired, int):
                readings[i] = sample.volts[i, wired]
            else:
                readings[i] = 0.0  # nothing wired to this input
            if self.state.channels[channel].function == "VOLT":
                # the source's output resistance and the input's form a divider
                input_ohm = self.state.channels[channel].input_ohm()
                readings[i] *= input_ohm / (input_ohm + self.rig.rig.config.output_ohm)
                if abs(readings[i]) > OVER_RANGE * self.state.channels[channel].range_v:
                    readings[i] = OVERLOAD
        if self.overload_next:
            self.overload_next = False
            readings[0::len(scan.channels)] = OVERLOAD
        return readings

    def _format(self, value: float, channel: int, t: float, start: float) -> str:
        """One reading with the fields FORMat:READing asks for; the time stamp is the reading's
        time of day (ABSolute) or its seconds since the start of the scan (RELative)."""
        form = self.state.form
        unit = {"VOLT": " VDC", "TEMP": " C"}[self.state.channels[channel].function] if form["UNIT"] else ""
        parts = [f"{value:+.8E}{unit}"]
        if form["TIME"] and self.state.time_absolute:
            stamp = CLOCK_AT_ZERO + timedelta(seconds=round(t, 3))
            parts.append(f"{stamp:%Y,%m,%d,%H,%M},{stamp.second + stamp.microsecond / 1e6:06.3f}")
        elif form["TIME"]:
            parts.append(f"{t - start:.3f}")
        if form["CHAN"]:
            parts.append(f"{channel:03d}")
        if form["ALAR"]:
            parts.append("0")
        return ",".join(parts)
