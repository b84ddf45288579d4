"""The report of a simulated run: every plot holds the data it claims, the HTML stands alone, the
PDF has every page, and `labcal report` turns bad input into one line and exit code 2."""

from __future__ import annotations

import base64
import html
import json
import re
import shutil
import sqlite3
import warnings
from pathlib import Path

import numpy as np
import pytest
from lab_server import accessible, parses_cleanly
from simulated_runs import simulated_run

from labcal.analysis.kinematics import NO_MISALIGNMENT, Misalignment, gravity
from labcal.app.run_documents import write_run_outputs
from labcal.cli import main
from labcal.config.settings import CertificateSettings
from labcal.documents.certificate import read_certificate
from labcal.documents.issuing import build_certificate
from labcal.documents.report import fitted
from labcal.documents.report_figures import envelope_figure, figures, inferred_attitude
from labcal.documents.report_tables import tables
from labcal.store.record import load_run

TOLERANCE_DEG = 0.01


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    base = tmp_path_factory.mktemp("report")
    # The rig's tables without index errors or wobble: a dry run has no station file to put the
    # tables' index accuracy in the budget, and since the device model removes the device's
    # misalignments (tens of arcseconds by default) those ±2″ would be all the error bars miss
    rig = base / "rig.toml"
    rig.write_text("[device]\nindex_arcsec = 0\nwobble_arcsec = 0\n")
    run_dir = simulated_run(base / "run", base / "lab.sqlite", seed=3, rig=rig, report=False)  # issued below
    settings = CertificateSettings(attitude_u95_max_deg=TOLERANCE_DEG)
    return write_run_outputs(run_dir, settings, db=base / "lab.sqlite")


RESIDUALS = "Residuals per sensor of the "  # the residual figure's heading starts so


@pytest.fixture(scope="module")
def drawn(outputs):
    record = load_run(outputs.certificate_path.parent)
    fit, device, _ = fitted(record)
    figs = dict(figures(outputs.certificate, record, fit, device))
    [residuals] = [title for title in figs if title.startswith(RESIDUALS)]
    figs[RESIDUALS] = figs.pop(residuals)
    return record, fit, figs, residuals


def _certified_residuals(cert, record) -> np.ndarray:
    """V − B − g(p, r, y, u; misalignments)ᵀS of every reading, from the certificate's coefficients
    and its device section's misalignments (nominal gravity where it has none) through the
    kinematics alone, not through the fit (K×3, V)."""
    r = record.readings
    mis = NO_MISALIGNMENT if cert.device is None else Misalignment.from_degrees(
        **{n: m.value_arcsec / 3600.0 for n, m in cert.device.misalignments.items()})
    g = gravity(*(np.radians(a) for a in (r.pitch_deg, r.roll_deg, r.y_deg, r.u_deg)), mis)
    X = np.array(cert.fit.coefficients)
    return r.volts - X[0] - g @ X[1:]


def _labelled(ax) -> None:
    """Every axis labelled with its unit; an x axis shared with the panel below (its ticks shown
    only there) is labelled there instead."""
    shown_x = any(t.get_visible() and t.get_text() for t in ax.get_xticklabels())
    labels = [ax.get_ylabel()] + ([ax.get_xlabel()] if shown_x else []) + \
        ([ax.get_zlabel()] if hasattr(ax, "get_zlabel") else [])
    for label in labels:
        assert re.search(r"\(.+\)", label), f"axis label {label!r} has no unit"


def _marker_data(ax) -> tuple[np.ndarray, np.ndarray]:
    """x and y of the plotted points (lines drawn with markers, reference lines left out)."""
    lines = [line for line in ax.get_lines() if line.get_marker() not in ("None", "", None)]
    return (np.concatenate([line.get_xdata() for line in lines]),
            np.concatenate([line.get_ydata() for line in lines]))


def test_the_html_report_parses_cleanly_and_is_accessible(outputs, browser):
    """The report a reader opens: html5lib's strict parser and axe-core in Chromium (WCAG 2.1 A, AA)."""
    parses_cleanly(outputs.html_path.read_text(encoding="utf-8"), "report.html")
    page = browser.new_page()
    try:
        page.goto(outputs.html_path.as_uri())
        accessible(page, "report.html")
    finally:
        page.close()


def test_residual_plots_hold_every_residual_of_the_certified_model_and_both_bands(outputs, drawn):
    """The dry run's certificate rests on the device model: the residual page plots that model's
    residuals (computed here from the readings, the certified coefficients and misalignments), and
    its heading, in the figure list and in the HTML, names the model and each sensor's RMS in µV."""
    record, fit, figs, heading = drawn
    cert = outputs.certificate
    assert cert.fit.model == "device"
    resid = _certified_residuals(cert, record)
    rms = np.sqrt(np.mean(resid**2, axis=0))
    assert np.all(rms < 1e-3)  # tens of µV: stated in µV
    linear_rms = np.sqrt(np.mean(fit.ls.residuals**2, axis=0))
    assert np.all(np.abs(linear_rms / rms - 1) > 0.05)  # the two models' residuals are told apart
    stated = ", ".join(f"{s} {v * 1e6:.3g} µV" for s, v in zip("xyz", rms, strict=True))
    assert heading.startswith(f"{RESIDUALS}device model (") and heading.endswith(f"residual RMS {stated}")
    assert html.escape(heading) in outputs.html_path.read_text(encoding="utf-8")
    fig = figs[RESIDUALS]
    assert "device model the certificate states" in fig._suptitle.get_text()
    axes = np.array(fig.axes).reshape(3, 2)
    for j in range(3):
        for col, angle in enumerate((record.readings.pitch_deg, record.readings.roll_deg)):
            ax = axes[j, col]
            _labelled(ax)
            assert ax.get_ylabel().endswith("(µV)") and ax.get_title().endswith(f"RMS {rms[j] * 1e6:.3g} µV")
            x, y = _marker_data(ax)
            assert len(y) == len(record.readings) == 64
            # to the rounding of B + gᵀS (volts near 1, so ~1e-15 V = 1e-9 µV)
            np.testing.assert_allclose(np.sort(y), np.sort(resid[:, j] * 1e6), rtol=0, atol=1e-6)
            np.testing.assert_array_equal(np.sort(x), np.sort(angle))
            prediction, confidence = (np.abs(c.get_paths()[0].vertices[:, 1]) for c in ax.collections)
            assert np.all(np.isfinite(prediction)) and confidence.max() > 0
            assert prediction.max() > confidence.max()  # a new reading is less certain than the mean


def test_inferred_attitude_errors_are_plotted_with_their_u95(outputs, drawn):
    record, _, figs, _ = drawn
    e = inferred_attitude(outputs.certificate, record)
    fig = figs["Errors of the attitude inferred from each calibration reading"]
    for ax, angle in zip(fig.axes, ("pitch", "roll"), strict=True):
        _labelled(ax)
        points = [c.lines[0].get_ydata() for c in ax.containers]
        errors = e[f"{angle}_error"][np.isfinite(e[f"{angle}_error"])]
        np.testing.assert_allclose(np.sort(np.concatenate(points)), np.sort(errors), rtol=1e-12)
    # Pitch ±90° leaves 32 of the 64 readings without roll (Soto's plan visits it once per roll).
    assert np.isfinite(e["pitch_error"]).sum() == 64 and np.isfinite(e["roll_error"]).sum() == 32
    # The error bars are honest: a 95 % interval covers the error at most points (64 correlated points
    # per angle, so at least 85 % rather than exactly 95 %).
    for angle in ("pitch", "roll"):
        # Within 1° of the poles pitch is bounded by ±90° and its linearised U95 does not describe its
        # error (the true attitude is tens of arcseconds off the pole the plan names): not counted
        ok = np.isfinite(e[f"{angle}_error"]) & (np.abs(e["nominal_pitch"]) < 89.0)
        covered = np.abs(e[f"{angle}_error"][ok]) <= e[f"U95_{angle}"][ok]
        assert covered.mean() >= 0.85
    # Errors are small against a degree away from the poles (the sphere estimator's pitch within 1° of
    # ±90° is off by up to ~0.06° on this rig: a known limitation, reported, not this test's subject).
    assert np.nanmax(np.abs(e["pitch_error"][np.abs(e["nominal_pitch"]) < 89.0])) < 0.02


def test_envelope_plot_matches_the_certificate(outputs, drawn):
    _, _, figs, _ = drawn
    cert = outputs.certificate
    fig = figs["Attitude uncertainty over the usage envelope"]
    for ax, largest_cert in zip(fig.axes, (cert.attitude.pitch_U95_max_deg, cert.attitude.roll_U95_max_deg),
                                strict=True):
        _labelled(ax)
        largest, rms, tolerance = ax.get_lines()
        assert len(largest.get_xdata()) == 25  # -60..60° in 5° steps
        assert np.all(largest.get_ydata() >= rms.get_ydata())
        assert np.max(largest.get_ydata()) == pytest.approx(largest_cert, rel=1e-12)
        assert set(tolerance.get_ydata()) == {TOLERANCE_DEG}


def test_sphere_plot_shows_every_point_of_every_mount(drawn):
    record, _, figs, _ = drawn
    fig = figs["The plan's points on the gravity sphere"]
    fig.canvas.draw()  # 3-D scatter offsets exist once projected
    ax = fig.axes[0]
    _labelled(ax)
    scatters = [c for c in ax.collections if len(c.get_offsets()) > 1]
    assert [len(c.get_offsets()) for c in scatters] == [16] * 4  # 16 points × 4 mounts
    labels = sorted(int(t.get_text()) for t in ax.texts)
    assert labels == [8, 8, 8, 8, 16, 16] and sum(labels) == 64  # Soto's plan: 6 cardinal directions


def test_html_is_one_self_contained_file(outputs):
    text = outputs.html_path.read_text(encoding="utf-8")
    assert not re.search(r"https?://|<link|<script|url\(", text)
    images = re.findall(r'<img alt="[^"]*" src="data:image/png;base64,([^"]+)"', text)
    # four figures, and the device model's residuals: four-mount-64 identifies the device
    assert len(images) == 5 and all(base64.b64decode(i)[:8] == b"\x89PNG\r\n\x1a\n" for i in images)
    for t in tables(outputs.certificate):
        assert t.title.replace("&", "&amp;") in text
    assert "Statement of conformity: PASS" in text and outputs.certificate.digest.value in text


def test_pdf_has_text_and_figure_pages(outputs):
    pdf = outputs.pdf_path.read_bytes()
    assert pdf.startswith(b"%PDF")
    pages = len(re.findall(rb"/Type\s*/Page\b(?!s)", pdf))
    assert pages >= 4 + 1  # the tables' text, then one page per figure


def test_cli_regenerates_certificate_report_and_history(outputs, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(outputs.certificate_path.parent, run_dir)
    for name in ("certificate.json", "report.html", "report.pdf"):
        (run_dir / name).unlink()
    db = tmp_path / "lab.sqlite"
    code = main(["report", str(run_dir), "--tolerance-deg", "0.0001", "--db", str(db), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and doc["passed"] is False  # U95 ≈ 0.0005° (device model) exceeds 0.0001°
    assert doc["serial"] == "SIMULATED" and doc["database"] == str(db)
    cert = read_certificate(run_dir / "certificate.json")
    assert cert.certificate_id == outputs.certificate.certificate_id  # same calibration, same id
    assert (run_dir / "report.html").stat().st_size > 0 and (run_dir / "report.pdf").stat().st_size > 0
    assert main(["history", "SIMULATED", "--db", str(db), "--json"]) == 0
    assert len(json.loads(capsys.readouterr().out)["calibrations"]) == 1


def _one_line_error(capsys, *args: str) -> str:
    assert main(list(args)) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    return captured.err


def _broken_copy(outputs, tmp_path, edit) -> str:
    """A copy of the run directory and of its journal (so edits stay local), then ``edit``."""
    run_dir = tmp_path / "run"
    shutil.copytree(outputs.certificate_path.parent, run_dir)
    info = json.loads((run_dir / "run.json").read_text())
    journal = tmp_path / "journal.sqlite"
    with sqlite3.connect(info["journal"]) as source, sqlite3.connect(journal) as copy:
        source.backup(copy)
    (run_dir / "run.json").write_text(json.dumps({**info, "journal": str(journal)}))
    edit(run_dir)
    return str(run_dir)


def _interrupted(run_dir):
    info = json.loads((run_dir / "run.json").read_text())
    with sqlite3.connect(info["journal"]) as con:
        con.execute("UPDATE runs SET status='interrupted', reason='Ctrl-C' WHERE id=?", (info["run_id"],))


def _without_journal(run_dir):
    info = json.loads((run_dir / "run.json").read_text())
    del info["journal"]
    (run_dir / "run.json").write_text(json.dumps(info))


@pytest.mark.parametrize("edit, message", [
    (lambda d: (d / "run.json").unlink(), "not a run directory (no run.json)"),
    (lambda d: (d / "run.json").write_text("{"), "run.json: unreadable"),
    (_without_journal, "names no journal; was this run made by labcal run?"),
    (_interrupted, "the run is interrupted (Ctrl-C); only a complete run gets a certificate"),
])
def test_bad_run_directories(outputs, tmp_path, capsys, edit, message):
    run_dir = _broken_copy(outputs, tmp_path, edit)
    assert message in _one_line_error(capsys, "report", run_dir, "--db", str(tmp_path / "db.sqlite"))


def test_the_report_comes_from_the_journal_not_the_exports(outputs, tmp_path, capsys):
    def drop_exports(d):
        (d / "readings.csv").unlink()
        (d / "plan.toml").unlink()

    run_dir = _broken_copy(outputs, tmp_path, drop_exports)
    assert main(["report", run_dir, "--db", str(tmp_path / "db.sqlite"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    cert = json.loads(Path(doc["certificate"]).read_text())
    assert cert["data"]["readings_sha256"] == outputs.certificate.data.readings_sha256


def test_bad_arguments(outputs, tmp_path, capsys):
    run_dir = str(outputs.certificate_path.parent)
    db = str(tmp_path / "db.sqlite")
    assert "no such run directory" in _one_line_error(capsys, "report", str(tmp_path / "nope"), "--db", db)
    assert "usage_pitch_deg [-100, 10] must be increasing within -90..90" in _one_line_error(
        capsys, "report", run_dir, "--usage-pitch", "-100", "10", "--db", db)
    assert "no such station file" in _one_line_error(capsys, "report", run_dir, "--station",
                                                     str(tmp_path / "none.toml"), "--db", db)
    for bad in ("-1", "inf", "nan"):  # refused by the option itself, naming it and its range
        assert f"argument --tolerance-deg: {bad} is" in _one_line_error(
            capsys, "report", run_dir, "--tolerance-deg", bad, "--db", db)


def test_envelope_through_the_poles(drawn):
    """Pitch ±90° is in the envelope: roll is undefined on those two grid rows (2 × 73 attitudes) and
    the plot leaves them out without a warning."""
    record, fit, _, _ = drawn
    cert = build_certificate(record, fit, CertificateSettings(usage_pitch_deg=(-90, 90)))
    assert cert.attitude.roll_undefined_points == 146 and np.isfinite(cert.attitude.roll_U95_max_deg)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        largest = envelope_figure(cert).axes[1].get_lines()[0].get_ydata()
    assert np.isnan(largest[[0, -1]]).all() and np.isfinite(largest[1:-1]).all()
