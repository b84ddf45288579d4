"""What can go wrong talking to a device. Every driver failure is a `DriverError`, and that is a
`LabcalError`: the CLI prints its message on one line (which device, what happened, what to do)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from labcal.errors import LabcalError


class DriverError(LabcalError):
    """A device did not do what was asked."""

    def __init__(self, message: str, device: str | None = None):
        super().__init__(f"{device}: {message}" if device else message)
        self.device = device  # set once the message names the device


class NoReply(DriverError):
    """Silence until the timeout (a device that is off, a wrong address or line setting)."""


class BadReply(DriverError):
    """A reply arrived but is not what the protocol allows (noise, bad CRC, a stale reply)."""


class PortClosed(DriverError):
    """The port or connection went away in the middle of an exchange; reconnecting may help."""


class LinkLost(DriverError):
    """The port could not be reopened within the reconnect budget."""


class SettingsRefused(DriverError):
    """The operating system refused a line setting of a serial port (a pty carries no parity, an
    adapter has no such baud rate): not a port to reopen, a station file to correct."""


class Rejected(DriverError):
    """The device answered but refused the command (exception response, error code)."""


class Busy(Rejected):
    """The device (or a gateway in front of it) could not take the request now: Modbus exceptions
    06h (busy), 0Ah (gateway path unavailable), 0Bh (gateway target did not respond). Nothing was
    done, so an exchange that is safe to repeat is repeated, as after a lost reply."""


class DeviceFault(DriverError):
    """The device reports a fault state (alarm, disabled stage, overload) or missed its target."""


class Overloaded(DeviceFault):
    """A channel read the overload value. The scan's readings ride with the fault (``readings``:
    samples × channels, volts, the overload value where it was read), so that the run journals the
    window it discards, as it does every other."""

    def __init__(self, message: str, device: str | None, readings: object):
        super().__init__(message, device)
        self.readings = readings


class OutOfLimits(DriverError):
    """A move was refused before anything was sent: the target lies outside the soft limits."""


# Failures after which the same exchange may be tried again (when repeating it is safe).
TRANSIENT = (NoReply, BadReply, PortClosed, Busy)


HINTS: dict[type[DriverError], str] = {
    NoReply: "check that it is powered and cabled, and its address and line settings in the station file",
    BadReply: "check the line settings (baud rate, parity) and the cable",
    PortClosed: "check the cable and the port",
    Busy: "it stayed busy through every retry; check the gateway and the drive behind it",
    LinkLost: "check the cable, the port name, and that no other program holds the port",
}


@contextmanager
def on_device(device: str) -> Iterator[None]:
    """Tell a driver failure inside as one line naming ``device`` and, for link trouble, what to check."""
    try:
        yield
    except DriverError as exc:
        if exc.device is not None:
            raise
        hint = HINTS.get(type(exc))
        raise type(exc)(f"{exc}; {hint}" if hint else str(exc), device) from None
