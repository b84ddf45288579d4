"""The closed forms and groupings that make a million-row fit fast, against the general code."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from labcal.analysis.kinematics import gravity, nominal_gravity
from labcal.analysis.replication import point_groups


def test_nominal_gravity_in_closed_form_is_the_chain_with_no_misalignment():
    rng = np.random.default_rng(2)
    angles = rng.uniform(-2 * np.pi, 2 * np.pi, (4, 500))
    assert np.max(np.abs(nominal_gravity(*angles) - gravity(*angles))) < 1e-15
    mounts = np.radians([[0, 0], [180, 0], [0, 180], [180, 180]])
    for y, u in mounts:
        assert np.max(np.abs(nominal_gravity(*angles[:2], y, u) - gravity(*angles[:2], y, u))) < 1e-15


def test_point_groups_number_the_distinct_rows_as_numpy_unique_does():
    rng = np.random.default_rng(3)
    keys = rng.integers(-3, 3, (2000, 4)).astype(float) * 30.0
    inverse, n = point_groups(keys)
    expected_unique, expected_inverse = np.unique(keys, axis=0, return_inverse=True)
    assert n == len(expected_unique) and np.array_equal(inverse, expected_inverse.ravel())


def _fit_and_volts(tmp_path, rows: int):
    """A fit of a simulated instrument, and a voltages CSV of ``rows`` rows (one at pitch 90°)."""
    import json as _json

    readings = tmp_path / "r.csv"
    subprocess.run([sys.executable, "-m", "labcal.cli", "simulate", "--noise", "1e-5", "--out",
                    str(readings)], check=True, capture_output=True)
    fit = subprocess.run([sys.executable, "-m", "labcal.cli", "fit", str(readings), "--json"], check=True,
                         capture_output=True, text=True).stdout
    (tmp_path / "fit.json").write_text(fit)
    x = np.array(_json.loads(fit)["coefficients"])
    rng = np.random.default_rng(5)
    p, r = rng.uniform(-1.4, 1.4, rows), rng.uniform(-3, 3, rows)
    p[0], r[0] = np.pi / 2, 0.0
    v = x[0] + nominal_gravity(p, r, 0, 0) @ x[1:]
    np.savetxt(tmp_path / "v.csv", v, delimiter=",", header="vx,vy,vz", comments="", fmt="%.12g")
    return tmp_path / "fit.json", tmp_path / "v.csv"


def test_attitude_streams_json_and_csv_that_say_what_the_rows_say(tmp_path):
    import json as _json

    fit, volts = _fit_and_volts(tmp_path, 25_001)  # more than two chunks
    base = [sys.executable, "-m", "labcal.cli", "attitude", "--cert", str(fit), "--csv", str(volts)]
    doc = _json.loads(subprocess.run([*base, "--json"], check=True, capture_output=True, text=True).stdout)
    lines = subprocess.run(base, check=True, capture_output=True, text=True).stdout.splitlines()
    assert len(doc["rows"]) == 25_001 and len(lines) == 25_002
    header = lines[0].split(",")
    first, last = dict(zip(header, lines[1].split(","), strict=True)), lines[-1].split(",")
    assert first["cf_roll_deg"] == "" and doc["rows"][0]["closed_form"]["roll_deg"] is None
    assert "roll is undefined" in doc["rows"][0]["closed_form"]["roll_note"]
    row = doc["rows"][-1]["sphere_least_squares"]
    assert last[0] == "25001" and float(last[header.index("ls_pitch_deg")]) == pytest.approx(row["pitch_deg"],
                                                                                             rel=1e-8)


def test_a_closed_pipe_ends_quietly(tmp_path):
    fit, volts = _fit_and_volts(tmp_path, 50_000)
    labcal = str(Path(sys.executable).with_name("labcal"))
    proc = subprocess.run(f"'{labcal}' attitude --cert '{fit}' --csv '{volts}' | head -2", shell=True,
                          capture_output=True, text=True, timeout=120)
    assert len(proc.stdout.splitlines()) == 2 and proc.stderr == "", proc.stderr
