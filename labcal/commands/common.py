"""What every command shares: the two consoles and JSON output."""

from __future__ import annotations

import argparse
import importlib
import math
import re
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    import ctypes
    import datetime as dt
    import json
    import shlex

    from rich import console, markup
    from rich import table as rich_table
    from rich.console import Console

    from labcal.app import labdatabase
    from labcal.app.histories import History
    from labcal.config import json_values, uncertainty
    from labcal.config import lab as config_lab
else:
    config_lab = lazy("labcal.config.lab")  # start-up without pydantic
    console = lazy("rich.console")  # start-up without rich
    ctypes = lazy("ctypes")  # start-up without ctypes
    dt = lazy("datetime")  # --help without datetime (1 ms of a 35 ms start-up)
    json = lazy("json")  # --help without json (1.4 ms)
    json_values = lazy("labcal.config.json_values")  # start-up without 3 more modules
    labdatabase = lazy("labcal.app.labdatabase")  # start-up without pydantic
    markup = lazy("rich.markup")  # start-up without rich
    rich_table = lazy("rich.table")  # start-up without rich
    shlex = lazy("shlex")  # start-up without shlex
    uncertainty = lazy("labcal.config.uncertainty")  # pydantic: only when the option is given


def literal(value: object) -> str:
    """``value`` as Rich prints it, character for character: a serial ``ACC[/x]`` or a folder
    ``run[1]`` is text, not markup (unescaped, the first crashed the console after a run)."""
    return markup.escape(str(value))


def command_line(*words: object) -> str:
    """A command to copy into a shell: each word quoted as the shell needs it (`shlex.quote`), then
    made literal for Rich."""
    return literal(shlex.join(str(w) for w in words))


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
        options = self.__dict__.pop("_options")
        self.__class__ = console.Console  # type: ignore[assignment]
        console.Console.__init__(self, **options)  # type: ignore[arg-type]
        return self  # type: ignore[return-value]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._become(), name)

    def __enter__(self) -> Console:
        return self._become().__enter__()

    def __exit__(self, *exc: object) -> None:
        self._become().__exit__(*exc)


out: Console = _LazyConsole(highlight=False)  # type: ignore[assignment]
err: Console = _LazyConsole(stderr=True, highlight=False, soft_wrap=True)  # type: ignore[assignment]  # prose: the terminal wraps it


def keep_freed_memory() -> None:
    """Let the process reuse the memory of freed arrays instead of returning it to the system.

    A million-reading file makes dozens of arrays of tens of MiB, each freed before the next is
    made. glibc hands every such block back to the kernel (mmap/munmap) and the next array pays a
    page fault for each of its 4 KiB pages again: a sixth of `labcal fit` on 1e6 readings. Raising
    glibc's mmap and trim thresholds keeps the freed blocks for reuse; peak memory is unchanged
    (the same arrays are alive at once), and a command lasts seconds, so nothing is held for long.
    Elsewhere than glibc there is no mallopt, and nothing is done."""
    if not sys.platform.startswith("linux"):
        return
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is not None:
        m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h>
        mallopt(m_mmap_threshold, 1 << 30)
        mallopt(m_trim_threshold, 1 << 30)


def format_duration(seconds: float) -> str:
    """'1 h 02 min 03 s' or '25 min 04 s': a run's or a plan's length, as the estimate and the log say it."""
    seconds = int(round(seconds))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h} h {m:02d} min {s:02d} s" if h else f"{m} min {s:02d} s"


def print_json(doc: dict) -> None:
    """One JSON document on stdout and nothing else (`--json`)."""
    sys.stdout.write(json.dumps(json_values.json_safe(doc), indent=2) + "\n")


def print_history(history: History) -> None:
    """A history (`labcal.app.histories`): its calibrations, its tables with each flagged change in
    red, each flagged change in words, the tally with the rule that flagged them, and where the plot
    went (the instrument's and the device's histories end alike)."""
    for entry in history.entries:
        out.print(f"  {entry}")
    for t in history.tables:
        table = rich_table.Table(title=t.title)
        for col in t.columns:
            table.add_column(col, justify="right")
        for row in t.rows:
            table.add_row(*(f"[bold red]{c.text} ▲[/]" if c.flagged else c.text for c in row))
        out.print(table)
    for change in history.flagged:
        out.print(f"[bold red]change:[/] {change}")
    out.print(f"{history.tally}; {len(history.flagged)} change(s) flagged by {history.rule}.")
    if history.plot:
        out.print(f"plot written to {history.plot}")


def add_power_on_options(p: argparse.ArgumentParser) -> None:
    """--powered-on and --warmed-up: what the technician says about the instrument's warm-up."""
    group = p.add_mutually_exclusive_group()
    group.add_argument("--powered-on", metavar="HH:MM",
                       help="when the instrument was switched on (local time; YYYY-MM-DD HH:MM for another "
                            "day): the checklist holds it to the station's [instrument] warm_up_min")
    group.add_argument("--warmed-up", action="store_true",
                       help="the instrument has warmed up (e.g. left on overnight): go on whatever the "
                            "station's warm-up time (journaled with the run)")


def warn_if_secret_in(db_option: str | None) -> None:
    """One line when --db carries a password: every account on this machine reads a command line
    (``ps``)."""
    if db_option and config_lab.redacted(db_option) != db_option:
        sys.stderr.write("warning: the password in --db is visible to every account on this machine (ps); "
                         "keep it in ~/.pgpass or $PGPASSWORD, or give the URL in $LABCAL_DB\n")


def add_db_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", metavar="PATH|URL",
                   help="the lab database: a SQLite file, or postgresql://USER@HOST:PORT/DBNAME (default: "
                        "$LABCAL_DB, else the lab file's database; see `labcal config path`)")


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


# The largest attitude U95 (and tolerance on it) a calibration of these instruments is plausibly asked
# for: they reach arcseconds to a few hundredths of a degree. A bare number above it is refused, as
# the likely slip of arcseconds written as degrees (7.5 meant as 7.5″ is 3600 times too loose).
PLAUSIBLE_U95_MAX_DEG = 1.0


def angle_deg(hi: float, plausible_max: float = PLAUSIBLE_U95_MAX_DEG) -> Callable[[str], float]:
    """An argparse ``type`` for a positive angle in degrees that may also carry its unit, where a slip
    between degrees and arcseconds is likely: ``0.002`` and ``0.002deg`` (or ``°``) are degrees,
    ``7.5arcsec`` (or ``"``, ``″``), ``0.5arcmin``, ``mrad``, ``µrad``, ``rad`` are converted to
    degrees. A number given without a unit above ``plausible_max`` degrees is refused in one line that
    names the likely slip; one with a unit is taken as written, up to ``hi`` degrees."""
    expected = (f"expected an angle 0 < x ≤ {hi:g}°: degrees (0.002 or 0.002deg) or with its unit "
                "(7.5arcsec, 7.5\", 0.5arcmin, 40urad)")

    def convert(text: str) -> float:
        found = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S*)\s*", text)
        if found is None:
            raise argparse.ArgumentTypeError(f"{text} is not an angle; {expected}")
        number, unit = float(found[1]), found[2]
        units = uncertainty.UNITS["angle"]
        if unit and unit not in units:
            raise argparse.ArgumentTypeError(f"{text!r}: {unit!r} is not a unit of angle; use one of "
                                             f"{', '.join(units)}")
        degrees = number if not unit else number * units[unit] / units["deg"]
        if not (math.isfinite(degrees) and 0 < degrees <= hi):
            raise argparse.ArgumentTypeError(f"{text} is out of range; {expected}")
        if not unit and degrees > plausible_max:
            meant = degrees / 3600  # the number as arcseconds, in degrees
            raise argparse.ArgumentTypeError(
                f"{text} is read as {text}° ({degrees * 3600:g}″), far above any attitude U95 a calibration "
                f"reaches (at most {plausible_max:g}°); if you meant {text} arcseconds, write {text}arcsec "
                f"(= {meant:.3g}°)")
        return degrees

    convert.__name__ = "an angle"
    return convert


SEED = bounded(int, 0, 2**32 - 1)
TIME_SCALE = bounded(float, 0, 100_000, lo_open=True)  # what the emulators accept (sim/emulation.py)


def bounded_field(model: str, field: str) -> Callable[[str], float]:
    """``bounded`` with the range of a pydantic model's field (its ge/gt/le/lt), so that the option
    and the file setting it overrides accept the same values. ``model`` is "module:Class", imported
    only when the option is given: building the parser (`--help`) must not import pydantic."""

    def convert(text: str) -> float:
        module, _, name = model.partition(":")
        info = getattr(importlib.import_module(module), name).model_fields[field]
        kind = int if info.annotation is int else float
        limits = {n: getattr(m, n) for m in info.metadata for n in ("ge", "gt", "le", "lt") if hasattr(m, n)}
        return bounded(kind, limits.get("ge", limits.get("gt")), limits.get("le", limits.get("lt")),
                       lo_open="gt" in limits, hi_open="lt" in limits)(text)

    convert.__name__ = "a number"
    return convert


def outcome_of_checks(flags, allowed: bool, source: str) -> int:
    """List the readings the gross-error checks refused (one line per finding, on stderr; the
    result is already printed, so nothing is lost) and fail unless ``allowed`` (--allow-outliers)."""
    if not flags:
        return 0

    for message in dict.fromkeys(f.message if f.check == "mount" else f"reading {f.row}: {f.message}"
                                 for f in flags):
        err.print(f"[bold yellow]gross error:[/] {message}", markup=True, highlight=False)
    if allowed:
        err.print(f"{len({f.row for f in flags})} reading(s) flagged; accepted (--allow-outliers)")
        return 0
    raise LabcalError(f"{source}: {len({f.row for f in flags})} reading(s) failed the gross-error checks "
                      "(listed above); check or re-measure them, or accept them with --allow-outliers")


def lab_of(option: str | None, create: bool):
    """The lab database a register command reads (``create``: or makes, for an addition)."""
    return labdatabase.open_lab(labdatabase.OpenLab(option, must_exist=not create))


def day_given(text: str | None) -> dt.date:
    """--on DATE, else today on this computer's calendar (a due date is a day where the lab is)."""
    if text is None:
        return dt.datetime.now().astimezone().date()
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise LabcalError(f"--on {text!r}: give a date as YYYY-MM-DD") from None


def register_write(args: argparse.Namespace, write: Callable[[Any, str, Any], Any], fields: Any, *,
                   create: bool, said: Callable[[Any, Any], str]) -> int:
    """One register's addition or change (`labcal instrument add|edit`, `labcal standard add|edit`):
    ``write(lab, serial, fields)`` on the lab database, then the row as JSON or ``said(row, lab)``."""
    lab = lab_of(args.db, create)
    try:
        row = write(lab, args.serial, fields)
    finally:
        lab.close()
    if args.json:
        print_json(row.to_json())
    else:
        out.print(said(row, lab), markup=False)
    return 0
