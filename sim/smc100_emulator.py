"""Newport SMC100 controllers (one per address on a daisy-chained port) driving emulated tables.

Written from the SMC100CC/PP User's Manual, not from labcal's driver: the states, error codes and
the rules of which command each state accepts are transcribed below with their place in the
manual (§2.2 "Controller states" and its state diagram, §2.3 "Command set": each command's
"allowed in" states and the ``TE`` error table; as excerpted in reference/hardware_protocols.md
§2.2). NOT REFERENCED after power-up, HOMING on ``OR``, READY, MOVING on ``PA`` (accepted in
READY only: a ``PA`` while MOVING is refused with error M), DISABLE on ``MM0``, ``ST`` refused
when NOT REFERENCED (error H). Queries are answered with their echo; a refused command is not
answered and its error waits for ``TE``. Motion is the rig's own table physics.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from labcal.sim.emulated_rig import EmulatedRig

# Controller states, the two hex digits at the end of the TS reply (manual §2.2; TS command page)
NOT_REFERENCED = frozenset(range(0x0A, 0x12))  # 0Ah from reset ... 11h from JOGGING
CONFIGURATION = frozenset({0x14})
HOMING = frozenset({0x1E, 0x1F})  # 1Eh by command, 1Fh from the keypad
MOVING = frozenset({0x28})
READY = frozenset({0x32, 0x33, 0x34, 0x35})  # from HOMING, MOVING, DISABLE, JOGGING
DISABLE = frozenset({0x3C, 0x3D, 0x3E})  # from READY, MOVING, JOGGING
POWER_UP, HOMING_BY_COMMAND, MOVING_STATE = 0x0A, 0x1E, 0x28
READY_FROM_HOMING, READY_FROM_MOVING, READY_FROM_DISABLE = 0x32, 0x33, 0x34
DISABLE_FROM_READY, DISABLE_FROM_MOVING = 0x3C, 0x3D
NOT_REFERENCED_FROM_HOMING = 0x0B
# Command error codes returned by TE (manual §2.3, TE command page): the letters this emulator uses
ERROR_CODES = frozenset("ABCDEFGHIJKLMNSUVWX")  # "@" = no error
UNKNOWN_COMMAND, OUT_OF_RANGE, NOT_ALLOWED, HOMING_STARTED = "A", "C", "D", "E"
OUT_OF_LIMITS = "G"
IN_STATE = {"NOT REFERENCED": "H", "CONFIGURATION": "I", "DISABLE": "J", "READY": "K", "HOMING": "L",
            "MOVING": "M"}  # "not allowed in <state>"
EXECUTION_ERROR = "V"
FOLLOWING_ERROR = 0x0020  # positioner error bit (TS, first four hex digits)
VERSION = "SMC_CC - labcal emulator 1.0"
COMMAND = re.compile(r"(\d{1,2})([A-Za-z]{2})(.*)")


@dataclass
class Positioner:
    """One controller and its stage."""

    name: str  # the rig's table it drives: "pitch" or "roll"
    stage: str = "URS100BCC"
    state: int = POWER_UP
    errors: int = 0
    last_error: str = "@"
    speed: float = 20.0
    accel: float = 80.0
    limits: tuple[float, float] = (-1e9, 1e9)  # SL, SR (hardware_protocols.md §2.2 "Limits")
    target: float = 0.0


class Smc100Emulator:
    eol = b"\r\n"
    networked = False  # on TCP through a serial-device server, which a controller's power cycle leaves up

    def __init__(self, rig: EmulatedRig, positioners: dict[int, Positioner]):
        self.rig = rig
        self.positioners = positioners
        self.stops: list[tuple[str, float]] = []  # (table, rig time) of each ST a controller received

    # --- LineDevice -------------------------------------------------------------------------
    def route(self, line: str) -> str:
        match = COMMAND.fullmatch(line.replace(" ", ""))
        positioner = self.positioners.get(int(match.group(1))) if match else None
        return positioner.name if positioner else ""

    def refuse(self, line: str, code: int | str | None) -> None:
        match = COMMAND.fullmatch(line.replace(" ", ""))
        if match and (p := self.positioners.get(int(match.group(1)))):
            p.last_error = str(code) if code in ERROR_CODES else EXECUTION_ERROR

    def alarm(self, name: str, code: int | str | None) -> None:
        """A following error: the stage stops and the controller disables it."""
        for p in self.positioners.values():
            if p.name == name:
                with self.rig.lock:
                    self._update(p)
                    p.errors |= int(code) if isinstance(code, int) else FOLLOWING_ERROR
                    p.state = DISABLE_FROM_MOVING if p.state in MOVING else DISABLE_FROM_READY
                    self.rig.axis(p.name).stop()

    def power_cycle(self, name: str) -> None:
        """The controller of table ``name`` switched off and on: the stage stops where it is and
        the controller comes up NOT REFERENCED from reset (0Ah, the power-up state of §2.2's state
        diagram), no error kept, its speed and acceleration back to the stored ones (VA and AC set
        by command are not saved outside CONFIGURATION). It takes no PA until homed (error H).
        (Its position counter is left reading the stage's angle: a simplification.)"""
        stored = Positioner(name)
        for p in self.positioners.values():
            if p.name == name:
                with self.rig.lock:
                    self.rig.axis(p.name).stop()
                    p.state, p.errors, p.last_error = POWER_UP, 0, "@"
                    p.speed, p.accel = stored.speed, stored.accel

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
            p.state = READY_FROM_MOVING if p.state in MOVING else READY_FROM_HOMING

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
        if mnemonic == "TH":  # the set-point: where the last move was sent
            return f"{p.target:.6f}"
        if mnemonic == "ID" and query:
            return p.stage
        if mnemonic == "VE":
            return VERSION
        if mnemonic in ("VA", "AC", "SL", "SR", "PA") and query:
            setting = {"VA": p.speed, "AC": p.accel, "SL": p.limits[0], "SR": p.limits[1], "PA": p.target}
            return f"{setting[mnemonic]:g}"
        if mnemonic == "OR":  # allowed in NOT REFERENCED only
            why = (None if p.state in NOT_REFERENCED else HOMING_STARTED if p.state in HOMING
                   else self._state_error(p))
            return self._fail(p, why, lambda: self._move(p, 0.0, HOMING_BY_COMMAND))
        if mnemonic == "PA":  # allowed in READY only (the manual's state diagram: READY → MOVING)
            target = _number(value)
            why = None if p.state in READY else self._state_error(p)
            if target is None:
                return self._fail(p, why or OUT_OF_RANGE, None)
            if why is None and not p.limits[0] <= target <= p.limits[1]:
                why = OUT_OF_LIMITS
            return self._fail(p, why, lambda: self._move(p, target, MOVING_STATE))
        if mnemonic == "ST":  # refused in NOT REFERENCED and CONFIGURATION; a no-op when still
            self.stops.append((p.name, self.rig.clock.now()))
            if p.state in NOT_REFERENCED | CONFIGURATION:
                return self._fail(p, self._state_error(p), None)
            if p.state in MOVING | HOMING:  # "decelerating stop" (§2.2 command table): MOVING until still
                axis.decelerate()
                p.target = float(axis.angle_at(axis.motion_end))
                if p.state in HOMING:
                    p.state = NOT_REFERENCED_FROM_HOMING
            return None
        if mnemonic == "MM":
            if value == "0":
                return self._fail(p, None if p.state in READY else NOT_ALLOWED,
                                  lambda: setattr(p, "state", DISABLE_FROM_READY))
            if value == "1":
                return self._fail(p, None if p.state in DISABLE else NOT_ALLOWED,
                                  lambda: setattr(p, "state", READY_FROM_DISABLE))
            return self._fail(p, OUT_OF_RANGE, None)
        if mnemonic in ("VA", "AC"):
            number = _number(value)
            return self._fail(p, OUT_OF_RANGE if number is None or number <= 0 else None,
                              lambda: setattr(p, "speed" if mnemonic == "VA" else "accel", number))
        if mnemonic == "RS":
            axis.stop()
            p.state, p.errors = POWER_UP, 0
            return None
        return self._fail(p, UNKNOWN_COMMAND, None)

    @staticmethod
    def _state_error(p: Positioner) -> str:
        """The "not allowed in <state>" code for the controller's present state."""
        for name, states in (("NOT REFERENCED", NOT_REFERENCED), ("CONFIGURATION", CONFIGURATION),
                             ("DISABLE", DISABLE), ("READY", READY), ("HOMING", HOMING), ("MOVING", MOVING)):
            if p.state in states:
                return IN_STATE[name]
        return NOT_ALLOWED

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
