"""The `labcal` command line. User errors print one line and exit 2; never a traceback."""

from __future__ import annotations

import argparse
import sys

from labcal import __version__
from labcal.commands import (
    attitude,
    certificate,
    config,
    device,
    export,
    fit,
    history,
    plan,
    report,
    run,
    sim,
    simulate,
    station,
)
from labcal.commands.common import EXIT_INTERRUPTED, EXIT_USER_ERROR, err
from labcal.commands.logfile import add_log_options, logging_to
from labcal.errors import LabcalError

COMMAND_GROUPS = (run, fit, simulate, plan, attitude, report, history, device, station, sim, export,
                  config, certificate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="labcal", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Calibrate three-axis accelerometer attitude instruments on a two-axis "
                    "rotary calibration device (Soto 2020; Tripp & Tcheng 1999).",
        epilog="examples:\n  labcal run --sim --yes\n  labcal fit runs/*/readings.csv --json\n"
               "  labcal plan show four-mount-64",
    )
    parser.add_argument("--version", action="version", version=f"labcal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in COMMAND_GROUPS:
        group.register(sub)
    add_log_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with logging_to(args.log_file, args.log_level):
            return args.func(args)
    except LabcalError as exc:
        err.print(f"[bold red]labcal: error:[/] {exc}")
        return EXIT_USER_ERROR
    except KeyboardInterrupt as exc:
        err.print("[bold red]interrupted[/]")
        signum = getattr(exc, "signum", None)  # SIGTERM, SIGHUP: 128 + its number, as a shell says it
        return EXIT_INTERRUPTED if signum is None else 128 + signum


if __name__ == "__main__":
    sys.exit(main())
