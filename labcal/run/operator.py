"""Talking to the technician: prompts in bench words, answered at the console, by --yes, or from
a file of answers (for tests and unattended runs).

Nothing confirms a prompt by accident: keys typed while points were measured are thrown away
before each prompt (the prompt says so), a bell calls the technician to a remount, "n", "not yet"
or "wait" keep the prompt open, and only "stop" (or "q") ends the run there. At a terminal the
prose wraps at word boundaries at its width; in a file or pipe each paragraph stays one line.
"""

from __future__ import annotations

import os
import select
import sys
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, Protocol

from rich.console import Console

from labcal.analysis.kinematics import Mount
from labcal.devices.station import may_be_moving
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.run.mounting import drawing

if TYPE_CHECKING:
    import msvcrt
    import termios
else:
    msvcrt = lazy("msvcrt")  # start-up without not importable alone
    termios = lazy("termios")  # start-up without termios

PauseChoice = Literal["resume", "abort"]


class OperatorDeclined(Exception):
    """The operator chose to stop at a prompt (or nobody answered)."""


Heard = Callable[[str, str], None]  # (the reply, what it did) for a reply that kept a prompt open


class Terminal:
    """The terminal a run shares with its prompts: not an event, because a prompt must have the
    terminal (a progress bar taken down, keys echoing) before it asks, and the answer to Ctrl-C is
    said at once, from the signal handler, where nothing may be published or journaled. The console's
    progress view is one (`labcal.commands.console.ProgressDisplay`); this one is a terminal with
    nothing drawn on it."""

    def pause(self) -> AbstractContextManager[object]:
        """Context in which a prompt may use the terminal."""
        return nullcontext()

    def notice(self, text: str) -> None:
        """Say ``text`` now (rich markup): what the first Ctrl-C did."""

    def typed(self) -> str:
        """The keys typed at the terminal since the last call, while nothing asks (`GATE_KEY`: the
        operator asks for the thermal gate before the next point); none where nobody types."""
        return ""


GATE_KEY = "g"  # typed during a run: hold it at the thermal gate before its next point


class Operator(Protocol):
    heard: Heard | None  # told of every reply that keeps a prompt open, so the journal has each answer
    confirms_mounts: bool  # True: confirms each remount itself (--yes): nobody is asked to make one

    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        """Return once the instrument is mounted as asked; raise OperatorDeclined to stop."""

    def after_pause(self, why: str, moving: tuple[str, ...] = ()) -> PauseChoice:
        """The run is paused, with the tables still unless ``moving`` names tables whose stop
        failed: go on, or stop here (resumable later)."""


def mount_request(mount: Mount, step: int, n_steps: int, note: str = "") -> str:
    extra = f" {note[0].upper()}{note[1:]}." if note else ""
    return (f"Mount {step} of {n_steps}: put the instrument on the [bold]{mount.describe()}[/] "
            f"({mount}).{extra} The tables are level and will not move until you confirm.")


MOUNT_QUESTION = ("Type [bold]y[/] and Enter when mounted ([bold]n[/]: not yet, the prompt stays; "
                  "[bold]stop[/]: end the run here, resumable later): ")
PAUSE_QUESTION = "Type [bold]r[/] and Enter to resume, [bold]a[/] to abort (the run can be resumed later): "
YES, STOP = ("y", "yes"), ("stop", "q", "quit")
NOT_YET = ("n", "no", "not yet", "wait")
RESUME, ABORT = ("r", "resume"), ("a", "abort", "stop", "q", "quit")


def discard_typeahead(fd: int) -> int:
    """Throw away whatever was typed on terminal ``fd`` before now, whole lines and a line begun
    alike; the number of bytes thrown away. Keys pressed while points were being measured must
    not answer the next prompt. Nothing on anything but a terminal: piped answers are answers."""
    if sys.platform == "win32":  # the console's own key queue
        discarded = 0
        while msvcrt.kbhit():
            msvcrt.getwch()
            discarded += 1
        return discarded
    try:
        saved = termios.tcgetattr(fd)
    except (termios.error, OSError):
        return 0
    # Out of line-by-line (canonical) mode, a line still being typed can be read too; the count
    # says whether to tell the technician. tcflush then empties whatever is left.
    raw = [*saved[:6], list(saved[6])]
    raw[3] &= ~(termios.ICANON | termios.ECHO)
    raw[6][termios.VMIN], raw[6][termios.VTIME] = 0, 0
    discarded = 0
    try:
        termios.tcsetattr(fd, termios.TCSANOW, raw)
        while chunk := os.read(fd, 4096):
            discarded += len(chunk)
    except OSError:
        pass
    finally:
        termios.tcflush(fd, termios.TCIFLUSH)
        termios.tcsetattr(fd, termios.TCSANOW, saved)
    return discarded


class QuietKeys:
    """Keys typed while the run's progress is shown neither echo into the progress line nor edit
    a line: echo and line-by-line (canonical) mode off on stdin, put back as found on leaving,
    whatever ends the run (Ctrl-C, a stop signal, a fault). Re-enterable: a prompt leaves it (the
    technician sees the answer typed) and the progress enters it again. Nothing is read: keys
    typed meanwhile wait in the terminal's queue, which each prompt empties before it asks
    (`discard_typeahead`), so they still answer nothing. Nothing happens unless stdin is a
    terminal this process has in the foreground (from the background, changing the terminal
    would stop the process with SIGTTOU)."""

    # Keys `typed` read off the queue (to see the thermal gate's key) are gone from it, yet were typed
    # ahead of the next prompt all the same: that prompt counts them with what it discards itself.
    read_ahead = 0

    def __init__(self) -> None:
        self.fd: int | None = None
        self.saved: list[Any] | None = None
        if sys.platform == "win32":  # the console shows no keys typed while nobody reads
            return
        try:
            fd = sys.stdin.fileno()
            if not os.isatty(fd):
                return
        except (AttributeError, ValueError, OSError):  # no stdin, or one replaced by a test
            return
        try:
            foreground = os.tcgetpgrp(fd)
        except OSError:  # not this process's controlling terminal: no job control to upset
            foreground = os.getpgrp()
        if foreground == os.getpgrp():
            self.fd = fd

    def __enter__(self) -> QuietKeys:
        if self.fd is None or self.saved is not None:
            return self
        try:
            saved = termios.tcgetattr(self.fd)
            quiet = [*saved[:6], list(saved[6])]
            quiet[3] &= ~(termios.ECHO | termios.ICANON)
            quiet[6][termios.VMIN], quiet[6][termios.VTIME] = 1, 0
            self.saved = saved  # before the change: an interrupt right after it still restores
            termios.tcsetattr(self.fd, termios.TCSANOW, quiet)
        except (termios.error, OSError):
            self.saved = None
        return self

    def typed(self) -> str:
        """What was typed and is waiting, read without waiting (while the keys are quiet: a prompt
        reads its own answer); nothing where stdin is not this process's terminal."""
        if self.fd is None or self.saved is None:
            return ""
        keys = b""
        try:
            while select.select([self.fd], [], [], 0)[0] and len(keys) < 1024:
                chunk = os.read(self.fd, 64)
                if not chunk:
                    break
                keys += chunk
        except OSError:
            return ""
        QuietKeys.read_ahead += len(keys)
        return keys.decode("utf-8", "replace")

    @staticmethod
    def take_read_ahead() -> int:
        """How many keys `typed` read since the last prompt asked (and none from now on)."""
        read, QuietKeys.read_ahead = QuietKeys.read_ahead, 0
        return read

    def __exit__(self, exc_type: type[BaseException] | None = None, exc: BaseException | None = None,
                 tb: TracebackType | None = None) -> None:
        saved, self.saved = self.saved, None
        if self.fd is None or saved is None:
            return
        try:
            termios.tcsetattr(self.fd, termios.TCSANOW, saved)
        except (termios.error, OSError):  # the terminal is gone (its window closed): nothing to restore
            pass


class _Asking:
    """Shared by the console and the scripted operator: only where answers come from differs."""

    console: Console
    heard: Heard | None = None
    confirms_mounts = False

    def answer(self, question: str) -> str:
        raise NotImplementedError

    def discard_typeahead(self) -> int:
        """Throw away answers typed before the prompt appeared; how many keys that was."""
        return 0

    def call(self) -> None:
        """Call the technician to the bench."""

    def say(self, text: str, end: str = "\n") -> None:
        """Prose: wrapped at word boundaries at a terminal's width, one line in a file or pipe."""
        self.console.print(text, end=end, soft_wrap=not self.console.is_terminal)

    def _until(self, question: str, accepted: dict[tuple[str, ...], str]) -> str:
        discarded = self.discard_typeahead()
        if discarded:
            self.say(f"[yellow]Ignored {discarded} key(s) typed before this prompt appeared; "
                     "answer it now.[/]")
        while True:
            reply = " ".join(self.answer(question).lower().split())
            for words, meaning in accepted.items():
                if reply in words:
                    return meaning
            if reply in NOT_YET:
                self.say("Take your time: nothing moves until you answer.")
            else:
                self.say(f"[yellow]{reply!r} is not one of the answers.[/]")
            if self.heard is not None:
                self.heard(reply, "not yet" if reply in NOT_YET else "not one of the answers")

    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        self.call()
        self.say(mount_request(mount, step, n_steps, note))
        for line in drawing(mount):
            self.console.print(f"  {line}", markup=False, no_wrap=True, overflow="crop", soft_wrap=False)
        if self._until(MOUNT_QUESTION, {YES: "y", STOP: "stop"}) == "stop":
            raise OperatorDeclined("operator stopped the run at the remount prompt")

    def after_pause(self, why: str, moving: tuple[str, ...] = ()) -> PauseChoice:
        tables = (f"[bold red]The stop did not reach the {may_be_moving(moving)}: it may still be moving;"
                  " make it safe before you resume.[/]" if moving else "The tables are still.")
        self.say(f"[bold]Paused[/] ({why}). {tables} Every reading so far is saved.")
        return self._until(PAUSE_QUESTION, {RESUME: "resume", ABORT: "abort"})  # type: ignore[return-value]


class ConsoleOperator(_Asking):
    """Asks at the terminal and waits for the answer."""

    def __init__(self, console: Console):
        self.console = console

    def answer(self, question: str) -> str:
        self.say(question, end="")
        try:
            return self.console.input()
        except EOFError:
            raise OperatorDeclined("no answer at the prompt (input closed)") from None

    def discard_typeahead(self) -> int:
        try:
            fd = sys.stdin.fileno()
        except (AttributeError, ValueError, OSError):  # no stdin, or one replaced by a test
            return 0
        return discard_typeahead(fd) + QuietKeys.take_read_ahead() if os.isatty(fd) else 0

    def call(self) -> None:
        if self.console.is_terminal:  # a bell on a terminal; never a BEL byte in a log file
            self.console.file.write("\a")
            self.console.file.flush()


class ScriptedOperator(_Asking):
    """Answers from a file, one answer per line, in order; echoes each so the log reads like a session."""

    def __init__(self, console: Console, path: str | Path):
        self.console = console
        try:
            self.answers = [line.strip() for line in Path(path).read_text(encoding="utf-8").splitlines()
                            if line.strip() and not line.lstrip().startswith("#")]
        except OSError as exc:
            raise LabcalError(f"{path}: cannot read the answers file ({exc.strerror})") from None

    def answer(self, question: str) -> str:
        if not self.answers:
            raise OperatorDeclined("the answers file has no answer left for this prompt")
        reply = self.answers.pop(0)
        self.say(f"{question}{reply} [dim](from the answers file)[/]")
        return reply


class AutoOperator(ConsoleOperator):
    """--yes: confirms every remount itself, saying so. A pause (someone pressed Ctrl-C) still
    asks at the console, since the person who pressed it is there."""

    confirms_mounts = True

    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        self.say(mount_request(mount, step, n_steps, note) + " [dim](--yes: confirmed)[/]")
