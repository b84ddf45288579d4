"""Fit options on the shipped plans, honest digits and progress."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from rich.console import Console

from labcal.analysis.coning import coning
from labcal.analysis.fit import fit_readings
from labcal.cli import main
from labcal.commands.console import ProgressDisplay, with_standard_error
from labcal.config.emulation import InstrumentTruth
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.run.events import PointMeasured, Status
from labcal.run.sequencer import Forecast, schedule
from labcal.sim.direct import simulate_readings
from labcal.store.journal import PointRecord


def test_omega_near_zero_is_flagged_because_its_interval_undercovers():
    """An ideal instrument (Ω = 0 on every axis), 200 noisy calibrations: Ω̂ ± 1.96·u covers the true
    0 about 85 % of the time (Rayleigh: 1 − exp(−1.96²/2) = 0.853), not 95 % — and the fit says so."""
    plan = load_plan("four-mount-64")[0]
    covered, flagged = [], []
    for seed in range(200):
        readings = simulate_readings(plan, InstrumentTruth(), noise_v=1e-4, seed=seed)
        for sensor in coning(fit_readings(readings)):
            omega, u = sensor.values[2], np.sqrt(sensor.covariance[2, 2])
            covered.append(abs(omega - 0.0) <= 1.96 * u)
            flagged.append(not sensor.to_json()["omega_interval_reliable"])
    rayleigh = 1 - np.exp(-1.96**2 / 2)
    assert abs(np.mean(covered) - rayleigh) < 3 * np.sqrt(rayleigh * (1 - rayleigh) / len(covered))
    assert np.mean(flagged) > 0.97  # P(Ω̂ < 3u | Ω = 0) = 1 − exp(−4.5) = 0.989


@pytest.fixture
def readings_csv(tmp_path, capsys) -> str:
    path = tmp_path / "readings.csv"
    truth = tmp_path / "truth.toml"
    truth.write_text("B = [0.01, 0, 0]\nS = [[5, 0.01, 0], [0, 5, 0], [0, 0, 5]]\n")
    assert main(["simulate", "--noise", "1e-4", "--truth", str(truth), "--out", str(path)]) == 0
    capsys.readouterr()
    return str(path)


def test_extend_harmonics_on_four_mount_64_drops_the_aliased_terms_with_a_note(readings_csv, capsys):
    assert main(["fit", readings_csv, "--extend", "harmonics", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["extensions"]["names"] == ["cos 2α", "cos 2R"]  # sin 2α, sin 2R vanish on 0/90/180/270
    assert any("sin 2α, sin 2R left out: this plan cannot estimate them" in n for n in doc["notes"])


def test_extend_temperature_prints_the_terms_and_coning_marks_omega(tmp_path, capsys, terminal):
    terminal(100)
    assert main(["run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "run")]) == 0
    readings = tmp_path / "run" / "readings.csv"
    capsys.readouterr()
    assert main(["fit", str(readings), "--extend", "temperature", "--model", "coning"]) == 0
    out = capsys.readouterr().out
    assert "Extension terms (t_ref = " in out and "dS_x/dT (V/(g·°C))" in out and "dB/dT (V/°C)" in out
    assert "± u (k=1)" in out


@pytest.mark.parametrize("value,se,expected", [
    (4.98715012345, 0.0000193, "+4.987150 ± 0.000019"),
    (-0.01048312, 0.000027, "-0.010483 ± 0.000027"),
    (1234.5678, 12.0, "+1235 ± 12"),
    (0.5, float("nan"), "+0.5"),
])
def test_coefficients_to_the_digits_their_standard_error_supports(value, se, expected):
    assert with_standard_error(value, se) == expected


def test_progress_of_a_resume_counts_what_remains_and_fits_80_columns():
    buffer = io.StringIO()
    console = Console(file=buffer, width=80, force_terminal=False)
    plan, _ = load_plan("four-mount-64")
    steps = schedule(plan, SequencerSettings())
    forecast = Forecast({s.seq: 10.0 for s in steps}, {}, {})  # 64 steps of 10 s on the rig's clock
    ahead = forecast.ahead(steps[16:])  # resumed after 16 points
    assert ahead[0][1] == 480.0 and ahead[1][1] == 470.0  # the 48 steps that remain, not all 64; then 47
    display = ProgressDisplay(console, 64, done=16)
    with display:
        display(Status(run_id=1, rig_time_s=3713.0, status="running", at="start", points_done=16,
                       points_total=64, eta_s=ahead[0][1]))
        assert display.progress.tasks[0].fields["rig_eta"] == "8:00"
        record = PointRecord(16, 1, 180, 0, 270, 270, 270, 270, 1, "ok", 3700.0, 3723.0, 10,
                             0.1, 0.2, 0.3, 1e-5, 1e-5, 1e-5, None, 2.0, "settled")
        display(PointMeasured(run_id=1, rig_time_s=3723.0, seq=16, replicate=1, mount=2, pitch_deg=270,
                              roll_deg=270, volts=(0.1, 0.2, 0.3), settle_s=2.0, ok=True, points_done=17,
                              points_total=64, record=record))
        display(Status(run_id=1, rig_time_s=3723.0, status="running", at="point", points_done=17,
                       points_total=64, eta_s=ahead[1][1]))
    text = buffer.getvalue()
    assert "'rig' is the rig's own clock" in text  # said once, where the line starts
    final = [line for line in text.splitlines() if "17/64" in line][-1]
    assert "rig 1:02:03 ETA 7:50" in final and "…" not in final and len(final) <= 80
