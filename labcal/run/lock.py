"""One process per run: an exclusive lock on a small file beside the lab database.

The lock is the operating system's (``flock``), not a row or a marker file: it is held while the
process that took it measures, and the kernel releases it when that process ends in any way —
normal exit, exception, Ctrl-C or ``kill -9`` — so a lock is never left stale by a crash, and the
next `labcal resume` takes it over without anyone deleting anything. The file also says who holds
it (pid, host, start time, command), for the one line another process prints when it is refused.

A run whose journal says "running" while nobody holds its lock was interrupted: its process died
without closing it (`held_by` tells the two apart).
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
from datetime import UTC, datetime
from pathlib import Path

from labcal.errors import LabcalError


def lock_path(db: Path, run_id: int) -> Path:
    """The lock file of a run: beside the database, so every process that shares the journal
    (whatever its current folder) meets the same file."""
    return db.with_name(f"{db.name}.run-{run_id}.lock")


class RunLock:
    """``with RunLock(db, run_id):`` — held for the block; another process gets one LabcalError line
    naming the holder. Released on any exit (the kernel drops it with the process). Re-entrant
    within one process (`labcal resume` takes it before it changes anything, the runner again
    while it measures): flock would refuse a second open of the same file even to its owner."""

    _held: dict[Path, list] = {}  # lock file -> [fd, holders] of this process

    def __init__(self, db: Path, run_id: int, doing: str = "measuring"):
        self.path = lock_path(Path(db).resolve(), run_id)
        self.run_id = run_id
        self.doing = doing
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        if self._fd is not None:
            return self
        mine = RunLock._held.get(self.path)
        if mine is not None:
            mine[1] += 1
            self._fd = mine[0]
            return self
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise LabcalError(f"{self.path}: cannot open the run's lock file ({exc.strerror}); the "
                              "database's folder must be writable") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = _describe(fd)
            os.close(fd)
            raise LabcalError(f"run {self.run_id} is in use by {who}; wait for it to finish, or stop it "
                              "there (Ctrl-C) and run the command again") from None
        except OSError as exc:
            os.close(fd)
            raise LabcalError(f"{self.path}: cannot lock run {self.run_id} ({exc.strerror})") from None
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "doing": self.doing,
                  "since_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                  "command": " ".join(["labcal", *sys.argv[1:]])[:200]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)
        self._fd = fd
        RunLock._held[self.path] = [fd, 1]
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        mine = RunLock._held[self.path]
        mine[1] -= 1
        self._fd = None
        if mine[1] == 0:
            del RunLock._held[self.path]
            try:
                os.ftruncate(mine[0], 0)  # nobody holds it now: say nothing stale
            except OSError:
                pass
            os.close(mine[0])  # closing drops the flock

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _describe(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        info = {}
    if not isinstance(info, dict) or "pid" not in info:
        return "another labcal process"
    return (f"pid {info.get('pid')} on {info.get('host', '?')} ({info.get('doing', 'measuring')} since "
            f"{info.get('since_utc', '?')}: {info.get('command', 'labcal')})")


def held_by(db: Path, run_id: int) -> str | None:
    """Who holds the run's lock right now (None when nobody does: a 'running' run is then an
    interrupted one). Takes and drops the lock to find out, so it never waits."""
    path = lock_path(Path(db).resolve(), run_id)
    if path in RunLock._held:
        return f"this process (pid {os.getpid()})"
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return _describe(fd)
    finally:
        os.close(fd)
    return None
