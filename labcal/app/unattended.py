"""A run with nobody at the station: the front end a script gives `start_run` and `resume_run`
(`labcal.api` uses it). Every remount is taken as done (on the simulated rig and its emulators the
rig remounts itself; at a real bench a script runs only plans of one mount, or a fixture that
remounts), a pause ends the run where it is (resumable, as the command line's "stop" is), an unmet
item of the pre-run checklist refuses the run with nothing moved, and what a technician would read
goes to a logger (``labcal.run``) and to ``say``, if given."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.bench.checklist import PowerOn, journaled, refusal, run_checklist, unmet
from labcal.lazy import lazy
from labcal.run import operator as run_operator
from labcal.run.operator import mount_request
from labcal.store.journal import db_path
from labcal.store.labdb import lab_server

if TYPE_CHECKING:
    from rich import text as rich_text

    from labcal.analysis.kinematics import Mount
    from labcal.bench.hardware import Bench
    from labcal.config.run_metadata import Checklist
    from labcal.devices.station import Station
    from labcal.run.events import RunEvent
    from labcal.run.operator import Heard, PauseChoice, Terminal
else:
    rich_text = lazy("rich.text")  # start-up without rich

LOG = logging.getLogger("labcal.run")


class _Confirms:
    """An operator that confirms every mount and stops at every pause (`labcal.run.operator.Operator`)."""

    heard: Heard | None = None  # nothing is typed at an unattended station
    confirms_mounts = True

    def __init__(self, say: Callable[[str], None]):
        self.say = say

    def confirm_mount(self, mount: Mount, step: int, n_steps: int, note: str = "") -> None:
        self.say(f"{mount_request(mount, step, n_steps, note)} (unattended: confirmed)")

    def after_pause(self, why: str, moving: tuple[str, ...] = ()) -> PauseChoice:
        self.say(f"paused ({why}): nobody is at the station, so the run stops here; resume it later")
        return "abort"


class _Silent:
    """No progress view: the run's events still reach the journal and every other subscriber."""

    KINDS: tuple[str, ...] = ()

    def __call__(self, event: RunEvent) -> None:
        return None


class Unattended:
    """`labcal.app.calibration.FrontEnd` for a script: see the module's docstring."""

    def __init__(self, say: Callable[[str], None] | None = None, db: str | None = None,
                 out: str | None = None):
        self._say, self.db, self.out = say, db, out

    def say(self, text: str, markup: bool = True) -> None:
        if markup:
            text = rich_text.Text.from_markup(text).plain
        LOG.info("%s", text)
        if self._say is not None:
            self._say(text)

    def operator(self) -> _Confirms:
        return _Confirms(self.say)

    def checklist(self, bench: Bench | None, station: Station, points: int, samples: int) -> Checklist:
        config = None if bench is None else bench.config
        items = run_checklist(config, bench, station, db=db_path(self.db),
                              run_folder=Path(self.out or "runs"), points=points, samples=samples,
                              power=PowerOn(), now=datetime.now().astimezone(), server=lab_server(self.db))
        for item in items:
            self.say(f"checklist: {item.name}: {item.status}" + (f" ({item.why})" if item.why else ""))
        if unmet(items):
            raise refusal(unmet(items))
        return journaled(items, PowerOn())

    def unregistered(self, serial: str) -> bool:
        """Nobody is there to say that an unregistered serial is meant: refused (unless the lab file
        allows ad-hoc serials, which is decided before this is asked)."""
        return False

    @contextmanager
    def display(self, total: int, done: int) -> Iterator[tuple[_Silent, Terminal]]:
        yield _Silent(), run_operator.Terminal()
