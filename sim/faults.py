"""Fault injection for the protocol emulators: what goes wrong, on which requests, how often.

Each emulated device has a `FaultInjector`. The emulator asks it about every request it receives
(described as text: the ASCII line, or ``fc03 00CC`` for Modbus) and applies the fault it gets:

- ``no-reply``: the request is executed but its reply is lost;
- ``late-reply``: the reply leaves ``delay_s`` late;
- ``garbled``: the reply's bytes are corrupted (for Modbus RTU: a bad CRC);
- ``alarm``: the device raises an alarm (AZ alarm code, SMC100 following error, DMM overload);
- ``exception``: the device refuses the request (Modbus exception response, SMC100 error code,
  SCPI error in the queue);
- ``close-port``: the port or connection is closed, and reopened after ``reopen_s`` if given;
- ``lost-request``: the request never reaches the device (noise on the request: a Modbus slave
  drops a frame whose CRC fails, Modbus over Serial Line V1.02 §2.5.1.2), so nothing is done and
  nothing is answered;
- ``truncated``: only the first half of the reply arrives;
- ``dropped-byte``: one byte of the reply is lost on the line (an RS-232 overrun), the byte at
  index ``code`` (default 8: a mantissa digit of a SCPI reading such as ``+5.01318258E+00``);
- ``power-cycle``: the device is switched off and on as the request arrives (the request is lost;
  the DMM only): back to its power-on state, and a network connection to it is dropped.
"""

from __future__ import annotations

import re
import threading
from collections import deque
from dataclasses import dataclass, field

from labcal.config.emulation import FaultKind


@dataclass
class Fault:
    kind: FaultKind
    count: int = 1  # matching requests affected
    after: int = 0  # matching requests let through first
    match: str | None = None  # regular expression searched in the request's description
    delay_s: float = 1.0  # late-reply
    code: int | str | None = None  # alarm / exception: the device's code (each device has a default);
    # dropped-byte: the index of the byte lost
    reopen_s: float | None = None  # close-port: reopen after this long; None: stays closed
    seen: int = field(default=0, repr=False)

    def __post_init__(self):
        self.kind = FaultKind(self.kind)


class FaultInjector:
    """Thread-safe: emulators run in their own threads, tests inject from the main one."""

    def __init__(self):
        self._lock = threading.Lock()
        self._faults: list[Fault] = []
        self.applied: list[tuple[FaultKind, str]] = []  # what happened to which request, in order
        self.recent: deque[str] = deque(maxlen=1000)  # the latest requests, faulty or not
        self.requests = 0

    def add(self, fault: Fault) -> Fault:
        with self._lock:
            self._faults.append(fault)
        return fault

    def clear(self) -> None:
        with self._lock:
            self._faults.clear()

    def take(self, request: str) -> Fault | None:
        """The fault to apply to this request, if any (the first pending one that matches)."""
        with self._lock:
            self.requests += 1
            self.recent.append(request)
            for fault in self._faults:
                if fault.match is not None and not re.search(fault.match, request):
                    continue
                fault.seen += 1
                if fault.seen <= fault.after:
                    continue
                if fault.seen - fault.after >= fault.count:
                    self._faults.remove(fault)
                self.applied.append((fault.kind, request))
                return fault
            return None

    def count(self, kind: FaultKind) -> int:
        with self._lock:
            return sum(1 for applied, _ in self.applied if applied == kind)


DROPPED_AT = 8  # dropped-byte's default: "+5.01318258E+00" → "+5.0131828E+00", a number still


def drop_byte(data: bytes, fault: Fault) -> bytes:
    """The reply without one byte (`FaultKind.DROPPED_BYTE`), at the fault's ``code`` index."""
    at = fault.code if isinstance(fault.code, int) else DROPPED_AT
    return data[:at] + data[at + 1:] if 0 <= at < len(data) else data


def garble(data: bytes) -> bytes:
    """The same bytes with some flipped: a burst of line noise that keeps the frame's length."""
    if not data:
        return data
    noisy = bytearray(data)
    for i in range(len(noisy) // 2, len(noisy), 3):
        noisy[i] ^= 0xA5
    noisy[-1] ^= 0x5A  # the last byte always changes: a Modbus RTU CRC byte, or the line end
    return bytes(noisy)
