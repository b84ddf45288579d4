"""The calibration device's history: estimates stored per device id, changes flagged."""

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


# --- sittings, ageing and expiry of a device correction --------------------------------------------
def dated(source: str, days: float, a: float, U: float = 1.96) -> DeviceEstimate:
    """An estimate of CD-7 at 01:00 UTC plus the fraction of ``days``, that many whole days before
    today (whatever the hour now: two estimates of one day stay on one day); u = U/1.96 = 1″."""
    from datetime import UTC, datetime, time, timedelta

    day = datetime.combine(datetime.now(UTC).date(), time(1), tzinfo=UTC) - timedelta(days=int(days))
    return estimate(source, (day + timedelta(days=days - int(days))).isoformat(), a, U)


@pytest.mark.parametrize(("history", "sittings"), [
    ([("run-1", 3.0, 40.0), ("run-2", 3.0 + 1 / 24, 40.2)], 1),  # 01:00 and 02:00 of one day: one sitting
    ([("run-1", 20.0, 40.0), ("run-2", 10.0, 40.0)], 1),  # the same values: the same readings again
    ([("run-1", 20.0, 40.0), ("run-2", 10.0, 40.2)], 2),
])
def test_estimates_of_one_day_or_of_the_same_readings_are_one_sitting(history, sittings, tmp_path):
    """Two estimates are two pieces of evidence only from two sittings: another UTC day and other
    readings; with one sitting the device is not judged in control and no correction is offered."""
    db = tmp_path / "lab.sqlite"
    for source, days, a in history:
        device_history.store(dated(source, days, a), db)
    kept = device_history.in_sittings(device_history.estimates_for("CD-7", db))
    assert len(kept) == sittings and kept[-1].source == "run-2"
    correction, why = device_history.correction_for("CD-7", db)
    if sittings == 1:
        assert correction is None and "from 1 sitting(s); two sittings" in why
    else:
        assert correction is not None and why == ""


def test_a_corrections_u_grows_with_its_age_at_the_walk_rate_of_its_history(tmp_path):
    """Three sittings 30 days apart whose a moved by 2.5″ each time (u = 1″ each, so in control: the
    history flags only |Δ| > √(1.96² · 2) = 2.77″): the moment estimate of the walk's variance rate, by
    hand, is (2 · 2.5² − 2 · 2 · 1²)/60 = 0.14167 arcsec²/day; the correction 10 days after the last
    estimate carries √(1 + 0.14167 · 10) = 1.5546″ for a, the others (no change, q̂ = 0) their own 1″."""
    from labcal.analysis.kinematics import ARCSEC

    db = tmp_path / "lab.sqlite"
    for source, days, a in (("run-1", 70.0, 40.0), ("run-2", 40.0, 42.5), ("run-3", 10.0, 45.0)):
        device_history.store(dated(source, days, a), db)
    today = device_history.calibrated(dated("now", 0.0, 0.0))  # 01:00 UTC today: ten days after run-3
    correction, why = device_history.correction_for("CD-7", db, now=today)
    assert why == "" and correction is not None
    assert correction.u_rad["a"] / ARCSEC == pytest.approx(1.5546, abs=0.0001)
    assert correction.u_rad["b"] / ARCSEC == pytest.approx(1.0, rel=1e-6)


def test_the_walk_rate_and_its_uncertainty_are_those_of_simulated_histories():
    """Monte Carlo: 4000 histories of five sittings at irregular intervals, each estimate's error
    normal with its stated u, the truth a random walk of rate q = 0.05 arcsec²/day: the mean of q̂ is
    q (within 3 standard errors; the truncation at 0 is rare at this rate); the variance formula at the
    true rate is the scatter of q̂ within 10 %, and the stated u(q̂) (the formula at each history's
    own q̂) within 25 % in the median."""
    from datetime import UTC, datetime, timedelta

    import numpy as np

    from labcal.analysis.device_ageing import walk_rate

    rng = np.random.default_rng(34)
    q, days = 0.05, np.array([0.0, 40.0, 75.0, 130.0, 160.0])
    u = np.full((5, 6), 0.4)
    start = datetime(2026, 1, 1, tzinfo=UTC)
    times = [start + timedelta(days=float(d)) for d in days]
    found, stated = [], []
    for _ in range(4000):
        walk = np.cumsum(np.vstack([np.zeros(6), rng.normal(0, np.sqrt(q * np.diff(days))[:, None], (4, 6))]),
                         axis=0)
        values = walk + rng.normal(0.0, u)
        rate = walk_rate(times, list(values), list(u))
        found.append(rate.q)
        stated.append(rate.u_q)
    found_a, stated_a = np.array(found), np.array(stated)
    assert abs(found_a.mean() - q) < 3 * found_a.std() / np.sqrt(found_a.size)
    # at the true rate, by hand: Var Σd² = 2(Σ C_ii² + 2 Σ C_i,i+1²), C_ii = 2u² + qΔt, C_i,i+1 = −u²
    c = 2 * 0.4**2 + q * np.diff(days)
    at_truth = np.sqrt(2 * (np.sum(c**2) + 2 * 3 * 0.4**4)) / 160.0
    assert at_truth == pytest.approx(float(found_a.std()), rel=0.10)
    # stated, it is a plug-in of each history's own q̂: about right, not exact
    assert float(np.median(stated_a)) == pytest.approx(float(found_a.std()), rel=0.25)


def test_a_correction_past_its_age_or_its_uses_is_not_offered_and_its_plan_is_refused(tmp_path, monkeypatch,
                                                                                     capsys):
    """The lab file's limits (here 30 days and 2 uses): an estimate 40 days old is expired, one line
    naming the plan that identifies the device again; within the age, a plan is refused once its
    estimate has corrected two complete runs."""
    from labcal.documents.device_history import IDENTIFYING_PLAN, correction_uses, expired

    lab = tmp_path / "labcal.toml"
    lab.write_text("[device_correction]\nmax_age_days = 30\nmax_uses = 2\n", encoding="utf-8")
    monkeypatch.setenv("LABCAL_CONFIG", str(lab))
    db = tmp_path / "lab.sqlite"
    device_history.store(dated("run-1", 60.0, 40.0), db)
    device_history.store(dated("run-2", 40.0, 40.2), db)
    today = device_history.calibrated(dated("now", 0.0, 0.0))  # 01:00 UTC today: 40 days after run-2
    correction, why = device_history.correction_for("CD-7", db, now=today)
    assert correction is None
    assert "run-2 is 40 days old, past the lab's 30-day limit" in why and f"--plan {IDENTIFYING_PLAN}" in why
    device_history.store(dated("run-3", 5.0, 40.1), db)
    assert device_history.correction_for("CD-7", db)[0] is not None
    assert correction_uses("CD-7", "run-3", db) == 0
    from labcal.config.corrections import DeviceCorrectionTable
    from labcal.config.plans import correction_toml
    from labcal.store.journal import Journal, Manifest

    table = DeviceCorrectionTable(device_id="CD-7", source="run-3", calibrated_utc="x",
                                  value_arcsec=dict.fromkeys(NAMES, 0.0), U_arcsec=dict.fromkeys(NAMES, 1.0),
                                  u_arcsec=dict.fromkeys(NAMES, 1.0))
    with Journal(db) as journal:
        for n in range(2):
            run = journal.start_run(Manifest(run_dir=f"run-dir-{n}", plan_name="corrected",
                                             plan_text=correction_toml(table), station_text="",
                                             software_version="0", settings={}, metadata={}))
            journal.finish(run, "complete")
    assert correction_uses("CD-7", "run-3", db) == 2
    latest = device_history.estimates_for("CD-7", db)[-1]
    why = expired("CD-7", "run-3", device_history.calibrated(latest), db)
    assert why is not None and "has corrected 2 runs, the lab's limit (2)" in why
