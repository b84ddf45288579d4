"""Talking to the technician: remount prompts in bench words, answered at the console or by --yes."""

from __future__ import annotations

from typing import Protocol

from rich.console import Console

from labcal.kinematics import Mount


class OperatorDeclined(Exception):
    """The operator chose to stop at a prompt."""


class Operator(Protocol):
    def confirm_mount(self, mount: Mount, step: int, n_steps: int) -> None:
        """Return once the instrument is mounted as asked; raise OperatorDeclined to stop."""


def mount_request(mount: Mount, step: int, n_steps: int) -> str:
    return (f"Mount {step} of {n_steps}: put the instrument on the [bold]{mount.describe()}[/] "
            f"({mount}). The tables are level and will not move until you confirm.")


class ConsoleOperator:
    """Asks at the terminal and waits for the answer."""

    def __init__(self, console: Console):
        self.console = console

    def confirm_mount(self, mount: Mount, step: int, n_steps: int) -> None:
        self.console.print(mount_request(mount, step, n_steps))
        while True:
            try:
                answer = self.console.input("Type [bold]y[/] and Enter when mounted, [bold]q[/] to stop: ")
            except EOFError:
                raise OperatorDeclined("no answer at the remount prompt (input closed)") from None
            answer = answer.strip().lower()
            if answer in ("y", "yes"):
                return
            if answer in ("q", "quit", "n", "no"):
                raise OperatorDeclined("operator stopped the run at the remount prompt")


class AutoOperator:
    """Answers every prompt with yes (`--yes`), saying so, for unattended and simulated runs."""

    def __init__(self, console: Console):
        self.console = console

    def confirm_mount(self, mount: Mount, step: int, n_steps: int) -> None:
        self.console.print(mount_request(mount, step, n_steps) + " [dim](--yes: confirmed)[/]")
