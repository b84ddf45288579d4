"""Angle options take their unit where a slip between degrees and arcseconds is likely: `7.5arcsec`,
`7.5"` and `0.002deg` are taken as written, and a bare number far above any attitude U95 a calibration
reaches (7.5, meant as 7.5″) is refused in one line that names the slip, before anything runs.
Through the command line; every expected value converted here by hand (1″ = 1/3600°)."""

from __future__ import annotations

import json

import pytest
from test_instruments import InProcess


@pytest.fixture
def lc(capsys) -> InProcess:
    return InProcess(capsys)


@pytest.mark.parametrize("command", [["plan", "optimize", "--target-attitude-u95-deg"],
                                     ["run", "--sim", "--yes", "--tolerance-deg"],
                                     ["report", "run-folder", "--tolerance-deg"]])
def test_a_bare_number_meant_as_arcseconds_is_refused_in_one_line_naming_the_slip(lc, tmp_path, command):
    done = lc(*command, "7.5", check=2)
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "7.5 is read as 7.5° (27000″)" in done.stderr and "write 7.5arcsec (= 0.00208°)" in done.stderr
    assert not (tmp_path / "runs").exists()  # the run never started


def test_an_angle_in_arcseconds_reaches_the_optimizer_in_degrees(lc):
    done = lc("plan", "optimize", "--target-attitude-u95-deg", "7.5arcsec", "--json")
    assert json.loads(done.stdout)["target_u95_deg"] == pytest.approx(7.5 / 3600, rel=1e-12)


@pytest.mark.parametrize(("given", "degrees"), [
    ('7.5"', 7.5 / 3600), ("7.5″", 7.5 / 3600), ("0.002deg", 0.002), ("0.002°", 0.002), ("0.002", 0.002),
    ("0.25arcmin", 0.25 / 60), ("40urad", 40e-6 * 180 / 3.141592653589793), ("1", 1.0)])
def test_each_unit_of_angle_is_taken_in_degrees(given, degrees):
    from labcal.commands.common import angle_deg

    assert angle_deg(90)(given) == pytest.approx(degrees, rel=1e-12)


@pytest.mark.parametrize(("given", "said"), [("7.5x", "'x' is not a unit of angle"),
                                             ("0arcsec", "out of range"), ("-1deg", "out of range"),
                                             ("seven", "is not an angle")])
def test_a_bad_angle_is_one_line(lc, given, said):
    done = lc("plan", "optimize", f"--target-attitude-u95-deg={given}", check=2)
    assert said in done.stderr and done.stderr.count("\n") == 1
