"""One attitude U95: `labcal attitude --cert`, certificate.json (its budget and its
attitude envelope), the report and the DCC state the same U95 for the same attitude, and it is the
complete one — Type A and the station's Type B — not the fit's Type A alone."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from simulated_runs import simulated_run

from labcal.cli import main
from labcal.documents.certificate import format_uncertainty, read_certificate

STATION = Path(__file__).resolve().parents[2] / "stations" / "lab-example.toml"
DCC = "{https://ptb.de/dcc}"
SI = "{https://ptb.de/si}"


@pytest.fixture(scope="module")
def issued(tmp_path_factory):
    base = tmp_path_factory.mktemp("one-u95")
    run_dir = simulated_run(base / "run", base / "lab.sqlite", seed=5, report=False)  # issued just below
    assert main(["report", str(run_dir), "--station", str(STATION), "--db", str(base / "lab.sqlite")]) == 0
    return run_dir


def _attitude_json(cert_path: Path, volts: np.ndarray, tmp_path: Path, capsys) -> dict:
    csv = tmp_path / "volts.csv"
    csv.write_text("vx,vy,vz\n" + "".join(",".join(f"{v:.12g}" for v in row) + "\n" for row in volts))
    capsys.readouterr()
    assert main(["attitude", "--cert", str(cert_path), "--csv", str(csv), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_every_output_states_the_same_u95(issued, tmp_path, capsys):
    cert = read_certificate(issued / "certificate.json")
    budget = cert.uncertainty_budget
    assert budget is not None and budget.covariance
    X = cert.coefficients
    totals = {t.angle: t for t in budget.totals}
    envelope = cert.attitude
    for angle, stated in (("pitch", envelope.pitch_U95_max_deg), ("roll", envelope.roll_U95_max_deg)):
        total = totals[angle]
        pitch, roll = np.radians(total.worst_at_deg)
        g = np.array([np.sin(pitch), np.cos(pitch) * np.sin(roll), np.cos(pitch) * np.cos(roll)])
        row = _attitude_json(issued / "certificate.json", (X[0] + g @ X[1:])[None], tmp_path,
                             capsys)["rows"][0]["sphere_least_squares"]
        # 1. the budget's total, 2. the certificate's envelope, 3. `labcal attitude --cert`
        assert row[f"U95_{angle}_deg"] == pytest.approx(total.U95_arcsec / 3600, rel=1e-6)
        assert stated == pytest.approx(total.U95_arcsec / 3600, rel=1e-9)
        # 4. the DCC
        root = ET.parse(issued / "certificate.dcc.xml").getroot()
        reals = {r.findtext(f"{SI}label"): float(r.findtext(f"{SI}value")) for r in root.iter(f"{SI}real")}
        assert reals[f"U95 {angle}"] == pytest.approx(total.U95_arcsec / 3600, rel=1e-9)
        # 5. the report, as people read it (two significant digits)
        assert f"{format_uncertainty(stated)}°" in (issued / "report.html").read_text(encoding="utf-8")
    # and it is the complete one: the station's Type B inputs make it larger than the fit's Type A,
    # recomputed here by hand at level attitude from the fit's covariance (pitch from sensor x alone)
    cal_a = np.array(cert.fit.covariance)[0, :4, :4]
    f = np.array([1.0, 0.0, 0.0, 1.0])
    u_type_a = np.degrees(np.sqrt(f @ cal_a @ f + cert.fit.reading_sd[0] ** 2) / X[1, 0])
    level = _attitude_json(issued / "certificate.json", (X[0] + X[3])[None], tmp_path,
                           capsys)["rows"][0]["sphere_least_squares"]
    assert level["u_pitch_deg"] > 1.5 * u_type_a


def test_the_dcc_covariance_is_the_one_its_u_comes_from(issued):
    """Each sensor's covariance in the DCC gives back its coefficients' U: √diag · k = U (the budget's
    complete covariance, not the fit's Type A beside the budget's U)."""
    cert = read_certificate(issued / "certificate.json")
    root = ET.parse(issued / "certificate.dcc.xml").getroot()
    regions = list(root.iter(f"{SI}ellipsoidalRegion"))
    assert len(regions) == 3
    for j, region in enumerate(regions):
        columns = region.find(f"{SI}covarianceMatrix").findall(f"{SI}column")
        matrix = np.array([[float(c.findtext(f"{SI}value")) for c in col.findall(f"{SI}covariance")]
                           for col in columns])
        # the DCC states sensitivities per m s⁻², through g_n = 9.80665 m s⁻² (exact, by definition)
        per_unit = np.array([1.0, 1 / 9.80665, 1 / 9.80665, 1 / 9.80665])
        matrix = matrix / np.outer(per_unit, per_unit)
        k = cert.expanded_uncertainty.k[j]
        np.testing.assert_allclose(k * np.sqrt(np.diag(matrix)), cert.U[:, j], rtol=1e-9)
        assert np.all(np.sqrt(np.diag(matrix)) > 1.01 * np.array(cert.fit.standard_errors)[:, j])
