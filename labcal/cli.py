"""The `labcal` command line. User errors print one line and exit 2; never a traceback."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

from labcal import __version__
from labcal.commands import attitude, fit, history, plan, report, run, sim, simulate, station
from labcal.commands.common import EXIT_INTERRUPTED, EXIT_USER_ERROR, err
from labcal.errors import LabcalError

COMMAND_GROUPS = (run, fit, simulate, plan, attitude, report, history, station, sim)
LOG_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="labcal", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Calibrate three-axis accelerometer attitude instruments on a two-axis "
                    "rotary calibration device (Soto 2020; Tripp & Tcheng 1999).",
        epilog="examples:\n  labcal run --sim --yes\n  labcal fit runs/*/readings.csv --json\n"
               "  labcal plan show four-mount-64",
    )
    parser.add_argument("--version", action="version", version=f"labcal {__version__}")
    parser.add_argument("--log-file", metavar="FILE",
                        help="append labcal's log to FILE: at debug every device exchange, at warning "
                             "every retry, reconnect, late reply and failed stop")
    parser.add_argument("--log-level", choices=LOG_LEVELS,
                        help="how much to log (default info); without --log-file the log goes to stderr")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in COMMAND_GROUPS:
        group.register(sub)
    return parser


class UtcFormatter(logging.Formatter):
    """2026-11-23T22:31:54.123Z WARNING labcal.drivers.transport: ... (one clock for every bench)."""

    converter = time.gmtime

    def __init__(self) -> None:
        super().__init__("%(asctime)s.%(msecs)03dZ %(levelname)s %(name)s: %(message)s", "%Y-%m-%dT%H:%M:%S")


@contextmanager
def logging_to(path: str | None, level: str | None) -> Iterator[None]:
    """labcal's log (loggers ``labcal.*``) in ``path``, or on stderr when only a level is given,
    for the command's duration. Without either nothing is printed: the drivers' warnings still
    reach a run's journal."""
    logger = logging.getLogger("labcal")
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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.getLogger("labcal").addHandler(_QUIET)  # no log unless asked (not Python's last resort)
    try:
        with logging_to(args.log_file, args.log_level):
            return args.func(args)
    except LabcalError as exc:
        err.print(f"[bold red]labcal: error:[/] {exc}")
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        err.print("[bold red]interrupted[/]")
        return EXIT_INTERRUPTED


_QUIET = logging.NullHandler()

if __name__ == "__main__":
    sys.exit(main())
