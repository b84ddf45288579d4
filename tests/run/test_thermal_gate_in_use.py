"""The thermal gate while a run waits at it: the estimate counts it only where the station reads a
temperature, the status (and its ETA) is said at every read, a Ctrl-C pauses the wait, and the
operator may ask for the gate during a run (a key at the console)."""

from __future__ import annotations

import json
import os
import signal
import sqlite3

import pytest

from labcal.config.emulation import DeviceTruth, InstrumentTruth, RigConfig
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings, SettleSettings, ThermalGate
from labcal.run.estimate import Timing, estimate
from labcal.run.events import EventBus, Paused, Status
from labcal.run.operator import GATE_KEY, AutoOperator, PauseChoice, Terminal
from labcal.sim.rig import SimRig

WARMUP_C, WARMUP_TAU_S = 2.0, 600.0  # 2 °C above the lab at switch-on, decaying over 10 min
GATE = ThermalGate(rate_c_per_min=0.05, hold_s=300.0, poll_s=30.0)
SETTLE = SettleSettings(tau_s=0.5, noise_v=20e-6, samples=10)


def rig(warmup_c: float = WARMUP_C) -> SimRig:
    truth = InstrumentTruth(noise_v=20e-6, warmup_c=warmup_c, warmup_tau_s=WARMUP_TAU_S)
    config = RigConfig(device=DeviceTruth(misalignment_deg={}, index_arcsec=0, wobble_arcsec=0),
                       instrument=truth, lab_temp_swing_c=0.0, remount_s=0.0)
    return SimRig(config, seed=3)


def thermal_notes(tmp_path) -> list[dict]:
    with sqlite3.connect(tmp_path / "journal.sqlite") as db:
        return [{"message": m, "data": json.loads(d), "t": t} for m, d, t in db.execute(
            "SELECT message, data, station_time FROM events WHERE kind = 'thermal' ORDER BY id")]


class ResumesAfterAPause(AutoOperator):
    """--yes, and the person who pressed Ctrl-C answers the pause prompt: go on."""

    def after_pause(self, why: str, moving: tuple[str, ...] = ()) -> PauseChoice:
        return "resume"


def calibrate_on(rig_: SimRig, tmp_path, settings: SequencerSettings, events: EventBus | None = None,
                 terminal: Terminal | None = None, plan_name: str = "four-mount-64"):
    from conftest import quiet_console

    from labcal.run.runner import calibrate
    from labcal.store.journal import Journal

    plan, text = load_plan(plan_name)
    (tmp_path / "run").mkdir(exist_ok=True)
    forecast = estimate(plan, settings, Timing(clamp_s=rig_.config.clamp_s, sample_s=rig_.config.nplc
                                               / rig_.config.line_hz, remount_s=0.0)).forecast()
    with Journal(tmp_path / "journal.sqlite") as journal:
        return calibrate(plan, text, rig_.station(), "simulated rig", ResumesAfterAPause(quiet_console()),
                         settings, tmp_path / "run", journal, events, terminal=terminal, forecast=forecast)


def test_the_estimate_counts_no_gate_where_the_station_reads_no_temperature():
    """The gate waits only where a temperature is read: a station without a temperature channel
    (az-modbus-rtu) estimates a gated run as an ungated one; one with it (az-modbus-tcp, channel
    104) adds the hold at each of four mounts."""
    from labcal.bench.setup import station_timing
    from labcal.config.station import load_station

    plan, _ = load_plan("four-mount-64")
    gated = SequencerSettings(thermal_gate=GATE)
    without, _ = load_station("az-modbus-rtu")
    with_channel, _ = load_station("az-modbus-tcp")
    assert without.dmm.temperature_channel is None and with_channel.dmm.temperature_channel is not None
    for config, added in ((without, 0.0), (with_channel, 4 * GATE.hold_s)):
        timing = station_timing(config)
        assert timing.temperature == (added > 0)
        extra = estimate(plan, gated, timing).total_s - estimate(plan, SequencerSettings(), timing).total_s
        assert extra == pytest.approx(added, abs=1e-6)
        assert estimate(plan, gated, timing).thermal_s == added


def test_the_status_is_said_at_every_read_of_the_gate_and_its_eta_counts_the_wait(tmp_path):
    """While the first mount's gate waits out the warm-up, a status is published at each read
    (every poll_s of rig time) with the ETA of the rest; it falls by about poll_s per read while the
    hold is still ahead, and stays above the rest of the run after the mount."""
    bus = EventBus()
    seen: list[Status] = []
    bus.subscribe(lambda e: seen.append(e) if isinstance(e, Status) else None, kinds=("status",))
    calibrate_on(rig(), tmp_path, SequencerSettings(settle=SETTLE, thermal_gate=GATE), bus)
    waiting = [s for s in seen if s.at == "thermal"]
    first_mount = next(s for s in seen if s.at == "mount")
    first = [s for s in waiting if s.rig_time_s < first_mount.rig_time_s]
    # the warm-up's rate 0.2·e^{-t/600} °C/min reaches 0.05 after 600·ln 4 ≈ 832 s: ~27 reads at 30 s
    assert len(first) >= 20
    times = [s.rig_time_s for s in first]
    assert all(30.0 <= b - a <= 31.0 for a, b in zip(times, times[1:], strict=False))
    etas = [s.eta_s for s in first]
    assert all(e is not None for e in etas)
    for a, b, ta, tb in zip(etas[:8], etas[1:9], times, times[1:], strict=False):  # the hold ahead
        assert a - b == pytest.approx(tb - ta, abs=1.0)
    assert min(etas) > first_mount.eta_s  # the wait is in the ETA until the gate opens
    assert all(s.points_done == 0 for s in first)
    with sqlite3.connect(tmp_path / "journal.sqlite") as db:  # the wait's statuses are not journaled
        assert db.execute("SELECT COUNT(*) FROM events WHERE kind = 'status' AND data LIKE '%thermal%'"
                          ).fetchone() == (0,)
    notes = thermal_notes(tmp_path)
    assert notes[0]["data"].get("waiting") and "waiting until the temperature settles" in notes[0]["message"]


def test_ctrl_c_during_the_gates_wait_pauses_the_run_and_the_gate_goes_on_after(tmp_path):
    """A Ctrl-C (SIGINT) while the gate waits: the run pauses there (journaled with its reason), the
    operator resumes, and the gate still waits until the temperature settles."""
    bus = EventBus()
    paused: list[Paused] = []
    sent = []

    def on_status(event):
        if isinstance(event, Status) and event.at == "thermal" and not sent:
            sent.append(event.rig_time_s)
            os.kill(os.getpid(), signal.SIGINT)

    bus.subscribe(on_status, kinds=("status",))
    bus.subscribe(lambda e: paused.append(e) if isinstance(e, Paused) else None, kinds=("pause",))
    result = calibrate_on(rig(), tmp_path, SequencerSettings(settle=SETTLE, thermal_gate=GATE), bus)
    assert sent and len(paused) == 1 and paused[0].why == "Ctrl-C during the thermal gate's wait"
    assert result.outcome.points_recorded == 64
    ends = [n for n in thermal_notes(tmp_path) if "waited_s" in n["data"]]
    assert len(ends) == 4 and all(n["data"]["settled"] for n in ends)
    with sqlite3.connect(tmp_path / "journal.sqlite") as db:
        kinds = [k for (k,) in db.execute("SELECT kind FROM events ORDER BY id")]
    assert "pause" in kinds and "resume" in kinds


class TypesGateKey(Terminal):
    """A terminal at which the operator types the gate's key once, after ``after`` calls."""

    def __init__(self, after: int):
        self.calls, self.after = 0, after

    def typed(self) -> str:
        self.calls += 1
        return GATE_KEY if self.calls == self.after else ""


def test_the_gate_asked_for_during_a_run_waits_before_the_next_point(tmp_path):
    """The key typed after the fifth point of the first mount: before the sixth, the run waits at
    the gate again (journaled as asked for), at least its hold; a run with no gate says it has none."""
    settings = SequencerSettings(settle=SETTLE, thermal_gate=GATE)
    calibrate_on(rig(warmup_c=0.0), tmp_path, settings, terminal=TypesGateKey(after=5))
    asked = [n for n in thermal_notes(tmp_path) if n["data"].get("on_demand") and "waited_s" in n["data"]]
    assert len(asked) == 1 and "(asked for during the run)" in asked[0]["message"]
    assert asked[0]["data"]["waited_s"] >= GATE.hold_s
    with sqlite3.connect(tmp_path / "journal.sqlite") as db:
        t5, t6 = (db.execute("SELECT t_start FROM points WHERE seq = ?", (i,)).fetchone()[0] for i in (4, 5))
    assert t6 - t5 >= GATE.hold_s
    assert t5 < asked[0]["t"] < t6

    (tmp_path / "none").mkdir()
    calibrate_on(rig(warmup_c=0.0), tmp_path / "none", SequencerSettings(settle=SETTLE),
                 terminal=TypesGateKey(after=5))
    (note,) = thermal_notes(tmp_path / "none")
    assert note["message"].startswith("thermal gate asked for, but the run has none")



@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_keys_typed_at_the_console_during_a_run_are_read_without_waiting():
    """The console's quiet keys on a pseudo-terminal: nothing typed reads as nothing at once; the
    gate's key typed reads back; the terminal's settings are restored on leaving."""
    import termios

    from labcal.run.operator import QuietKeys

    master, slave = os.openpty()
    try:
        keys = QuietKeys()
        keys.fd = slave  # the run's terminal: this pty's, not the test runner's stdin
        before = termios.tcgetattr(slave)
        with keys:
            assert keys.typed() == ""
            os.write(master, GATE_KEY.encode())
            assert keys.typed() == GATE_KEY
            assert keys.typed() == ""
        assert termios.tcgetattr(slave) == before
    finally:
        os.close(master)
        os.close(slave)
