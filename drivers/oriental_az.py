"""Oriental Motor AZ series drives (AZD-AD/KD and the like) over Modbus RTU or Modbus TCP.

Direct data operation: one FC 10h write of the operation-data block both sets and starts a move.
Every value is 32 bits in two registers, upper word first; positions are in steps, speeds in Hz
(steps/s), rates in 0.001 kHz/s (= steps/s²). With the drive's wrap setting on (one turn of the
table) positions stay in 0..N−1 and the move is "wrap proximity", the shortest way round; a table
with soft limits uses plain absolute moves instead. Register map: hardware_protocols.md §2.1.
"""

from __future__ import annotations

import logging
from enum import IntEnum, IntFlag

from labcal.devices.station import Clock
from labcal.drivers.axis import AxisStatus, IndexAxis
from labcal.drivers.errors import TRANSIENT, DeviceFault, DriverError, on_device
from labcal.drivers.modbus import ModbusLink, int32_words, words_int32

log = logging.getLogger(__name__)
HALF_TURN_DEG = 180.0  # from here on, a wrapping drive is told the way round (FWD or RVS)
RELEASE_TRIES = 5  # attempts to clear the STOP input, each a write read back (each write is retried)

# --- register map (wire addresses of the upper word of each 32-bit pair) --------------------
DDO = 0x0058  # operation data No., type, position, speed, rate, stop rate, current, trigger, destination
DDO_FIELDS = ("data_no", "type", "position", "speed", "rate", "stop_rate", "current", "trigger",
              "destination")
INPUT_AUTO_OFF = 0x0078  # driver input command, bits released by the drive after one scan
INPUT_REF = 0x007C  # driver input command (reference), latched; bits in the lower word 0x007D
STATUS = 0x007E  # driver output status; the present alarm follows at 0x0080
ALARM = 0x0080
ALARM_HISTORY = 0x0082  # ten pairs, newest first
HISTORY = 10
COMM_ERROR = 0x00AC
COMMAND_POSITION = 0x00C6
FEEDBACK_POSITION = 0x00CC
FEEDBACK_SPEED = 0x00D0  # Hz
ALARM_RESET = 0x0180  # maintenance commands: execute on a 0 → 1 write
CLEAR_ALARM_HISTORY = 0x0184
P_PRESET = 0x018A
CONFIGURATION = 0x018C


class Input(IntFlag):
    """Driver input command bits (factory assignment)."""

    START = 1 << 3
    ZHOME = 1 << 4
    STOP = 1 << 5
    FREE = 1 << 6
    ALM_RST = 1 << 7


class Output(IntFlag):
    """Driver output status bits (factory assignment)."""

    HOME_END = 1 << 4
    READY = 1 << 5
    INFO = 1 << 6
    ALM_A = 1 << 7
    SYS_BSY = 1 << 8
    MOVE = 1 << 13
    IN_POS = 1 << 14


class OpType(IntEnum):
    ABSOLUTE = 1
    INCREMENTAL = 2
    WRAP_ABSOLUTE = 8
    WRAP_PROXIMITY = 9
    WRAP_FORWARD = 10
    WRAP_REVERSE = 11


ALARMS = {
    0x10: "excessive position deviation", 0x20: "overcurrent", 0x21: "main circuit overheat",
    0x22: "overvoltage", 0x23: "main power off", 0x25: "undervoltage", 0x26: "motor overheat",
    0x28: "sensor error", 0x2A: "ABZO communication error", 0x30: "overload", 0x31: "overspeed",
    0x33: "absolute position error (needs P-PRESET or homing)", 0x34: "command pulse error",
    0x41: "EEPROM error", 0x42: "sensor error at power-on", 0x43: "rotation error at power-on",
    0x44: "encoder EEPROM error", 0x45: "motor combination error",
    0x4A: "return-to-home incomplete", 0x51: "regeneration resistor overheat",
    0x53: "HWTO input circuit error", 0x60: "both limit sensors active",
    0x61: "reverse limit sensor connection",
    0x62: "home-seeking error", 0x63: "no HOMES", 0x64: "TIM/Z/SLIT error", 0x66: "hardware overtravel",
    0x67: "software overtravel", 0x68: "HWTO detected (safe torque off)", 0x6A: "home offset error",
    0x6D: "mechanical overtravel", 0x70: "operation data error", 0x71: "electronic gear setting error",
    0x72: "wrap setting error", 0x81: "network bus error", 0x83: "communication switch setting error",
    0x84: "RS-485 communication error", 0x85: "RS-485 communication timeout",
    0x8E: "network converter error", 0xF0: "CPU error",
}
NOT_RESETTABLE = frozenset({0x20, 0x28, 0x33, 0x41})  # need the power cycled or a P-PRESET


def alarm_text(code: int) -> str:
    what = ALARMS.get(code, "unknown alarm")
    how = ("cannot be reset by command: clear the cause and cycle the drive's power" if code in NOT_RESETTABLE
           else "clear the cause, then `labcal station check STATION --reset-alarms`")
    return f"alarm {code:02X}h ({what}); {how}"


def ddo_registers(op_type: int, position: int, speed_hz: int, rate: int, current_permille: int = 1000,
                  trigger: int = 1) -> list[int]:
    """The 18 registers of one direct-data-operation write that sets and starts a move."""
    values = (0, op_type, position, speed_hz, rate, rate, current_permille, trigger, 0)
    return [word for value in values for word in int32_words(value)]


def decode_status(registers: list[int]) -> tuple[Output, int]:
    """Output bits and the present alarm code from the four registers at `STATUS`."""
    return Output(words_int32(*registers[0:2]) & 0xFFFF), words_int32(*registers[2:4])


def status_words(bits: Output, alarm: int) -> str:
    names = [flag.name for flag in (Output.READY, Output.MOVE, Output.IN_POS, Output.SYS_BSY) if flag in bits]
    if alarm:
        names.append(f"ALM-A {alarm:02X}h")
    return " ".join(n.replace("_", "-") for n in names if n) or "not ready"


class AzAxis(IndexAxis):
    model = "Oriental Motor AZ"

    def __init__(self, name: str, link: ModbusLink, unit: int, clock: Clock, *, steps_per_degree: float,
                 speed_dps: float, accel_dps2: float, wrap: bool = True,
                 limits_deg: tuple[float, float] | None = None, tolerance_arcsec: float = 5.0,
                 poll_s: float = 0.05, cable_wrap_deg: float | None = None):
        super().__init__(name, f"unit {unit} on {link.where}", clock, limits_deg=limits_deg,
                         tolerance_arcsec=tolerance_arcsec, poll_s=poll_s, cable_wrap_deg=cable_wrap_deg)
        self.link, self.unit = link, unit
        self.steps_per_degree = steps_per_degree
        self.steps_per_turn = round(360 * steps_per_degree)
        self.wrap = wrap
        self.counts_turns = not wrap  # with the wrap setting on, positions stay within one turn
        self.speed_hz = max(1, round(speed_dps * steps_per_degree))
        self.rate = max(1, round(accel_dps2 * steps_per_degree))
        self._stop_on = False  # a stop set the STOP input and no release has been read back off yet

    def _read(self, address: int, count: int) -> list[int]:
        with on_device(self.device):
            return self.link.read(self.unit, address, count)

    def _write(self, address: int, values: list[int]) -> None:
        with on_device(self.device):
            if len(values) == 1:
                self.link.write_one(self.unit, address, values[0])
            else:
                self.link.write(self.unit, address, values)

    def _pulse(self, address: int) -> None:
        """A maintenance command: 0 → 1 executes; the 0 after it arms the next one."""
        self._write(address, int32_words(1))
        self._write(address, int32_words(0))

    def status(self) -> AxisStatus:
        bits, alarm = decode_status(self._read(STATUS, 4))
        return AxisStatus(ready=Output.READY in bits, moving=Output.MOVE in bits,
                          in_position=Output.IN_POS in bits and Output.MOVE not in bits,
                          fault=alarm_text(alarm) if alarm or Output.ALM_A in bits else None,
                          words=status_words(bits, alarm))

    def angle(self) -> float:
        return words_int32(*self._read(FEEDBACK_POSITION, 2)) / self.steps_per_degree

    def _go(self, target_deg: float, travel_deg: float = 0.0) -> None:
        """With the wrap setting on, the drive's coordinates stay within one turn and do not say
        which way round: half a turn or more goes by wrap absolute FWD or RVS (the way the caller's
        cable wrap chose), less by wrap proximity (the shortest way, the same way; it never makes a
        full turn out of a target a step behind the table). Without it, a plain absolute move.
        After a stop whose acknowledgement was lost (the STOP input may still be on, and the drive
        would start nothing), the input is released first."""
        if self._stop_on:
            log.warning("%s: releasing the STOP input left by a stop that was not confirmed", self.device)
            self.release_stop()
        steps = round(target_deg * self.steps_per_degree)
        op_type = OpType.ABSOLUTE
        if self.wrap:
            op_type = (OpType.WRAP_FORWARD if travel_deg >= HALF_TURN_DEG else OpType.WRAP_REVERSE
                       if travel_deg <= -HALF_TURN_DEG else OpType.WRAP_PROXIMITY)
            steps %= self.steps_per_turn
        self._write(DDO, ddo_registers(op_type, steps, self.speed_hz, self.rate))

    def _halt(self) -> None:
        """STOP on, then off again, in the lower word of the input command (a decelerating stop).

        STOP is a level, not a pulse: while it is on the drive starts nothing, so a release that
        does not arrive leaves the table stopped for good. Setting and clearing cannot be one write
        (the drive acts on the level it sees), so the release is read back and repeated until the
        drive reports the input off, and a release that never lands is an error that says so."""
        self._stop_on = True  # until a release is read back off
        with on_device(self.device):
            self.link.write_one(self.unit, INPUT_REF + 1, Input.STOP)
        self.release_stop()

    def send_stop(self) -> None:
        """STOP on in every drive on the bus, by one broadcast frame that no drive answers: one
        frame stops both tables of a shared line, and a drive that does not answer delays nothing.
        `stop` then sets it again per drive, confirmed, and releases it."""
        self._stop_on = True
        with on_device(self.device):
            self.link.broadcast_one(INPUT_REF + 1, Input.STOP)

    def not_ready_why(self) -> str:
        try:
            stop_on = self.stop_input_on()
        except DriverError:
            return ""
        return ("; its STOP input is on (a stop whose release never arrived), so no move starts: release "
                "it with `labcal station check STATION --reset-alarms`" if stop_on else "")

    def stop_input_on(self) -> bool:
        """Whether the drive's STOP input (reference input command) is on."""
        return bool(words_int32(*self._read(INPUT_REF, 2)) & Input.STOP)

    def release_stop(self) -> None:
        """Clear the STOP input and read it back; repeated until the drive reports it off."""
        failure: DriverError | None = None
        for attempt in range(1, RELEASE_TRIES + 1):
            try:
                self._write(INPUT_REF + 1, [0])
                if not self.stop_input_on():
                    self._stop_on = False
                    return
                failure = None
            except TRANSIENT as exc:
                failure = exc
            log.warning("%s: STOP input still on after release attempt %d of %d%s", self.device, attempt,
                        RELEASE_TRIES, f" ({failure})" if failure else "")
        raise DeviceFault(f"the STOP input may still be on after {RELEASE_TRIES} attempts to release it "
                          f"({failure or 'read back on'}): the table will not move until it is off; "
                          "check the line, then `labcal station check STATION --reset-alarms`", self.device)

    def prepare(self) -> None:
        """Refuse a drive whose STOP input is on (an earlier stop whose release never arrived):
        no move would start, and the run would fail later with a misleading stall."""
        if self.stop_input_on():
            raise DeviceFault("its STOP input is on (left on by an interrupted stop?), so no move can "
                              "start; release it with `labcal station check STATION --reset-alarms`, "
                              "then run or resume again", self.device)
        super().prepare()

    def alarm(self) -> int:
        return words_int32(*self._read(ALARM, 2))

    def alarm_history(self) -> tuple[int, ...]:
        """The drive's alarm history 1..10, newest first (0 where empty), in one read of its ten
        pairs (hardware_protocols.md §2.1, 0082h–0095h): an alarm stays in it after a reset, by
        this master or any other."""
        words = self._read(ALARM_HISTORY, 2 * HISTORY)
        return tuple(words_int32(*words[i:i + 2]) for i in range(0, 2 * HISTORY, 2))

    def _fault_memory(self) -> tuple[int, ...]:
        return self.alarm_history()

    def _fault_since(self, memory: object, status: AxisStatus) -> str | None:
        """An alarm the history gained since ``memory`` (the history as the window opened; a new
        alarm goes in first and pushes the rest down), or a history cleared meanwhile. The present
        alarm, if any, is the status's fault already."""
        assert isinstance(memory, tuple)
        now = self.alarm_history()
        if now == memory:
            return None
        shifts = range(1, HISTORY + 1)
        new = next((now[:shift] for shift in shifts if now[shift:] == memory[:HISTORY - shift]), None)
        if new is None:
            return "its alarm history changed during the measurement window (cleared by another master?)"
        raised = ", ".join(f"{code:02X}h ({ALARMS.get(code, 'unknown alarm')})" for code in new)
        reset = "" if status.fault else ", and was reset since"
        return f"alarm {raised} was raised during the measurement window (alarm history){reset}"

    def reset_alarm(self) -> None:
        self._pulse(ALARM_RESET)

    def preset_position(self) -> None:
        """P-PRESET: the present position becomes the preset position (commissioning a table)."""
        self._pulse(P_PRESET)

    def identify(self) -> str:
        """The AZ register map (hardware_protocols.md §2.1) documents no product or firmware
        register, so the identity is the model and the unit, confirmed by a status read (a drive
        that does not answer has no identity)."""
        self._read(STATUS, 2)
        return f"{self.model} unit {self.unit} on {self.link.where}"
