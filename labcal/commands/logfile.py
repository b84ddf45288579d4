"""labcal's log, for every command: `labcal --log-file FILE --log-level debug|info|warning`.

The drivers log every exchange at DEBUG and every retry, reconnect, late reply and failed stop at
WARNING (loggers ``labcal.drivers.*``); a run also journals those warnings (`labcal.run.devicelog`),
so without a log file nothing is printed and nothing is lost.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    import logging
    import logging as _logging
else:
    _logging = lazy("logging")  # start-up without logging

LOG_LEVELS = ("debug", "info", "warning")  # logging's names, lower case (logging loads after parsing)


def add_log_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log-file", metavar="FILE",
                        help="append labcal's log to FILE: at debug every device exchange, at warning "
                             "every retry, reconnect, late reply and failed stop")
    parser.add_argument("--log-level", choices=LOG_LEVELS,
                        help="how much to log (default info); without --log-file the log goes to stderr")


def utc_formatter() -> logging.Formatter:  # logging is imported only once a command runs
    """``2026-11-23T22:31:54.123Z WARNING labcal.drivers.transport: …``: UTC, like the journal."""
    class UtcFormatter(_logging.Formatter):
        def formatTime(self, record: _logging.LogRecord, datefmt: str | None = None) -> str:  # noqa: N802
            return (time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
                    + f".{int(record.msecs):03d}Z")

    return UtcFormatter("%(asctime)s %(levelname)s %(name)s: %(message)s")


@contextmanager
def logging_to(path: str | None, level: str | None) -> Iterator[None]:
    """labcal's log (loggers ``labcal.*``) appended to ``path``, or on stderr when only a level is
    given, for the block's duration; a file that cannot be opened is a one-line error."""
    logger = _logging.getLogger("labcal")
    if not any(isinstance(h, _logging.NullHandler) for h in logger.handlers):
        logger.addHandler(_logging.NullHandler())  # no log unless asked for (not Python's last resort)
    if path is None and level is None:
        yield
        return
    handler: _logging.Handler
    if path is None:
        handler = _logging.StreamHandler(sys.stderr)
    else:
        try:
            handler = _logging.FileHandler(path, encoding="utf-8")
        except OSError as exc:
            raise LabcalError(f"--log-file {path}: cannot open it ({exc.strerror or exc}); give a file in a "
                              "folder you can write to") from None
    handler.setFormatter(utc_formatter())
    before = logger.level
    logger.setLevel((level or "info").upper())  # logging knows its levels by name
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(before)
        handler.close()
