"""The sequencer on the simulated rig: interrupts, resume, operator checks, limits, settling."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from conftest import quiet_console, run_on_rig

from labcal.analysis.kinematics import MOUNTS, Mount
from labcal.bench.setup import sim_station
from labcal.config.emulation import RigConfig
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings, SettleSettings
from labcal.devices.winding import left_at
from labcal.errors import LabcalError
from labcal.run.events import EventBus
from labcal.run.operator import AutoOperator, OperatorDeclined, ScriptedOperator
from labcal.run.runner import calibrate, execute, open_for_resume
from labcal.run.sequencer import schedule
from labcal.sim.rig import SimRig
from labcal.store.journal import Journal

STATIC_LAB = str(Path(__file__).parent.parent / "data" / "rig_static_lab.toml")


class After:
    """Does something (raise, or signal this process) when the n-th point is done: a subscriber of
    the run's "point" events (`events()` gives a bus with it subscribed)."""

    def __init__(self, n: int, action):
        self.n, self.action, self.done = n, action, 0

    def events(self) -> EventBus:
        bus = EventBus()
        bus.subscribe(self, kinds=("point",))
        return bus

    def __call__(self, event):
        self.done += 1
        if self.done in (self.n if isinstance(self.n, tuple) else (self.n,)):
            self.action()


def ctrl_c():
    os.kill(os.getpid(), signal.SIGINT)


def journal_run(tmp_path, setup, after=None, operator=None, settings=None, plan_name="four-mount-64"):
    plan, text = load_plan(plan_name)
    run_dir = tmp_path / "run"
    run_dir.mkdir(exist_ok=True)
    settings = settings or SequencerSettings(settle=setup.settle)
    with Journal(tmp_path / "j.sqlite") as journal:
        return calibrate(plan, text, setup.station, setup.text, operator or AutoOperator(quiet_console()),
                         settings, run_dir, journal, after and after.events())


def resume_in_process(run_dir: Path, operator=None):
    ctx = open_for_resume(run_dir)  # as `labcal resume` does: the rig's clock and tables where they were left
    setup = sim_station(None, None, snapshot=ctx.station_text, start_time_s=ctx.journal.rig_time(ctx.run_id),
                        tables_at=left_at(ctx.journal.events(ctx.run_id)))
    with ctx.journal, ctx.lock:
        return execute(ctx.journal, ctx.run_id, run_dir, ctx.plan, setup.station,
                       operator or AutoOperator(quiet_console()), ctx.settings)


def test_schedule_snakes_mounts_and_reseats_between_replicates():
    plan, _ = load_plan("four-mount-64")
    plan = plan.model_copy(update={"replicates": 3})
    steps = schedule(plan, SequencerSettings())
    blocks = [s for s in steps if s.block_start]
    assert [b.mount for b in blocks] == list(MOUNTS) + list(MOUNTS)[::-1] + list(MOUNTS)
    assert [s.seq for s in steps] == list(range(192)) and len(blocks) == 12
    for rep in (1, 2, 3):  # every replicate visits every point of every mount once
        got = sorted((s.mount.y_deg, s.mount.u_deg, s.pitch_deg, s.roll_deg)
                     for s in steps if s.replicate == rep)
        assert got == sorted((y, u, p, r) for y, u in plan.mounts for p, r in plan.points)


def test_even_replicates_walk_the_shortest_tour_backwards():
    """Each point is reached from the other side in the next replicate, so the transient a move
    leaves (signed like the move) cancels between replicates instead of adding up."""
    plan, _ = load_plan("four-mount-64")
    plan = plan.model_copy(update={"replicates": 2})
    steps = schedule(plan, SequencerSettings())
    for mount in MOUNTS:
        tours = [[(s.pitch_deg, s.roll_deg) for s in steps if s.replicate == rep and s.mount == mount]
                 for rep in (1, 2)]
        assert tours[1] == tours[0][::-1] and tours[0] != tours[1]


def test_first_ctrl_c_pauses_after_the_point_then_the_run_goes_on(tmp_path):
    answers = tmp_path / "answers.txt"
    answers.write_text("y\nr\ny\ny\ny\n")  # mount 1, resume after the pause, mounts 2-4
    result = journal_run(tmp_path, sim_station(None, 1), After(10, ctrl_c),
                         ScriptedOperator(quiet_console(), answers))
    assert result.outcome.points_recorded == 64
    with Journal(tmp_path / "j.sqlite") as journal:
        events = journal.events(result.run_id)
        kinds = [e.kind for e in events]
        assert "pause" in kinds and "resume" in kinds
        pause_at = kinds.index("pause")
        paused_at = events[pause_at].station_time
        points_before = [p for p in journal.points(result.run_id) if p.t_end <= paused_at]
        assert len(points_before) == 10  # paused right after the 10th point, nothing cut short


def test_second_ctrl_c_stops_the_tables_at_once_and_keeps_every_point(tmp_path):
    setup = sim_station(None, 2)
    rig_axes = setup.station.pitch, setup.station.roll
    stops = []
    for axis in rig_axes:
        original = axis.stop
        axis.stop = (lambda a, o: lambda: (stops.append(a.name), o()))(axis, original)
    with pytest.raises(KeyboardInterrupt):
        journal_run(tmp_path, setup, After(7, lambda: (ctrl_c(), ctrl_c())))
    assert sorted(stops) == ["pitch", "roll"]
    with Journal(tmp_path / "j.sqlite") as journal:
        run = journal.run(1)
        assert run.status == "interrupted" and len(journal.points(1)) == 7
    assert len((tmp_path / "run" / "readings.csv").read_text().strip().splitlines()) == 1 + 7


def test_a_failing_stop_does_not_hide_why_the_run_ended(tmp_path):
    setup = sim_station(None, 3)

    def broken_stop():
        raise OSError("port closed")

    setup.station.roll.stop = broken_stop
    with pytest.raises(KeyboardInterrupt) as exc:
        journal_run(tmp_path, setup, After(3, lambda: (_ for _ in ()).throw(KeyboardInterrupt)))
    assert exc.value.__notes__ == ["STOP FAILED: the stop did not reach the roll table (roll: port closed)"]
    with Journal(tmp_path / "j.sqlite") as journal:
        stops = [e for e in journal.events(1) if e.kind == "stop"]
    assert [s.data["may_be_moving"] for s in stops] == [["roll"]]


def test_a_wrong_mount_is_caught_before_any_point_is_kept(tmp_path):
    setup = sim_station(STATIC_LAB, 4)
    rig_remounted = setup.station.remounted
    mistakes = {Mount(180, 0): Mount(0, 180)}  # first time asked for top-backward, the technician errs

    def technician(mount):
        rig_remounted(mistakes.pop(mount, mount))

    setup.station.remounted = technician
    result = journal_run(tmp_path, setup)
    with Journal(tmp_path / "j.sqlite") as journal:
        faults = [e.message for e in journal.events(result.run_id) if e.kind == "fault"]
        points = journal.points(result.run_id)
    assert faults == ["wrong mount: expected y=180°, u=0°, reads as y=0°, u=180°"]
    assert len(points) == 64
    x = result.fit.coefficients
    assert np.max(np.abs(x[1:][~np.eye(3, dtype=bool)] - np.array(
        [[0.0106, 0.0074], [-0.015, -0.0027], [-0.0105, -0.0061]]).ravel())) < 1e-4


def test_limits_are_checked_before_anything_moves(tmp_path):
    setup = sim_station(None, 5)

    def check(angle):
        if (angle % 360) == 270:
            raise LabcalError("270° is outside the soft limits [-100°, 200°]")

    setup.station.pitch.check_angle = check
    with pytest.raises(LabcalError, match="plan refused before any motion: pitch 270° is outside"):
        journal_run(tmp_path, setup)
    assert setup.station.pitch.travel_deg == 0 and setup.station.roll.travel_deg == 0


def test_a_point_that_never_settles_is_retried_then_handled_by_the_policy(tmp_path):
    """The rig's noise is 20 µV; the sequencer is told to expect 2 µV, so no window ever passes
    the scatter test: each point is retried once, recorded as failed, and the policy decides. The
    window the test refused first is journaled as discarded, with its samples: nothing taken is lost."""
    tight = SettleSettings(noise_v=2e-6, max_dwell_s=6)
    with pytest.raises(LabcalError, match="finished without enough good points to fit"):
        run_on_rig(SimRig(RigConfig(), seed=6), "one-mount-16", tmp_path,
                   SequencerSettings(settle=tight, check_mount=False, on_failure="skip"))
    with Journal(tmp_path / "journal.sqlite") as journal:
        failed = journal.points(1, status="failed")
        retries = [e for e in journal.events(1) if e.kind == "retry"]
        discarded = [e.data for e in journal.events(1) if e.kind == "discarded"]
        assert journal.run(1).status == "failed"
    assert len(failed) == 16 and len(retries) == 16
    assert sorted(d["seq"] for d in discarded) == sorted(p.seq for p in failed)
    assert all(d["attempt"] == 1 and len(d["samples"]) >= tight.samples for d in discarded)
    assert all(p.attempt == 2 and p.settle_verdict != "settled" for p in failed)
    (tmp_path / "abort").mkdir()
    with pytest.raises(LabcalError, match="did not settle.*on_failure = abort"):
        run_on_rig(SimRig(RigConfig(), seed=6), "one-mount-16", tmp_path / "abort",
                   SequencerSettings(settle=tight, check_mount=False, on_failure="abort"))


def test_resumed_run_equals_the_uninterrupted_one(tmp_path):
    """Noise is drawn per point, so an interrupted and resumed run on a static lab gives the
    uninterrupted coefficients to a small fraction of their uncertainty. What remains is the
    tables' transient history: the first point after the resume is reached by another move, and
    settling leaves each point's mean a bias of up to σ/√N by design; one point of 64 moves the
    coefficients by a few hundredths of their SE, inside the 0.1 SE settling is held to."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    whole = journal_run(tmp_path / "a", sim_station(STATIC_LAB, 7))
    with pytest.raises(KeyboardInterrupt):
        journal_run(tmp_path / "b", sim_station(STATIC_LAB, 7),
                    After(23, lambda: (_ for _ in ()).throw(KeyboardInterrupt)))
    resumed = resume_in_process(tmp_path / "b" / "run")
    assert resumed.outcome.points_recorded == 64
    diff = np.abs(resumed.fit.coefficients - whole.fit.coefficients) / whole.fit.stderr
    assert np.max(diff) < 0.1, diff


def test_dry_run_estimate_matches_the_rig_and_moves_nothing(tmp_path, capsys):
    from labcal.cli import main

    assert main(["run", "--sim", "--dry-run", "--json", "--seed", "9"]) == 0
    estimate = json.loads(capsys.readouterr().out)
    assert main(["run", "--sim", "--yes", "--json", "--no-report", "--seed", "9",
                 "--out", str(tmp_path / "run")]) == 0
    actual = json.loads(capsys.readouterr().out)["simulated_rig_time_s"]
    assert estimate["total_s"] == pytest.approx(actual, rel=0.05)
    assert estimate["points"] == 64 and not (tmp_path / "dry").exists()


def test_resume_refuses_what_it_cannot_continue(tmp_path, capsys, lab_database):
    from labcal.cli import main

    run_dir = tmp_path / "run"
    assert main(["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16",
                 "--out", str(run_dir)]) == 0
    capsys.readouterr()
    assert main(["resume", str(run_dir), "--yes", "--no-report"]) == 0  # only checks its exports
    assert "already complete; its files in" in capsys.readouterr().err
    assert main(["resume", str(tmp_path / "nowhere")]) == 2
    assert "no such run directory" in capsys.readouterr().err
    with sqlite3.connect(lab_database) as con:  # someone edits the plan inside the journal
        con.execute("UPDATE runs SET status='interrupted', plan_text=plan_text || '# edited'")
    assert main(["resume", str(run_dir), "--yes"]) == 2
    assert "does not match its recorded hash" in capsys.readouterr().err


def test_a_device_fault_pauses_and_resuming_retries_the_point(tmp_path):
    """A voltmeter that fails once (as an emulator's injected fault would) stops the tables and
    pauses with the device's message; the operator resumes and the point is measured again."""
    from labcal.drivers.errors import NoReply

    setup = sim_station(None, 10)
    dmm, calls = setup.station.dmm, {"n": 0}
    real_read = dmm.read

    def flaky_read(n):
        calls["n"] += 1
        if calls["n"] == 40:
            raise NoReply("no reply to READ? within 2 s", "DMM (34970A at socket://127.0.0.1:5025)")
        return real_read(n)

    dmm.read = flaky_read
    answers = tmp_path / "answers.txt"
    answers.write_text("y\ny\ny\nr\ny\n")  # the 40th read is in mount 3: mounts 1-3, resume, mount 4
    result = journal_run(tmp_path, setup, operator=ScriptedOperator(quiet_console(), answers))
    assert result.outcome.points_recorded == 64
    with Journal(tmp_path / "j.sqlite") as journal:
        events = journal.events(result.run_id)
    faults = [e.message for e in events if e.kind == "fault"]
    assert faults == ["DMM (34970A at socket://127.0.0.1:5025): no reply to READ? within 2 s"]
    assert [e.kind for e in events].count("pause") == 1


def test_a_device_fault_with_nobody_to_answer_stops_and_keeps_every_point(tmp_path):
    setup = sim_station(None, 11)
    real_move = setup.station.roll.move_to
    moves = {"n": 0}

    def failing_move(angle, **way):
        moves["n"] += 1
        if moves["n"] > 12:
            raise LabcalError("roll table (simulated): alarm 0x30 overload")
        real_move(angle, **way)

    setup.station.roll.move_to = failing_move
    answers = tmp_path / "answers.txt"
    answers.write_text("y\n")  # mount 1 only: the pause finds no answer
    # the fault is why the run stopped; the unanswered pause comes second
    with pytest.raises(OperatorDeclined, match=r"^fault: roll table \(simulated\): alarm 0x30 overload; "
                                               "paused, and the answers file has no answer left for this "
                                               "prompt$"):
        journal_run(tmp_path, setup, operator=ScriptedOperator(quiet_console(), answers))
    with Journal(tmp_path / "j.sqlite") as journal:
        assert journal.run(1).status == "stopped" and len(journal.points(1)) == 10  # 2 moves: load, check


def test_during_a_run_a_stop_waits_for_the_device_exchange_to_finish():
    """The drivers' exchanges are critical sections of the run's Ctrl-C handler: a second Ctrl-C
    arriving in the middle of one is raised only when the exchange is complete."""
    from labcal.drivers.transport import uninterruptible
    from labcal.run.interrupts import Interrupts

    finished = []
    with Interrupts() as interrupts, pytest.raises(KeyboardInterrupt):
        with uninterruptible(interrupts.critical):
            ctrl_c()  # first: a pause is requested, nothing is raised
            ctrl_c()  # second: deferred
            finished.append("reply read")
    assert finished == ["reply read"] and interrupts.count == 2
