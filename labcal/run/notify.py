"""Notifications through apprise: the technician learns of a remount, a pause or the end of a run
without standing at the station's terminal (issue 24).

`LABCAL_NOTIFY` (comma-separated apprise URLs) or the lab file's ``notify`` names where they go
(`labcal.config.lab.LabConfig.notify_urls`). The run's events reach a `RunNotifier`, a subscriber
of the run's event bus like the console view (the sequencer never imports this module), which puts
three of them into words:

- a remount prompt: "labcal station bench-2, run 7: mount 3 of 4 (bottom side of the plate, x
  sensor pointing forward; y=0°, u=180°): remount the instrument";
- a pause: "… run 7: paused: fault: roll table …: alarm 10h …";
- the run's end: "… run 7: finished: complete, 64 of 64 points; …the fit's figures" (or failed,
  stopped, interrupted, and why).

A notification is never worth a reading. `Notifications` sends from a worker thread of its own
through a queue, so the run's thread only appends to a list: a slow or dead endpoint costs the run
nothing. A send that fails (apprise says so, or raises) is told once, in one line, and the run
goes on; at the run's end `close` waits a few seconds at most for the queue to drain and then says
what was not sent. apprise missing is also one line and no notifications. What is refused is a URL
that apprise cannot parse: that is a typing mistake, caught before anything moves (`parse_urls`).
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
from labcal.errors import LabcalError

if TYPE_CHECKING:
    from labcal.run.events import Paused, Prompt, RunEvent, Status

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

    ``warn`` prints one line (the command's console); it is called at most once for failures while
    the run goes on, and once at `close` if anything is left unsent."""

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
        self._apprise = self._load()
        self._worker: threading.Thread | None = None
        if self._apprise is not None:
            self._worker = threading.Thread(target=self._work, name="labcal-notify", daemon=True)
            self._worker.start()

    def _load(self) -> Any:
        """apprise with every URL added; None (one line said) when apprise is not installed. A URL
        apprise cannot parse is refused: the run has not started, so nothing is lost."""
        try:
            import apprise
        except ImportError:
            self._warn_once(f"notifications are off: {self.source} names notification URLs, but apprise is "
                            "not installed (pip install 'labcal[lab]'); the run goes on without them")
            return None
        sender = apprise.Apprise()
        for i, url in enumerate(self.urls, 1):
            if not sender.add(url):
                raise LabcalError(f"{self.source}: URL {i} of {len(self.urls)} ({shown(url)}) is not a notification "
                                  "URL apprise understands; see https://github.com/caronc/apprise/wiki for "
                                  "the forms, or leave it out")
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
        import apprise

        while (message := self._queue.get()) is not None:
            self._busy = message
            why = ""
            try:
                with apprise.LogCapture(level=logging.WARNING, fmt="%(message)s") as said:
                    ok = bool(self._apprise.notify(body=message.body, title=message.title))
                why = "; ".join(line for line in said.getvalue().splitlines() if line.strip()) if not ok else ""
            except Exception as exc:  # a plugin's bug, a network library's surprise: never the run's
                ok, why = False, f"{type(exc).__name__}: {exc}"
            if ok:
                self.sent.append(message)
            else:
                self.failed.append(message)
                log.warning("notification not sent (%s): %s", message.what, why)
                self._warn_once(f"notification not sent ({message.what}): {why or 'apprise reported a failure'}"
                                f" [{', '.join(shown(u) for u in self.urls)}]; the run goes on, and later "
                                "failures are counted at its end")
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
        unsent = [m for m in (self._busy, *self._pending()) if m is not None] if self._worker.is_alive() else []
        later = self.failed[1:]  # the first failure was told when it happened
        if unsent or later:
            parts = [f"{len(later)} more failed ({', '.join(m.what for m in later)})"] if later else []
            if unsent:
                parts.append(f"{len(unsent)} still queued after {self.drain_s:g} s "
                             f"({', '.join(m.what for m in unsent)})")
            self.warn(f"notifications not sent: {'; '.join(parts)}")

    def _pending(self) -> list[Message]:
        pending = []
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
