"""Prompts nothing confirms by accident, driven as a technician drives them: a real `labcal run`
on a pseudo-terminal, keys typed ahead while points are measured, a narrow window."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import sqlite3
import struct
import subprocess
import termios
import threading
import time
from pathlib import Path

import pytest
from cli import LABCAL
from emulators import private_file

from labcal.analysis.kinematics import MOUNTS
from labcal.run.mounting import drawing

pytestmark = pytest.mark.long(seconds=22)  # runs answering prompts on a pseudo-terminal: handed out first

ANSI = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]|\x1b\][^\x07\x1b]*(\x07|\x1b\\)|\x1b[()][0-9A-B]")


def committed(db: Path) -> int:
    try:
        with sqlite3.connect(db) as con:
            return con.execute("SELECT COUNT(*) FROM points").fetchone()[0]
    except sqlite3.OperationalError:
        return 0


def mount_answers(db: Path) -> list[str]:
    with sqlite3.connect(db) as con:
        return [m for (m,) in con.execute("SELECT message FROM events WHERE kind='answer' ORDER BY id")]


class Terminal:
    """`labcal ARGS` with a pseudo-terminal for stdin, stdout and stderr, ``columns`` wide."""

    def __init__(self, *args: str, columns: int = 100, controlling: bool = False):
        """``controlling``: the pty is labcal's controlling terminal (as a shell's is), so that
        Ctrl-C typed there is a SIGINT to it."""
        master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))
        env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
        env["TERM"] = "xterm"

        def take_terminal() -> None:  # in the child, after setsid: this session's terminal
            fcntl.ioctl(0, termios.TIOCSCTTY, 0)

        self.proc = subprocess.Popen([LABCAL, *args], stdin=slave, stdout=slave, stderr=slave, env=env,
                                     start_new_session=True,
                                     preexec_fn=take_terminal if controlling else None)
        os.close(slave)
        self.master = master
        self.raw = b""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                chunk = os.read(self.master, 65536)
            except OSError:  # EIO: the child closed its end
                return
            if not chunk:
                return
            self.raw += chunk

    @property
    def screen(self) -> str:
        """What was written, without colours and cursor movements, lines ended by \\n."""
        return ANSI.sub("", self.raw.decode("utf-8", "replace")).replace("\r\n", "\n").replace("\r", "\n")

    def echoes(self) -> bool:
        """Whether the terminal echoes keys and edits lines now (the pty's settings as labcal
        left them: the master reads the slave's)."""
        lflag = termios.tcgetattr(self.master)[3]
        return bool(lflag & termios.ECHO) and bool(lflag & termios.ICANON)

    def type(self, keys: str) -> None:
        os.write(self.master, keys.encode())

    def wait_for(self, text: str, count: int = 1, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while self.screen.count(text) < count:
            assert self.proc.poll() is None, f"labcal ended before {text!r} #{count}:\n{self.screen}"
            assert time.monotonic() < deadline, f"no {text!r} #{count} within {timeout} s:\n{self.screen}"
            time.sleep(0.01)

    def close(self) -> int:
        try:
            code = self.proc.wait(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self._reader.join(timeout=5)
            os.close(self.master)
        return code


@pytest.fixture
def terminals():
    opened: list[Terminal] = []

    def start(*args: str, columns: int = 100, controlling: bool = False) -> Terminal:
        opened.append(Terminal(*args, columns=columns, controlling=controlling))
        return opened[-1]

    yield start
    for t in opened:
        if t.proc.poll() is None:
            t.proc.kill()
            t.close()


def test_keys_typed_during_mount_3_do_not_confirm_mount_4(tmp_path, lab_database, terminals):
    """The technician answers mount 3 with "y⏎" and, while its points are measured, types "y⏎"
    again and a stray "y": before, that second line confirmed mount 4 unseen. Now the prompt
    throws both away, says so, and waits; mount 4 begins only on a "y" typed at its prompt."""
    term = terminals("run", "--sim", "--no-report", "--seed", "3", "--out", str(tmp_path / "run"))
    for mount in (1, 2):
        term.wait_for(f"Mount {mount} of 4")
        term.wait_for("when mounted", count=mount)
        term.type("y\r")
    term.wait_for("when mounted", count=3)
    term.type("y\ry\ry")  # mount 3's answer, then typed ahead while its points are measured
    term.wait_for("when mounted", count=4)
    time.sleep(0.5)  # a confirmed mount 4 would be measuring by now
    assert committed(lab_database) == 48 and term.proc.poll() is None
    assert "Ignored 3 key(s) typed before this prompt appeared" in term.screen
    assert term.raw.count(b"\a") == 4  # a bell for each remount
    term.type("y\r")
    assert term.close() == 0, term.screen
    assert committed(lab_database) == 64
    assert mount_answers(lab_database) == ["mount: confirmed"] * 4


def test_typed_ahead_answers_do_not_confirm_the_mounts_when_nothing_checks_them(tmp_path, lab_database,
                                                                                terminals):
    """With --no-mount-check no gravity check would catch an unseen confirmation: "y⏎y⏎y⏎" typed
    ahead during mount 1 must confirm none of mounts 2–4."""
    term = terminals("run", "--sim", "--no-report", "--no-mount-check", "--out", str(tmp_path / "run"))
    term.wait_for("when mounted")
    term.type("y\r" + "y\ry\ry\r")
    for mount in (2, 3, 4):
        term.wait_for("when mounted", count=mount)
        time.sleep(0.3)
        assert committed(lab_database) == 16 * (mount - 1) and term.proc.poll() is None
        if mount == 2:
            assert "Ignored 6 key(s) typed before this prompt appeared" in term.screen
        term.type("y\r")
    assert term.close() == 0, term.screen
    assert committed(lab_database) == 64


def test_not_yet_keeps_the_prompt_open_and_stop_ends_the_run(tmp_path, lab_database, terminals):
    """"n" used to end the whole run. "n", "not yet" and "wait" now keep the prompt; "stop" ends
    the run there, resumable."""
    term = terminals("run", "--sim", "--no-report", "--out", str(tmp_path / "run"))
    term.wait_for("when mounted")
    for k, word in enumerate(("n", "not yet", "wait"), start=1):
        term.type(f"{word}\r")
        term.wait_for("nothing moves until you answer", count=k)
    assert committed(lab_database) == 0 and term.proc.poll() is None
    term.type("stop\r")
    assert term.close() == 1
    assert "operator stopped the run at the remount prompt" in term.screen
    assert "continue with: labcal resume" in term.screen


@pytest.mark.parametrize("columns", [30, 57])
def test_the_remount_prompt_draws_the_mount_and_wraps_at_word_boundaries(tmp_path, terminals, columns):
    """A narrow terminal: every line of the prompt fits, no word is cut, and the drawing of the
    mount asked for (plate, dowels, x arrow) is there whole."""
    term = terminals("run", "--sim", "--no-report", "--out", str(tmp_path / "run"), columns=columns)
    for mount in MOUNTS[:2]:
        term.wait_for("later):", count=MOUNTS.index(mount) + 1)
        block = term.screen.rsplit("Mount ", 1)[1]
        lines = ("Mount " + block).splitlines()
        assert all(len(line) <= columns for line in lines), lines
        words = ("Mount 2 of 4:" if mount == MOUNTS[1] else "Mount 1 of 4:").split() + \
            f"put the instrument on the {mount.describe()} ({mount}).".split()
        tokens = " ".join(lines).split()
        assert tokens[:len(words)] == words, lines  # a word cut by the wrap would not match
        art = [f"  {line}" for line in drawing(mount)]
        start = lines.index(art[0])
        assert lines[start:start + len(art)] == art, lines
        term.type("y\r")
    term.proc.terminate()
    term.close()


def test_the_drawings_tell_the_four_mounts_apart():
    """Each mount's drawing: the x arrow points forward (right, as the table's front) for y = 0
    and backward for y = 180; the instrument sits above the plate for u = 0, below for u = 180."""
    for mount in MOUNTS:
        art = drawing(mount)
        plate = next(i for i, line in enumerate(art) if line.startswith("====o"))
        arrow = next(i for i, line in enumerate(art) if " x " in f" {line} ")
        assert ("x -->" in art[arrow]) == (mount.y_deg == 0)
        assert ("<-- x" in art[arrow]) == (mount.y_deg == 180)
        assert (arrow < plate) == (mount.u_deg == 0)
        assert max(map(len, art)) <= 22
    assert len({tuple(drawing(m)) for m in MOUNTS}) == 4


def test_keys_typed_during_the_progress_do_not_echo_and_the_terminal_is_restored(tmp_path, lab_database,
                                                                                terminals):
    """Keys typed while points are measured used to echo into the progress line. Now, while the
    progress is shown, the terminal neither echoes nor edits lines; each prompt (a remount, the
    pause after a Ctrl-C) has it echo again and still throws the keys away, and a stop signal
    ending the run mid-progress leaves it echoing as found. An emulated station at 50× so that a
    mount's points take seconds of wall time."""
    station = private_file("az-modbus-tcp", tmp_path)
    term = terminals("run", "--station", str(station), "--emulate", "--time-scale", "50", "--no-report",
                     "--out", str(tmp_path / "run"), controlling=True)
    assert term.echoes()  # as the test made it: the checks below can fail
    term.wait_for("when mounted")
    assert term.echoes()  # the prompt: the technician sees the answer typed
    term.type("y\r")
    term.wait_for("1/64")  # the first point of mount 1 is in the progress line
    assert not term.echoes()
    term.type("zqxj\r")
    term.wait_for("when mounted", count=2)
    assert term.echoes()
    assert "Ignored 5 key(s) typed before this prompt appeared" in term.screen
    assert "zqxj" not in term.screen
    assert committed(lab_database) == 16
    term.type("y\r")
    term.wait_for("17/64")
    assert not term.echoes()
    term.type("\x03")  # Ctrl-C: a pause after this point, at a prompt that echoes
    term.wait_for("to resume")
    assert term.echoes()
    term.type("r\r")
    term.wait_for("/64", count=term.screen.count("/64") + 1)
    assert not term.echoes()
    term.proc.terminate()  # SIGTERM mid-progress: the tables stop, the run ends with an exception
    term.proc.wait(timeout=60)
    assert term.echoes()  # read before close() closes the pty
    assert term.close() == 128 + 15, term.screen
    assert "interrupted (SIGTERM)" in term.screen
