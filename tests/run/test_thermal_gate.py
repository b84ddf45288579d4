"""The thermal gate: before each mount's points the run waits until the instrument's temperature
changes slowly enough for long enough; the simulated instrument's warm-up settles, and the
estimate counts the wait."""

from __future__ import annotations

import json
import math
import sqlite3

import pytest
from conftest import run_on_rig

from labcal.config.emulation import DeviceTruth, InstrumentTruth, RigConfig
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings, SettleSettings, ThermalGate
from labcal.run.estimate import Timing, estimate
from labcal.sim.rig import SimRig

WARMUP_C, WARMUP_TAU_S = 2.0, 600.0  # the instrument 2 °C above the lab at switch-on, decaying over 10 min
GATE = ThermalGate(rate_c_per_min=0.05, hold_s=300.0, poll_s=30.0)
# Its rate is (WARMUP_C/τ)·e^{−t/τ} per second: 0.2·e^{−t/600} °C/min, within 0.05 °C/min only
# after t = 600·ln 4 ≈ 832 s of rig time (the lab's own swing is off).
SETTLED_AFTER_S = WARMUP_TAU_S * math.log(60 * WARMUP_C / WARMUP_TAU_S / GATE.rate_c_per_min)


def rig() -> SimRig:
    truth = InstrumentTruth(noise_v=20e-6, warmup_c=WARMUP_C, warmup_tau_s=WARMUP_TAU_S)
    config = RigConfig(device=DeviceTruth(misalignment_deg={}, index_arcsec=0, wobble_arcsec=0),
                       instrument=truth, lab_temp_swing_c=0.0, remount_s=0.0)
    return SimRig(config, seed=3)


def first_point_and_notes(tmp_path) -> tuple[float, list[dict]]:
    with sqlite3.connect(tmp_path / "journal.sqlite") as db:
        first = db.execute("SELECT MIN(t_start) FROM points").fetchone()[0]
        notes = [{"message": m, "data": json.loads(d)}
                 for m, d in db.execute("SELECT message, data FROM events WHERE kind = 'thermal'")
                 if "waited_s" in json.loads(d)]  # each wait's end (its beginning is journaled too)
    return first, notes


def test_the_thermal_gate_holds_a_run_until_the_warm_up_settles(tmp_path):
    """Without the gate the first point is measured while the instrument still warms faster than
    0.05 °C/min; with it, not before the rate has fallen below the limit (832 s, by hand from the
    warm-up's exponential), and the wait is journaled at each of the plan's four mounts, the first
    one the longest."""
    settle = SettleSettings(tau_s=0.5, noise_v=20e-6, samples=10)
    (tmp_path / "free").mkdir()
    (tmp_path / "gated").mkdir()
    run_on_rig(rig(), "four-mount-64", tmp_path / "free", SequencerSettings(settle=settle))
    free_first, free_notes = first_point_and_notes(tmp_path / "free")
    assert free_first < SETTLED_AFTER_S and not free_notes

    run_on_rig(rig(), "four-mount-64", tmp_path / "gated",
               SequencerSettings(settle=settle, thermal_gate=GATE))
    first, notes = first_point_and_notes(tmp_path / "gated")
    assert first >= SETTLED_AFTER_S
    assert len(notes) == 4 and all(n["data"]["settled"] for n in notes)
    waits = [n["data"]["waited_s"] for n in notes]
    assert waits[0] >= SETTLED_AFTER_S - 60 and waits[0] == max(waits)
    assert all(w >= GATE.hold_s for w in waits)  # the rate must be seen low for hold_s each time
    assert "thermal gate: waited" in notes[0]["message"]


def test_the_estimate_includes_the_thermal_gates_least_wait_at_every_mount():
    """Four mounts, a 300 s hold each: the estimate grows by 1200 s, all of it in the mounting."""
    plan, _ = load_plan("four-mount-64")
    timing = Timing(clamp_s=1.0, sample_s=0.2, remount_s=300.0)
    free = estimate(plan, SequencerSettings(), timing)
    gated = estimate(plan, SequencerSettings(thermal_gate=GATE), timing)
    assert gated.total_s - free.total_s == pytest.approx(4 * 300.0, abs=1e-6)
    assert gated.mounting_s - free.mounting_s == pytest.approx(4 * 300.0, abs=1e-6)
    assert gated.thermal_s == 4 * 300.0


def test_a_dry_run_shows_the_thermal_gates_wait(tmp_path, capsys):
    """`labcal run --sim --thermal-gate 0.05 300 --dry-run --json`: 1200 s more than without, all of it
    the gate's (four mounts of four-mount-64, 300 s each)."""
    from cli import cli

    code, out, err = cli(capsys, "run", "--sim", "--dry-run", "--json")
    assert code == 0, err
    free = json.loads(out)
    code, out, err = cli(capsys, "run", "--sim", "--dry-run", "--json", "--thermal-gate", "0.05", "300")
    assert code == 0, err
    gated = json.loads(out)
    assert gated["thermal_gate_s"] == 1200.0 and "thermal_gate_s" not in free
    assert gated["total_s"] - free["total_s"] == 1200.0


def test_a_station_files_thermal_gate_is_validated_with_the_file(tmp_path):
    """[instrument] thermal_gate is read with the station file; a rate of zero is refused there."""
    from labcal.config.station import InstrumentSettings

    given = {"thermal_gate": {"rate_c_per_min": 0.05, "hold_s": 300}}
    assert InstrumentSettings.model_validate(given).thermal_gate == GATE
    with pytest.raises(ValueError, match="rate_c_per_min"):
        InstrumentSettings.model_validate({"thermal_gate": {"rate_c_per_min": 0, "hold_s": 300}})
