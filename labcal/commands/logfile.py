"""labcal's log, for every command: `labcal --log-file FILE --log-level debug|info|warning`.

The drivers log every exchange at DEBUG and every retry, reconnect, late reply and failed stop at
WARNING (loggers ``labcal.drivers.*``); a run also journals those warnings (`labcal.run.devicelog`),
so without a log file nothing is printed and nothing is lost.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

from labcal.errors import LabcalError

LOG_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING}
_QUIET = logging.NullHandler()  # no log unless asked for (not Python's last-resort printing to stderr)


def add_log_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log-file", metavar="FILE",
                        help="append labcal's log to FILE: at debug every device exchange, at warning "
                             "every retry, reconnect, late reply and failed stop")
    parser.add_argument("--log-level", choices=LOG_LEVELS,
                        help="how much to log (default info); without --log-file the log goes to stderr")


class UtcFormatter(logging.Formatter):
    """``2026-11-23T22:31:54.123Z WARNING labcal.drivers.transport: …``: UTC, like the journal."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s")

    def formatTime(self, record: logging.LogRecord, datefmt: str | None = None) -> str:  # noqa: N802
        return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z"


@contextmanager
def logging_to(path: str | None, level: str | None) -> Iterator[None]:
    """labcal's log (loggers ``labcal.*``) appended to ``path``, or on stderr when only a level is
    given, for the block's duration; a file that cannot be opened is a one-line error."""
    logger = logging.getLogger("labcal")
    logger.addHandler(_QUIET)
    if path is None and level is None:
        yield
        return
    handler: logging.Handler
    if path is None:
        handler = logging.StreamHandler(sys.stderr)
    else:
        try:
            handler = logging.FileHandler(path, encoding="utf-8")
        except OSError as exc:
            raise LabcalError(f"--log-file {path}: cannot open it ({exc.strerror or exc}); give a file in a "
                              "folder you can write to") from None
    handler.setFormatter(UtcFormatter())
    before = logger.level
    logger.setLevel(LOG_LEVELS[level or "info"])
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(before)
        handler.close()
