"""Talking to the technician: prompts in bench words, answered at the console, by --yes, or from
a file of answers (for tests and unattended runs)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Protocol

from rich.console import Console

from labcal.analysis.kinematics import Mount
from labcal.errors import LabcalError
from labcal.run.station import may_be_moving

PauseChoice = Literal["resume", "abort"]


class OperatorDeclined(Exception):
    """The operator chose to stop at a prompt (or nobody answered)."""


class Operator(Protocol):
    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        """Return once the instrument is mounted as asked; raise OperatorDeclined to stop."""

    def after_pause(self, why: str, moving: tuple[str, ...] = ()) -> PauseChoice:
        """The run is paused, with the tables still unless ``moving`` names tables whose stop
        failed: go on, or stop here (resumable later)."""


def mount_request(mount: Mount, step: int, n_steps: int, note: str = "") -> str:
    extra = f" {note[0].upper()}{note[1:]}." if note else ""
    return (f"Mount {step} of {n_steps}: put the instrument on the [bold]{mount.describe()}[/] "
            f"({mount}).{extra} The tables are level and will not move until you confirm.")


MOUNT_QUESTION = "Type [bold]y[/] and Enter when mounted, [bold]q[/] to stop: "
PAUSE_QUESTION = "Type [bold]r[/] and Enter to resume, [bold]a[/] to abort (the run can be resumed later): "
YES, NO = ("y", "yes"), ("q", "quit", "n", "no")
RESUME, ABORT = ("r", "resume"), ("a", "abort", "q", "quit")


class _Asking:
    """Shared by the console and the scripted operator: only where answers come from differs."""

    console: Console

    def answer(self, question: str) -> str:
        raise NotImplementedError

    def _until(self, question: str, accepted: dict[tuple[str, ...], str]) -> str:
        while True:
            reply = self.answer(question).strip().lower()
            for words, meaning in accepted.items():
                if reply in words:
                    return meaning
            self.console.print(f"[yellow]{reply!r} is not one of the answers.[/]")

    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        self.console.print(mount_request(mount, step, n_steps, note))
        if self._until(MOUNT_QUESTION, {YES: "y", NO: "q"}) == "q":
            raise OperatorDeclined("operator stopped the run at the remount prompt")

    def after_pause(self, why: str, moving: tuple[str, ...] = ()) -> PauseChoice:
        tables = (f"[bold red]The stop did not reach the {may_be_moving(moving)}: it may still be moving;"
                  " make it safe before you resume.[/]" if moving else "The tables are still.")
        self.console.print(f"[bold]Paused[/] ({why}). {tables} Every reading so far is saved.")
        return self._until(PAUSE_QUESTION, {RESUME: "resume", ABORT: "abort"})  # type: ignore[return-value]


class ConsoleOperator(_Asking):
    """Asks at the terminal and waits for the answer."""

    def __init__(self, console: Console):
        self.console = console

    def answer(self, question: str) -> str:
        try:
            return self.console.input(question)
        except EOFError:
            raise OperatorDeclined("no answer at the prompt (input closed)") from None


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
        self.console.print(f"{question}{reply} [dim](from the answers file)[/]")
        return reply


class AutoOperator(ConsoleOperator):
    """--yes: confirms every remount itself, saying so. A pause (someone pressed Ctrl-C) still
    asks at the console, since the person who pressed it is there."""

    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        self.console.print(mount_request(mount, step, n_steps, note) + " [dim](--yes: confirmed)[/]")
