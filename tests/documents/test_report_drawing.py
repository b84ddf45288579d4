"""The report draws each figure once: the HTML's PNG and the PDF's figure page are one drawing."""

from __future__ import annotations

import base64
import io
import re

import numpy as np
from matplotlib.figure import Figure
from matplotlib.image import imread
from simulated_runs import simulated_run

from labcal.analysis.fit import fit_readings
from labcal.app import run_documents
from labcal.documents import report, report_figures
from labcal.documents.issuing import build_certificate
from labcal.store.record import load_run


def test_each_figure_is_drawn_once_and_the_html_and_pdf_carry_the_same_pixels(tmp_path, monkeypatch):
    run_dir = simulated_run(tmp_path / "run", tmp_path / "lab.sqlite", seed=5, report=False)
    record = load_run(run_dir)
    fit = fit_readings(record.readings)
    cert = build_certificate(record, fit, None)
    made: list[Figure] = []
    draws: dict[int, int] = {}
    original_figures, original_draw = report_figures.figures, Figure.draw

    def remember(*args):
        out = original_figures(*args)
        made.extend(fig for _, fig in out)
        return out

    def counting_draw(self, renderer):
        draws[id(self)] = draws.get(id(self), 0) + 1
        return original_draw(self, renderer)

    monkeypatch.setattr(report_figures, "figures", remember)
    monkeypatch.setattr(Figure, "draw", counting_draw)
    html_path, pdf_path = report.write_report(run_dir, cert, record, fit)
    assert len(made) == 4 and [draws.get(id(f)) for f in made] == [1, 1, 1, 1]
    pngs = re.findall(r'src="data:image/png;base64,([^"]+)"', html_path.read_text(encoding="utf-8"))
    assert len(pngs) == 4
    pixels = imread(io.BytesIO(base64.b64decode(pngs[0])))
    width, height = made[0].get_size_inches() * report_figures.FIGURE_DPI
    assert pixels.shape[:2] == (round(height), round(width)) and np.ptp(pixels) > 0
    pdf = pdf_path.read_bytes()
    assert pdf.count(b"/Subtype /Image") >= 4  # the four drawings, embedded as images


def test_issuing_fits_the_device_model_once(tmp_path, monkeypatch):
    """Checking the run folder against the journal fits the linear and the device model (fit.json is
    derived from them); the certificate and the report reuse those fits instead of fitting again."""
    from labcal.analysis import device_fit

    run_dir = simulated_run(tmp_path / "run", tmp_path / "lab.sqlite", seed=5, report=False)
    calls = []
    original = device_fit.fit_device
    monkeypatch.setattr(device_fit, "fit_device", lambda *a, **k: calls.append(1) or original(*a, **k))
    outputs = run_documents.write_run_outputs(run_dir, db=tmp_path / "lab.sqlite")
    assert len(calls) == 1 and outputs.certificate.device is not None
