"""One Modbus master per bus (an RS-485 line, or a TCP gateway), on the real pymodbus client.

pymodbus frames and checks the bytes (CRC, transaction ids); this link adds what a bench needs:
its own bounded retries (pymodbus is told not to retry, so only exchanges known to be safe are
repeated; a busy device or gateway, exceptions 06h/0Ah/0Bh, counts as a missing reply), a reopened
port after a late reply or a vanished port, the RTU silent interval before every request, and
replies checked for shape and turned into driver errors. Units on one bus share one link: one
bus, one owner. Every frame is logged at DEBUG in hex (logger ``labcal.drivers.modbus``).
"""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Callable, Sequence

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.pdu import ExceptionResponse, ModbusPDU

from labcal.devices.station import CriticalSection
from labcal.drivers.errors import BadReply, Busy, NoReply, PortClosed, Rejected
from labcal.drivers.transport import (
    awaiting_reply,
    open_serial,
    quiet_line,
    reconnect,
    retried,
    uninterruptible,
)

logging.getLogger("pymodbus").addHandler(logging.NullHandler())  # our errors say it in one line
log = logging.getLogger(__name__)

TURNAROUND_S = 0.1  # after a broadcast on a serial line the master waits this long before its next request,
# for every slave to have processed it (Modbus over Serial Line V1.02 §2.4.1: "typically 100 ms to 200 ms")
BROADCAST = 0  # the address every slave on a serial line obeys and none answers (Modbus over Serial Line
# V1.02 §2.2; AZ: hardware_protocols.md §2.1, "0 = broadcast (no reply)"); a gateway forwards it as such

EXCEPTION_CODES = {
    1: "illegal function", 2: "illegal data address", 3: "illegal data value",
    4: "slave device failure", 5: "acknowledge", 6: "slave device busy", 8: "memory parity error",
    10: "gateway path unavailable", 11: "gateway target failed to respond",
}

BUSY_CODES = frozenset({0x06, 0x0A, 0x0B})  # nothing done; asking again later may succeed

Trace = Callable[[bool, bytes], bytes]


def silent_interval_s(baudrate: int, bits_per_char: int = 11) -> float:
    """t3.5, the silence that must precede every RTU frame: 3.5 character times (11 bits each),
    fixed at 1.75 ms above 19200 Bd (Modbus over Serial Line V1.02, §2.5.1.1)."""
    return 1.75e-3 if baudrate > 19200 else 3.5 * bits_per_char / baudrate


class SilentInterval:
    """A pymodbus packet trace that holds each request back until the line has been silent for
    t3.5 since the last byte received or sent: a request that starts earlier runs into the previous
    frame, and a strict slave drops both (a reply arrives, and on a daisy chain our own request
    ends, only a moment before the next request would otherwise go out)."""

    def __init__(self, baudrate: int, bits_per_char: int, then: Trace | None = None):
        self.t35 = silent_interval_s(baudrate, bits_per_char)
        self.char_s = bits_per_char / baudrate
        self.then = then
        self.quiet_from = 0.0  # monotonic time of the end of the last byte on the line

    def __call__(self, sending: bool, packet: bytes) -> bytes:
        if sending:
            while (wait := self.quiet_from + self.t35 - time.monotonic()) > 0:
                time.sleep(wait)
            self.quiet_from = time.monotonic() + len(packet) * self.char_s
        else:
            self.quiet_from = max(self.quiet_from, time.monotonic())
        return trace_frame(sending, packet, self.then)


def trace_frame(sending: bool, packet: bytes, then: Trace | None) -> bytes:
    """Log a frame at DEBUG (hex) and hand it to ``then``, a test's trace, if any."""
    if packet and log.isEnabledFor(logging.DEBUG):
        log.debug("%s %s", ">" if sending else "<", packet.hex(" "))
    return then(sending, packet) if then else packet


def int32_words(value: int) -> list[int]:
    """A signed 32-bit value as two registers, upper word first (two's complement)."""
    if not -(2**31) <= value < 2**31:
        raise ValueError(f"{value} does not fit in 32 bits")
    raw = value & 0xFFFFFFFF
    return [raw >> 16, raw & 0xFFFF]


def words_int32(upper: int, lower: int) -> int:
    raw = (upper << 16) | lower
    return raw - 2**32 if raw & 0x80000000 else raw


def checked(response: object, function_code: int, address: int, count: int) -> list[int]:
    """The registers of a well-formed reply to (function_code, address, count); raises `Rejected`
    for an exception response and `BadReply` for anything else that is not the expected reply."""
    if isinstance(response, ExceptionResponse) or (isinstance(response, ModbusPDU) and response.isError()):
        code = getattr(response, "exception_code", 0)
        refused = Busy if code in BUSY_CODES else Rejected
        raise refused(f"exception {code:02X}h ({EXCEPTION_CODES.get(code, 'unknown code')}) "
                      f"to function {function_code:02X}h at {address:04X}h")
    if not isinstance(response, ModbusPDU) or response.function_code != function_code:
        raise BadReply(f"reply {response} does not answer function {function_code:02X}h")
    registers = list(getattr(response, "registers", []) or [])
    if function_code == 0x03 and len(registers) != count:
        raise BadReply(f"{len(registers)} registers in the reply, {count} asked for")
    if function_code in (0x06, 0x10) and getattr(response, "address", None) != address:
        raise BadReply(f"write acknowledged at {getattr(response, 'address', None)}, not {address:04X}h")
    if function_code == 0x10 and getattr(response, "count", None) != count:
        raise BadReply(f"write of {count} registers acknowledged as {getattr(response, 'count', None)}")
    return registers


class ModbusLink:
    """A Modbus master on one bus; every method is one exchange, retried because all are safe
    to repeat (reads, absolute-move writes, stop pulses, edge-triggered resets)."""

    def __init__(self, client: ModbusSerialClient | ModbusTcpClient, where: str, *, timeout_s: float,
                 retries: int, reconnect_s: float, open_port: Callable[[], object]):
        self.client = client
        self.where = where
        self.open_port = open_port  # opens the client's socket; raises what the OS said
        self.timeout_s = timeout_s
        self.tries = retries + 1
        self.reconnect_s = reconnect_s
        self.critical: CriticalSection | None = None  # the run's, while a run drives this link
        self.turnaround_s = 0.0  # serial lines: the wait after a broadcast (a gateway keeps its own)
        self._quiet_until = 0.0  # no request before this (monotonic): the turnaround of a broadcast
        self._broadcast: tuple[int, int] | None = None  # the last broadcast (address, value)
        self._cut_since: float | None = None  # a stop cut a wait for a reply short: when (monotonic)

    @classmethod
    def serial(cls, port: str, *, baudrate: int, bytesize: int, parity: str, stopbits: int,
               timeout_s: float, retries: int, reconnect_s: float, trace: Trace | None = None) -> ModbusLink:
        """Modbus RTU on a serial port or pyserial URL (a pty, ``socket://`` to a serial server)."""
        bits_per_char = 1 + bytesize + (parity != "N") + stopbits
        silence = SilentInterval(baudrate, bits_per_char, trace)
        client = ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate, bytesize=bytesize,
                                    parity=parity, stopbits=stopbits, timeout=timeout_s, retries=0,
                                    reconnect_delay=0, trace_packet=silence)

        def open_port() -> None:
            """pymodbus's own connect() logs why a port does not open and returns False; this
            keeps the reason (no such port, permission denied, port busy)."""
            client.socket = open_serial(port, baudrate=baudrate, bytesize=bytesize, parity=parity,
                                        stopbits=stopbits, timeout=timeout_s, write_timeout=timeout_s,
                                        inter_byte_timeout=client.inter_byte_timeout)

        link = cls(client, port, timeout_s=timeout_s, retries=retries, reconnect_s=reconnect_s,
                   open_port=open_port)
        link.turnaround_s = TURNAROUND_S
        return link

    @classmethod
    def tcp(cls, host: str, port: int, *, timeout_s: float, retries: int, reconnect_s: float,
            trace: Trace | None = None) -> ModbusLink:
        """Modbus TCP (MBAP framing), e.g. through an RS-485 gateway: unit id = slave address."""
        client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0, reconnect_delay=0,
                                 trace_packet=lambda sending, packet: trace_frame(sending, packet, trace))

        def open_port() -> None:
            client.socket = socket.create_connection((host, port), timeout=timeout_s)

        return cls(client, f"tcp {host}:{port}", timeout_s=timeout_s, retries=retries,
                   reconnect_s=reconnect_s, open_port=open_port)

    def read(self, unit: int, address: int, count: int) -> list[int]:
        """FC 03, read holding registers."""
        def request() -> object:
            return self.client.read_holding_registers(address, count=count, device_id=unit)
        return self._exchange(request, 0x03, address, count)

    def write(self, unit: int, address: int, values: Sequence[int]) -> None:
        """FC 10h, write multiple registers."""
        self._exchange(lambda: self.client.write_registers(address, list(values), device_id=unit),
                       0x10, address, len(values))

    def write_one(self, unit: int, address: int, value: int) -> None:
        """FC 06, write single register."""
        self._exchange(lambda: self.client.write_register(address, value, device_id=unit), 0x06, address, 1)

    def broadcast_one(self, address: int, value: int) -> None:
        """FC 06 to every unit on the bus at once, sent once: nobody answers a broadcast, so nothing
        is waited for and nothing retried (a stop that must not wait for a dead unit's retries)."""
        if (address, value) == self._broadcast and time.monotonic() < self._quiet_until:
            return  # the same broadcast just went out (two drives of one bus each asked for it)
        with uninterruptible(self.critical):
            self._take_back()
            if not self.client.connected:
                reconnect(self.open_port, 0.0, self.where)  # one attempt: the stop's confirmation retries
            try:
                self.client.write_register(address, value, device_id=BROADCAST, no_response_expected=True)
            except ConnectionException as exc:
                self.close()
                raise PortClosed(f"{self.where} closed ({exc})") from None
            self._quiet_until = time.monotonic() + self.turnaround_s
            self._broadcast = (address, value)

    def _exchange(self, request: Callable[[], object], function_code: int, address: int,
                  count: int) -> list[int]:
        def once() -> list[int]:
            if (wait := self._quiet_until - time.monotonic()) > 0:
                time.sleep(wait)
            self._broadcast = None
            self._take_back()
            if not self.client.connected:
                reconnect(self.open_port, self.reconnect_s, self.where)
            try:
                with awaiting_reply(self.critical):  # pymodbus writes the request at once, then waits
                    response = request()
            except KeyboardInterrupt:  # a stop cut the wait short: the next frame takes the line back
                self._cut_since = time.monotonic()
                raise
            except ConnectionException as exc:
                self.close()
                raise PortClosed(f"{self.where} closed ({exc})") from None
            except ModbusIOException as exc:
                if "No response" in str(exc):
                    raise NoReply(f"no reply within {self.timeout_s:g} s") from None
                raise BadReply(f"reply does not match the request ({exc})") from None
            except (ValueError, IndexError, KeyError, TypeError, AttributeError) as exc:
                raise BadReply(f"undecodable reply ({type(exc).__name__}: {exc})") from None
            return checked(response, function_code, address, count)

        return retried(once, self.tries, self._recover, self.critical, what=self.where)

    def _take_back(self) -> None:
        """The bus after a stop cut a wait for a reply short. Over TCP the connection is dropped and
        the next frame goes out on a new one (a late reply, matched by transaction id on the old one,
        is never read). On a serial line, where a live unit's reply may be on its way and nothing must
        be sent over it, the line is taken back once quiet (`quiet_line`), what arrived discarded."""
        since, self._cut_since = self._cut_since, None
        if since is None or not self.client.connected:
            return
        discard = getattr(getattr(self.client, "socket", None), "reset_input_buffer", None)
        if self.turnaround_s == 0.0 or discard is None:
            self.close()
            return
        quiet_line(self._waiting, discard, since, self.timeout_s, self.where)

    def _recover(self) -> None:
        """Let a late reply arrive, then reopen the port: the reopened port starts with empty
        buffers, so a late reply is never taken for the answer to the next request (RTU has no
        transaction ids to tell them apart)."""
        try:
            with awaiting_reply(self.critical):
                time.sleep(min(self.timeout_s, 0.5))
        except KeyboardInterrupt:
            self._cut_since = time.monotonic()
            raise
        late = self._waiting()
        log.warning("%s: reopening the port%s", self.where,
                    f" ({late} late byte(s) discarded with it)" if late else " before the next try")
        self.close()

    def _waiting(self) -> int:
        """Bytes that arrived after the exchange gave up (a late reply), without reading them."""
        port = getattr(self.client, "socket", None)
        try:
            if isinstance(port, socket.socket):
                port.setblocking(False)
                return len(port.recv(4096, socket.MSG_PEEK))
            return int(getattr(port, "in_waiting", 0))
        except (OSError, ValueError, TypeError):
            return 0

    def close(self) -> None:
        self.client.close()  # type: ignore[no-untyped-call]  # pymodbus: the sync clients' close() is unannotated
