"""ASCII lines to an instrument through VISA (pyvisa): GPIB, USB-TMC, VXI-11, HiSLIP, raw SCPI
sockets and serial ports, by resource string (``GPIB0::9::INSTR``, ``TCPIP0::host::inst0::INSTR``,
``TCPIP0::host::5025::SOCKET``, ``USB0::0x2A8D::0x5101::MY123::INSTR``, ``ASRL/dev/ttyUSB0::INSTR``).

The same rules as `labcal.drivers.transport.LineTransport`, so a SCPI driver does not know which it
has: opened on first use (and reopened after the resource went away), a timeout on every read,
silence is `NoReply`, bytes that are not a line of ASCII text are `BadReply`, a late reply is
drained before the next question. The VISA library is pyvisa-py (``@py``, installed with labcal)
unless the station names a vendor's (a path to libvisa, or ``@ivi``). Lines are logged at DEBUG.
"""

from __future__ import annotations

import logging
import socket
import time
from typing import Any

import pyvisa

from labcal.devices.station import CriticalSection
from labcal.drivers.errors import LinkLost, NoReply, PortClosed
from labcal.drivers.transport import ascii_line, awaiting_reply, reconnect

log = logging.getLogger(__name__)
QUIET_S = 0.05  # draining: read in slices this long until the line has been quiet for a timeout


def resource_manager(library: str) -> Any:
    """The VISA library's resource manager; `LinkLost` naming the library when it cannot load."""
    try:
        return pyvisa.ResourceManager(library)
    except (OSError, ValueError, pyvisa.errors.Error) as exc:
        raise LinkLost(f"cannot load the VISA library {library!r} ({str(exc).splitlines()[0]}); install it, "
                       "or set visa_library = \"@py\" (pyvisa-py, installed with labcal)") from None


class VisaLink:
    """One VISA resource, as lines of ASCII."""

    def __init__(self, resource: str, *, library: str = "@py", eol: str = "\n", timeout_s: float = 1.0,
                 reconnect_s: float = 5.0, serial: dict[str, Any] | None = None):
        self.resource, self.library, self.eol = resource, library, eol
        self.where = f"VISA {resource}"
        self.timeout_s = timeout_s
        self.reconnect_s = reconnect_s
        self.serial = serial or {}  # baud_rate, data_bits, parity... for an ASRL resource
        self.critical: CriticalSection | None = None  # the run's, while a run drives this link
        self._manager: Any = None
        self._instrument: Any = None
        self.opens = 0  # how many times the resource has been opened

    def _open(self) -> Any:
        if self._instrument is None:
            if self._manager is None:
                self._manager = resource_manager(self.library)

            def connect() -> None:
                try:
                    self._instrument = self._manager.open_resource(
                        self.resource, read_termination=self.eol, write_termination=self.eol, **self.serial)
                except pyvisa.errors.VisaIOError as exc:
                    raise OSError(exc.description or str(exc)) from None
                except (ValueError, pyvisa.errors.Error) as exc:  # a malformed resource string
                    raise ValueError(str(exc).splitlines()[0]) from None

            reconnect(connect, self.reconnect_s, self.where)
            self.opens += 1
            self._no_delay()
        return self._instrument

    def _no_delay(self) -> None:
        """On a raw socket, send each command at once: with Nagle's algorithm a short command waits
        for the previous one's acknowledgement, which the instrument delays (~40 ms a command).
        VISA's VI_ATTR_TCPIP_NODELAY says so; pyvisa-py accepts the attribute but cannot set it,
        so its session's socket is told directly."""
        if not self.resource.upper().endswith("::SOCKET"):
            return
        try:
            self._instrument.set_visa_attribute(pyvisa.constants.ResourceAttribute.tcpip_nodelay,
                                                pyvisa.constants.VI_TRUE)
        except Exception:  # noqa: BLE001 - pyvisa-py raises its own UnknownAttribute here
            session = getattr(self._instrument.visalib, "sessions", {}).get(self._instrument.session)
            sock = getattr(session, "interface", None)
            if isinstance(sock, socket.socket):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def _lost(self, exc: Exception) -> PortClosed:
        self.close()
        return PortClosed(f"{self.where} went away ({exc})")

    def write_line(self, text: str) -> None:
        instrument = self._open()
        log.debug("%s > %s", self.where, text)
        try:
            instrument.write_raw((text + self.eol).encode("ascii"))
        except (pyvisa.errors.VisaIOError, OSError) as exc:
            raise self._lost(exc) from None

    def read_line(self, timeout_s: float | None = None) -> str:
        """The next line without its terminator; NoReply on silence, BadReply on bytes that are
        not ASCII text."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        instrument = self._open()
        instrument.timeout = max(1, round(timeout * 1000))
        try:
            with awaiting_reply(self.critical):
                raw = bytes(instrument.read_raw())
        except KeyboardInterrupt:  # a stop cut the wait short: reopened before the next question, so the
            self.close()  # late reply is not taken for its answer (the driver verifies a reopened device)
            raise
        except pyvisa.errors.VisaIOError as exc:
            if exc.error_code == pyvisa.constants.StatusCode.error_timeout:
                raise NoReply(f"no reply within {timeout:g} s") from None
            raise self._lost(exc) from None
        except OSError as exc:
            raise self._lost(exc) from None
        return ascii_line(raw, self.where)

    def query(self, text: str, timeout_s: float | None = None) -> str:
        self.write_line(text)
        return self.read_line(timeout_s)

    def drain(self) -> None:
        """Discard input until the resource has been quiet for one timeout (three at most): a late
        reply must not be taken for the answer to the next question."""
        if self._instrument is None:
            return
        now = time.monotonic()
        quiet_until, give_up = now + self.timeout_s, now + 3 * self.timeout_s
        self._instrument.timeout = round(QUIET_S * 1000)
        while now < min(quiet_until, give_up):
            try:
                late = bytes(self._instrument.read_raw())
                log.warning("%s: late reply discarded: %r", self.where, late[:60])
                quiet_until = time.monotonic() + self.timeout_s
            except pyvisa.errors.VisaIOError as exc:
                if exc.error_code != pyvisa.constants.StatusCode.error_timeout:
                    self.close()
                    return
            except OSError:
                self.close()
                return
            now = time.monotonic()

    def drop_connection(self) -> None:
        """After a failed exchange, a network resource (``TCPIP…``) is closed and the next exchange
        opens it again: a half-open connection never answers again. A serial one stays open."""
        if self._instrument is not None and self.resource.upper().startswith("TCPIP"):
            log.warning("%s: closing the connection; the next exchange opens a new one", self.where)
            self.close()

    def close(self) -> None:
        if self._instrument is not None:
            try:
                self._instrument.close()
            except Exception:  # noqa: BLE001 - a resource that is already gone cannot be closed twice
                log.debug("%s: closing failed", self.where, exc_info=True)
            finally:
                self._instrument = None
