"""The closed forms and groupings that make a million-row fit fast, against the general code."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli import cli, in_process

from labcal.analysis.kinematics import gravity, nominal_gravity
from labcal.analysis.replication import distinct, point_groups


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


@pytest.mark.parametrize("column", [
    np.array([3, 1, 4, 1, 5, 9, 2, 6]),  # small whole numbers: counted, not sorted
    np.array([7, 7, 7]),
    np.array([-2, 5, -2, 0]),  # negative: sorted
    np.array([1, 10**12, 1]),  # beyond the counting range: sorted
    np.array([0.5, -1.0, 0.5, 3.0]),  # not whole numbers: sorted
    np.array([], dtype=np.int64),
])
def test_distinct_values_and_their_indices_are_numpy_uniques(column):
    values, index = distinct(column)
    expected_values, expected_index = np.unique(column, return_inverse=True)
    assert np.array_equal(values, expected_values) and np.array_equal(index, expected_index.ravel())


def _fit_and_volts(tmp_path, rows: int):
    """A fit of a simulated instrument, and a voltages CSV of ``rows`` rows (one at pitch 90°)."""
    import json as _json

    readings = tmp_path / "r.csv"
    code, _, err = in_process("simulate", "--noise", "1e-5", "--out", str(readings))
    assert code == 0, err
    code, fit, err = in_process("fit", str(readings), "--json")
    assert code == 0, err
    (tmp_path / "fit.json").write_text(fit)
    x = np.array(_json.loads(fit)["coefficients"])
    rng = np.random.default_rng(5)
    p, r = rng.uniform(-1.4, 1.4, rows), rng.uniform(-3, 3, rows)
    p[0], r[0] = np.pi / 2, 0.0
    v = x[0] + nominal_gravity(p, r, 0, 0) @ x[1:]
    np.savetxt(tmp_path / "v.csv", v, delimiter=",", header="vx,vy,vz", comments="", fmt="%.12g")
    return tmp_path / "fit.json", tmp_path / "v.csv"


def test_attitude_streams_json_and_csv_that_say_what_the_rows_say(tmp_path, capsys):
    import json as _json

    fit, volts = _fit_and_volts(tmp_path, 25_001)  # more than two chunks
    base = ["attitude", "--cert", str(fit), "--csv", str(volts)]
    code, out, err = cli(capsys, *base, "--json")
    assert code == 0, err
    doc = _json.loads(out)
    code, out, err = cli(capsys, *base)
    assert code == 0, err
    lines = out.splitlines()
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


def _replicated_readings(seed: int, replicates: int = 3):
    """Noisy readings of a four-mount grid, rows shuffled, some angles written +360° (same point)."""
    from labcal.analysis.readings import Readings

    rng = np.random.default_rng(seed)
    pitch, roll = (a.ravel() for a in np.meshgrid(np.arange(-150.0, 180, 60), np.arange(-180.0, 180, 45)))
    mounts = np.array([[0, 0], [180, 0], [0, 180], [180, 180]], float)
    rows = np.array([(r, y, u, p, q) for r in range(1, replicates + 1) for y, u in mounts
                     for p, q in zip(pitch, roll, strict=True)])
    rows = rows[rng.permutation(len(rows))]
    rows[::7, 3] += 360.0
    g = nominal_gravity(*np.radians(rows[:, [3, 4, 1, 2]]).T)
    X = np.vstack([[0.01, -0.02, 0.03], 5 * np.eye(3) + rng.normal(0, 0.01, (3, 3))])
    bias = 2e-3 * np.sin(3 * np.radians(rows[:, 3:4]))  # a lack of fit the replicates reveal
    volts = X[0] + g @ X[1:] + bias + rng.normal(0, 2e-5, (len(rows), 3))
    return Readings(rows[:, 0].astype(int), rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], volts)


def test_the_fit_on_point_means_is_the_fit_on_every_reading():
    """The point-means fit against the general one on every reading (QR of the full design,
    replication analysis on it): the same normal equations, so equal to rounding; 1e-6 of a
    standard error and 1e-12 V are far below any digit a certificate states."""
    from labcal.analysis.fit import fit_readings, readings_points
    from labcal.analysis.models import Model
    from labcal.analysis.regression import least_squares
    from labcal.analysis.replication import analyse

    readings = _replicated_readings(5)
    fit = fit_readings(readings)
    _, design = Model().design(readings_points(readings))
    every = least_squares(design, readings.volts)
    assert np.all(np.abs(fit.ls.coef - every.coef) <= 1e-6 * every.stderr)
    assert np.allclose(fit.ls.cov_unscaled, every.cov_unscaled, rtol=1e-9,
                       atol=1e-12 * np.max(np.diag(every.cov_unscaled)))  # zeros off the diagonal
    assert np.max(np.abs(fit.ls.residuals - every.residuals)) < 1e-12
    assert fit.ls.dof == every.dof
    groups = point_groups(np.round(np.column_stack([readings.y_deg, readings.u_deg, readings.pitch_deg,
                                                    readings.roll_deg]) % 360, 6))[0]
    assert len(readings.points) == groups.max() + 1 == 6 * 8 * 4
    replication = analyse(design, readings.volts, groups, readings.replicate)
    assert replication is not None and fit.replication is not None
    for name in ("sigma_prec", "sigma_bias", "lack_of_fit_ms"):
        assert np.allclose(getattr(fit.replication, name), getattr(replication, name), rtol=1e-9, atol=0)
    assert fit.replication.lack_of_fit.significant.all()  # the sin 3p bias is seen


def test_point_groups_compare_canonical_values():
    angles = np.array([10.0, 370.0, -350.0, 20.0, 10.0 + 1e-12])
    inverse, n = point_groups([angles], lambda v: np.round(v % 360.0, 9) % 360.0)
    assert n == 2 and list(inverse) == [0, 0, 0, 1, 0]
