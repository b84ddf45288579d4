"""The `labcal` command line. User errors print one line and exit 2; never a traceback."""

from __future__ import annotations

import argparse
import os
import sys

from labcal.commands import attitude, fit, history, plan, report, run, sim, simulate, station
from labcal.commands.common import EXIT_INTERRUPTED, EXIT_USER_ERROR, err
from labcal.errors import LabcalError

COMMAND_GROUPS = (run, fit, simulate, plan, attitude, report, history, station, sim)


class _Version(argparse.Action):
    """`--version`, reading the installed version only when asked (importlib.metadata is slow)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="show program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        from labcal import __version__

        parser.exit(message=f"labcal {__version__}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="labcal", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Calibrate three-axis accelerometer attitude instruments on a two-axis "
                    "rotary calibration device (Soto 2020; Tripp & Tcheng 1999).",
        epilog="examples:\n  labcal run --sim --yes\n  labcal fit runs/*/readings.csv --json\n"
               "  labcal plan show four-mount-64",
    )
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in COMMAND_GROUPS:
        group.register(sub)
    return parser


EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a writer whose reader left


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except BrokenPipeError:
        # the reader has gone (`labcal attitude … | head`): stop quietly; point stdout at devnull so
        # that the interpreter's own flush at exit does not fail on the closed pipe again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except LabcalError as exc:
        err.print(f"[bold red]labcal: error:[/] {exc}")
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        err.print("[bold red]interrupted[/]")
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
