"""What every command shares: the two consoles and JSON output."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable

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


def bounded(kind: type[int] | type[float], lo: float | None = None, hi: float | None = None, *,
            lo_open: bool = False, hi_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type`` for a finite number in a range: a value outside it (or nan, inf, a word)
    is refused before the command starts, in one line that names the option and the valid range
    (argparse puts ``argument --OPTION:`` in front of the message)."""
    what = "a whole number" if kind is int else "a number"
    def show(limit: float) -> str:
        return str(int(limit)) if kind is int else f"{limit:g}"

    lo_text = "" if lo is None else f"{show(lo)} {'<' if lo_open else '≤'} "
    hi_text = "" if hi is None else f" {'<' if hi_open else '≤'} {show(hi)}"
    expected = f"expected {what}{f' x with {lo_text}x{hi_text}' if lo_text or hi_text else ''}"

    def convert(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}; {expected}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} is not a finite number; {expected}")
        low_ok = lo is None or (value > lo if lo_open else value >= lo)
        high_ok = hi is None or (value < hi if hi_open else value <= hi)
        if not (low_ok and high_ok):
            raise argparse.ArgumentTypeError(f"{text} is out of range; {expected}")
        return value

    convert.__name__ = what  # argparse names the type in its own messages
    return convert


SEED = bounded(int, 0, 2**32 - 1)
TIME_SCALE = bounded(float, 0, 100_000, lo_open=True)  # what the emulators accept (sim/emulation.py)


def bounded_field(model: type, field: str) -> Callable[[str], float]:
    """``bounded`` with the range of a pydantic model's field (its ge/gt/le/lt), so that the option
    and the file setting it overrides accept the same values."""
    info = model.model_fields[field]  # type: ignore[attr-defined]
    kind = int if info.annotation is int else float
    limits = {name: getattr(m, name) for m in info.metadata for name in ("ge", "gt", "le", "lt")
              if hasattr(m, name)}
    return bounded(kind, limits.get("ge", limits.get("gt")), limits.get("le", limits.get("lt")),
                   lo_open="gt" in limits, hi_open="lt" in limits)


def outcome_of_checks(flags, allowed: bool, source: str) -> int:
    """List the readings the gross-error checks refused (one line per finding, on stderr; the
    result is already printed, so nothing is lost) and fail unless ``allowed`` (--allow-outliers)."""
    if not flags:
        return 0
    from labcal.errors import LabcalError

    for message in dict.fromkeys(f.message if f.check == "mount" else f"reading {f.row}: {f.message}"
                                 for f in flags):
        err.print(f"[bold yellow]gross error:[/] {message}", markup=True, highlight=False)
    if allowed:
        err.print(f"{len({f.row for f in flags})} reading(s) flagged; accepted (--allow-outliers)")
        return 0
    raise LabcalError(f"{source}: {len({f.row for f in flags})} reading(s) failed the gross-error checks "
                      "(listed above); check or re-measure them, or accept them with --allow-outliers")
