"""The readings CSV (docs/design.md §5): one row per calibration point, header required.

Required columns: replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz; optional temp_c;
any other column is ignored on reading. Every error names the file, the line and the column.

A clean file (plain numbers, no quotes, no blank lines) is read by numpy's C parser at numpy
speed; anything that parser refuses, and any row the checks refuse, is read again row by row to
say in one line what is wrong where. The rules are written once, on columns, and applied to all
rows at once or to one row.
"""

from __future__ import annotations

import csv
import io
import math
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.readings import Readings
from labcal.config import files
from labcal.config.files import read_text, write_atomic
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.config import streams
else:
    streams = lazy("labcal.config.streams")  # start-up without 3 more modules

REQUIRED = ("replicate", "y_deg", "u_deg", "pitch_deg", "roll_deg", "vx", "vy", "vz")
OPTIONAL = ("temp_c",)
# Written by labcal after the contract's columns: what a metrologist needs to audit a point.
EXTRA = ("n_samples", "sd_vx", "sd_vy", "sd_vz", "time_s")
ABSOLUTE_ZERO_C, MAX_TEMP_C = -273.15, 1000.0  # a temperature beyond these is a typo or a broken probe
MAX_REPLICATE = 1e9  # no lab repeats a plan a billion times; a larger number is a typo (and no int64)


def _number(text: str, where: str) -> float:
    if not text.strip():
        raise LabcalError(f"{where}: empty; every point needs a value here")
    try:
        value = float(text)
    except ValueError:
        raise LabcalError(f"{where}: {text.strip()!r} is not a number") from None
    if not math.isfinite(value):
        raise LabcalError(f"{where}: value is {text.strip()}; remove or re-measure this point")
    return value


def _check_angles(cols: dict[str, NDArray], where) -> None:
    """Mount angles 0 or 180, table angles within ±360°, whole replicates ≥ 1, on every row of
    ``cols``; the first row that fails raises, ``where(row)`` naming its file and line."""
    def not_a_mount(v: NDArray) -> NDArray:
        return ~np.isin(v % 360, (0.0, 180.0))

    def out_of_range(v: NDArray) -> NDArray:
        return ~((-360.0 <= v) & (v <= 360.0))

    def not_a_replicate(v: NDArray) -> NDArray:
        return (v != np.floor(v)) | (v < 1)

    def not_a_temperature(v: NDArray) -> NDArray:
        return ~((ABSOLUTE_ZERO_C < v) & (v <= MAX_TEMP_C))

    rules = [("y_deg", not_a_mount, "{:g} is not a mount angle (0 or 180)"),
             ("u_deg", not_a_mount, "{:g} is not a mount angle (0 or 180)"),
             ("pitch_deg", out_of_range, "{:g}° is outside -360..360"),
             ("roll_deg", out_of_range, "{:g}° is outside -360..360"),
             ("replicate", not_a_replicate, "{:g} is not a whole number ≥ 1"),
             ("replicate", lambda v: v > MAX_REPLICATE,
              f"{{:g}} is beyond any replicate number (1 to {MAX_REPLICATE:g})")]
    if "temp_c" in cols:  # 1e308 °C overflowed the temperature terms' products
        rules.append(("temp_c", not_a_temperature,
                      f"{{:g}} °C is no temperature a calibration is made at ({ABSOLUTE_ZERO_C:g} < t ≤ "
                      f"{MAX_TEMP_C:g} °C)"))
    # each rule judges a value alone: judged on a column's few distinct values, a clean million-row
    # file passes in a tenth of the time; a column with a bad value is searched row by row
    distinct = {name: np.unique(cols[name]) for name, _, _ in rules}
    firsts = [(int(np.argmax(bad(cols[name]))), k) for k, (name, bad, _) in enumerate(rules)
              if bad(distinct[name]).any()]
    if firsts:
        row, k = min(firsts)
        name, _, message = rules[k]
        raise LabcalError(f"{where(row)}, column {name}: {message.format(cols[name][row])}")


def read_numeric_csv(path: str | Path, kind: str, required: tuple[str, ...], optional: tuple[str, ...] = (),
                     check=None) -> dict[str, NDArray]:
    """Numeric columns of a CSV with a header, by name; other columns are ignored.

    Every error names the file, the line and the column. ``check(columns, where)`` may validate
    the rows further (see `_check_angles`). Lines starting with "#" before the header are comments
    (`read_readings` reads a units entry there).
    """
    return _read_csv(path, kind, required, optional, check).columns


class _Csv:
    """What `_read_csv` read: the wanted columns, the comment lines before the header, the header,
    and the file's text where it was read whole (a pipe, or a file the fast parser refused)."""

    def __init__(self, columns: dict[str, NDArray], comments: list[str], header: list[str], text: str | None):
        self.columns, self.comments, self.header, self.text = columns, comments, header, text


MAX_COMMENT_LINES = 100  # comment lines before the header: a units entry, a note; never a whole file


def _leading_comments(path: Path, text: str | None) -> list[str]:
    """The lines starting with "#" before the header (at most MAX_COMMENT_LINES)."""
    comments: list[str] = []
    try:
        with path.open(encoding="utf-8-sig", newline="") if text is None else io.StringIO(text) as f:
            while len(comments) < MAX_COMMENT_LINES:
                line = f.readline(1 << 16)
                if not line.lstrip().startswith("#"):
                    break
                comments.append(line.rstrip("\r\n"))
    except (OSError, UnicodeDecodeError):
        return []  # the reader below says what is wrong with the file
    return comments


def _read_csv(path: str | Path, kind: str, required: tuple[str, ...], optional: tuple[str, ...] = (),
              check=None, absent: tuple[str, ...] = ()) -> _Csv:
    """``absent``: required columns that may be empty on every row (NaN), never on some rows only: the
    outputs of the sensors a package does not have (Tripp & Tcheng §6)."""
    path = Path(path)
    piped = streams.read_pipe(path, kind) if streams.kind_of(path, kind) == "pipe" else None  # read once
    comments = _leading_comments(path, piped)
    skip = len(comments)
    fast = _read_clean(path, required, optional, piped, skip)
    if fast is not None:
        try:
            if check:
                check(fast[0], lambda row: f"{path}: line {row + 2 + skip}")
            return _Csv(fast[0], comments, fast[1], piped)
        except LabcalError:
            pass  # say it with the exact line (blank lines are skipped above): read row by row

    text = read_text(path, kind) if piped is None else piped
    if not text.strip():
        raise LabcalError(f"{path}: file is empty; expected a header line {','.join(required)}")
    reader = csv.reader(text.splitlines()[skip:])
    try:
        header = [h.strip() for h in next(reader)]
    except csv.Error as exc:
        raise LabcalError(f"{path}: line {1 + skip}: {exc}; is this a readings CSV?") from None
    except StopIteration:
        raise LabcalError(f"{path}: comments only; expected a header line {','.join(required)}") from None
    missing = [c for c in required if c not in header]
    if missing:
        raise LabcalError(
            f"{path}: missing column(s) {', '.join(missing)}; the header must contain {','.join(required)}"
        )
    wanted = required + tuple(c for c in optional if c in header)
    index = {c: header.index(c) for c in wanted}
    rows: list[list[float]] = []
    line_no = 1 + skip
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:  # e.g. a field over the csv module's limit of 131 072 characters
            raise LabcalError(f"{path}: line {line_no + 1}: {exc}; is this a readings CSV?") from None
        line_no = reader.line_num + skip
        if not any(cell.strip() for cell in row):
            continue
        where = f"{path}: line {line_no}"
        if len(row) < len(header):
            raise LabcalError(f"{where}: {len(row)} fields, the header has {len(header)}")
        values = {c: math.nan if c in absent and not row[i].strip() else
                  _number(row[i], f"{where}, column {c}") for c, i in index.items()}
        if check:
            check({c: np.array([v]) for c, v in values.items()}, lambda _, where=where: where)
        rows.append([values[c] for c in wanted])
    if not rows:
        raise LabcalError(f"{path}: header only, no data rows")
    data = np.array(rows)
    for c in absent:  # a sensor a package has not is empty throughout; one it has, nowhere
        empty = np.isnan(data[:, wanted.index(c)])
        if empty.any() and not empty.all():
            k = int(np.argmax(empty)) if empty.sum() < len(empty) / 2 else int(np.argmin(empty))
            raise LabcalError(f"{path}: data row {k + 1}, column {c}: "
                              + ("empty; every point needs a value here" if empty[k] else
                                 "a value, where the column is empty on most rows")
                              + " (a sensor the package has not is empty on every row, one it has on none)")
    return _Csv({c: data[:, k] for k, c in enumerate(wanted)}, comments, header, text)


def _read_clean(path: Path, required: tuple[str, ...], optional: tuple[str, ...], text: str | None = None,
                skip: int = 0) -> tuple[dict[str, NDArray], list[str]] | None:
    """The wanted columns of a clean file by numpy's C parser, or None where it refuses anything
    (a quote, an empty or non-numeric field, a short row, a field too long, bad encoding) or reads
    a value that is not finite: the row-by-row reader then says what and where. The header's last
    column is parsed too, so that a row shorter than the header is refused as it is row by row.
    ``text``: the file's text, already read (from a pipe, which cannot be read twice); ``skip``:
    the comment lines before the header. Returns the columns and the header."""
    try:
        with path.open(encoding="utf-8-sig", newline="") if text is None else io.StringIO(text) as f:
            for _ in range(skip):
                f.readline(1 << 16)
            header = [h.strip() for h in next(csv.reader([f.readline()]))]
        if any(c not in header for c in required):
            return None
        wanted = required + tuple(c for c in optional if c in header)
        columns = sorted({header.index(c) for c in wanted} | {len(header) - 1})
        with warnings.catch_warnings():  # header only: the row-by-row reader says so in one line
            warnings.simplefilter("ignore", UserWarning)
            source = path if text is None else io.StringIO(text)
            data = np.loadtxt(source, delimiter=",", skiprows=1 + skip, usecols=columns, ndmin=2,
                              comments=None, encoding="utf-8-sig", quotechar=None)
    except (OSError, ValueError, UnicodeDecodeError, csv.Error, StopIteration):
        return None
    if not len(data) or not np.isfinite(data).all():
        return None
    return {c: data[:, columns.index(header.index(c))] for c in wanted}, header


UNITS = ("V", "mV", "counts", "m/s2")  # what an instrument's outputs may be read in
_UNIT_SPELLINGS = {"v": "V", "volt": "V", "volts": "V", "mv": "mV", "millivolt": "mV", "millivolts": "mV",
                   "count": "counts", "counts": "counts", "lsb": "counts", "m/s2": "m/s2", "m/s^2": "m/s2",
                   "m/s²": "m/s2", "m s-2": "m/s2"}
_UNITS_COMMENT = re.compile(r"^\s*#\s*units\s*[=:]\s*(.*?)\s*$", re.IGNORECASE)


def coefficient_units(units: str) -> str:
    """The fit JSON's ``layout.units`` for outputs in ``units``: B in them, S in them per g."""
    return f"{units} (bias), {units}/g (sensitivity)"


def unit_named(text: str, where: str) -> str:
    """One of UNITS from how a person writes it ("mV", "millivolts", "m/s^2"); one line otherwise."""
    unit = _UNIT_SPELLINGS.get(text.strip().strip("\"'").lower())
    if unit is None:
        raise LabcalError(f"{where}: units {text.strip()!r} is not one of {', '.join(UNITS)}")
    return unit


def _units_of(path: Path, read: _Csv) -> str | None:
    """The units a readings file states: a "# units = mV" line before the header, or a units
    column (one value throughout); None where it states none. Both must agree."""
    stated: dict[str, str] = {}
    for k, line in enumerate(read.comments):
        match = _UNITS_COMMENT.match(line)
        if match:
            stated[unit_named(match[1], f"{path}: line {k + 1}")] = f"line {k + 1}"
    if "units" in read.header:
        text = read.text if read.text is not None else files.read_text(path, "readings")
        column = read.header.index("units")
        rows = csv.reader(text.splitlines()[len(read.comments) + 1:])
        values = {row[column].strip() for row in rows if len(row) > column and row[column].strip()}
        for value in values:
            stated[unit_named(value, f"{path}: column units")] = "column units"
    if len(stated) > 1:
        raise LabcalError(f"{path}: the file states more than one unit ({', '.join(sorted(stated))}); "
                          "its outputs must all be in one")
    return next(iter(stated), None)


def read_readings(path: str | Path, units: str | None = None) -> Readings:
    """Load and validate a readings CSV; raise LabcalError naming file, line and column.

    The outputs' unit is ``units`` (from --units), else what the file states ("# units = mV" before
    the header, or a units column), else volts; --units and the file must not disagree."""
    read = _read_csv(path, "readings", REQUIRED, OPTIONAL, _check_angles, absent=("vy", "vz"))
    stated = _units_of(Path(path), read)
    if units is not None and stated is not None and units != stated:
        raise LabcalError(f"{path}: the file states its outputs in {stated}, {{0}} says {units}; leave out "
                          "{0} or correct the file", "units")
    cols = read.columns
    windows = _windows(Path(path), read, len(cols["replicate"]))
    return Readings(
        replicate=cols["replicate"].astype(int),
        y_deg=cols["y_deg"], u_deg=cols["u_deg"], pitch_deg=cols["pitch_deg"], roll_deg=cols["roll_deg"],
        volts=np.column_stack([cols["vx"], cols["vy"], cols["vz"]]),
        temp_c=cols.get("temp_c"), units=units or stated or "V",
        window_sd=None if windows is None else windows[0], window_n=None if windows is None else windows[1],
    )


WINDOWS = ("n_samples", "sd_vx", "sd_vy", "sd_vz")  # the audit columns that say how each point scattered


def _windows(path: Path, read: _Csv, rows: int) -> tuple[NDArray, NDArray] | None:
    """Each point's window, from the audit columns labcal writes (the samples' sd per output and their
    number), where every row has them as plain numbers; else None — they are an audit, not the
    contract's columns, so a file whose audit is incomplete is read without them, never refused."""
    if not all(c in read.header for c in WINDOWS):
        return None
    got = _read_clean(path, WINDOWS, (), read.text, len(read.comments))
    if got is None or len(got[0]["n_samples"]) != rows:
        return None
    n, sd = got[0]["n_samples"], np.column_stack([got[0][c] for c in WINDOWS[1:]])
    if np.any(n < 1) or np.any(n != np.floor(n)) or np.any(sd < 0):
        return None
    return sd, n


def write_readings(path: str | Path, readings: Readings) -> None:
    """Write a whole Readings set (used by `labcal simulate`)."""
    with ReadingsWriter(path, temperature=readings.temp_c is not None, audit=False) as writer:
        for i in range(len(readings)):
            writer.append(
                replicate=int(readings.replicate[i]), y_deg=readings.y_deg[i], u_deg=readings.u_deg[i],
                pitch_deg=readings.pitch_deg[i], roll_deg=readings.roll_deg[i], volts=readings.volts[i],
                temp_c=None if readings.temp_c is None else readings.temp_c[i],
            )


class ReadingsWriter:
    """Collects one row per point; on a clean close the whole file is written atomically
    (`write_atomic`), so a reader or a crash never sees a file cut short. The journal, not this
    file, is what keeps a reading: readings.csv is an export of it, rewritten whole.

    ``temperature``: write the temp_c column; ``audit``: write the per-point audit columns.
    """

    def __init__(self, path: str | Path, temperature: bool = True, audit: bool = True):
        self.path = Path(path)
        self.temperature, self.audit = temperature, audit
        self._file = io.StringIO(newline="")
        self._csv = csv.writer(self._file)
        self._csv.writerow(REQUIRED + OPTIONAL * temperature + EXTRA * audit)
        self.count = 0

    def append(
        self, *, replicate: int, y_deg: float, u_deg: float, pitch_deg: float, roll_deg: float,
        volts: Sequence[float | None], temp_c: float | None = None, sd: Sequence[float | None] | None = None,
        n_samples: int | None = None, time_s: float | None = None,
    ) -> None:
        def fmt(x: float | None, spec: str = ".10g") -> str:
            return "" if x is None or (isinstance(x, float) and math.isnan(x)) else format(float(x), spec)

        row = [replicate, fmt(y_deg, "g"), fmt(u_deg, "g"), fmt(pitch_deg, ".17g"), fmt(roll_deg, ".17g"),
               *(fmt(v, ".17g") for v in volts)]
        if self.temperature:
            row.append(fmt(temp_c, ".4f"))
        if self.audit:
            sds = (None, None, None) if sd is None else sd
            row += ["" if n_samples is None else n_samples, *(fmt(s, ".4g") for s in sds), fmt(time_s, ".3f")]
        self._csv.writerow(row)
        self.count += 1

    def text(self) -> str:
        return self._file.getvalue()

    def close(self) -> None:
        write_atomic(self.path, self.text())

    def __enter__(self) -> ReadingsWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:  # a failure half-way writes nothing: the old file stays whole
            self.close()
