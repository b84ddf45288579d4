"""Newport SMC100 (CC/PP) motion controllers over their ASCII serial protocol.

Commands are ``<address><mnemonic><value>`` lines ending CR LF; replies echo address and mnemonic
(``1TP`` → ``1TP45.000000``). A command that fails is not answered: the controller keeps the
error, and ``TE`` reports it (once). So every command here is followed by ``TE``, and silence after
a query is explained by asking ``TE``. Up to 31 controllers share one port (addresses 1..31).
Protocol: hardware_protocols.md §2.2 and PyMeasure's smc100 driver.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from typing import TypeVar, overload

from labcal.devices.station import Clock
from labcal.drivers.axis import AxisStatus, IndexAxis
from labcal.drivers.errors import TRANSIENT, BadReply, DeviceFault, NoReply, Rejected, on_device
from labcal.drivers.transport import LineTransport, retried

EOL = b"\r\n"
T = TypeVar("T")
log = logging.getLogger(__name__)
SETPOINT_TOLERANCE_DEG = 1e-6  # TH answers with six decimals, as PA was sent
LIMITLESS_DEG = 1e6  # software limits at least this far out leave a free table free (thousands of turns)

STATES = {
    0x0A: "NOT REFERENCED from reset", 0x0B: "NOT REFERENCED from HOMING",
    0x0C: "NOT REFERENCED from CONFIGURATION", 0x0D: "NOT REFERENCED from DISABLE",
    0x0E: "NOT REFERENCED from READY", 0x0F: "NOT REFERENCED from MOVING",
    0x10: "NOT REFERENCED, ESP stage error", 0x11: "NOT REFERENCED from JOGGING",
    0x14: "CONFIGURATION", 0x1E: "HOMING", 0x1F: "HOMING from the keypad", 0x28: "MOVING",
    0x32: "READY from HOMING", 0x33: "READY from MOVING", 0x34: "READY from DISABLE",
    0x35: "READY from JOGGING", 0x3C: "DISABLE from READY", 0x3D: "DISABLE from MOVING",
    0x3E: "DISABLE from JOGGING", 0x46: "JOGGING from READY", 0x47: "JOGGING from DISABLE",
}
NOT_REFERENCED = frozenset(range(0x0A, 0x12))
HOMING = frozenset({0x1E, 0x1F})
MOVING = frozenset({0x28})
READY = frozenset({0x32, 0x33, 0x34, 0x35})
DISABLE = frozenset({0x3C, 0x3D, 0x3E})

POSITIONER_ERRORS = {
    0x0200: "80 W output power exceeded", 0x0100: "DC voltage too low", 0x0080: "wrong ESP stage",
    0x0040: "homing time-out", 0x0020: "following error", 0x0010: "short circuit",
    0x0008: "RMS current limit", 0x0004: "peak current limit", 0x0002: "positive end of run",
    0x0001: "negative end of run",
}

COMMAND_ERRORS = {
    "A": "unknown message code", "B": "bad address", "C": "parameter missing or out of range",
    "D": "command not allowed", "E": "home sequence already started", "F": "ESP stage name unknown",
    "G": "displacement out of limits", "H": "not allowed in NOT REFERENCED",
    "I": "not allowed in CONFIGURATION", "J": "not allowed in DISABLE", "K": "not allowed in READY",
    "L": "not allowed in HOMING", "M": "not allowed in MOVING", "N": "position out of software limits",
    "S": "communication time-out", "U": "EEPROM error", "V": "error during execution",
    "W": "not allowed for PP", "X": "not allowed for CC",
}


def parse_reply(line: str, address: int, mnemonic: str) -> str:
    """The value in a reply ``<address><MNEMONIC><value>``; `BadReply` if it does not echo them."""
    echo = f"{address}{mnemonic.rstrip('?').upper()}"
    if not line.startswith(echo):
        raise BadReply(f"reply {line[:40]!r} does not echo {echo!r}")
    return line[len(echo):].strip()


def parse_number(value: str) -> float:
    try:
        number = float(value)
    except ValueError:
        raise BadReply(f"{value[:40]!r} is not a number") from None
    if not math.isfinite(number):
        raise BadReply(f"{value[:40]!r} is not a finite number")
    return number


def parse_state(value: str) -> tuple[int, int]:
    """``TS`` value ``EEEESS`` → (positioner error bits, controller state)."""
    if not re.fullmatch(r"[0-9A-Fa-f]{6}", value):
        raise BadReply(f"status {value[:40]!r} is not six hex digits")
    return int(value[:4], 16), int(value[4:], 16)


def parse_error_code(value: str) -> str:
    if len(value) != 1 or value != "@" and value not in COMMAND_ERRORS:
        raise BadReply(f"error code {value[:40]!r} is not one of @, A..X")
    return value


def describe_state(errors: int, state: int) -> str:
    words = f"{STATES.get(state, 'unknown state')} ({state:02X}h)"
    bits = [text for mask, text in POSITIONER_ERRORS.items() if errors & mask]
    return words + (f", positioner error: {', '.join(bits)}" if bits else "")


class Smc100Axis(IndexAxis):
    model = "Newport SMC100"

    def __init__(self, name: str, link: LineTransport, address: int, clock: Clock, *, speed_dps: float,
                 accel_dps2: float, limits_deg: tuple[float, float] | None = None,
                 tolerance_arcsec: float = 5.0, poll_s: float = 0.05, home_timeout_s: float = 60.0,
                 retries: int = 2, cable_wrap_deg: float | None = None):
        super().__init__(name, f"address {address} on {link.where}", clock, limits_deg=limits_deg,
                         tolerance_arcsec=tolerance_arcsec, poll_s=poll_s, cable_wrap_deg=cable_wrap_deg)
        self.link, self.address = link, address
        self.speed_dps, self.accel_dps2 = speed_dps, accel_dps2
        self.home_timeout_s = home_timeout_s
        self.tries = retries + 1
        self._unread_te = False  # a `send_stop` whose TE is still in the controller
        self._last_ts: tuple[int, int] | None = None  # (positioner errors, state) of the last TS read

    # --- exchanges --------------------------------------------------------------------------
    def _error_code(self) -> str:
        return parse_error_code(parse_reply(self.link.query(f"{self.address}TE"), self.address, "TE"))

    def _refused(self, what: str, code: str) -> Rejected:
        return Rejected(f"refused {what}: error {code} ({COMMAND_ERRORS[code]})", self.device)

    @overload
    def ask(self, mnemonic: str) -> str: ...
    @overload
    def ask(self, mnemonic: str, parse: Callable[[str], T]) -> T: ...

    def ask(self, mnemonic: str, parse: Callable[[str], object] = str) -> object:
        """A query (``TP``, ``TS``, ``ID?``...): its value, parsed (a reply that does not parse is
        asked again). Silence is explained by ``TE``."""
        def once() -> object:
            self.link.write_line(f"{self.address}{mnemonic}")
            try:
                line = self.link.read_line()
            except NoReply:
                code = self._error_code()
                if code != "@":
                    raise self._refused(mnemonic, code) from None
                raise
            return parse(parse_reply(line, self.address, mnemonic))

        with on_device(self.device):
            return retried(once, self.tries, self.link.drain, self.link.critical, self.device)

    def do(self, command: str, safe: bool = True) -> None:
        """A command, then ``TE``; raises `Rejected` with the controller's reason. Commands safe to
        repeat (absolute moves, stop, settings) are retried; homing is not."""
        def once() -> None:
            self.link.write_line(f"{self.address}{command}")
            code = self._error_code()
            if code != "@":
                raise self._refused(command, code)

        with on_device(self.device):
            retried(once, self.tries if safe else 1, self.link.drain, self.link.critical, self.device)

    # --- the axis ---------------------------------------------------------------------------
    def status(self) -> AxisStatus:
        errors, state = self._last_ts = self.ask("TS", parse_state)
        words = describe_state(errors, state)
        fault = None
        if errors or state in DISABLE or state in NOT_REFERENCED or state not in STATES:
            fault = words + ("; home it (a run homes it first)" if state in NOT_REFERENCED and not errors
                             else "; clear the cause, then re-enable it (MM1) or home it")
        return AxisStatus(ready=state in READY, moving=state in MOVING | HOMING, in_position=state in READY,
                          fault=fault, words=words, needs_homing=state in NOT_REFERENCED and not errors)

    def angle(self) -> float:
        return self.ask("TP", parse_number)

    def _fault_memory(self) -> tuple[int, int]:
        """The controller's state as the window opens (``TS``): the state it is left in names the
        transition that led there (manual §2.2 state table: 33h READY from MOVING after a move,
        34h READY from DISABLE after MM0 then MM1), so a disable and re-enable inside the window,
        or a homing, leaves a READY state other than this one."""
        return self.ask("TS", parse_state)

    def _fault_since(self, memory: object, status: AxisStatus) -> str | None:
        assert isinstance(memory, tuple)
        opened_errors, opened = memory
        if opened_errors:
            return f"as the measurement window opened it reported {describe_state(opened_errors, opened)}"
        if self._last_ts is None or status.fault or status.moving:
            return None  # the status says what is wrong already
        errors, state = self._last_ts
        if state == opened:
            return None
        return (f"its controller went from {describe_state(0, opened)} to {describe_state(errors, state)} "
                "during the measurement window: it was disabled, homed or moved by something other than "
                "this run")

    def _go(self, target_deg: float, travel_deg: float = 0.0) -> None:
        """``PA`` once, then ``TE``; the stage counts turns, so the unwrapped target is the way round.
        The controller takes ``PA`` only in READY, so when the ``TE``
        reply is lost, sending ``PA`` again would be refused while the stage moves (error M) and
        stop the run: the state (``TS``) and the set-point (``TH``) tell whether the move began."""
        command = f"PA{target_deg:.6f}"
        with on_device(self.device):
            self.link.write_line(f"{self.address}{command}")
            try:
                code = self._error_code()
            except TRANSIENT as exc:
                log.warning("%s: the reply to TE after %s was lost (%s); asking the state instead",
                            self.device, command, exc)
                self.link.drain()
                self._confirm_move(command, target_deg)
                return
            if code != "@":
                raise self._refused(command, code)

    def _confirm_move(self, command: str, target_deg: float) -> None:
        """After a ``PA`` whose acknowledgement was lost: moving, or READY with the set-point on
        the target, means it was taken; READY elsewhere means it never arrived (sent once more)."""
        errors, state = self.ask("TS", parse_state)
        if state in MOVING and not errors:
            return
        if state in READY and not errors:
            if abs(self.ask("TH", parse_number) - float(f"{target_deg:.6f}")) <= SETPOINT_TOLERANCE_DEG:
                return
            log.warning("%s: %s did not arrive; sending it again (READY)", self.device, command)
            self.do(command, safe=False)
            return
        raise DeviceFault(f"after {command}: {describe_state(errors, state)}", self.device)

    def send_stop(self) -> None:
        """``ST`` once, without its ``TE``: a command gets no reply, so the next controller's ``ST``
        follows it on the chain at once. `stop` then reads the ``TE`` this leaves (a stage NOT
        REFERENCED refuses ``ST`` with error H, which must not be taken for the next command's)."""
        with on_device(self.device):
            self._unread_te = True
            self.link.write_line(f"{self.address}ST")

    def _halt(self) -> None:
        """``ST``, but only to a stage that can be moving: the controller refuses ``ST`` when NOT
        REFERENCED. When the state cannot be read, ``ST`` is sent anyway (a stop must be tried).
        After `send_stop`, its ``TE`` is read first (any refusal there is of that ``ST``)."""
        if self._unread_te:
            code = self.ask("TE", parse_error_code)
            self._unread_te = False
            log.debug("%s: the ST sent without TE left %s", self.device, code)
        try:
            state = self.ask("TS", parse_state)[1]
        except TRANSIENT as exc:
            log.warning("%s: state unreadable before stopping (%s); sending ST anyway", self.device, exc)
            state = None
        if state is not None and state not in MOVING | HOMING:
            log.debug("%s: not moving (%s): nothing to stop", self.device, describe_state(0, state))
            return
        try:
            self.do("ST")
        except Rejected:
            # Refused because the stage left MOVING/HOMING between TS and ST (a homing that ended or
            # was aborted: NOT REFERENCED refuses ST). The stage then moves no more, which is what
            # the stop is for; asked again to be sure. Still moving: the stop failed, loudly.
            state = self.ask("TS", parse_state)[1]
            if state in MOVING | HOMING:
                raise
            log.info("%s: ST refused in %s: the stage is not moving", self.device, describe_state(0, state))

    def identify(self) -> str:
        """``ID?`` (the stage) and ``VE`` (controller and firmware), as the manual documents them."""
        return f"{self.model} address {self.address}: stage {self.ask('ID?')}, {self.ask('VE')}"

    def software_limits(self) -> tuple[float, float]:
        """The controller's own software limits, ``SL?`` and ``SR?`` (degrees): it refuses a ``PA``
        beyond them."""
        return self.ask("SL?", parse_number), self.ask("SR?", parse_number)

    def check_software_limits(self) -> None:
        """Refuse a station whose limits reach beyond the controller's: a planned angle the station
        allows would otherwise be refused mid-run, with a table half-way through a plan."""
        lo, hi = self.software_limits()
        if self.limits is None:
            if lo > -LIMITLESS_DEG or hi < LIMITLESS_DEG:
                raise DeviceFault(f"the controller's software limits are [{lo:g}°, {hi:g}°] (SL, SR) but the "
                                  "station file gives no limits_deg (a free table, moved the shortest way "
                                  "round); set limits_deg within the controller's, or widen SL and SR",
                                  self.device)
            return
        (low, high) = self.limits
        if low < lo or high > hi:
            raise DeviceFault(f"the station's limits_deg [{low:g}°, {high:g}°] exceed the controller's "
                              f"software limits [{lo:g}°, {hi:g}°] (SL, SR); narrow limits_deg in the "
                              "station file, or widen SL and SR on the controller", self.device)

    def prepare(self) -> None:
        """Check the controller's software limits against the station's, home the stage if it is not
        referenced (it moves!), enable it if disabled, and set the speed and acceleration from the
        station file."""
        self.check_software_limits()  # before anything moves
        errors, state = self.ask("TS", parse_state)
        if errors and state not in NOT_REFERENCED:
            raise DeviceFault(describe_state(errors, state), self.device)
        if state in NOT_REFERENCED:
            self.commanded = True
            self.do("OR", safe=False)
            self._target = None
            started = self.clock.now()
            while (state := self.ask("TS", parse_state)[1]) in HOMING:
                if self.clock.now() > started + self.home_timeout_s:
                    self._halt()
                    where = self.angle()
                    errors, state = self.ask("TS", parse_state)
                    raise DeviceFault(
                        f"homing (OR) did not find home within home_timeout_s = {self.home_timeout_s:g} s; "
                        f"the stage was stopped (ST) at {where:.3f}°, now {describe_state(errors, state)}; "
                        "check that nothing blocks the stage and that its home switch is cabled, or raise "
                        "home_timeout_s in the station file if homing from there takes longer", self.device)
                self.clock.sleep(self.poll_s)
        if state in DISABLE:
            self.do("MM1")
        super().prepare()
        self.do(f"VA{self.speed_dps:g}")
        self.do(f"AC{self.accel_dps2:g}")
