"""Write docs/reference/cli.md: every command's and subcommand's `--help`, as the command line's own
parsers print it, so that the reference cannot say what the parsers do not. Run from the repository
root after changing an option; tests/repository/test_documents.py fails while the file differs.

    .venv/bin/python tools/cli_reference.py
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

TARGET = Path("docs/reference/cli.md")
WIDTH = "100"  # argparse wraps at $COLUMNS: one width, whatever the terminal


def sections(parser: argparse.ArgumentParser, words: tuple[str, ...] = ("labcal",)) -> list[tuple[str, str]]:
    """(command words, its help) for the parser and every subcommand below it, depth first."""
    found = [(" ".join(words), parser.format_help())]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                found += sections(child, (*words, name))
    return found


def text() -> str:
    from labcal.cli import build_parser

    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        helps = sections(build_parser())
    finally:
        if before is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = before
    lines = ["# Command-line reference", "",
             "Every command's `--help`, generated from the parsers by `tools/cli_reference.py`: do not edit.",
             ""]
    for words, help_text in helps:
        lines += [f"## {words}", "", "```text", help_text.rstrip(), "```", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    TARGET.write_text(text(), encoding="utf-8")
    sys.stdout.write(f"{TARGET}\n")
