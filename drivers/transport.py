"""Byte links to devices, chosen by configuration, and the rules every exchange follows.

A link is a serial port given by path or any pyserial URL (``socket://host:port``, ``loop://``,
``rfc2217://``...) or a raw TCP connection to ``host:port``. Every exchange has a timeout; an
exchange that is safe to repeat is retried a bounded number of times; a vanished port is
reopened with backoff; Ctrl-C waits until the exchange in flight is complete so that no reply is
left half-read on the line. Every line is logged at DEBUG, every retry, reconnect and late reply at
WARNING (loggers ``labcal.drivers.*``), so that a degrading line leaves a record.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import termios
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from types import FrameType
from typing import Any, Protocol, TypeVar

import serial

from labcal.devices.station import CriticalSection
from labcal.drivers.errors import TRANSIENT, BadReply, LinkLost, NoReply, PortClosed, SettingsRefused

T = TypeVar("T")
log = logging.getLogger(__name__)

BACKOFF_FIRST_S = 0.05
BACKOFF_MAX_S = 1.0
SLICE_S = 0.02  # streams return what arrived within this; callers loop until their own deadline
CUT_QUIET_S = 0.05  # after a stop cut the wait for a reply short, the line is taken back once it has been
# quiet this long since the request or the last byte: a live device's reply starts within a few
# milliseconds (SMC100 and AZ answer within 10 ms of the request's end; an RTU frame's bytes are at most
# t1.5 apart, Modbus over Serial Line V1.02 §2.5.1.1), so a reply on its way ends first and nothing is
# sent over it on a shared line; a dead controller's silence costs only this


@contextmanager
def uninterruptible(critical: CriticalSection | None = None) -> Iterator[None]:
    """Defer the first Ctrl-C until the block is done, then raise it (a second one is immediate).

    During a run the run's own handler owns Ctrl-C and hands its links ``critical``: the block is
    then one of its critical sections (a first Ctrl-C asks for a pause, a second is deferred to the
    end of the exchange). Only the main thread receives signals; elsewhere, or inside another such
    block, this is a no-op.
    """
    if critical is not None and threading.current_thread() is threading.main_thread():
        with critical():
            yield
        return
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    pending: list[int] = []

    def defer(signum: int, frame: FrameType | None) -> None:
        if pending:
            raise KeyboardInterrupt
        pending.append(signum)

    signal.signal(signal.SIGINT, defer)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if pending:
        raise KeyboardInterrupt


@contextmanager
def awaiting_reply(critical: CriticalSection | None) -> Iterator[None]:
    """The part of an exchange that waits for the reply, its request on the line: during a run a
    stop is raised here at once instead of after the reply timeout (the caller then takes the line
    back before its next frame, `quiet_line`). Outside a run, or off the main thread: nothing."""
    if critical is not None and threading.current_thread() is threading.main_thread():
        with critical(awaiting_reply=True):
            yield
    else:
        yield


def quiet_line(waiting: Callable[[], int], discard: Callable[[], object], since: float, timeout_s: float,
               where: str) -> None:
    """After a wait for a reply was cut short: wait until no byte has arrived for `CUT_QUIET_S`
    since ``since`` (the request's end) or the last byte (``waiting()``: bytes received so far),
    at most ``timeout_s``, then ``discard`` what arrived, so that the next frame neither runs into a
    late reply on a shared line nor takes it for its own answer."""
    seen, quiet_from, give_up = waiting(), since, time.monotonic() + timeout_s
    while (now := time.monotonic()) < min(quiet_from + CUT_QUIET_S, give_up):
        time.sleep(min(SLICE_S / 4, quiet_from + CUT_QUIET_S - now))
        if (count := waiting()) != seen:
            seen, quiet_from = count, time.monotonic()
    if seen:
        log.warning("%s: %d byte(s) of a reply cut short by a stop discarded", where, seen)
    discard()


def retried(exchange: Callable[[], T], tries: int, recover: Callable[[], None],
            critical: CriticalSection | None = None, what: str = "device") -> T:
    """Run an exchange that is safe to repeat (a read, an absolute move, a stop) up to ``tries``
    times; ``recover`` clears the line between tries (late replies, a reopened port); each try is
    uninterruptible (``critical``: the run's critical section, when a run has handed one). Each
    repeat is logged as a WARNING naming ``what`` and the failure that caused it."""
    for attempt in range(tries):
        try:
            with uninterruptible(critical):
                return exchange()
        except TRANSIENT as exc:
            if attempt + 1 >= tries:
                raise
            log.warning("%s: retry %d of %d after: %s", what, attempt + 1, tries - 1, exc)
            recover()
    raise AssertionError("tries must be >= 1")


def reconnect(connect: Callable[[], object], budget_s: float, what: str) -> None:
    """Call ``connect`` until it succeeds (returns anything but False without raising), waiting
    0.05 s, 0.1 s, ... up to 1 s between attempts; `LinkLost` once ``budget_s`` is spent."""
    deadline = time.monotonic() + budget_s
    delay = BACKOFF_FIRST_S
    failures = 0
    while True:
        try:
            if connect() is not False:
                if failures:
                    log.warning("%s: reopened after %d failed attempt(s)", what, failures)
                return
            reason = "connection refused"
        except (OSError, serial.SerialException, ValueError) as exc:
            errno = getattr(exc, "errno", None)
            reason = os.strerror(errno) if isinstance(errno, int) else str(exc) or type(exc).__name__
        failures += 1
        if time.monotonic() + delay > deadline:
            tried = f"; kept trying for {budget_s:g} s" if budget_s > 0 else ""
            raise LinkLost(f"cannot open {what} ({reason}){tried}")
        log.warning("%s: cannot open (%s); trying again in %g s", what, reason, delay)
        time.sleep(delay)
        delay = min(2 * delay, BACKOFF_MAX_S)


def ascii_line(raw: bytes, where: str) -> str:
    """A reply line without its terminator, logged; `BadReply` for bytes that are not ASCII text."""
    text = raw.decode("ascii", errors="replace").rstrip("\r\n")
    log.debug("%s < %s", where, text)
    if "\ufffd" in text or not text.isprintable():
        raise BadReply(f"garbled reply {raw[:40]!r}")
    return text


class Lines(Protocol):
    """What a line-protocol driver needs from its link: `LineTransport`, or a VISA resource
    (`labcal.drivers.visa.VisaLink`)."""

    where: str
    timeout_s: float
    critical: CriticalSection | None
    opens: int  # how many times the link has been opened: a driver verifies a device after a reopening

    def write_line(self, text: str) -> None: ...

    def read_line(self, timeout_s: float | None = None) -> str: ...

    def query(self, text: str, timeout_s: float | None = None) -> str: ...

    def drain(self) -> None: ...

    def drop_connection(self) -> None:
        """After a failed exchange: a network connection is closed, so that the next exchange
        opens a new one; a serial line is left open."""

    def close(self) -> None: ...


class Stream(Protocol):
    """An open byte stream: what a line transport needs from a serial port or a socket."""

    def write(self, data: bytes) -> None: ...

    def read_some(self) -> bytes:
        """What arrives within `SLICE_S` (b"" if nothing); raises OSError if the port is gone."""

    def close(self) -> None: ...


# 9600 8N1, what a port is probed at to name the setting it refuses
LINE_SETTINGS: dict[str, Any] = {"baudrate": 9600, "bytesize": 8, "parity": "N", "stopbits": 1,
                                 "xonxoff": False}


def open_serial(url: str, **settings: Any) -> serial.Serial:
    """A serial port or pyserial URL, opened for this process alone with the station's line
    settings. A setting the operating system refuses is `SettingsRefused` naming it (found by
    trying each on the port at 9600 8N1), at once: reopening would be refused the same way."""
    try:
        port = serial.serial_for_url(url, exclusive=True, **settings)
        if dropped := _not_kept(port, settings):  # a pty takes parity without a word, and drops it
            port.close()
            raise SettingsRefused(f"{url} does not keep {' and '.join(dropped)} (it reads back other line "
                                  "settings); set the station file's line settings to ones the port and the "
                                  "device support")
        return port
    except termios.error as exc:
        reason = exc.args[1] if len(exc.args) > 1 else str(exc)
    except ValueError as exc:  # pyserial: a baud rate the port cannot be set to
        if "baud" not in str(exc).lower():
            raise
        reason = str(exc)
    refused = [f"{name} = {_spelled(value)}" for name, value in settings.items()
               if name in LINE_SETTINGS and _refuses(url, name, value)]
    given = ", ".join(f"{name} = {_spelled(settings[name])}" for name in LINE_SETTINGS if name in settings)
    what = (f"refuses {' and '.join(refused)}" if refused else f"refuses its line settings ({given})")
    raise SettingsRefused(f"{url} {what} (the operating system says: {reason}); set the station file's "
                          "line settings to ones the port and the device support")


def _not_kept(port: serial.SerialBase, settings: dict[str, Any]) -> list[str]:
    """The line settings asked for that the port's terminal attributes do not hold (a device node
    only: a URL such as ``socket://`` has none)."""
    fd = getattr(port, "fd", None)
    if not isinstance(fd, int):
        return []
    cflag = termios.tcgetattr(fd)[2]
    sizes = {termios.CS5: 5, termios.CS6: 6, termios.CS7: 7, termios.CS8: 8}
    held = {"parity": "N" if not cflag & termios.PARENB else "O" if cflag & termios.PARODD else "E",
            "bytesize": sizes.get(cflag & termios.CSIZE), "stopbits": 2 if cflag & termios.CSTOPB else 1}
    return [f"{name} = {_spelled(settings[name])}" for name, value in held.items()
            if name in settings and settings[name] != value]


def _refuses(url: str, name: str, value: object) -> bool:
    """Whether the port, open at 9600 8N1, refuses this one setting (False if it cannot be opened)."""
    try:
        port = serial.serial_for_url(url, exclusive=True, **LINE_SETTINGS)
    except (termios.error, ValueError, OSError, serial.SerialException):
        return False
    try:
        setattr(port, name, value)
        return False
    except (termios.error, ValueError, serial.SerialException):
        return True
    finally:
        with suppress(termios.error, ValueError, OSError, serial.SerialException):
            port.close()


def _spelled(value: object) -> str:
    return (f'"{value}"' if isinstance(value, str) else str(value).lower() if isinstance(value, bool)
            else str(value))


class SerialStream:
    """A serial port or pyserial URL."""

    def __init__(self, url: str, *, baudrate: int, bytesize: int, parity: str, stopbits: float,
                 xonxoff: bool, timeout_s: float):
        self.network = url.lower().startswith(("socket://", "rfc2217://"))  # a serial-device server
        self.port = open_serial(url, baudrate=baudrate, bytesize=bytesize, parity=parity, stopbits=stopbits,
                                xonxoff=xonxoff, timeout=SLICE_S, write_timeout=timeout_s)

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except serial.SerialException as exc:
            raise OSError(str(exc)) from None

    def read_some(self) -> bytes:
        try:
            first = self.port.read(1)
            return first + self.port.read(self.port.in_waiting) if first else b""
        except serial.SerialException as exc:
            raise OSError(str(exc)) from None

    def close(self) -> None:
        self.port.close()


class TcpStream:
    """A raw TCP connection (SCPI on port 5025, a serial-device server)."""

    network = True

    def __init__(self, host: str, port: int, timeout_s: float):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.settimeout(SLICE_S)

    def write(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read_some(self) -> bytes:
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return b""
        if not data:
            raise ConnectionResetError("the other end closed the connection")
        return data

    def close(self) -> None:
        self.sock.close()


class LineTransport:
    """ASCII lines over a stream that is opened on first use and reopened when it vanishes."""

    def __init__(self, where: str, open_stream: Callable[[], Stream], *, eol: bytes = b"\n",
                 timeout_s: float = 1.0, reconnect_s: float = 5.0):
        self.where = where  # e.g. "tcp 127.0.0.1:5025", for messages
        self.open_stream = open_stream
        self.eol = eol
        self.timeout_s = timeout_s
        self.reconnect_s = reconnect_s
        self._stream: Stream | None = None
        self._buffer = b""
        self.critical: CriticalSection | None = None  # the run's, while a run drives this link
        self.opens = 0
        self._cut_since: float | None = None  # a stop cut a wait for a reply short: the request's end
        self._last_write = 0.0

    def _open(self) -> Stream:
        if self._stream is None:
            def connect() -> None:
                self._stream = self.open_stream()
            reconnect(connect, self.reconnect_s, self.where)
            self._buffer = b""
            self.opens += 1
        assert self._stream is not None
        return self._stream

    def _lost(self, exc: OSError) -> PortClosed:
        self.close()
        return PortClosed(f"{self.where} closed ({exc})")

    def write_line(self, text: str) -> None:
        stream = self._open()
        if self._cut_since is not None:
            self._take_back(stream)
        log.debug("%s > %s", self.where, text)
        try:
            stream.write(text.encode("ascii") + self.eol)
        except OSError as exc:
            raise self._lost(exc) from None
        self._last_write = time.monotonic()

    def _take_back(self, stream: Stream) -> None:
        """The line after a stop cut a wait for its reply short (`quiet_line`): a controller's
        reply on its way ends and is discarded before the next line goes out."""
        since, self._cut_since = self._cut_since, None
        arrived = [self._buffer]

        def waiting() -> int:
            try:
                arrived.append(stream.read_some())
            except OSError:
                pass
            return sum(map(len, arrived))

        quiet_line(waiting, lambda: setattr(self, "_buffer", b""), since or 0.0, self.timeout_s, self.where)

    def read_line(self, timeout_s: float | None = None) -> str:
        """The next line without its terminator; NoReply on silence, BadReply on a partial line
        or bytes that are not ASCII text."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        stream = self._open()
        deadline = time.monotonic() + timeout
        try:
            with awaiting_reply(self.critical):
                while b"\n" not in self._buffer:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        partial, self._buffer = self._buffer, b""
                        if partial:
                            raise BadReply(f"incomplete reply {partial[:40]!r} after {timeout:g} s")
                        raise NoReply(f"no reply within {timeout:g} s")
                    try:
                        self._buffer += stream.read_some()
                    except OSError as exc:
                        raise self._lost(exc) from None
        except KeyboardInterrupt:  # a stop cut the wait short: the next line takes the line back first
            self._cut_since = self._last_write
            raise
        raw, _, self._buffer = self._buffer.partition(b"\n")
        return ascii_line(raw, self.where)

    def query(self, text: str, timeout_s: float | None = None) -> str:
        self.write_line(text)
        return self.read_line(timeout_s)

    def drain(self) -> None:
        """Discard input until the line has been quiet for one timeout (a late reply must not be
        taken for the answer to the next question); gives up listening after three timeouts."""
        self._buffer = b""
        if self._stream is None:
            return
        now = time.monotonic()
        quiet_until, give_up = now + self.timeout_s, now + 3 * self.timeout_s
        try:
            with awaiting_reply(self.critical):  # a stop need not wait for a dead controller's silence
                while now < min(quiet_until, give_up):
                    if late := self._stream.read_some():
                        log.warning("%s: late reply discarded: %r", self.where, late[:60])
                        quiet_until = time.monotonic() + self.timeout_s
                    now = time.monotonic()
        except OSError:
            self.close()
        except KeyboardInterrupt:
            self._cut_since = time.monotonic()
            raise

    def drop_connection(self) -> None:
        """After a failed exchange, a network connection is closed and the next exchange opens a
        new one, as a Modbus TCP link does between tries: a connection the device (or a switch on the
        way) has forgotten without a word stays writable and never answers again (half-open), and a
        late reply on the old one is never read. A serial line stays open (`drain` clears it)."""
        if self._stream is not None and getattr(self._stream, "network", False):
            log.warning("%s: closing the connection; the next exchange opens a new one", self.where)
            self.close()

    def close(self) -> None:
        if self._stream is not None:
            try:
                self._stream.close()
            finally:
                self._stream = None
                self._buffer = b""
