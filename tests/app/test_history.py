"""History: three calibrations of one instrument, a bias shift injected before the third.

Null behaviour of the rule on this rig (measured over 8 seeds, 84 coefficient changes): the largest
|Δ| was 0.08 of the limit k·√(u₁² + u₂²) ≈ 40 µV for the bias, because most of the residual scatter
that sets u repeats from run to run (fixed device misalignments). A 100 µV shift is ≈ 2.5 limits.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from simulated_runs import rig_with_bias_shift, simulated_run

from labcal.analysis.device_fit import preferred_fit
from labcal.analysis.fit import fit_readings
from labcal.cli import main
from labcal.documents.history import RULE, certificates_for, changes, store
from labcal.documents.issuing import build_certificate
from labcal.store.record import load_run

SERIAL = "SN-1001"
SHIFT_V = 1e-4


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """Three calibrations through `labcal run`; the third after the bias moved. The first two are
    stored by the Python API (no report drawn, to save time), the third by `labcal report`."""
    base = tmp_path_factory.mktemp("history")
    db = base / "lab.sqlite"
    for n in (1, 2):
        record = load_run(simulated_run(base / f"cal{n}", db, seed=20 + n, serial=SERIAL, report=False))
        fit = fit_readings(record.readings)  # on the model `labcal run` certifies: the device model
        store(build_certificate(record, fit, device=preferred_fit(record.readings, fit)[0]), db)
    shifted = rig_with_bias_shift(base / "shifted.toml", (SHIFT_V, 0.0, 0.0))
    run_dir = simulated_run(base / "cal3", db, seed=23, rig=shifted, serial=SERIAL, report=False)
    assert main(["report", str(run_dir), "--db", str(db), "--json"]) == 0
    return db


def test_only_the_injected_drift_is_flagged(lab):
    certs = certificates_for(SERIAL, lab, include_simulated=True)
    assert len(certs) == 3
    assert [c.calibrated_utc for c in certs] == sorted(c.calibrated_utc for c in certs)
    found = changes(certs)
    assert len(found) == 2 * 12  # two consecutive pairs × 12 coefficients
    flagged = [c for c in found if c.flagged]
    assert len(flagged) == 1
    (drift,) = flagged
    assert (drift.row, drift.sensor) == (0, 0) and (drift.before, drift.after) == (certs[1].certificate_id,
                                                                                     certs[2].certificate_id)
    assert drift.delta == pytest.approx(SHIFT_V, abs=1e-5)  # run-to-run scatter of B is ~1–3 µV here
    assert drift.delta > 2 * drift.limit


def test_rule_uses_welch_satterthwaite_coverage(lab):
    certs = certificates_for(SERIAL, lab, include_simulated=True)
    change = changes(certs)[0]  # bias of sensor x, calibration 1 → 2
    u1, u2 = certs[0].standard_uncertainty[0, 0], certs[1].standard_uncertainty[0, 0]
    # the device model's ν = 3K − 18 = 174 per certificate (the linear fit's was 60 per sensor)
    assert certs[0].fit.uncertainty_dof[0] == certs[1].fit.uncertainty_dof[0] == 3 * 64 - 18
    nu = (u1**2 + u2**2) ** 2 / (u1**4 / 174 + u2**4 / 174)
    assert change.nu == pytest.approx(nu, rel=1e-12) and 174 < change.nu <= 348
    assert change.limit == pytest.approx(stats.t.ppf(0.975, nu) * np.hypot(u1, u2), rel=1e-12)


def test_history_command_json_and_plot(lab, tmp_path, capsys):
    plot = tmp_path / "history.png"
    assert main(["history", SERIAL, "--include-simulated", "--db", str(lab), "--json", "--plot",
                 str(plot)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["serial"] == SERIAL and doc["rule"] == RULE and len(doc["calibrations"]) == 3
    assert [(f["coefficient"], f["sensor"]) for f in doc["flagged"]] == [("B", "x")]
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["history", SERIAL, "--include-simulated", "--db", str(lab)]) == 0
    text = capsys.readouterr().out
    assert "1 change(s) flagged" in text and "B of sensor x" in text


def test_database_path_option_environment_and_default(lab, monkeypatch, capsys):
    from labcal.store.journal import db_path

    monkeypatch.setenv("LABCAL_DB", str(lab))
    assert main(["history", SERIAL, "--include-simulated", "--json"]) == 0  # $LABCAL_DB when there is no --db
    assert len(json.loads(capsys.readouterr().out)["calibrations"]) == 3
    assert db_path("x.sqlite").name == "x.sqlite"  # --db wins over the environment
    monkeypatch.delenv("LABCAL_DB")
    monkeypatch.setenv("XDG_DATA_HOME", "/srv/data")
    assert db_path(None) == Path("/srv/data/labcal/labcal.sqlite")  # not relative to the current folder


def test_table_lives_beside_the_journal_in_wal_mode(lab):
    with sqlite3.connect(lab) as conn:
        tables = {name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        assert {"certificates", "runs", "points"} <= tables  # the run journal shares the file
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_reissuing_replaces_the_certificate_of_the_same_calibration(lab):
    certs = certificates_for(SERIAL, lab, include_simulated=True)
    store(certs[0], lab)
    assert len(certificates_for(SERIAL, lab, include_simulated=True)) == 3


def test_altered_row_is_refused(lab, tmp_path, capsys):
    db = tmp_path / "copy.sqlite"
    with sqlite3.connect(lab) as src, sqlite3.connect(db) as dst:
        src.backup(dst)
    with sqlite3.connect(db) as conn:
        cid, doc = conn.execute("SELECT certificate_id, document FROM certificates LIMIT 1").fetchone()
        doc = json.loads(doc)
        doc["fit"]["coefficients"][0][0] += 1e-6
        conn.execute("UPDATE certificates SET document = ? WHERE certificate_id = ?", (json.dumps(doc), cid))
    assert main(["history", SERIAL, "--include-simulated", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert f"certificate {cid}: digest mismatch" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args, message", [
    (["history", "SN-NOPE"], "no certificates for instrument 'SN-NOPE'"),
    (["history", SERIAL, "--include-simulated", "--plot", "/nonexistent/h.png"],
     "/nonexistent/h.png: cannot write the plot"),
    (["history", SERIAL, "--include-simulated", "--plot", "HISTORY.xyz"],
     "HISTORY.xyz: cannot write the plot (Format 'xyz' is not supported"),  # matplotlib's words, then ours
    (["history", SERIAL], "has only simulated certificates"),  # dry runs never pass for real ones
])
def test_bad_input_is_one_line(lab, capsys, args, message):
    assert main([*args, "--db", str(lab)]) == 2
    captured = capsys.readouterr()
    assert message in captured.err and captured.out == "" and len(captured.err.strip().splitlines()) == 1
    if "SN-NOPE" in args:
        assert f"known serials: {SERIAL}" in captured.err


def test_missing_database_is_one_line(tmp_path, capsys):
    assert main(["history", SERIAL, "--include-simulated", "--db", str(tmp_path / "none.sqlite")]) == 2
    err = capsys.readouterr().err
    assert "none.sqlite: no such database" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "none.sqlite").exists()  # a query never creates a database


def test_without_uncertainty_every_change_is_flagged(lab):
    """Noise-free data give u = 0: ν is infinite, k = 1.96 and any nonzero change exceeds a zero limit."""
    certs = certificates_for(SERIAL, lab, include_simulated=True)[:2]
    exact = [c.model_copy(update={"fit": c.fit.model_copy(update={"standard_errors": [[0.0] * 3] * 4})})
             for c in certs]
    found = changes(exact)
    assert all(c.limit == 0.0 and c.k == pytest.approx(1.959964, abs=1e-6) for c in found)
    assert [c.flagged for c in found] == [c.delta != 0.0 for c in found]
