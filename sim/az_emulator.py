"""Oriental Motor AZ drives on a pymodbus server, driving the emulated tables.

Written from the vendor's documents, not from labcal's driver: every register address, bit and
code below is transcribed here with its source beside it (the AZ series "Function edition /
RS-485 communication" manual HM-60262E as excerpted in reference/hardware_protocols.md §2.1, and
the Modbus over Serial Line specification V1.02), so a misreading in the driver shows as a
disagreement. Every read is computed from the rig's physics at that moment, every write acts on
it. Emulated: direct data operation (types absolute, incremental, wrap absolute/proximity/
forward/reverse), the status bits (READY, MOVE, IN-POS after the table's clamp, ALM-A), present
alarm and history, alarm reset, P-PRESET, the STOP input (a decelerating stop at the table's rate, and
no operation starts while it stays on; READY is off meanwhile) and FREE, command and feedback position and
speed. On an RTU line a request that begins within t3.5 of the previous frame is dropped, as a
strict slave does, and the silence before each request is recorded (`AzServer.gaps`). Not
emulated: stored operation data, START/ZHOME inputs, parameters. Units answer on one bus: Modbus
TCP (a gateway), Modbus RTU on a pty pair, or RTU over a TCP socket.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from labcal.config.emulation import FaultKind
from labcal.sim.emulated_rig import EmulatedRig
from labcal.sim.endpoint import Endpoint
from labcal.sim.faults import Fault, FaultInjector, drop_byte, garble
from labcal.sim.ptys import PtyPair

logging.getLogger("pymodbus").addHandler(logging.NullHandler())

# --- register map: wire addresses of the upper word of each 32-bit pair (HM-60262E, "Direct data
# operation", "Driver input/output commands", "Monitor commands", "Maintenance commands"; the
# addresses as listed in hardware_protocols.md §2.1 with their sources there) ------------------
DDO = 0x0058  # direct data operation: data No. 0058h, type 005Ah, position 005Ch, speed 005Eh,
DDO_PAIRS = 9  # rate 0060h, stop rate 0062h, current 0064h, trigger 0066h, destination 0068h
DDO_TYPE, DDO_POSITION, DDO_SPEED, DDO_RATE, DDO_TRIGGER = 1, 2, 3, 4, 7  # pair index in the block
INPUT_AUTO_OFF = 0x0078  # driver input command, automatic OFF
INPUT_REF = 0x007C  # driver input command (reference): bits in the lower word 007Dh
STATUS = 0x007E  # driver output status, bits in the lower word 007Fh
ALARM = 0x0080  # present alarm
ALARM_HISTORY = 0x0082  # alarm history 1..10 (0082h–0095h)
HISTORY = 10
COMM_ERROR = 0x00AC  # present communication error
COMMAND_POSITION = 0x00C6  # steps
FEEDBACK_POSITION = 0x00CC  # steps
FEEDBACK_SPEED_RPM = 0x00CE  # r/min
FEEDBACK_SPEED_HZ = 0x00D0  # Hz
ALARM_RESET = 0x0180  # maintenance commands: execute on a 0 → 1 write of the pair
CLEAR_ALARM_HISTORY = 0x0184
P_PRESET = 0x018A
CONFIGURATION = 0x018C
# (address, registers, read-only): the map's blocks; anything else answers "illegal data address"
BLOCKS = ((DDO, 2 * DDO_PAIRS, False), (INPUT_AUTO_OFF, 6, False), (STATUS, 2, True), (ALARM, 22, True),
          (COMM_ERROR, 2, True), (COMMAND_POSITION, 2, True), (FEEDBACK_POSITION, 6, True),
          (ALARM_RESET, 14, False))


class In(IntFlag):
    """Driver input command bits, factory assignment (HM-60262E "Driver input command"; §2.1)."""

    STOP = 1 << 5  # on: decelerating stop; while on, no operation starts
    FREE = 1 << 6  # on: motor de-energised (coasts)
    ALM_RST = 1 << 7  # on-edge: alarm reset


class Out(IntFlag):
    """Driver output status bits, factory assignment (HM-60262E "Driver output status"; §2.1)."""

    READY = 1 << 5
    ALM_A = 1 << 7
    MOVE = 1 << 13
    IN_POS = 1 << 14


class Op(IntEnum):
    """Direct data operation types (HM-60262E "Operation type"; §2.1, DDO type row)."""

    ABSOLUTE = 1
    INCREMENTAL = 2  # based on the command position
    WRAP_ABSOLUTE = 8
    WRAP_PROXIMITY = 9
    WRAP_FORWARD = 10
    WRAP_REVERSE = 11


# Alarm codes (HM-60262E alarm list; §2.1 alarm table)
EXCESSIVE_DEVIATION = 0x10  # what a stalled table raises
OPERATION_DATA_ERROR = 0x70  # speed 0, a wrap type with the wrap setting off
NOT_RESETTABLE = frozenset({0x20, 0x28, 0x33, 0x41})  # overcurrent, sensor, absolute position, EEPROM
DEFAULT_ALARM = EXCESSIVE_DEVIATION
WRAP_WAYS = {Op.WRAP_PROXIMITY: "shortest", Op.WRAP_FORWARD: "forward", Op.WRAP_REVERSE: "reverse"}
BROADCAST = 0  # every drive executes a request to address 0 and none answers (§2.1: "0 = broadcast (no
# reply)", and its simulator checklist "Broadcast (address 0): execute, no reply"; Modbus over Serial
# Line V1.02 §2.2)
T35_ABOVE_19200_S = 1.75e-3  # Modbus over Serial Line V1.02 §2.5.1.1: t3.5 fixed above 19200 Bd


def pair(value: int) -> list[int]:
    """A signed 32-bit value as the two registers the drive uses, upper word first (HM-60262E
    "Data format"; Oriental Motor FAQ 0331: −1000 is FFFFh FC18h)."""
    raw = value & 0xFFFFFFFF
    return [raw >> 16, raw & 0xFFFF]


def unpair(upper: int, lower: int) -> int:
    raw = (upper << 16) | lower
    return raw - (1 << 32) if raw & 0x80000000 else raw


@dataclass
class AzUnit:
    """One drive: its settings and the state the registers show."""

    name: str  # the rig table it drives
    steps_per_degree: float
    wrap: bool = True
    alarm: int = 0
    history: list[int] = field(default_factory=list)
    ddo: list[int] = field(default_factory=lambda: [0] * DDO_PAIRS)
    inputs: int = 0
    offset: int = 0  # device steps − rig steps, changed by P-PRESET
    preset: int = 0  # the preset-position parameter
    command: int = 0  # command position, steps
    maintenance: dict[int, int] = field(default_factory=dict)
    # a bind: each move stops this many steps short of its target, a deviation the drive cannot
    # close, so IN-POS stays off (it turns on once the deviation is within the IN-POS output band:
    # §2.1 simulator checklist, "IN-POS=1 when |cmd-fb| <= the in-position band") and MOVE is off
    stall_steps: int = 0
    stalled: bool = False  # the last move ended short (stall_steps)

    @property
    def steps_per_turn(self) -> int:
        return round(360 * self.steps_per_degree)


class AzDrives:
    """The drives' register semantics (called with the rig locked)."""

    def __init__(self, rig: EmulatedRig, units: dict[int, AzUnit]):
        self.rig, self.units = rig, units
        self.stops: list[tuple[str, float]] = []  # (table, rig time) of each STOP input turned on

    def _steps(self, unit: AzUnit) -> int:
        """Feedback position in device steps (within one turn if the wrap setting is on)."""
        angle = float(self.rig.axis(unit.name).angle_at(self.rig.clock.now()))
        steps = round(angle * unit.steps_per_degree) + unit.offset
        return steps % unit.steps_per_turn if unit.wrap else steps

    def _status(self, unit: AzUnit) -> int:
        axis, now = self.rig.axis(unit.name), self.rig.clock.now()
        moving = now < axis.motion_end
        bits = Out(0)
        if unit.alarm:
            bits |= Out.ALM_A
        elif not moving and not unit.inputs & (In.FREE | In.STOP):
            bits |= Out.READY
        if moving:
            bits |= Out.MOVE
        elif now >= axis.motion_end + axis.clamp_s and not unit.alarm and not unit.stalled:
            bits |= Out.IN_POS
        return int(bits)

    def read(self, unit: AzUnit, address: int) -> int:
        """The 32-bit value of the pair at ``address``."""
        axis = self.rig.axis(unit.name)
        if DDO <= address < DDO + 2 * DDO_PAIRS:
            return unit.ddo[(address - DDO) // 2]
        if ALARM_HISTORY <= address < ALARM_HISTORY + 2 * HISTORY:
            i = (address - ALARM_HISTORY) // 2
            return unit.history[i] if i < len(unit.history) else 0
        moving = self.rig.clock.now() < axis.motion_end
        speed_hz = round(axis.speed * unit.steps_per_degree) if moving else 0
        return {INPUT_AUTO_OFF: 0, INPUT_REF: unit.inputs, STATUS: self._status(unit), ALARM: unit.alarm,
                COMM_ERROR: 0, COMMAND_POSITION: unit.command, FEEDBACK_POSITION: self._steps(unit),
                FEEDBACK_SPEED_RPM: round(speed_hz * 60 / unit.steps_per_turn), FEEDBACK_SPEED_HZ: speed_hz,
                }.get(address, unit.maintenance.get(address, 0))

    def write(self, unit: AzUnit, address: int, value: int) -> None:
        if DDO <= address < DDO + 2 * DDO_PAIRS:
            unit.ddo[(address - DDO) // 2] = value
            if address == DDO + 2 * DDO_TRIGGER and value:
                self._start(unit)
        elif address in (INPUT_REF, INPUT_AUTO_OFF):
            rising = In(value & ~unit.inputs if address == INPUT_REF else value)
            if address == INPUT_REF:
                unit.inputs = value
            self._inputs(unit, rising)
        elif address in (ALARM_RESET, CLEAR_ALARM_HISTORY, P_PRESET, CONFIGURATION):
            if value == 1 and unit.maintenance.get(address, 0) == 0:
                self._maintenance(unit, address)
            unit.maintenance[address] = value

    def raise_alarm(self, unit: AzUnit, code: int) -> None:
        unit.alarm = code
        unit.history = [code, *unit.history][:HISTORY]
        self.rig.axis(unit.name).stop()

    def _inputs(self, unit: AzUnit, rising: In) -> None:
        if In.STOP in rising:  # a decelerating stop (HM-60262E "STOP input"; §2.1 "Stop (decelerate)")
            self.stops.append((unit.name, self.rig.clock.now()))
            self.rig.axis(unit.name).decelerate()
        if In.ALM_RST in rising:
            self._maintenance(unit, ALARM_RESET)
        if In.FREE in rising:
            self.rig.axis(unit.name).stop()

    def _maintenance(self, unit: AzUnit, address: int) -> None:
        if address == ALARM_RESET and unit.alarm not in NOT_RESETTABLE:
            unit.alarm = 0
        elif address == CLEAR_ALARM_HISTORY:
            unit.history = []
        elif address == P_PRESET:
            angle = float(self.rig.axis(unit.name).angle_at(self.rig.clock.now()))
            unit.offset = unit.preset - round(angle * unit.steps_per_degree)

    def _start(self, unit: AzUnit) -> None:
        """Direct data operation: start the move the DDO registers describe."""
        if unit.alarm or unit.inputs & (In.FREE | In.STOP):
            return  # a drive in alarm, de-energised, or held by its STOP input starts nothing
        op_type, position = unit.ddo[DDO_TYPE], unit.ddo[DDO_POSITION]
        speed, rate = unit.ddo[DDO_SPEED], unit.ddo[DDO_RATE]
        wrap_type = op_type in (Op.WRAP_ABSOLUTE, *WRAP_WAYS)
        if speed <= 0 or rate <= 0 or op_type not in {*Op} or wrap_type and not unit.wrap:
            self.raise_alarm(unit, OPERATION_DATA_ERROR)
            return
        axis = self.rig.axis(unit.name)
        axis.speed, axis.accel = speed / unit.steps_per_degree, rate / unit.steps_per_degree
        angle = float(axis.angle_at(self.rig.clock.now()))
        if op_type in WRAP_WAYS:
            axis.move_to((position - unit.offset) / unit.steps_per_degree, WRAP_WAYS[Op(op_type)])
            unit.command = position
        elif op_type == Op.INCREMENTAL:
            axis.move_to(angle + position / unit.steps_per_degree, "direct")
            unit.command = self._steps(unit) + position
        else:  # absolute: straight to the position, never across the wrap point
            current = self._steps(unit)
            axis.move_to(angle + (position - current) / unit.steps_per_degree, "direct")
            unit.command = position
        unit.stalled = unit.stall_steps != 0
        if unit.stalled:  # the same move, ending short of its target the way it came
            end = float(axis.angle_at(axis.motion_end))
            axis.move_to(end - (1.0 if end >= angle else -1.0) * unit.stall_steps / unit.steps_per_degree,
                         "direct")


def _listen_failure(endpoint: Endpoint, exc: RuntimeError) -> OSError:
    """Why pymodbus could not listen on ``endpoint``, as the OSError a listener of our own gets
    there (the port is taken, the address is not this host's), for `Emulation` to say in one line."""
    if endpoint.kind != "pty":
        try:
            socket.create_server((endpoint.host, endpoint.port)).close()
        except OSError as reason:  # create_server appends the address, which the caller names already
            return OSError(reason.errno, os.strerror(reason.errno)) if reason.errno else reason
    return OSError(f"{exc}".rstrip("."))


class AzServer:
    """The drives on one bus, served by pymodbus from a thread of their own."""

    def __init__(self, drives: AzDrives, endpoint: Endpoint, faults: dict[str, FaultInjector]):
        self.drives, self.endpoint, self.faults = drives, endpoint, faults
        self._replies: deque[Fault | None] = deque()  # faults for the replies still to be sent
        self._current: Fault | None = None  # the fault of the request being executed
        self.gaps: list[float] = []  # RTU: silence before each request since the last frame, s
        self.dropped = 0  # RTU requests dropped for starting within t3.5
        self.after_broadcast: list[float] = []  # RTU: silence before the first request after each broadcast
        # every request heard, as (monotonic time, unit, function code, address): what reached the
        # drives, whoever sent it (a test checks from here what a run did or did not send)
        self.received: list[tuple[float, int, int, int]] = []
        self._broadcast_heard = False
        self._last_rx = 0.0  # when the last bytes arrived (RTU)
        self._line_quiet_from: float | None = None  # when our last reply left
        self._request_gap: float | None = None  # the silence before the request being received
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._pty: PtyPair | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name=f"emulator {endpoint}",
                                        daemon=True)
        self._thread.start()
        try:
            self._call(self._open())
        except BaseException:
            self.close()  # the loop's thread too: a port that is taken leaves nothing running
            raise

    def _call(self, coroutine):
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(timeout=30)

    @property
    def address(self) -> str:
        return str(self.endpoint)

    # --- serving ----------------------------------------------------------------------------
    def _devices(self) -> list[SimDevice]:
        blocks = [SimData(address, count=count, values=0, datatype=DataType.REGISTERS, readonly=readonly)
                  for address, count, readonly in BLOCKS]
        return [SimDevice(id=unit_id, simdata=list(blocks), action=self._action(unit_id))
                for unit_id in self.drives.units]

    async def _open(self) -> None:
        ep = self.endpoint
        if ep.kind == "tcp":
            self._server = ModbusTcpServer(self._devices(), address=(ep.host, ep.port), broadcast_enable=True,
                                           trace_pdu=self._trace_pdu, trace_packet=self._trace_packet)
        else:
            if ep.kind == "pty":
                self._pty = PtyPair(ep.link)
                port = self._pty.device_path
            else:
                port = f"socket://{ep.host}:{ep.port}"
            self._server = ModbusSerialServer(self._devices(), framer=FramerType.RTU, port=port,
                                              baudrate=115200, broadcast_enable=True,
                                              trace_pdu=self._trace_pdu, trace_packet=self._trace_packet)
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError as exc:  # pymodbus says only "Could not start listen": the port says why
            raise _listen_failure(ep, exc) from None
        if ep.kind != "pty":
            # pymodbus types the transport as asyncio.BaseTransport; a listener's is an asyncio.Server
            server = self._server.transport
            self.endpoint = ep.bound(server.sockets[0].getsockname()[1])  # type: ignore[attr-defined]

    async def _shut(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None
        if self._pty is not None:
            self._pty.close()
            self._pty = None
        self._replies.clear()

    async def _bounce(self, reopen_s: float | None) -> None:
        """The port goes away (a pulled cable, a gateway reboot) and comes back if ``reopen_s``."""
        await self._shut()
        if reopen_s is not None:
            await asyncio.sleep(reopen_s)
            await self._open()

    # --- faults and semantics ---------------------------------------------------------------
    def _trace_pdu(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if not sending:
            heard = (time.monotonic(), pdu.dev_id, pdu.function_code, getattr(pdu, "address", 0))
            self.received.append(heard)
        if not sending and pdu.dev_id == BROADCAST:
            self._current = self._request_gap = None  # every drive executes it; no reply leaves, so
            if self.endpoint.kind != "tcp":  # the line is quiet from the frame's last bytes
                self._line_quiet_from = self._last_rx
                self._broadcast_heard = True
        elif not sending:
            unit = self.drives.units.get(pdu.dev_id)
            description = f"fc{pdu.function_code:02d} {getattr(pdu, 'address', 0):04X}"
            injector = self.faults.get(unit.name) if unit else None
            self._current = injector.take(description) if injector else None
            gap, self._request_gap = self._request_gap, None
            if gap is not None and gap < T35_ABOVE_19200_S:  # the serial server runs above 19200 Bd
                self.dropped += 1  # the frame ran into the previous one: a strict slave drops both
                self._current = Fault(FaultKind.LOST_REQUEST)
            silent = unit is None  # nobody at that address on an RS-485 line: silence
            self._replies.append(Fault(FaultKind.NO_REPLY) if silent else self._current)
        return pdu

    def _trace_packet(self, sending: bool, packet: bytes) -> bytes:
        if self.endpoint.kind != "tcp" and packet:
            self._time_rtu(sending)
        if not sending or not packet:
            return packet
        fault = self._replies.popleft() if self._replies else None
        kind = fault.kind if fault else None
        if kind in (FaultKind.NO_REPLY, FaultKind.CLOSE_PORT, FaultKind.LOST_REQUEST):
            if kind == FaultKind.CLOSE_PORT:
                assert fault is not None
                self._loop.create_task(self._bounce(fault.reopen_s))
            return b""
        if fault is not None and kind == FaultKind.LATE_REPLY:
            time.sleep(fault.delay_s)  # the bus is busy meanwhile, as it would be
        if kind == FaultKind.GARBLED:
            return packet[:2] + b"\xa5\x5a" + packet[4:] if self.endpoint.kind == "tcp" else garble(packet)
        if kind == FaultKind.TRUNCATED:
            return packet[:len(packet) // 2]
        if kind == FaultKind.DROPPED_BYTE and fault is not None:
            return drop_byte(packet, fault)
        return packet

    def _time_rtu(self, sending: bool) -> None:
        """The silence on the line before each request: from our last reply leaving to the first
        bytes of the next request arriving (pymodbus traces every chunk it reads; the first chunk
        after a complete frame starts a request)."""
        now = time.monotonic()
        if not sending:
            self._last_rx = now
        if sending:
            self._line_quiet_from = now
        elif self._request_gap is None and self._line_quiet_from is not None:
            self._request_gap = now - self._line_quiet_from
            self.gaps.append(self._request_gap)
            if self._broadcast_heard:
                self.after_broadcast.append(self._request_gap)
                self._broadcast_heard = False
            self._line_quiet_from = None
    def _action(self, unit_id: int):
        unit = self.drives.units[unit_id]

        async def action(fc: int, start: int, address: int, count: int, registers: list[int],
                         values: list[int] | None) -> ExcCodes | None:
            fault, self._current = self._current, None
            if fault and fault.kind == FaultKind.LOST_REQUEST:
                return None  # never reached the drive: nothing done (and nothing answered)
            if fault and fault.kind == FaultKind.EXCEPTION:
                return ExcCodes(int(fault.code) if fault.code is not None else ExcCodes.DEVICE_FAILURE)
            with self.drives.rig.lock:
                if fault and fault.kind == FaultKind.ALARM:
                    self.drives.raise_alarm(unit, DEFAULT_ALARM if fault.code is None else int(fault.code))
                if values is None:
                    for at in range(address & ~1, address + count, 2):
                        for i, word in enumerate(pair(self.drives.read(unit, at))):
                            if 0 <= at + i - start < len(registers):
                                registers[at + i - start] = word
                    return None
                if fc == 0x10 and (address % 2 or count % 2):
                    return ExcCodes.ILLEGAL_ADDRESS  # 32-bit values are written as whole pairs
                pairs = range(address & ~1, address + count, 2)
                words = {a: registers[a - start] for at in pairs for a in (at, at + 1)}
                words.update({address + i: v for i, v in enumerate(values)})  # FC 06 may write half a pair
                for at in pairs:
                    self.drives.write(unit, at, unpair(words[at], words[at + 1]))
            return None

        return action

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._call(self._shut())
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)
        self._loop.close()
