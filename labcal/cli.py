"""The `labcal` command line. User errors print one line and exit 2; never a traceback."""

from __future__ import annotations

import argparse
import gc
import os
import re
import sys
from collections.abc import Collection
from importlib import import_module
from typing import TYPE_CHECKING, NoReturn

import labcal
from labcal.commands import COMMANDS
from labcal.commands.common import EXIT_INTERRUPTED, EXIT_USER_ERROR, err
from labcal.commands.logfile import add_log_options, logging_to
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from rich import markup
else:
    markup = lazy("rich.markup")  # start-up without rich

# labcal's matrices are a few columns wide (a million rows of 3 or 4): OpenBLAS's worker threads only
# wait on each other over them, and on a shared 2-core machine they made `labcal fit` on 1e6 readings
# 2.5× slower in its checks. Read by OpenBLAS when numpy loads, which no import above does; the
# environment still wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors on one line (and where the usage is), like every other user error;
    subcommands' parsers are of this class too (argparse makes them of their parent's class)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USER_ERROR, f"{self.prog}: error: {message} (usage: {self.prog} --help)\n")


class _Version(argparse.Action):
    """`--version`, reading the installed version only when asked (importlib.metadata is slow)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="show program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        parser.exit(message=f"labcal {labcal.__version__}\n")


def build_parser(only: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The command line. With ``only`` (the words of the command line), only the commands named
    there are built, with their modules imported; every other one is listed by its name and help,
    which is all `labcal --help` shows of it (`labcal.commands.COMMANDS`)."""
    parser = OneLineParser(
        prog="labcal", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Calibrate three-axis accelerometer attitude instruments on a two-axis "
                    "rotary calibration device (Soto 2020; Tripp & Tcheng 1999).",
        epilog="examples:\n  labcal run --sim --yes\n  labcal fit runs/*/readings.csv --json\n"
               "  labcal plan show four-mount-64",
    )
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    wanted = None if only is None else {COMMANDS[word][0] for word in only if word in COMMANDS}
    added: set[str] = set()
    for name, (module, summary) in COMMANDS.items():
        if wanted is not None and module not in wanted:
            sub.add_parser(name, help=summary, add_help=False)  # listed; never parsed, as not named
        elif module not in added:
            import_module(f"labcal.commands.{module}").register(sub)
            added.add(module)
    add_log_options(parser)
    return parser


NEGATIVE_LIST = re.compile(r"^-\d[\d.eE+-]*,")  # "-30,100": argparse would read it as an option


def _one_value_options(parser: argparse.ArgumentParser) -> set[str]:
    """Every option string, in the whole tree of subcommands, that takes exactly one value."""
    found = {o for a in parser._actions if a.nargs is None and a.option_strings for o in a.option_strings}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                found |= _one_value_options(child)
    return found


def _attach_negative_lists(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """``--at -30,100`` as ``--at=-30,100``: a comma list that starts with a negative number is the
    option's value (argparse only recognises a lone negative number as one)."""
    options, joined = _one_value_options(parser), list[str]()
    for word in argv:
        if joined and joined[-1] in options and NEGATIVE_LIST.match(word):
            joined[-1] = f"{joined[-1]}={word}"
        else:
            joined.append(word)
    return joined


EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a writer whose reader left


# A labcal command makes millions of objects and drops most of them soon (a figure's artists, a
# fit's temporaries): at CPython's default, a collection of the youngest objects every 700 new ones,
# a dry run spent 0.37 s of its 3.2 s in the collector (530 young, 48 middle and 4 full collections),
# re-reading the libraries it had loaded. Every 50 000 it spends 0.1 s (8 young, none full); the
# objects not yet collected are a few megabytes at most. Cycles are still found, in larger batches:
# an object in a cycle that holds a file (a sqlite3 connection is one in Python 3.11) and is never
# closed stays open longer, so labcal closes what it opens, and a caller of `main` in its own
# process gets its own setting back.
GC_THRESHOLDS = (50_000, 20, 10)


def main(argv: list[str] | None = None) -> int:
    before = gc.get_threshold()
    gc.set_threshold(*GC_THRESHOLDS)
    try:
        return _command(argv)
    finally:
        gc.set_threshold(*before)


def script() -> int:
    """The installed `labcal` command: `main`, then an exit that skips the interpreter's last collection.

    At exit CPython collects garbage again over every object the collector tracks (matplotlib's,
    scipy's, SQLAlchemy's: 270 000 after a dry run, 96 000 after `labcal runs`) and over what clearing
    the modules leaves in cycles; that took 0.45 s of a 3.2 s dry run and 0.12 s of `labcal runs`.
    `gc.freeze` moves them all out of those collections' sight; objects are still freed
    by reference counting as modules are cleared, and atexit handlers (logging's flush among them)
    still run. Only garbage in reference cycles is left to the operating system, which is safe
    because labcal closes every file and database connection it opens. Not `main`'s own business:
    a script or a test calling `main` in its own process goes on collecting."""
    code = main()
    gc.freeze()
    return code


def _command(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(only=set(argv))  # a word that names a command is the command, or harmless
    try:
        args = parser.parse_args(_attach_negative_lists(parser, argv))
    except SystemExit as exc:  # --help, --version, or a wrong option (its one line is printed)
        return exc.code if isinstance(exc.code, int) else EXIT_USER_ERROR
    try:
        with logging_to(args.log_file, args.log_level):
            return args.func(args)
    except BrokenPipeError:
        # the reader has gone (`labcal attitude … | head`): stop quietly; point stdout at devnull so
        # that the interpreter's own flush at exit does not fail on the closed pipe again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except LabcalError as exc:
        # "pip install 'labcal[lab]'" as written, not as markup
        err.print(f"[bold red]labcal: error:[/] {markup.escape(str(exc))}")
        return EXIT_USER_ERROR
    except KeyboardInterrupt as exc:
        err.print("[bold red]interrupted[/]")
        signum = getattr(exc, "signum", None)  # SIGTERM, SIGHUP: 128 + its number, as a shell says it
        return EXIT_INTERRUPTED if signum is None else 128 + signum


if __name__ == "__main__":
    sys.exit(script())
