"""Serves a line-protocol device emulator (SMC100, SCPI) on a pty pair or a TCP port, one thread.

The device sees one request line at a time and returns its reply line (or None: no reply). Faults
from the device's `FaultInjector` are applied here, the same way for every line protocol.
"""

from __future__ import annotations

import contextlib
import os
import socket
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable
from typing import Protocol

from labcal.config.emulation import FaultKind
from labcal.sim.endpoint import Endpoint
from labcal.sim.faults import FaultInjector, drop_byte, garble
from labcal.sim.polling import readable, writable
from labcal.sim.ptys import PtyPair


class LineDevice(Protocol):
    eol: bytes
    networked: bool  # on TCP, the device's own network interface (a LAN DMM), not a serial-device server

    def route(self, line: str) -> str:
        """The name of the device a request addresses (whose faults apply)."""

    def handle(self, line: str) -> str | None:
        """Execute one request; its reply without terminator, or None when none is due."""

    def refuse(self, line: str, code: int | str | None) -> None:
        """Refuse the request as the device does for a bad one (error code, error queue)."""

    def alarm(self, name: str, code: int | str | None) -> None:
        """Raise the device's alarm on the named device."""

    def power_cycle(self, name: str) -> None:
        """Switch the named device off and on (its power-on state)."""


class _Channel:
    """One open connection (a socket or the emulator's end of a pty) with its input buffer."""

    def __init__(self, fd: int, send: Callable[[bytes], None], close: Callable[[], None]):
        self.fd, self.send, self.close = fd, send, close
        self.buffer = b""


class LineServer:
    def __init__(self, device: LineDevice, endpoint: Endpoint, faults: dict[str, FaultInjector],
                 char_s: float = 0.0):
        """``char_s``: replies leave no faster than one character in that many seconds, as on a
        real RS-232 line; 0: at once (a network link)."""
        self.device, self.endpoint, self.faults = device, endpoint, faults
        self.char_s = char_s
        self.errors: list[BaseException] = []  # emulator bugs, kept for tests to see
        # every request line heard, as (monotonic time, line): what reached the device, whoever
        # sent it (a test checks from here what a run did or did not send)
        self.received: list[tuple[float, str]] = []
        self._listener: socket.socket | None = None
        self._pty: PtyPair | None = None
        self._channels: dict[int, _Channel] = {}
        self._forgotten: list[_Channel] = []  # half-open connections: open here, never read again
        self._forget = False  # `forget_connections` asked; done by the serving thread
        self._reopen_at: float | None = None
        self._closed = False
        self._wake_r, self._wake_w = os.pipe()
        self._open()
        self._thread = threading.Thread(target=self._serve, name=f"emulator {endpoint}", daemon=True)
        self._thread.start()

    # --- the port ---------------------------------------------------------------------------
    def _open(self) -> None:
        if self.endpoint.kind == "pty":
            self._pty = PtyPair(self.endpoint.link)
            fd = os.open(self._pty.device_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            tty.setraw(fd)
            termios.tcflush(fd, termios.TCIOFLUSH)
            self._channels[fd] = _Channel(fd, lambda data: _write_all(fd, data), lambda: os.close(fd))
        else:
            listener = socket.create_server((self.endpoint.host, self.endpoint.port), reuse_port=False)
            listener.setblocking(False)
            self._listener = listener
            self.endpoint = self.endpoint.bound(listener.getsockname()[1])

    def forget_connections(self) -> None:
        """The device, or a switch on the way, forgets every open network connection without a
        word to the other end (no FIN, no reset): their sockets stay open here, never read again,
        so the other end's requests are sent without error and never answered (a half-open
        connection). New connections are served as before. Takes effect as the next request arrives."""
        self._forget = True

    def _close_port(self) -> None:
        for channel in [*self._channels.values(), *self._forgotten]:
            with contextlib.suppress(OSError):
                channel.close()
        self._channels.clear()
        self._forgotten.clear()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        if self._pty is not None:
            self._pty.close()
            self._pty = None

    @property
    def address(self) -> str:
        return str(self.endpoint)

    # --- the loop ---------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._closed:
            if self._reopen_at is not None and time.monotonic() >= self._reopen_at:
                self._reopen_at = None
                self._open()
            watched = [self._wake_r, *self._channels] + ([self._listener] if self._listener else [])
            timeout = None if self._reopen_at is None else max(0.0, self._reopen_at - time.monotonic())
            ready = readable(watched, timeout)
            if self._wake_r in ready:
                return
            if self._forget:
                self._forget = False
                if self._listener is not None:  # a pty is no connection to forget
                    self._forgotten += self._channels.values()
                    self._channels.clear()
                continue
            for item in ready:
                if item is self._listener:
                    self._accept()
                elif item in self._channels:
                    self._receive(self._channels[item])

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            conn, _ = self._listener.accept()
        except BlockingIOError:
            return
        conn.setblocking(True)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._channels[conn.fileno()] = _Channel(conn.fileno(), conn.sendall, conn.close)

    def _receive(self, channel: _Channel) -> None:
        try:
            data = os.read(channel.fd, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the other end hung up
            if self._pty is None:
                self._channels.pop(channel.fd, None)
                channel.close()
            return
        channel.buffer += data
        while b"\n" in channel.buffer and channel.fd in self._channels:
            raw, _, channel.buffer = channel.buffer.partition(b"\n")
            line = raw.decode("ascii", errors="replace").strip()
            if line:
                try:
                    self._request(channel, line)
                except OSError:
                    pass  # the requester went away before its reply
                except Exception as exc:  # noqa: BLE001 - an emulator bug must not kill the port
                    self.errors.append(exc)
                    print(f"labcal emulator: {type(exc).__name__}: {exc}", file=sys.stderr)

    def _request(self, channel: _Channel, line: str) -> None:
        self.received.append((time.monotonic(), line))
        name = self.device.route(line)
        injector = self.faults.get(name)
        fault = injector.take(line) if injector else None
        kind = fault.kind if fault else None
        if kind == FaultKind.CLOSE_PORT:
            assert fault is not None
            self._close_port()
            self._reopen_at = None if fault.reopen_s is None else time.monotonic() + fault.reopen_s
            return
        if kind == FaultKind.EXCEPTION:
            self.device.refuse(line, fault.code if fault else None)
            return
        if kind == FaultKind.LOST_REQUEST:
            return
        if kind == FaultKind.POWER_CYCLE:
            self.device.power_cycle(name)
            if self._listener is not None and self.device.networked:  # its LAN interface restarts too
                for fd, other in list(self._channels.items()):
                    self._channels.pop(fd)
                    with contextlib.suppress(OSError):
                        other.close()
            return
        if kind == FaultKind.ALARM:
            self.device.alarm(name, fault.code if fault else None)
        reply = self.device.handle(line)
        if reply is None or kind == FaultKind.NO_REPLY:
            return
        data = reply.encode("ascii")
        if kind == FaultKind.GARBLED:
            data = garble(data)
        if kind == FaultKind.DROPPED_BYTE and fault is not None:
            data = drop_byte(data, fault)
        if kind == FaultKind.TRUNCATED:
            channel.send(data[:len(data) // 2])
            return
        if kind == FaultKind.LATE_REPLY and fault is not None:
            time.sleep(fault.delay_s)
        self._send(channel, data + self.device.eol)

    def _send(self, channel: _Channel, data: bytes) -> None:
        """The reply, paced at the line's rate when it has one (in pieces of ~20 ms)."""
        if not self.char_s:
            channel.send(data)
            return
        piece = max(1, int(0.02 / self.char_s))
        for at in range(0, len(data), piece):
            started = time.monotonic()
            channel.send(data[at:at + piece])
            time.sleep(max(0.0, started + len(data[at:at + piece]) * self.char_s - time.monotonic()))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=10)
        self._close_port()
        os.close(self._wake_r)
        os.close(self._wake_w)


def _write_all(fd: int, data: bytes) -> None:
    while data:
        try:
            data = data[os.write(fd, data):]
        except BlockingIOError:
            writable(fd, 1.0)
