"""Waiting for file descriptors to be readable or writable, at any descriptor number.

`select.select` refuses a descriptor of 1024 or more (FD_SETSIZE) with "filedescriptor out of range";
a process that holds many files and sockets (a test worker, a long `labcal sim serve`) reaches such
numbers, and an emulator's thread then died with its port still open. `select.poll` has no such
limit. POSIX only, as the emulators' ptys are.
"""

from __future__ import annotations

import math
import select
from collections.abc import Iterable
from typing import Protocol, TypeVar


class HasFileno(Protocol):
    def fileno(self) -> int: ...


Waitable = TypeVar("Waitable", bound=int | HasFileno)


def readable(items: Iterable[Waitable], timeout: float | None) -> list[Waitable]:
    """Those of ``items`` (descriptors, or objects with ``fileno()``) ready to read, or closed at
    the other end, within ``timeout`` seconds (None: however long it takes)."""
    return _ready(items, select.POLLIN | select.POLLPRI, timeout)


def writable(fd: int, timeout: float) -> bool:
    """Whether ``fd`` can take more bytes within ``timeout`` seconds."""
    return bool(_ready([fd], select.POLLOUT, timeout))


def _ready(items: Iterable[Waitable], events: int, timeout: float | None) -> list[Waitable]:
    by_fd = {item if isinstance(item, int) else item.fileno(): item for item in items}
    poller = select.poll()
    for fd in by_fd:
        poller.register(fd, events)
    ms = None if timeout is None else max(0, math.ceil(timeout * 1000))  # not 0 for 0.4 ms: no spin
    # an error or hang-up on a descriptor makes it ready too: its reader then sees the error or EOF
    return [by_fd[fd] for fd, _ in poller.poll(ms)]
