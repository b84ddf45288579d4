"""`labcal fit` for instruments that do not speak volts: --units V|mV|counts|m/s2, or
the readings file's "# units = …" line or units column. Sensitivities are then per g in those
units, only volts are held to a DMM's range, and an out-of-range volt names --units.

The reference is the simulated truth (B = 0, S = I in V/g, noise 0: `labcal simulate`), scaled
here to each unit by hand: 16384 counts/g (a ±2 g 16-bit IMU), 1000 mV/V, 9.80665 m/s² per g."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from labcal.cli import main


@pytest.fixture(scope="module")
def exact(tmp_path_factory):
    """Noise-free readings of the ideal instrument, as rows of cells."""
    path = tmp_path_factory.mktemp("units") / "exact.csv"
    assert main(["simulate", "--noise", "0", "--out", str(path)]) == 0
    return list(csv.reader(path.read_text().splitlines()))


def _scaled(rows, tmp_path, scale: float, comment: str | None = None, column: str | None = None) -> str:
    lines = [comment] if comment else []
    lines.append(",".join(rows[0] + (["units"] if column else [])))
    for r in rows[1:]:
        lines.append(",".join(r[:5] + [repr(float(v) * scale) for v in r[5:8]] + r[8:]
                              + ([column] if column else [])))
    path = tmp_path / "scaled.csv"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _fit(capsys, *args) -> tuple[int, dict, str]:
    code = main(["fit", *args, "--model", "linear", "--json"])
    captured = capsys.readouterr()
    return code, (json.loads(captured.out) if captured.out else {}), captured.err


@pytest.mark.parametrize("units,scale,how", [
    ("counts", 16384.0, "option"), ("counts", 16384.0, "column"),
    ("mV", 1000.0, "comment"), ("m/s2", 9.80665, "option"), ("m/s2", 9.80665, "comment"),
])
def test_sensitivities_are_per_g_in_the_units(exact, tmp_path, capsys, units, scale, how):
    path = _scaled(exact, tmp_path, scale, f"# units = {units}" if how == "comment" else None,
                   units if how == "column" else None)
    code, doc, err = _fit(capsys, path, *(["--units", units] if how == "option" else []))
    assert code == 0, err
    X = np.array(doc["coefficients"])
    assert doc["units"] == units
    assert np.max(np.abs(X[0])) < 1e-9 * scale  # B = 0
    assert np.max(np.abs(X[1:] - scale * np.eye(3))) < 1e-9 * scale  # S = scale · I per g


def test_the_console_table_names_the_units(exact, tmp_path, capsys):
    path = _scaled(exact, tmp_path, 1000.0, "# units: millivolts")
    assert main(["fit", path, "--model", "linear"]) == 0
    text = capsys.readouterr().out
    assert "B (mV)" in text and "S_x (mV/g)" in text and "S_E (mV)" in text and "(V/g)" not in text


def test_counts_read_as_volts_are_refused_naming_units(exact, tmp_path, capsys):
    path = _scaled(exact, tmp_path, 16384.0)
    code, _, err = _fit(capsys, path)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "V is beyond any DMM range (|V| ≤ 1000 V)" in err and "give --units (mV, counts, m/s2)" in err


def test_the_dmm_range_holds_for_millivolts_only_as_volts(exact, tmp_path, capsys):
    path = _scaled(exact, tmp_path, 2e6, "# units = mV")  # 2000 V written in mV
    code, _, err = _fit(capsys, path)
    assert code == 2 and "mV is beyond any DMM range (|V| ≤ 1000 V)" in err and "--units" in err


@pytest.mark.parametrize("args,column,expected", [
    (["--units", "mV"], "counts", "the file states its outputs in counts, --units says mV"),
    (["--units", "furlongs"], None, "argument --units: units 'furlongs' is not one of V, mV, counts, m/s2"),
    ([], "parsecs", "column units: units 'parsecs' is not one of V, mV, counts, m/s2"),
])
def test_unit_mistakes_are_one_line(exact, tmp_path, capsys, args, column, expected):
    path = _scaled(exact, tmp_path, 16384.0, None, column)
    code, _, err = _fit(capsys, path, *args)
    assert code == 2 and expected in err and len(err.strip().splitlines()) == 1, err


def test_a_file_stating_two_units_is_refused(exact, tmp_path, capsys):
    path = _scaled(exact, tmp_path, 16384.0, "# units = mV", "counts")
    code, _, err = _fit(capsys, path)
    assert code == 2 and "states more than one unit (counts, mV)" in err


def test_comment_lines_keep_the_line_numbers_of_errors(exact, tmp_path, capsys):
    rows = [list(r) for r in exact]
    rows[3][4] = "400"  # the third data row: line 5 with one comment line before the header
    path = _scaled(rows, tmp_path, 1000.0, "# units = mV")
    code, _, err = _fit(capsys, path)
    assert code == 2 and f"{path}: line 5, column roll_deg: 400° is outside -360..360" in err


def test_a_residual_is_stated_in_the_units(tmp_path, capsys):
    path = tmp_path / "noisy.csv"
    assert main(["simulate", "--noise", "1e-4", "--seed", "3", "--out", str(path)]) == 0
    rows = list(csv.reader(path.read_text().splitlines()))
    # 20 σ on sensor x of reading 20 (pitch 0°, roll 270°: x reads 0 g there, so |g| moves by 2e-6 only
    # and the residual check, not the gravity check, sees it)
    rows[20][5] = repr(float(rows[20][5]) + 2e-3)
    path = _scaled(rows, tmp_path, 16384.0, "# units = counts")
    code, doc, err = _fit(capsys, path)
    assert code == 2 and [f["row"] for f in doc["gross_errors"]] == [20]
    import re

    # 2e-3 V × 16384 counts/V = 32.8 counts, less the share the fit takes (leverage ~4/64) and noise
    match = re.search(r"reading 20: sensor x: residual \+([\d.]+) counts is", err)
    assert match and 25 < float(match[1]) < 35, err
