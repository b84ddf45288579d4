"""A sensor package's calibration in use: `labcal fit` reads and fits a package's readings, and
`labcal attitude` infers its angles as its certificate states (Tripp & Tcheng §6.1-6.5). Expected
values are made here from the paper's equations written out, never by the code under test."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli import cli

from labcal.analysis.distributions import t_quantile
from labcal.documents.certificate import read_certificate

DEG = math.pi / 180


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A simulated single-axis and x–y package run each, ending in its certificate."""
    from labcal.cli import main

    base = tmp_path_factory.mktemp("package-runs")
    made = {}
    for package in ("single-axis", "two-axis-xy"):
        out = base / package
        assert main(["run", "--sim", "--instrument", package, "--yes", "--out", str(out / "run"), "--db",
                     str(out / "lab.sqlite")]) == 0
        made[package] = out
    return made


def tripp_output(c, axis: str, alpha, roll):
    """Tripp eqs. 2 and 4 written out, from a certificate's [b, S, Ω, A] (degrees)."""
    om, A = c.omega_deg * DEG, c.azimuth_deg * DEG
    if axis == "x":
        return c.b + c.S * (np.cos(om) * np.sin(alpha) - np.sin(om) * np.cos(alpha) * np.sin(roll + A))
    return c.b - c.S * (np.cos(om) * np.sin(roll) * np.cos(alpha)
                        - np.sin(om) * (np.sin(A) * np.sin(alpha) - np.cos(A) * np.cos(roll) * np.cos(alpha)))


def sigma_v(cert, j: int, alpha, roll):
    """σ_v = √(fᵀCf + σ₀²) of sensor j, f = [1, sin α, cos α sin R, cos α cos R] (Tripp eqs. 52, 73)."""
    f = np.array([1.0, np.sin(alpha), np.cos(alpha) * np.sin(roll), np.cos(alpha) * np.cos(roll)])
    C = np.array(cert.fit.covariance[j])[:4, :4]
    return math.sqrt(f @ C @ f + cert.fit.reading_sd[j] ** 2)


def test_labcal_fit_reads_a_packages_readings_and_fits_only_its_sensors(runs, capsys):
    """The run's readings.csv (vy, vz empty on every row) fitted by `labcal fit`: one column, the
    least squares of vx on [1, g] computed here by numpy, and the package's Tripp parameters."""
    import csv

    path = runs["single-axis"] / "run" / "readings.csv"
    code, out, err = cli(capsys, "fit", str(path), "--json")
    assert code == 0, err
    doc = json.loads(out)
    with path.open() as f:
        rows = list(csv.DictReader(f))
    assert all(r["vy"] == "" and r["vz"] == "" for r in rows)
    p, r = (np.radians([float(row[k]) for row in rows]) for k in ("pitch_deg", "roll_deg"))
    y, u = (np.array([float(row[k]) for row in rows]) for k in ("y_deg", "u_deg"))
    # nominal gravity in the instrument's axes: a mount turned half round its z axis (y = 180°)
    # reverses x and y, turned over about x (u = 180°) y and z, of the top-forward mount's
    # [sin p, cos p sin r, cos p cos r]
    g = np.column_stack([np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])
    g = g * np.where(y[:, None] == 180, [-1, -1, 1], 1) * np.where(u[:, None] == 180, [1, -1, -1], 1)
    vx = np.array([float(row["vx"]) for row in rows])
    expected, *_ = np.linalg.lstsq(np.column_stack([np.ones(len(g)), g]), vx, rcond=None)
    assert np.allclose(np.array(doc["coefficients"])[:, 0], expected, atol=1e-9)
    assert doc["layout"]["columns"] == ["sensor x"] and doc["package"]["package"] == "single-axis"
    s = expected[1:]
    assert doc["package"]["sensors"]["x"]["S"] == pytest.approx(np.linalg.norm(s), rel=1e-9)
    # Ω: the angle between the sensor's axis and x (Tripp §2.2's coning angle)
    assert doc["package"]["sensors"]["x"]["omega_deg"] == pytest.approx(
        np.degrees(np.arccos(s[0] / np.linalg.norm(s))), abs=1e-6)


def test_a_package_readings_column_empty_on_some_rows_only_is_refused_in_one_line(runs, tmp_path, capsys):
    lines = (runs["single-axis"] / "run" / "readings.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[3].split(",")
    cells[header.index("vy")] = "0.5"
    lines[3] = ",".join(cells)
    bad = tmp_path / "readings.csv"
    bad.write_text("\n".join(lines) + "\n")
    code, _, err = cli(capsys, "fit", str(bad))
    assert code == 2 and err.count("\n") == 1 and "column vy" in err and "Traceback" not in err


def test_attitude_of_a_single_axis_package_at_a_measured_roll_follows_eqs_79_and_81(runs, tmp_path, capsys):
    """Outputs made by eq. 2 with the certificate's own [b, S, Ω, A] at known pitch and roll: pitch
    comes back, and its U95 is k times eq. 81 (σ_v from the certificate's covariance, σ_R given)."""
    run = runs["single-axis"]
    cert = read_certificate(run / "run" / "certificate.json")
    c = cert.package.coefficients["x"]
    alpha = np.radians([-40.0, -5.0, 0.0, 25.0, 55.0])
    roll, sigma_r = 35 * DEG, 0.2 * DEG
    outputs = tripp_output(c, "x", alpha, roll)
    (tmp_path / "v.csv").write_text("vx\n" + "".join(f"{float(v)!r}\n" for v in outputs))
    code, out, err = cli(capsys, "attitude", "--cert", str(run / "run" / "certificate.json"), "--csv",
                         str(tmp_path / "v.csv"), "--roll-deg", "35", "--roll-sd-deg", "0.2", "--json",
                         "--db", str(run / "lab.sqlite"))
    assert code == 0, err
    rows = json.loads(out)["rows"]
    got = np.radians([row["pitch_deg"] for row in rows])
    assert np.allclose(got, alpha, atol=1e-10)
    om, A = c.omega_deg * DEG, c.azimuth_deg * DEG
    k = float(t_quantile(0.975, int(min(cert.fit.uncertainty_dof))))
    for a, row in zip(alpha, rows, strict=True):
        eq_81 = (math.sqrt(sigma_v(cert, 0, a, roll) ** 2 / c.S**2
                           + (math.sin(om) * math.cos(a) * math.cos(roll + A) * sigma_r) ** 2)
                 / abs(math.cos(om) * math.cos(a) + math.sin(om) * math.sin(a) * math.sin(roll + A)))
        assert row["U95_pitch_deg"] == pytest.approx(math.degrees(k * eq_81), rel=1e-9)
        assert row["roll_deg"] == pytest.approx(35.0) and row["U95_roll_deg"] is None
    code, _, err = cli(capsys, "attitude", "--cert", str(run / "run" / "certificate.json"), "--csv",
                       str(tmp_path / "v.csv"), "--db", str(run / "lab.sqlite"))
    assert code == 2 and err.rstrip("\n").endswith("give it (--roll-deg, or a roll_deg column)")


def test_attitude_of_an_x_y_package_inside_its_usable_range_and_refused_outside(runs, tmp_path, capsys):
    """Outputs made by eqs. 2 and 4 inside the certificate's usable range give back pitch and roll
    (Newton-Raphson); one attitude beyond it is refused in one line, naming its row."""
    run = runs["two-axis-xy"]
    cert = read_certificate(run / "run" / "certificate.json")
    p = cert.package
    assert p is not None and p.usable_pitch_deg is not None and p.usable_roll_deg is not None
    cx, cy = p.coefficients["x"], p.coefficients["y"]
    alpha = np.radians([0.0, 0.9 * p.usable_pitch_deg[1], -20.0])
    roll = np.radians([0.0, 0.9 * p.usable_roll_deg[0], 30.0])
    v = np.column_stack([tripp_output(cx, "x", alpha, roll), tripp_output(cy, "y", alpha, roll)])
    (tmp_path / "v.csv").write_text("vx,vy\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in v))
    code, out, err = cli(capsys, "attitude", "--cert", str(run / "run" / "certificate.json"), "--csv",
                         str(tmp_path / "v.csv"), "--json", "--db", str(run / "lab.sqlite"))
    assert code == 0, err
    rows = json.loads(out)["rows"]
    assert np.allclose(np.radians([r["pitch_deg"] for r in rows]), alpha, atol=1e-10)
    assert np.allclose(np.radians([r["roll_deg"] for r in rows]), roll, atol=1e-10)
    assert all(r["U95_pitch_deg"] <= p.u95_limit_deg and r["U95_roll_deg"] <= p.u95_limit_deg for r in rows)
    outside_pitch = np.radians(p.usable_pitch_deg[1] + 5)
    vx, vy = (tripp_output(c, a, outside_pitch, 0.0) for c, a in ((cx, "x"), (cy, "y")))
    (tmp_path / "out.csv").write_text(f"vx,vy\n{float(v[0, 0])!r},{float(v[0, 1])!r}\n"
                                      f"{float(vx)!r},{float(vy)!r}\n")
    code, _, err = cli(capsys, "attitude", "--cert", str(run / "run" / "certificate.json"), "--csv",
                       str(tmp_path / "out.csv"), "--db", str(run / "lab.sqlite"))
    last = err.rstrip("\n").rsplit("\n", 1)[-1]
    assert code == 2 and last.startswith("labcal: error: row 2: pitch") and "usable range" in last


def test_a_package_certificate_is_signed_with_its_dcc_and_verifies(runs, tmp_path):
    """A package's certificate approved with an Ed25519 key (`approve`; `labcal certificate approve`
    refuses a dry run, so the signing is called directly): the signature verifies with the public
    key, covers the DCC made of it (valid against PTB's schema), and an edit to the package section
    after signing is refused even with the seal recomputed."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from labcal.documents.approval import approve, verify
    from labcal.documents.certificate import certificate_from_doc, content_digest, write_certificate
    from labcal.documents.dcc import dcc_document, validation_error
    from labcal.errors import LabcalError

    cert = read_certificate(runs["two-axis-xy"] / "run" / "certificate.json")
    key = Ed25519PrivateKey.generate()
    signed = approve(cert, "A. Metrologist", "Technical manager", key)
    path = write_certificate(tmp_path / "certificate.json", signed)
    assert verify(path, key.public_key()).package == cert.package
    dcc = dcc_document(signed)
    assert validation_error(dcc) is None
    assert signed.approval is not None
    assert signed.approval.dcc_sha256 == hashlib.sha256(dcc).hexdigest()
    doc = json.loads(path.read_text())
    doc["package"]["usable_roll_deg"] = [-89.0, 89.0]  # a wider range than was computed and signed
    doc["digest"]["value"] = content_digest(doc)
    certificate_from_doc(doc, "edited")  # the seal alone would accept it
    (tmp_path / "edited.json").write_text(json.dumps(doc))
    with pytest.raises(LabcalError, match="signature does not match"):
        verify(tmp_path / "edited.json", key.public_key())


@pytest.mark.slow
def test_an_instruments_history_of_package_certificates_compares_only_the_sensors_it_has(tmp_path, capsys):
    """Two single-axis runs of one instrument (the dry run's serial): `labcal history` lists both,
    judges the change of the x sensor's four coefficients only (Δ written out here from the two
    certificates), and plots them."""
    from labcal.cli import main

    for name in ("first", "second"):
        assert main(["run", "--sim", "--instrument", "single-axis", "--yes", "--seed", str(len(name)),
                     "--out", str(tmp_path / name), "--db", str(tmp_path / "lab.sqlite")]) == 0
    capsys.readouterr()
    code, out, err = cli(capsys, "history", "SIMULATED", "--include-simulated", "--json", "--db",
                         str(tmp_path / "lab.sqlite"), "--plot", str(tmp_path / "history.png"))
    assert code == 0, err
    doc = json.loads(out)
    assert [c["sensors"] for c in doc["calibrations"]] == [["x"], ["x"]]
    first, second = (read_certificate(tmp_path / n / "certificate.json") for n in ("first", "second"))
    assert {c["sensor"] for c in doc["changes"]} == {"x"} and len(doc["changes"]) == 4
    delta = np.array(second.fit.coefficients)[:, 0] - np.array(first.fit.coefficients)[:, 0]
    assert np.allclose([c["delta"] for c in doc["changes"]], delta, rtol=1e-12, atol=0)
    assert (tmp_path / "history.png").stat().st_size > 0


@pytest.mark.parametrize("certified", [False, True], ids=["readings so far", "under its certificate"])
def test_the_lab_servers_residual_figure_of_a_package_run_draws_its_sensors(runs, certified):
    """The residual figure the lab server serves for a run, drawn from the journal's points (the
    linear fit so far, or the model its certificate states): a single-axis run's has one row of
    plots (the x sensor's), a PNG."""
    import io

    from PIL import Image
    from sqlalchemy import create_engine

    from labcal.app.residuals import _draw
    from labcal.documents.certificate import read_certificate

    cert = read_certificate(runs["single-axis"] / "run" / "certificate.json") if certified else None
    engine = create_engine(f"sqlite:///{runs['single-axis'] / 'lab.sqlite'}")
    with engine.connect() as conn:
        png = _draw(conn, 1, cert)
    engine.dispose()
    assert png is not None
    width, height = Image.open(io.BytesIO(png)).size
    assert width == 900 and height < 650 * 0.6  # one sensor's row of the three-sensor figure's height


def test_a_package_run_whose_pitch_table_slipped_is_judged_by_its_checks_and_issues_no_certificate(
        tmp_path, capsys):
    """A single-axis run whose pitch table's output slips 0.05° from rig time 1200 s (in the second
    mount) on: the end-of-run checks of the package's x sensor (its residual against the declared
    noise) find the readings scatter far beyond what the station declares, the points they name are
    measured again, and the run ends in one line with no certificate, every reading kept."""
    import sqlite3

    (tmp_path / "rig.toml").write_text('[[output_slips]]\ntable = "pitch"\ndegrees = 0.05\nat_s = 1200.0\n')
    code, _, err = cli(capsys, "run", "--sim", "--instrument", "single-axis", "--yes", "--seed", "1", "--rig",
                       str(tmp_path / "rig.toml"), "--out", str(tmp_path / "run"), "--db",
                       str(tmp_path / "j.db"))
    last = err.rstrip("\n").rsplit("\n", 1)[-1]
    assert code == 2 and "issued no certificate" in last and "reading(s) kept" in last
    assert not (tmp_path / "run" / "certificate.json").exists()
    with sqlite3.connect(tmp_path / "j.db") as db:
        checks = [m for (m,) in db.execute("SELECT message FROM events WHERE kind = 'checks' ORDER BY id")]
        assert db.execute("SELECT COUNT(*) FROM points").fetchone()[0] > 64  # the named points, again
    assert checks[0].startswith("measuring point(s)") and "sensor x" in checks[0]
