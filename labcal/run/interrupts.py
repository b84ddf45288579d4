"""Ctrl-C during a run: the first asks for a pause after the current point, the second stops
the tables at once; at a prompt, where nothing moves, the first stops. Neither cuts a journal
transaction or a device exchange in half: inside a `critical()` section the stop is deferred to the
section's end.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None


class Interrupts:
    def __init__(self, on_first: Callable[[], None] = lambda: None):
        self.count = 0
        self._prompting = False
        self._depth = 0
        self._deferred = False
        self._on_first = on_first
        self._previous: SignalHandler = None  # the handler to put back

    def __enter__(self) -> Interrupts:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)

    def _handle(self, signum: int, frame: object) -> None:
        if self._prompting:  # nothing moves at a prompt: Ctrl-C there means stop
            raise KeyboardInterrupt
        self.count += 1
        if self.count == 1:
            self._on_first()
        elif self._depth:
            self._deferred = True
        else:
            raise KeyboardInterrupt

    @property
    def pause_requested(self) -> bool:
        return self.count >= 1

    def resumed(self) -> None:
        """The operator chose to go on after a pause: the next Ctrl-C pauses again."""
        self.count = 0

    @contextmanager
    def prompting(self) -> Iterator[None]:
        """While the operator is asked something, Ctrl-C stops the run at once."""
        self._prompting = True
        try:
            yield
        finally:
            self._prompting = False

    @contextmanager
    def critical(self) -> Iterator[None]:
        """A section that must complete: a stop arriving inside is raised when it ends."""
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
            if self._depth == 0 and self._deferred:
                self._deferred = False
                raise KeyboardInterrupt
