"""What a path names before labcal reads it: a file is read as a file, a pipe as a stream that must
keep delivering, anything else is refused in one line.

`open()` on a named pipe with no writer blocks for ever, and reading `/dev/zero` or `/dev/urandom`
never ends while memory grows; neither is ever a readings, plan or certificate file. So a path is
looked at first (`kind_of`): a regular file is read as before; a pipe (`mkfifo`, or the
`/dev/fd/N` of a shell's process substitution) is read here without blocking, and refused when
it stays silent for `STALL_S` (no writer, or a writer that stalls) or carries a NUL byte (binary
data, which no text file holds); a device, a socket or a folder is refused at once. No pydantic,
no numpy: a clean readings file is read without them.
"""

from __future__ import annotations

import os
import select
import stat
import time
from pathlib import Path
from typing import TextIO

from labcal.errors import LabcalError

STALL_S = 3.0  # a pipe silent this long is refused: with start-up, well within the 10 s a technician waits
CHUNK = 1 << 16

_WHAT = ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
         (stat.S_ISSOCK, "a socket"))


def kind_of(path: str | Path, kind: str) -> str:
    """"file" (a regular file, or nothing there: the reader then says so), or "pipe"; anything
    else is one LabcalError line naming ``path`` and what it is."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return "file"  # missing, or unreadable: the file's own reader words it
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISFIFO(mode):
        return "pipe"
    what = next((name for test, name in _WHAT if test(mode)), "not a regular file")
    raise LabcalError(f"{path}: {what}, not a {kind} file; give the path of a {kind} file")


def read_pipe(path: str | Path, kind: str) -> str:
    """The whole text a pipe delivers until its writer closes it.

    Opened without blocking, so a pipe nobody writes to does not hang here; refused when no byte
    arrives for `STALL_S` seconds, or when a NUL byte arrives.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise LabcalError(f"{path}: cannot read {kind} file ({exc.strerror or exc})") from None
    try:
        return _drain(fd, str(path), kind, STALL_S)
    finally:
        os.close(fd)


def read_stream(stream: TextIO, source: str, kind: str) -> str:
    """The whole text of an open stream (standard input) that is a pipe, a file or a terminal; a
    device other than a terminal is refused like a path naming one, and a NUL byte like a pipe's.
    Waits as long as it takes: what comes on standard input is the user's to end. A stream with
    no descriptor (a program's own, in memory) is read as it is."""
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is both of the last two
        return stream.read()
    mode = os.fstat(fd).st_mode
    if not (stat.S_ISREG(mode) or stat.S_ISFIFO(mode) or os.isatty(fd)):
        what = next((name for test, name in _WHAT if test(mode)), "not a regular file")
        raise LabcalError(f"{source} is {what}, not a {kind} file; give the path of a {kind} file")
    return _drain(fd, source, kind, None)


def _drain(fd: int, source: str, kind: str, stall_s: float | None) -> str:
    poller = select.poll() if hasattr(select, "poll") else None  # Windows: no poll, no pipe at a path
    if poller is not None:
        poller.register(fd, select.POLLIN)
    chunks: list[bytes] = []
    last = time.monotonic()  # when the pipe last delivered (or was opened)
    while True:
        wait = None if stall_s is None else max(0.0, stall_s - (time.monotonic() - last)) * 1000
        if poller is not None and not poller.poll(wait):
            said = "nothing" if not chunks else "nothing more"
            raise LabcalError(f"{source}: a pipe that delivered {said} for {stall_s:g} s (no writer, or one "
                              f"that stalled); give a {kind} file, or write the whole file into the pipe")
        try:
            chunk = os.read(fd, CHUNK)
        except BlockingIOError:  # woken without data: wait out the rest of the silence
            continue
        except OSError as exc:
            raise LabcalError(f"{source}: cannot read {kind} file ({exc.strerror or exc})") from None
        if not chunk:
            break
        if b"\0" in chunk:
            raise LabcalError(f"{source}: binary data (a NUL byte), not a {kind} file")
        chunks.append(chunk)
        last = time.monotonic()
    try:
        return b"".join(chunks).decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise LabcalError(f"{source}: cannot read {kind} file ({exc})") from None
