"""One process per run, and one run per station: exclusive locks on small files beside the lab
database.

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
import hashlib
import json
import os
import socket
import sys
import tempfile
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
        StationLock.running()  # the station's lock, if this process holds one, names the run
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


def station_locks(db: Path) -> list[Path]:
    """The folders of the station locks: beside the lab database, so that every process that
    journals into it (whoever runs it, whatever its current folder) meets the same locks; and the
    user's runtime folder, so that this user's runs into two databases meet there."""
    db = Path(db).resolve()
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    mine = Path(runtime) if runtime else Path(tempfile.gettempdir()) / f"labcal-{os.getuid()}"
    return [db.with_name(f"{db.name}.stations"), mine / "labcal-stations"]


def link_key(bus: str) -> str:
    """A device's link as the station lock knows it, so that two station files naming one link
    agree: a serial port by its real path (``/dev/serial/by-id/…`` is a link to ``/dev/ttyUSB0``),
    a TCP address or pyserial socket URL as ``tcp:host:port`` (``localhost`` is 127.0.0.1), a VISA
    resource upper-cased (a raw socket resource as its TCP address, an ASRL one as its port)."""
    kind, _, where = bus.partition(":")
    if kind == "visa":
        resource = where.upper()
        parts = where.split("::")
        if resource.startswith("TCPIP") and resource.endswith("::SOCKET") and len(parts) == 4:
            kind, where = "tcp", f"{parts[1]}:{parts[2]}"
        elif resource.startswith("ASRL") and len(parts) == 2 and parts[0][4:].startswith("/"):
            kind, where = "port", parts[0][4:]
        else:
            return f"visa:{resource}"
    if kind == "port":
        scheme, sep, rest = where.partition("://")
        if sep and scheme.lower() in ("socket", "rfc2217"):
            kind, where = "tcp", rest.split("?")[0].rstrip("/")
        elif not sep:
            return f"port:{os.path.realpath(where)}"  # link_keys adds the path as given
        else:
            return f"port:{where}"
    host, _, port = where.rpartition(":")
    host = host.strip("[]").lower()
    return f"tcp:{'127.0.0.1' if host == 'localhost' else host}:{port}"


def link_keys(bus: str) -> set[str]:
    """The locks a link takes: its `link_key`, and a serial port's absolute path as given as well
    (an emulator's pty appears at its path only once served: the first run locked the path, a
    second one resolves it to the pty, and must meet the first's lock)."""
    keys = {link_key(bus)}
    kind, _, where = bus.partition(":")
    if kind == "port" and "://" not in where:
        keys.add(f"port:{os.path.abspath(where)}")
    return keys


class StationLock:
    """``with StationLock(folders, links, station):`` — one run per station at a time, across
    processes: an exclusive ``flock`` on one file per link of the station (keyed by `link_keys`) in
    each of ``folders`` (beside the lab database, for everyone who journals there; the user's
    runtime folder, for this user's runs into any database), so that two station files naming the
    same port or address conflict. Held from before the emulators start or a device is opened until
    the command ends, pauses included; released by the kernel when the process ends in any way. A
    second run gets one LabcalError line naming the station, the link, and who holds it (run id,
    pid, host). A file left naming a process that is gone (a ``kill -9``) is taken over, with a
    note (`notes`)."""

    _held: dict[Path, StationLock] = {}  # lock file -> this process's lock on it

    def __init__(self, folders: list[Path], links: dict[str, str], station: str, doing: str = "running"):
        """``links``: each device's bus (`LinkSettings.bus`) and the link in words (``where``)."""
        self.folders, self.station, self.doing = [Path(f) for f in folders], station, doing
        self.links = {key: where for bus, where in links.items() for key in link_keys(bus)}  # key -> in words
        self.notes: list[str] = []
        self._fds: dict[Path, int] = {}

    def acquire(self) -> StationLock:
        try:
            for folder in self.folders:
                try:
                    folder.mkdir(parents=True, exist_ok=True)
                except OSError as exc:
                    raise LabcalError(f"{folder}: cannot make the station locks' folder ({exc.strerror}); it "
                                      "must be writable") from None
                for key in sorted(self.links):
                    self._take(folder / f"link-{hashlib.sha256(key.encode()).hexdigest()[:16]}.lock", key)
        except BaseException:
            self.release()
            raise
        return self

    def _take(self, path: Path, key: str) -> None:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise LabcalError(f"{path}: cannot open the station's lock file ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = _holder(fd)
            os.close(fd)
            raise LabcalError(f"station {self.station}: {self.links[key]} is in use by {who}; one run per "
                              "station at a time: wait for that run to end, or stop it there") from None
        except OSError as exc:
            os.close(fd)
            raise LabcalError(f"{path}: cannot lock {self.links[key]} ({exc.strerror})") from None
        left = _read(fd)
        if left.get("pid") and left.get("host") == socket.gethostname() and not _alive(left["pid"]):
            note = (f"{self.links[key]} was locked by {_holder_text(left)}, which is no longer running; "
                    "lock taken over")
            if note not in self.notes:
                self.notes.append(note)
        self._fds[path] = fd
        StationLock._held[path] = self
        self._write(fd)

    def _write(self, fd: int) -> None:
        run_ids = sorted(path_run for path_run in (_run_of(p) for p in RunLock._held) if path_run is not None)
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "doing": self.doing,
                  "station": self.station, "run_id": run_ids[-1] if run_ids else None,
                  "since_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                  "command": " ".join(["labcal", *sys.argv[1:]])[:200]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)

    @classmethod
    def running(cls) -> None:
        """Say in this process's station locks which run it measures (called once a run's lock is
        taken: a new run has its id only once the journal has it)."""
        for path, lock in cls._held.items():
            lock._write(lock._fds[path])

    def release(self) -> None:
        for path, fd in self._fds.items():
            StationLock._held.pop(path, None)
            try:
                os.ftruncate(fd, 0)  # nobody holds it now: say nothing stale
            except OSError:
                pass
            os.close(fd)  # closing drops the flock
        self._fds.clear()

    def __enter__(self) -> StationLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _run_of(path: Path) -> int | None:
    """The run id of a run lock file (``labcal.sqlite.run-7.lock`` → 7)."""
    stem = path.name.removesuffix(".lock")
    _, _, number = stem.rpartition(".run-")
    return int(number) if number.isdigit() else None


def _read(fd: int) -> dict:
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _holder(fd: int) -> str:
    info = _read(fd)
    return _holder_text(info) if "pid" in info else "another labcal process"


def _holder_text(info: dict) -> str:
    run = f"run {info['run_id']}, " if info.get("run_id") is not None else ""
    return (f"{run}pid {info.get('pid')} on {info.get('host', '?')} ({info.get('doing', 'running')} since "
            f"{info.get('since_utc', '?')}: {info.get('command', 'labcal')})")


def _alive(pid: object) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True
