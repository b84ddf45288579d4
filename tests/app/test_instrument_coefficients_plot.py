"""An instrument's coefficients over time, drawn for its page: a PNG with each coefficient ± U
against its calibration date, the change that exceeds the combined expanded uncertainty in red — and
no red at all where nothing drifted; nothing for an instrument that is not registered. The
calibrations are the stored test certificate as a real (not simulated) calibration of the instrument
on two dates, sealed anew; the drift is a bias shift of 10 mV, against a U of a few µV."""

from __future__ import annotations

import copy
import io
import json
from pathlib import Path

import numpy as np
from matplotlib.image import imread

from labcal.app.instrument_pages import coefficients_png
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.cli import main
from labcal.documents import history
from labcal.documents.certificate import seal

STORED = Path(__file__).parent.parent / "data" / "certificates" / "simulated.json"
RED = np.array([214, 39, 40]) / 255  # matplotlib's "tab:red" (#d62728), what a flagged change is drawn in


def _calibration(serial: str, day: str, n: int, bias_shift_v: float):
    doc = copy.deepcopy(json.loads(STORED.read_text(encoding="utf-8")))
    for key in ("approval", "digest", "revision", "replaces"):
        doc.pop(key, None)
    doc["certificate_id"] = f"{serial}-{day}-{n}"
    doc["instrument"]["serial"] = serial
    doc["station"]["simulated"], doc["station"]["simulated_truth"] = False, None
    doc["calibrated_utc"] = doc["completed_utc"] = doc["issued_utc"] = f"{day}T12:00:00+00:00"
    doc["fit"]["coefficients"][0][0] += bias_shift_v
    return seal(doc)


def _red_pixels(png: bytes) -> int:
    rgb = imread(io.BytesIO(png), format="png")[..., :3]
    return int(np.sum(np.all(np.abs(rgb - RED) < 0.03, axis=-1)))


def _lab(tmp_path, shift_v: float):
    db = str(tmp_path / "lab.sqlite")
    assert main(["instrument", "add", "ACC-0200", "--interval", "365d", "--db", db]) == 0
    history.store(_calibration("ACC-0200", "2026-03-01", 1, 0.0), db)
    history.store(_calibration("ACC-0200", "2026-09-01", 2, shift_v), db)
    return open_lab(OpenLab(db))


def test_a_drifted_coefficient_is_drawn_in_red(tmp_path):
    lab = _lab(tmp_path, 0.010)
    try:
        png = coefficients_png(lab, "acc-0200")  # the register's serial, in any case
        missing = coefficients_png(lab, "ACC-9999")
    finally:
        lab.close()
    assert png is not None and png.startswith(b"\x89PNG\r\n\x1a\n")
    assert _red_pixels(png) > 20  # the change drawn 2.5 points wide, and its legend: tens of pixels
    assert missing is None


def test_no_red_where_nothing_drifted(tmp_path):
    lab = _lab(tmp_path, 0.0)
    try:
        png = coefficients_png(lab, "ACC-0200")
    finally:
        lab.close()
    assert png is not None and _red_pixels(png) == 0
