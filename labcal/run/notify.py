"""Notifications through apprise: the technician learns of a remount, a pause or the end of a run
without standing at the station's terminal.

`LABCAL_NOTIFY` (comma-separated apprise URLs) or the lab file's ``notify`` names where they go
(`labcal.config.lab.LabConfig.notify_urls`). The run's events reach a `RunNotifier`, a subscriber
of the run's event bus like the console view (the sequencer never imports this module), which puts
three of them into words:

- a remount prompt: "labcal bench-2, run 7 (ACC-0042): mount 3 of 4: remount the instrument on the
  bottom side of the plate, x sensor pointing forward (y=0°, u=180°)…";
- a pause: "… run 7 (ACC-0042): paused (fault: roll table …: alarm 10h …)…";
- the run's end: "… run 7 (ACC-0042): finished: complete, 64 of 64 points; …the fit's figures" (or
  failed, stopped, interrupted, and why).

Each names the run as the lab does (`RunName`): the bench (the station's name in the lab database,
as the lab's overview shows it, not the station file it uses), the lab's run number, the
instrument's serial, and, where the lab file gives the lab server's public address
(``server_url``), a link to the run's page on its last line. A run nobody attends (--yes, a script)
is remounted by whoever confirms its prompts (the simulated rig, a fixture): no notification asks a
person for a remount nobody will make.

A notification is never worth a reading. `Notifications` sends from a worker thread of its own
through a queue, so the run's thread only appends to a list: a slow or dead endpoint costs the run
nothing. A send that fails (apprise says so, or raises) is told once, in one line, and the run
goes on (later failures are logged); at the run's end `close` waits a few seconds at most for the
queue to drain and then says what was not sent. apprise missing is also one line and no
notifications. What is refused is a URL apprise cannot parse: a typing mistake, caught when the
notifications are set up, before anything moves (`lab_notifications`).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.analysis.kinematics import MOUNTS
from labcal.config.lab import load_lab_config
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.run.events import Paused, Prompt, RunEvent, Status

if TYPE_CHECKING:
    import apprise as _apprise
else:
    _apprise = lazy("apprise")  # start-up without apprise

log = logging.getLogger(__name__)

DRAIN_S = 5.0  # at the run's end, how long the queue may take to drain before the run's command ends
KINDS = ("prompt", "pause", "status")  # the events a notification is made of (`RunNotifier.handle`)
Warn = Callable[[str], None]


def split_urls(text: str) -> tuple[str, ...]:
    """The URLs of a comma-separated list (`LABCAL_NOTIFY`), blanks dropped."""
    return tuple(url.strip() for url in text.split(",") if url.strip())


def shown(url: str) -> str:
    """A URL as a message may show it: its scheme only, since the rest often holds a token or a
    password (apprise's own URLs for Slack, Telegram, e-mail…)."""
    scheme, sep, _ = url.partition("://")
    return f"{scheme}://…" if sep else repr(url[:12] + ("…" if len(url) > 12 else ""))


@dataclass(frozen=True)
class Message:
    """One notification: its title and body, and ``what`` it is about, for the end's account."""

    what: str
    title: str
    body: str


class Notifications:
    """Sends messages to apprise URLs from a worker thread; see the module for what it promises.

    ``warn`` prints one line (the command's console): at the first failure (the later ones are
    logged, not printed: one broken endpoint would otherwise print a line per remount), and at
    `close` if the queue did not drain in time."""

    def __init__(self, urls: Sequence[str], source: str, warn: Warn, drain_s: float = DRAIN_S) -> None:
        self.urls = tuple(urls)
        self.source = source
        self.warn = warn
        self.drain_s = drain_s
        self.sent: list[Message] = []
        self.failed: list[Message] = []
        self._queue: queue.Queue[Message | None] = queue.Queue()
        self._busy: Message | None = None  # the message the worker is sending
        self._warned = False
        self._closed = False
        self._apprise: Any = self._load() if self.urls else None  # an apprise.Apprise
        self._worker: threading.Thread | None = None
        if self._apprise is not None:
            self._worker = threading.Thread(target=self._work, name="labcal-notify", daemon=True)
            self._worker.start()

    def _load(self) -> Any:
        """apprise with every URL added; None (one line said) when apprise is not installed. A URL
        apprise cannot parse is refused: the run has not started, so nothing is lost. Built here,
        before anything moves: the callers set it up first (`lab_notifications`)."""
        try:
            import apprise
        except ImportError:
            self._warn_once(f"notifications are off: {self.source} names notification URLs, but apprise is "
                            "not installed (pip install 'labcal[lab]'); the run goes on without them")
            return None
        sender = apprise.Apprise()
        for i, url in enumerate(self.urls, 1):
            if not sender.add(url):
                raise LabcalError(f"{self.source}: URL {i} of {len(self.urls)} ({shown(url)}) is not a "
                                  "notification URL apprise understands; see https://github.com/caronc/"
                                  "apprise/wiki for the forms, or leave it out")
        return sender

    def _warn_once(self, line: str) -> None:
        if not self._warned:
            self._warned = True
            self.warn(line)

    def send(self, message: Message) -> None:
        """Queue ``message`` (returns at once; nothing after `close`)."""
        if self._worker is not None and not self._closed:
            self._queue.put(message)

    def _work(self) -> None:
        while (message := self._queue.get()) is not None:
            self._busy = message
            why = ""
            try:
                with _apprise.LogCapture(level=logging.WARNING, fmt="%(message)s") as said:
                    ok = bool(self._apprise.notify(body=message.body, title=message.title))
                lines = said.getvalue().splitlines()
                why = "" if ok else "; ".join(line for line in lines if line.strip())
            except Exception as exc:  # a plugin's bug, a network library's surprise: never the run's
                ok, why = False, f"{type(exc).__name__}: {exc}"
            if ok:
                self.sent.append(message)
            else:
                self.failed.append(message)
                log.warning("notification not sent (%s): %s", message.what, why)
                to, why = ", ".join(map(shown, self.urls)), why or "apprise reported a failure"
                self._warn_once(f"notification not sent ({message.what}) to {to}: {why}; the run goes on, "
                                "and later failures go to the log only (--log-file)")
            self._busy = None

    def close(self) -> None:
        """Let the queue drain for `drain_s` at most, then say in one line what was not sent."""
        if self._closed:
            return
        self._closed = True
        if self._worker is None:
            return
        self._queue.put(None)
        self._worker.join(self.drain_s)
        if not self._worker.is_alive():
            return
        unsent = [m for m in (self._busy, *self._pending()) if m is not None]
        if unsent:  # the worker goes on with the send it is in (a daemon: it never holds the process)
            self.warn(f"notifications not sent: {len(unsent)} still queued or unanswered after "
                      f"{self.drain_s:g} s ({', '.join(m.what for m in unsent)})")

    def _pending(self) -> list[Message]:
        pending: list[Message] = []
        while True:
            try:
                message = self._queue.get_nowait()
            except queue.Empty:
                return pending
            if message is None:  # the worker's stop, put back: it ends after the send it is in
                self._queue.put(None)
                return pending
            pending.append(message)

    def __enter__(self) -> Notifications:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class RunName:
    """How a run's notifications name it: ``bench``, the station's name in the lab database (marked
    "(simulated)" for a dry run), the instrument's ``serial``, and the lab server's public address
    (``server_url``, None: no link)."""

    bench: str
    serial: str | None = None
    server_url: str | None = None
    simulated: bool = False

    def who(self, run: str) -> str:
        bench = f"{self.bench} (simulated)" if self.simulated else self.bench
        return f"labcal {bench}, run {run}" + (f" ({self.serial})" if self.serial else "")

    def link(self, run: str) -> str | None:
        """The run's page, once the lab has numbered the run (a provisional label names no page)."""
        if not self.server_url or not run.isdigit():
            return None
        return f"{self.server_url.rstrip('/')}/runs/{run}"


def fit_figures(run_dir: Path) -> str:
    """The fit's figures from the run's fit.json (written before a run is journaled complete): its
    model, points and each sensor's residual standard error; '' when the file cannot be read."""
    try:
        doc = json.loads((run_dir / "fit.json").read_text(encoding="utf-8"))
        rse = ", ".join(f"{axis} {value * 1e3:.3g} mV"
                        for axis, value in zip("xyz", doc["residual_standard_error"], strict=True))
        points = f" of {doc['n_points']} points" if "n_points" in doc else ""
        return f"{doc['model']} fit{points}: residual standard error {rse}"
    except (OSError, ValueError, KeyError, TypeError):
        return ""


class RunNotifier:
    """A run's events put into words and handed to `Notifications` (subscribe ``handle`` with
    ``kinds=KINDS``; it only queues, so the run's thread never waits for a network)."""

    KINDS = KINDS

    def __init__(self, notifications: Notifications, name: RunName, run_dir: Path,
                 label: Callable[[int], str] = str, attended: bool = True) -> None:
        self.notifications = notifications
        self.name = name
        self.run_dir = run_dir
        self.label = label  # the run's number as the lab gives it (`labcal.store.labquery.lab_number_of`)
        self.attended = attended  # False: nobody is asked to remount (--yes, a script)

    def handle(self, event: RunEvent) -> None:
        message = self.compose(event)
        if message is not None:
            self.notifications.send(message)

    def compose(self, event: RunEvent) -> Message | None:
        """The notification an event makes, if any: a mount prompt (when someone is asked), a pause,
        the run's end; with the link to the run's page on its last line."""
        run = self.label(event.run_id)
        who = self.name.who(run)
        message = None
        if isinstance(event, Prompt) and event.what == "mount" and self.attended:
            message = self._mount(who, run, event)
        elif isinstance(event, Paused):
            message = self._paused(who, run, event)
        elif isinstance(event, Status) and event.at == "end":
            message = self._finished(who, run, event)
        link = self.name.link(run)
        if message is None or link is None:
            return message
        return Message(message.what, message.title, f"{message.body}\n{link}")

    def _mount(self, who: str, run: str, event: Prompt) -> Message:
        which = f"mount {event.step} of {event.n_steps}" if event.step is not None else "a mount"
        where = ""
        if event.mount is not None:
            mount = MOUNTS[event.mount - 1]  # Soto Table 3's numbering (`labcal.run.events.mount_number`)
            where = f" on the {mount.describe()} ({mount})"
        note = f" ({event.note})" if event.note else ""  # a replicate's re-seat, a wrong mount to correct
        return Message(which, f"labcal run {run} on {self.name.bench}: {which}",
                       f"{who}: {which}: remount the instrument{where}{note}; the tables wait until the "
                       "operator confirms it at the station")

    def _paused(self, who: str, run: str, event: Paused) -> Message:
        tables = (f"the stop did not reach the {', '.join(event.may_be_moving)} table(s): it may still be "
                  "moving" if event.may_be_moving else "the tables are still")
        return Message("the pause", f"labcal run {run} on {self.name.bench}: paused",
                       f"{who}: paused ({event.why}); {tables}; every reading so far is saved, and the run "
                       "waits for the operator to resume or abort it at the station")

    def _finished(self, who: str, run: str, event: Status) -> Message:
        counted = f"{event.points_done} of {event.points_total} points"
        if event.status == "complete":
            figures = fit_figures(self.run_dir)
            verdict = f"complete, {counted}" + (f"; {figures}" if figures else "")
        else:
            verdict = f"{event.status} ({event.reason or 'no reason given'}), {counted}"
            if event.status in ("stopped", "interrupted"):
                verdict += f"; labcal resume {self.run_dir} continues it"
        return Message("the end", f"labcal run {run} on {self.name.bench}: finished, {event.status}",
                       f"{who}: finished: {verdict}")


def lab_notifications(warn: Warn) -> Notifications:
    """The notifications the lab asks for ($LABCAL_NOTIFY, else the lab file's ``notify``), their
    URLs checked by apprise now, before anything moves; with none, a `Notifications` that sends
    nothing."""
    urls, source = load_lab_config().notify_urls()
    return Notifications(urls, source, warn)
