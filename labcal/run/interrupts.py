"""Signals during a run. Ctrl-C: the first asks for a pause after the current point, the second
stops the tables at once; at a prompt, where nothing moves, the first stops. SIGTERM and SIGHUP
(a service manager stopping labcal, the terminal closing) stop the tables at once, like a second
Ctrl-C: without a handler they would end the process with the tables still moving and the run
marked "running" in the journal.

No stop cuts a journal transaction or a device exchange in half: inside a `critical()` section it
is deferred to the section's end, save while an exchange only waits for its reply
(`critical(awaiting_reply=True)`): a dead controller would hold the stop for its whole reply timeout,
so there the stop is raised at once, and the link takes the line back before its next frame (it
lets a reply on its way end, then discards it: `labcal.drivers.transport.LineTransport`,
`labcal.drivers.modbus.ModbusLink`). While the tables are being stopped (`stopping()`), a signal is
only noted, so that an impatient third Ctrl-C cannot keep the second table from getting its stop;
it is raised at the next critical section's end (a stop after a fault is followed by journaling
the fault, before the pause prompt).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None

# the signals that stop a run at once; SIGHUP does not exist on Windows
STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class StopSignal(KeyboardInterrupt):
    """A signal that stops the run at once; ``reason`` names it for the journal and ``signum``
    gives the exit status (128 + signum, as a shell reports a process a signal ended)."""

    def __init__(self, signum: int, reason: str):
        super().__init__(reason)
        self.signum = signum
        self.reason = reason


class Interrupts:
    def __init__(self, on_first: Callable[[], None] = lambda: None):
        self.count = 0
        self._prompting = False
        self._stopping = False
        self._depth = 0
        self._awaiting = 0  # inside an exchange's wait for its reply, where a stop is raised at once
        self._deferred: StopSignal | None = None
        self._on_first = on_first
        self._previous: dict[int, SignalHandler] = {}  # the handlers to put back

    def __enter__(self) -> Interrupts:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, *STOP_SIGNALS):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            if previous is not None:
                signal.signal(signum, previous)
        self._previous.clear()

    def _handle(self, signum: int, frame: object) -> None:
        if signum == signal.SIGINT and not self._prompting:
            self.count += 1
            if self.count == 1:
                self._on_first()
                return
            reason = "Ctrl-C twice"
        elif signum == signal.SIGINT:  # nothing moves at a prompt: Ctrl-C there means stop
            reason = "Ctrl-C at a prompt"
        else:
            reason = signal.Signals(signum).name
        self.count = max(self.count, 2)
        stop = StopSignal(signum, reason)
        if self._stopping or (self._depth and not self._prompting and not self._awaiting):
            self._deferred = self._deferred or stop  # raised where it cuts neither a stop nor an exchange
        else:
            raise stop

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
    def stopping(self) -> Iterator[None]:
        """While both tables are told to stop, no signal interrupts that (it is deferred)."""
        self._stopping = True
        try:
            yield
        finally:
            self._stopping = False

    @contextmanager
    def critical(self, *, awaiting_reply: bool = False) -> Iterator[None]:
        """A section that must complete: a stop arriving inside is raised when it ends.
        ``awaiting_reply``: the part of an exchange that only waits for the device's reply, its
        request already on the line; a stop arriving there, or deferred until then, is raised at
        once (waiting out a dead controller's reply timeout would delay the live table's stop)."""
        self._depth += 1
        self._awaiting += awaiting_reply
        try:
            if awaiting_reply and self._deferred is not None and not self._stopping:
                stop, self._deferred = self._deferred, None
                raise stop
            yield
        finally:
            self._depth -= 1
            self._awaiting -= awaiting_reply
            if self._depth == 0 and self._deferred is not None and not self._stopping:
                stop, self._deferred = self._deferred, None
                raise stop


def _raise_stop(signum: int, frame: FrameType | None) -> None:
    raise StopSignal(signum, signal.Signals(signum).name)


@contextmanager
def stop_signals_raise() -> Iterator[None]:
    """Outside a run's own handler (homing the tables, starting the emulators), SIGTERM and SIGHUP
    raise `StopSignal` as Ctrl-C raises KeyboardInterrupt, so that the code that stops the tables
    on any exception runs for them too, instead of the process dying with a table moving."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, _raise_stop) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
