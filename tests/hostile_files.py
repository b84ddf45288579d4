"""Hostile versions of every kind of file labcal reads, and the check every parser must pass.

Each case starts from a valid file of its kind and makes it hostile in one way a file from
elsewhere can be: nested hundreds deep, a number at or beyond what a float holds (a 400-digit
integer, infinity, NaN, a subnormal), a huge string, a wrong type, random bytes, cut short. The
parser must either accept the file or raise `LabcalError` with one line — never another
exception. Shared by `test_hostile_files.py` (hypothesis drives it) and by the figures in the
issue's note (a plain loop over the same mutations, run against older checkouts too).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

EXTREMES = ("1e308", "-1e308", "1e309", "inf", "-inf", "nan", "5e-324", "-0.0", "0", "-1",
            "9" * 400, "-" + "9" * 400, '"x"', "[]", "{}", "true", '"' + "A" * 5000 + '"')


def deep_toml(depth: int) -> str:
    return "[" * depth + "]" * depth


def deep_json(depth: int) -> str:
    return "[" * depth + "]" * depth


def mutate_toml(text: str, choice: int, depth: int, where: int) -> str:
    """One hostile change to a TOML document: ``choice`` picks the kind, ``where`` the place."""
    values = [m for m in re.finditer(r"(?m)^(\s*[A-Za-z_][\w.-]*\s*=\s*)(.+)$", text)]
    kind = choice % 6
    if kind == 5 or not values:  # cut short anywhere
        return text[: where % (len(text) + 1)]
    m = values[where % len(values)]
    if kind == 0:
        new = deep_toml(depth)
    elif kind == 1:
        new = "{ a = " * depth + "1" + " }" * depth
    elif kind == 2:
        new = EXTREMES[where % len(EXTREMES)]
    elif kind == 3:
        new = "[" + ", ".join([EXTREMES[where % len(EXTREMES)]] * 3) + "]"
    else:
        new = '"' + "\\u0000" * (where % 7) + "$\\\\frac{" * (where % 5) + '"'
    return text[: m.start(2)] + new + text[m.end(2):]


def mutate_json(text: str, choice: int, depth: int, where: int) -> str:
    """One hostile change to a JSON document (numbers, arrays and strings replaced in place)."""
    values = list(re.finditer(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|\"[^\"]*\"", text))
    kind = choice % 6
    if kind == 5 or not values:
        return text[: where % (len(text) + 1)]
    m = values[where % len(values)]
    if kind == 0:
        new = deep_json(depth)
    elif kind == 1:
        new = '{"a": ' * depth + "1" + "}" * depth
    elif kind == 2:
        new = ("1e999", "-1e999", "NaN", "Infinity", "-Infinity", "9" * 400, "5e-324", "0", "null",
               "[]", "{}", '"x"')[where % 12]
    elif kind == 3:
        new = json.dumps("x" * (where % 100_000))
    else:
        new = "[" + ",".join(["1e308"] * (where % 50)) + "]"
    return text[: m.start()] + new + text[m.end():]


def mutate_csv(text: str, choice: int, depth: int, where: int) -> str:
    """One hostile change to a readings CSV (its field-length limit is another issue's)."""
    lines = text.splitlines()
    kind = choice % 4
    if kind == 3:
        return text[: where % (len(text) + 1)]
    row = 1 + where % max(1, len(lines) - 1)
    cells = lines[row].split(",") if row < len(lines) else []
    if not cells:
        return text
    col = where % len(cells)
    cells[col] = (("1e308", "-1e308", "1e999", "inf", "nan", "9" * 400, "5e-324", "", "x", "-0")[depth % 10]
                  if kind in (0, 1) else "1" * (depth % 5000))
    lines[row] = ",".join(cells)
    return "\n".join(lines) + "\n"


def one_line_or_accepted(parse: Callable[[Path], object], path: Path) -> str:
    """Parse ``path``: "ok", or "refused" when LabcalError says one line; anything else raises."""
    from labcal.errors import LabcalError

    try:
        parse(path)
    except LabcalError as exc:
        message = str(exc)
        assert message and "\n" not in message.strip(), message
        return "refused"
    return "ok"
