"""Newport SMC100 controllers (one per address on a daisy-chained port) driving emulated tables.

The controller state machine of the manual: NOT REFERENCED after power-up, HOMING on ``OR``,
READY, MOVING on ``PA``, DISABLE on ``MM0``. Queries are answered with their echo; a bad
command is not answered and its error waits for ``TE``. Motion is the rig's own table physics.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from labcal.drivers.newport_smc100 import COMMAND_ERRORS, DISABLE, HOMING, MOVING, NOT_REFERENCED, READY
from labcal.sim.emulated_rig import EmulatedRig

FOLLOWING_ERROR = 0x0020
VERSION = "SMC_CC - labcal emulator 1.0"
COMMAND = re.compile(r"(\d{1,2})([A-Za-z]{2})(.*)")


@dataclass
class Positioner:
    """One controller and its stage."""

    name: str  # the rig's table it drives: "pitch" or "roll"
    stage: str = "URS100BCC"
    state: int = 0x0A
    errors: int = 0
    last_error: str = "@"
    speed: float = 20.0
    accel: float = 80.0
    limits: tuple[float, float] = (-1e9, 1e9)
    target: float = 0.0


class Smc100Emulator:
    eol = b"\r\n"

    def __init__(self, rig: EmulatedRig, positioners: dict[int, Positioner]):
        self.rig = rig
        self.positioners = positioners

    # --- LineDevice -------------------------------------------------------------------------
    def route(self, line: str) -> str:
        match = COMMAND.fullmatch(line.replace(" ", ""))
        positioner = self.positioners.get(int(match.group(1))) if match else None
        return positioner.name if positioner else ""

    def refuse(self, line: str, code: int | str | None) -> None:
        match = COMMAND.fullmatch(line.replace(" ", ""))
        if match and (p := self.positioners.get(int(match.group(1)))):
            p.last_error = str(code) if code in COMMAND_ERRORS else "V"

    def alarm(self, name: str, code: int | str | None) -> None:
        """A following error: the stage stops and the controller disables it."""
        for p in self.positioners.values():
            if p.name == name:
                with self.rig.lock:
                    self._update(p)
                    p.errors |= int(code) if isinstance(code, int) else FOLLOWING_ERROR
                    p.state = 0x3D if p.state in MOVING else 0x3C
                    self.rig.axis(p.name).stop()

    def handle(self, line: str) -> str | None:
        match = COMMAND.fullmatch(line.replace(" ", ""))
        if not match:
            return None
        p = self.positioners.get(int(match.group(1)))
        if p is None:
            return None  # no controller at that address: silence on the chain
        mnemonic, value = match.group(2).upper(), match.group(3)
        with self.rig.lock:
            self._update(p)
            reply = self._execute(p, mnemonic, value)
        return None if reply is None else f"{match.group(1)}{mnemonic}{reply}"

    # --- the controller ---------------------------------------------------------------------
    def _update(self, p: Positioner) -> None:
        """Motion that has ended since the last request: MOVING → READY, HOMING → READY."""
        axis = self.rig.axis(p.name)
        if p.state in MOVING | HOMING and self.rig.clock.now() >= axis.motion_end + axis.clamp_s:
            p.state = 0x33 if p.state in MOVING else 0x32

    def _execute(self, p: Positioner, mnemonic: str, value: str) -> str | None:
        axis = self.rig.axis(p.name)
        query = value == "?"
        if mnemonic == "TE":
            code, p.last_error = p.last_error, "@"
            return code
        if mnemonic == "TS":
            errors, p.errors = p.errors, 0
            return f"{errors:04X}{p.state:02X}"
        if mnemonic == "TP":
            return f"{float(axis.angle_at(self.rig.clock.now())):.6f}"
        if mnemonic == "ID" and query:
            return p.stage
        if mnemonic == "VE":
            return VERSION
        if mnemonic in ("VA", "AC", "SL", "SR", "PA") and query:
            setting = {"VA": p.speed, "AC": p.accel, "SL": p.limits[0], "SR": p.limits[1], "PA": p.target}
            return f"{setting[mnemonic]:g}"
        if mnemonic == "OR":
            why = None if p.state in NOT_REFERENCED else "E" if p.state in HOMING else "K"
            return self._fail(p, why, lambda: self._move(p, 0.0, 0x1E))
        if mnemonic == "PA":
            target = _number(value)
            why = self._not_ready(p)
            if target is None:
                return self._fail(p, why or "C", None)
            if why is None and not p.limits[0] <= target <= p.limits[1]:
                why = "G"
            return self._fail(p, why, lambda: self._move(p, target, 0x28))
        if mnemonic == "ST":
            if p.state in MOVING | HOMING:
                axis.stop()
                p.state = 0x33 if p.state in MOVING else 0x0B
            return None
        if mnemonic == "MM":
            if value == "0":
                return self._fail(p, None if p.state in READY else "D", lambda: setattr(p, "state", 0x3C))
            if value == "1":
                return self._fail(p, None if p.state in DISABLE else "D", lambda: setattr(p, "state", 0x34))
            return self._fail(p, "C", None)
        if mnemonic in ("VA", "AC"):
            number = _number(value)
            return self._fail(p, "C" if number is None or number <= 0 else None,
                              lambda: setattr(p, "speed" if mnemonic == "VA" else "accel", number))
        if mnemonic == "RS":
            axis.stop()
            p.state, p.errors = 0x0A, 0
            return None
        return self._fail(p, "A", None)

    def _not_ready(self, p: Positioner) -> str | None:
        if p.state in NOT_REFERENCED:
            return "H"
        if p.state in DISABLE:
            return "J"
        if p.state in HOMING:
            return "L"
        return None  # READY, or MOVING: a new target replaces the old one

    def _move(self, p: Positioner, target: float, state: int) -> None:
        """Drive the stage to ``target`` at the controller's speed; MOVING (28h) or HOMING (1Eh)."""
        axis = self.rig.axis(p.name)
        axis.speed, axis.accel = p.speed, p.accel
        axis.move_to(target, "direct")
        p.state, p.target = state, target

    @staticmethod
    def _fail(p: Positioner, code: str | None, action: Callable[[], object] | None) -> None:
        """Refuse with ``code`` (kept for ``TE``), or carry out ``action``. Commands never reply."""
        if code is not None:
            p.last_error = code
        elif action is not None:
            action()
        return None


def _number(value: str) -> float | None:
    try:
        return float(value)
    except ValueError:
        return None
