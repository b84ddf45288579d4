"""The devices' warnings as journal events. The drivers log every retry, reconnect and late
reply as a WARNING (loggers ``labcal.drivers.*``); during a run each such record also becomes an
event of the run (kind ``link``), so that a degrading RS-485 line leaves a record in the journal
beside the points it slowed down, whether or not anyone asked for a log file."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

DRIVER_LOGGERS = "labcal.drivers"
EVENT_KIND = "link"


class JournalWarnings(logging.Handler):
    """Journals WARNING (and worse) records of the drivers through the run's ``event``."""

    def __init__(self, event: Callable[..., None]):
        super().__init__(logging.WARNING)
        self.event = event
        self.thread = threading.get_ident()  # the run's: its journal connection serves no other

    def emit(self, record: logging.LogRecord) -> None:
        if threading.get_ident() != self.thread:  # the drivers run on the run's thread; nothing
            return                                # else may write through its connection
        self.event(EVENT_KIND, record.getMessage(), logger=record.name, level=record.levelname)


@contextmanager
def journaled_warnings(event: Callable[..., None]) -> Iterator[None]:
    """While the block runs, the drivers' warnings are journaled by ``event(kind, message, **data)``."""
    logger = logging.getLogger(DRIVER_LOGGERS)
    handler = JournalWarnings(event)
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)
