"""The calibration device's history (issue 12): estimates stored per device id, changes flagged."""

from __future__ import annotations

import json

import pytest

from labcal.cli import main
from labcal.documents import device_history
from labcal.documents.device_history import DeviceEstimate
from labcal.errors import LabcalError

NAMES = "abdefk"


def estimate(source: str, when: str, a: float, U: float = 0.3) -> DeviceEstimate:
    return DeviceEstimate("CD-7", when, source, {n: (a if n == "a" else 10.0) for n in NAMES},
                          {n: U for n in NAMES})


def test_changes_beyond_the_combined_expanded_uncertainty_are_flagged(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    # √(0.3² + 0.3²) = 0.424″: a 0.4″ step stays, a 0.5″ step is flagged
    for n, a in ((1, 40.0), (2, 40.4), (3, 40.9)):
        device_history.store(estimate(f"run-{n}", f"2026-0{n}-01T00:00:00+00:00", a), db)
    device_history.store(estimate("run-3", "2026-03-01T00:00:00+00:00", 40.9), db)  # stored again: replaced
    assert main(["device", "history", "CD-7", "--db", str(db), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [e["source"] for e in doc["estimates"]] == ["run-1", "run-2", "run-3"]
    assert [(f["misalignment"], f["before"], f["after"]) for f in doc["flagged"]] == [("a", "run-2", "run-3")]
    assert doc["flagged"][0]["limit_arcsec"] == pytest.approx(0.3 * 2**0.5)
    plot = tmp_path / "cd.png"
    assert main(["device", "history", "CD-7", "--db", str(db), "--plot", str(plot)]) == 0
    text = capsys.readouterr().out
    assert plot.stat().st_size > 0 and "1 change(s) flagged" in text


def test_unknown_device_is_one_line(tmp_path):
    db = tmp_path / "lab.sqlite"
    device_history.store(estimate("run-1", "2026-01-01T00:00:00+00:00", 40.0), db)
    with pytest.raises(LabcalError, match=r"no device estimates for 'CD-8' in .*; known devices: CD-7"):
        device_history.estimates_for("CD-8", db)


def test_a_dry_run_stores_the_simulated_device(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    assert main(["run", "--sim", "--yes", "--json", "--db", str(db), "--out", str(tmp_path / "run")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["fit"]["model"] == "linear" and summary["device"]["model"] == "device"
    assert summary["model_note"].startswith("device model: the plan identifies all six")
    fit_json = json.loads((tmp_path / "run" / "fit.json").read_text())
    assert fit_json["model"] == "device" and fit_json["notes"][0] == summary["model_note"]
    device = json.loads((tmp_path / "run" / "device.json").read_text())
    assert device["device_id"] == "SIMULATED" and set(device["misalignments"]) == set(NAMES)
    assert main(["device", "history", "SIMULATED", "--db", str(db), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["estimates"]) == 1
    stored = {n: {"value_arcsec": m["value_arcsec"], "U_arcsec": m["U_arcsec"]}
              for n, m in device["misalignments"].items()}
    assert doc["estimates"][0]["misalignments"] == stored
    assert "Calibration-device misalignments" in (tmp_path / "run" / "report.html").read_text()
