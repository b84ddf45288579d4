"""What every command shares: the two consoles and JSON output."""

from __future__ import annotations

import argparse
import json
import sys

from rich.console import Console

from labcal.config.files import json_safe

EXIT_USER_ERROR = 2
EXIT_STOPPED = 1
EXIT_INTERRUPTED = 130
TIME_SCALE_HELP = "emulated seconds per wall-clock second (default: the station file's [emulation])"

out = Console(highlight=False)
err = Console(stderr=True, highlight=False, soft_wrap=True)  # prose: the terminal wraps it


def print_json(doc: dict) -> None:
    """One JSON document on stdout and nothing else (`--json`)."""
    sys.stdout.write(json.dumps(json_safe(doc), indent=2) + "\n")


def add_db_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", metavar="PATH",
                   help="the lab's SQLite database (default: $LABCAL_DB, else the lab file's database; "
                        "see `labcal config path`)")
