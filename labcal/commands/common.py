"""What every command shares: the two consoles and JSON output."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

EXIT_USER_ERROR = 2
EXIT_STOPPED = 1
EXIT_INTERRUPTED = 130
TIME_SCALE_HELP = "emulated seconds per wall-clock second (default: the station file's [emulation])"



class _LazyConsole:
    """A rich Console made on first use: importing rich costs every command, `--help` included,
    a tenth of a second, and most never print through it. On first use the object becomes the
    Console itself, so that whatever rich does with it (context managers, identity) just works."""

    def __init__(self, **options: Any):
        self._options = options

    def _become(self) -> Console:
        from rich.console import Console

        options = self.__dict__.pop("_options")
        self.__class__ = Console  # type: ignore[assignment]
        Console.__init__(self, **options)  # type: ignore[arg-type]
        return self  # type: ignore[return-value]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._become(), name)

    def __enter__(self) -> Console:
        return self._become().__enter__()

    def __exit__(self, *exc: object) -> None:
        self._become().__exit__(*exc)


out: Console = _LazyConsole(highlight=False)  # type: ignore[assignment]
err: Console = _LazyConsole(stderr=True, highlight=False, soft_wrap=True)  # type: ignore[assignment]  # prose: the terminal wraps it


def print_json(doc: dict) -> None:
    """One JSON document on stdout and nothing else (`--json`)."""
    import json

    from labcal.config.files import json_safe

    sys.stdout.write(json.dumps(json_safe(doc), indent=2) + "\n")


def add_db_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", metavar="PATH",
                   help="the lab's SQLite database (default: $LABCAL_DB, else runs/labcal.sqlite)")
