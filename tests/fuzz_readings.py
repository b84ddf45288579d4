"""Fuzzed readings files: one valid readings CSV changed in one or two of the ways a file from a
bench, a spreadsheet or a script goes wrong — a cell made hostile (`hostile_files.mutate_csv`), a
handful of rows left, every row at one attitude or one mount, constant or identical voltages (S
singular), a channel copied onto another, a constant or missing temperature (a zero regressor),
voltages scaled out of range, columns renamed or reordered, rows shuffled, cut or repeated.

Each file is made from a seeded generator, so a failure names the seed that rebuilds it. Shared
by `test_fuzz_readings.py` (fast and slow) and usable from a shell to count outcomes.
"""

from __future__ import annotations

import numpy as np
from hostile_files import mutate_csv

VOLTS = ("vx", "vy", "vz")


def _table(text: str) -> tuple[list[str], list[list[str]]]:
    lines = [line for line in text.splitlines() if line.strip()]
    return lines[0].split(","), [line.split(",") for line in lines[1:]]


def _text(header: list[str], rows: list[list[str]], newline: str = "\n") -> str:
    return newline.join([",".join(header), *(",".join(r) for r in rows)]) + newline


def _column(header: list[str], rows: list[list[str]], name: str, values) -> None:
    if name not in header:
        header.append(name)
        for r in rows:
            r.append("")
    k = header.index(name)
    for r, v in zip(rows, values, strict=False):
        while len(r) <= k:
            r.append("")
        r[k] = v if isinstance(v, str) else f"{v:.17g}"


def _mutate(rng: np.random.Generator, header: list[str], rows: list[list[str]]) -> tuple[list[str],
                                                                                         list[list[str]]]:
    """One structural change; the table's rows are lists of cells."""
    n = len(rows)
    kind = int(rng.integers(14))
    if n == 0:  # nothing left to change
        return header, rows
    if kind == 0:  # a few rows left (0 to 8), maybe repeated
        keep = rng.integers(0, n, int(rng.integers(0, 9)))
        rows = [list(rows[i]) for i in keep]
    elif kind == 1:  # identical voltages on every row
        v = rows[int(rng.integers(n))][5:8] if rng.random() < 0.5 else ["0", "0", "0"]
        for r in rows:
            r[5:8] = v
    elif kind == 2:  # one channel constant (dead or saturated)
        j = 5 + int(rng.integers(3))
        value = rng.choice(["0", "10.5", "-10.5", rows[0][j]])
        for r in rows:
            r[j] = value
    elif kind == 3:  # a channel copied onto another (two inputs on one sensor)
        a, b = rng.choice(3, 2, replace=False) + 5
        for r in rows:
            r[b] = r[a]
    elif kind == 4:  # every row at one attitude (and maybe one mount)
        src = rows[int(rng.integers(n))]
        cols = [3, 4] + ([1, 2] if rng.random() < 0.5 else [])
        for r in rows:
            for c in cols:
                r[c] = src[c]
    elif kind == 5:  # a temperature column: constant, random, empty somewhere, or one value off
        how = int(rng.integers(4))
        values = ([20.0] * n if how == 0 else list(rng.normal(20, 2, n)) if how == 1
                  else [("" if i == n // 2 else 20.0 + i * 1e-3) for i in range(n)] if how == 2
                  else [20.0] * (n - 1) + [float(rng.choice([1e308, -273.15, 1e6]))])
        _column(header, rows, "temp_c", values)
    elif kind == 6:  # voltages scaled: microvolts, kilovolts, beyond a float
        scale = float(rng.choice([1e-9, 1e-3, 1e3, 1e12, 1e300, -1.0, 0.0]))
        for r in rows:
            r[5:8] = [f"{float(v) * scale:.17g}" if _is_number(v) else v for v in r[5:8]]
    elif kind == 7:  # mounts changed: all one, random, or angles that are not mounts
        for r in rows:
            r[1] = str(rng.choice(["0", "180", "90", "360", "-180"]))
            r[2] = str(rng.choice(["0", "180"])) if rng.random() < 0.9 else "45"
    elif kind == 8:  # replicate numbers: random small, huge, zero, fractional
        for r in rows:
            r[0] = str(rng.choice(["1", "2", "3", "0", "1.5", "1e9", "99999999999"],
                                  p=[0.3, 0.3, 0.3, 0.025, 0.025, 0.025, 0.025]))
    elif kind == 9:  # columns reordered, one renamed, or an extra one
        order = list(rng.permutation(len(header)))
        header = [header[i] for i in order]
        rows = [[r[i] if i < len(r) else "" for i in order] for r in rows]
        if rng.random() < 0.3:
            header[int(rng.integers(len(header)))] += "_x"
        if rng.random() < 0.3:
            header.append("note")
            for r in rows:
                r.append('"a, b"')
    elif kind == 10:  # rows shuffled, repeated or cut
        rows = [list(rows[i]) for i in rng.permutation(n)]
        if rng.random() < 0.5:
            rows = rows + [list(r) for r in rows[: int(rng.integers(n + 1))]]
        else:
            rows = rows[: int(rng.integers(n + 1))]
    elif kind == 11:  # pitch and roll out of their range or off the grid
        for r in rng.choice(n, int(rng.integers(1, 4))):
            rows[r][3 + int(rng.integers(2))] = str(rng.choice(["400", "-361", "90", "89.9999", "1e-300"]))
    elif kind == 12:  # noise or outliers on the voltages
        sd = float(rng.choice([1e-6, 1e-3, 0.1, 1.0]))
        for r in rows:
            if _is_number(r[5]) and rng.random() < 0.5:
                r[5 + int(rng.integers(3))] = f"{float(r[5]) + rng.normal(0, sd):.17g}"
    else:  # pitch ±90° everywhere (roll undefined), or sensitivities collinear
        for r in rows:
            if rng.random() < 0.5:
                r[3] = str(rng.choice(["90", "-90"]))
            r[7] = r[5] if rng.random() < 0.5 else r[7]
    return header, rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def fuzzed_readings(base: str, seed: int) -> str:
    """The readings file ``base`` changed in one or two ways chosen by ``seed`` (a hostile cell
    one time in four)."""
    rng = np.random.default_rng(seed)
    header, rows = _table(base)
    for _ in range(int(rng.integers(1, 3))):
        header, rows = _mutate(rng, header, rows)
    text = _text(header, rows, "\r\n" if rng.random() < 0.05 else "\n")
    if rng.random() < 0.25:
        text = mutate_csv(text, int(rng.integers(100)), int(rng.integers(1, 5000)), int(rng.integers(10**6)))
    return text


FIT_OPTIONS = ([], ["--model", "linear"], ["--model", "coning"], ["--model", "device"],
               ["--extend", "temperature"], ["--extend", "harmonics"], ["--extend", "temperature,harmonics"],
               ["--test-extensions"], ["--at", "10,20"], ["--allow-outliers"])


def fit_options(seed: int) -> list[str]:
    return list(FIT_OPTIONS[seed % len(FIT_OPTIONS)])
