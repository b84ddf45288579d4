"""The lab's own certificate numbers (the lab file's ``[laboratory] certificate_number``, e.g.
``"{lab}-{year}-{seq:04d}"``): a Python format string over four fields — ``seq`` the lab-wide
sequence number (required; counted anew each calendar year where the format names ``year``, else
never reset, so that no two certificates share a number), ``year`` the calibration's year, ``lab``
the laboratory's code, ``serial`` the instrument's serial.
"""

from __future__ import annotations

from string import Formatter

FIELDS = ("lab", "year", "seq", "serial")


def fields_of(pattern: str) -> set[str]:
    return {name for _, name, _, _ in Formatter().parse(pattern) if name is not None}


def number_problem(pattern: str, code: str) -> str | None:
    """Why ``pattern`` makes no certificate number (None: it does)."""
    try:
        named = fields_of(pattern)
    except ValueError as exc:  # an unmatched brace
        return f"not a format ({exc})"
    unknown = sorted(named - set(FIELDS))
    if unknown:
        return f"unknown field(s) {', '.join('{' + n + '}' for n in unknown)}; the fields are " + \
            ", ".join("{" + n + "}" for n in FIELDS)
    if "seq" not in named:
        return ("it needs {seq}, the lab's sequence number (e.g. {seq:04d}), or two certificates share a "
                "number")
    if "lab" in named and not code:
        return "{lab} is the laboratory's code: set code = \"…\" under [laboratory]"
    try:
        sample = number(pattern, code, 2026, 1, "ACC-0042")
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        return f"not a format ({exc})"
    if not sample.isprintable() or not sample.strip() or "/" in sample:
        return f"makes {sample!r}, which is not a certificate number (one printable line, no /)"
    return None


def number(pattern: str, code: str, year: int, seq: int, serial: str) -> str:
    return pattern.format(lab=code, year=year, seq=seq, serial=serial)


def scope(pattern: str, year: int) -> int:
    """The sequence a number is counted in: the year's where the format names ``year``, else one (0)."""
    return year if "year" in fields_of(pattern) else 0
