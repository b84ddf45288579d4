"""A null-modem cable made of two pseudo-terminals, like ``socat pty,link=A pty,link=B``.

The emulator opens one end by its path, the driver the other; both are real ttys, so pyserial
and pymodbus use their ordinary serial code. The driver's end can be given a fixed name (a
symlink such as ``/tmp/labcal-sim/tables``) so that a station file can point at it. Closing
the pair is what a pulled cable looks like to both ends. (ptys cannot carry parity: use N.)
"""

from __future__ import annotations

import contextlib
import os
import pty
import threading
import tty
from pathlib import Path

from labcal.errors import LabcalError
from labcal.sim.polling import readable


class PtyPair:
    def __init__(self, link: str | Path | None = None):
        """``link``: where to put a symlink to the driver's end (refused if anything is there)."""
        self._made_folder: Path | None = None
        self._masters: list[int] = []
        self._slaves: list[int] = []
        for _ in range(2):
            master, slave = pty.openpty()
            tty.setraw(slave)  # no echo, no line editing until a program opens and sets it
            os.set_blocking(master, False)  # a full buffer drops bytes, as an overrun UART does
            self._masters.append(master)
            self._slaves.append(slave)  # held open so the masters never see a hang-up
        self.device_path = os.ttyname(self._slaves[0])
        self.driver_path = os.ttyname(self._slaves[1])
        self.link = Path(link) if link is not None else None
        if self.link is not None:
            try:
                self._make_link(self.link, self.driver_path)
            except BaseException:
                self._close_fds()
                raise
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._relay, name=f"pty relay {self.driver_path}", daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """What a driver opens: the symlink if there is one."""
        return str(self.link) if self.link is not None else self.driver_path

    def _make_link(self, link: Path, target: str) -> None:
        """The symlink a station file names, made only where nothing is: an existing file, symlink
        or folder there is someone's (perhaps another emulator's), never replaced or deleted. Only
        the link's own folder is made if missing (not its parents), and removed again on close."""
        if not link.parent.is_dir():
            try:
                link.parent.mkdir()
            except OSError as exc:
                raise LabcalError(f"{link}: cannot make the emulator's link folder {link.parent} "
                                  f"({exc.strerror}); create it, or name a link in an existing "
                                  "folder") from None
            self._made_folder = link.parent
        try:
            os.symlink(target, link)  # fails, atomically, if anything is there already
        except FileExistsError:
            raise LabcalError(f"{link}: exists; the emulator will not replace it (another emulator's link, "
                              "or one left by a crashed emulator: remove it if it is stale)") from None
        except OSError as exc:
            raise LabcalError(f"{link}: cannot create the emulator's link ({exc.strerror})") from None

    def _relay(self) -> None:
        a, b = self._masters
        peer = {a: b, b: a}
        while True:
            ready = readable([a, b, self._wake_r], None)
            if self._wake_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except BlockingIOError:
                    continue
                except OSError:
                    return
                with contextlib.suppress(BlockingIOError):
                    os.write(peer[fd], data)

    def _close_fds(self) -> None:
        for fd in self._masters + self._slaves:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._masters, self._slaves = [], []

    def close(self) -> None:
        """Pull the cable: both ends see the line go dead; the symlink goes too."""
        if not self._masters:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._close_fds()
        if self.link is not None and self.link.is_symlink() and os.readlink(self.link) == self.driver_path:
            self.link.unlink()  # ours: it still points at our pty
        if self._made_folder is not None:
            with contextlib.suppress(OSError):
                self._made_folder.rmdir()  # only if empty: nothing of anyone else's goes
