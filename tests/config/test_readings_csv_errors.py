"""The readings reader: clean files at numpy speed, and for every bad row the same one line as
row by row (file, line, column, what is wrong) — never a traceback."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.config.readings_csv import read_readings
from labcal.errors import LabcalError

HEADER = "replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz,note"
GOOD = "1,0,0,{p},0,0.1,0.2,5.0,7"


def write(tmp_path, *rows: str, header: str = HEADER):
    path = tmp_path / "r.csv"
    path.write_text("\n".join([header, *rows]) + "\n", encoding="utf-8")
    return path


def rows(n: int) -> list[str]:
    return [GOOD.format(p=i % 90) for i in range(n)]


@pytest.mark.parametrize(("bad", "message"), [
    ("1,0,0,5,0,,0.2,5.0,7", "line 5, column vx: empty; every point needs a value here"),
    ("1,0,0,5,0,abc,0.2,5.0,7", "line 5, column vx: 'abc' is not a number"),
    ("1,0,0,5,0,nan,0.2,5.0,7", "line 5, column vx: value is nan; remove or re-measure this point"),
    ("1,0,0,5,0,0.1,0.2,5.0", "line 5: 8 fields, the header has 9"),
    ("1,90,0,5,0,0.1,0.2,5.0,7", "line 5, column y_deg: 90 is not a mount angle (0 or 180)"),
    ("1,0,0,400,0,0.1,0.2,5.0,7", "line 5, column pitch_deg: 400° is outside -360..360"),
    ("1.5,0,0,5,0,0.1,0.2,5.0,7", "line 5, column replicate: 1.5 is not a whole number ≥ 1"),
    ('1,0,0,5,0,"0.1",0.2,5.0,#', None),  # quoted and odd, but valid: read row by row
])
def test_a_bad_row_is_one_line_naming_file_line_and_column(tmp_path, bad, message):
    path = write(tmp_path, *rows(3), bad, *rows(2))
    if message is None:
        assert len(read_readings(path)) == 6
        return
    with pytest.raises(LabcalError) as exc:
        read_readings(path)
    assert str(exc.value) == f"{path}: {message}"


def test_blank_lines_do_not_shift_the_line_a_bad_row_is_reported_on(tmp_path):
    path = write(tmp_path, *rows(2), "", "  ", "1,0,45,5,0,0.1,0.2,5.0,7")
    with pytest.raises(LabcalError, match=r": line 6, column u_deg: 45 is not a mount angle"):
        read_readings(path)
    assert len(read_readings(write(tmp_path, *rows(2), "", *rows(1)))) == 3


def test_a_field_over_the_csv_limit_is_one_line_not_a_crash(tmp_path):
    path = write(tmp_path, *rows(2), "1,0,0,5,0,0.1,0.2,5.0," + "9" * 200_000)
    with pytest.raises(LabcalError, match=r": line 4: field larger than field limit \(131072\)"):
        read_readings(path)


def test_the_fast_and_the_row_by_row_reader_agree_bit_for_bit(tmp_path):
    rng = np.random.default_rng(4)
    volts = rng.normal(0, 5, (200, 3)).tolist()
    lines = [f"{1 + i % 2},{180 * (i % 2)},0,{rng.integers(-180, 180)},{rng.integers(-360, 360)},"
             f"{volts[i][0]!r},{volts[i][1]!r},{volts[i][2]!r},x" for i in range(200)]
    fast = read_readings(write(tmp_path, *[ln[:-1] + "1" for ln in lines]))  # numeric last column
    slow = read_readings(write(tmp_path, *lines))  # 'x' in the last column: numpy refuses, row by row
    for name in ("replicate", "y_deg", "u_deg", "pitch_deg", "roll_deg", "volts"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name))
    assert np.array_equal(fast.volts, volts)


def test_a_replicate_number_beyond_any_lab_is_one_line(tmp_path):
    """1e300 is a whole number ≥ 1, but no replicate: it was cast to a garbage integer (found by the
    hostile-files fuzz as a RuntimeWarning)."""
    from labcal.config.readings_csv import read_readings
    from labcal.errors import LabcalError

    path = tmp_path / "r.csv"
    path.write_text("replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz\n1,0,0,0,0,0.1,0.2,1\n"
                    "1e300,0,0,10,0,0.1,0.2,1\n")
    with pytest.raises(LabcalError, match=r"line 3, column replicate: 1e\+300 is beyond any replicate"):
        read_readings(path)
