"""The run's events: the bus's two tiers, subscribers that fail, the event stream of a
simulated run against its journal and its schedule; and `labcal run --sim --pace X`."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from conftest import quiet_console

from labcal.bench.setup import sim_station
from labcal.cli import main
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.run.estimate import estimate
from labcal.run.events import (
    EVENTS,
    SCHEMA_FILE,
    Answer,
    Discarded,
    EventBus,
    Fault,
    Note,
    Paused,
    PointMeasured,
    Prompt,
    Resumed,
    Status,
    Stopped,
    json_schema,
)
from labcal.run.operator import AutoOperator
from labcal.run.runner import calibrate
from labcal.run.sequencer import schedule
from labcal.store.journal import Journal, PointRecord


def note(i: int) -> Note:
    return Note(run_id=1, rig_time_s=float(i), name="retry", message=f"note {i}")


# --- the bus ------------------------------------------------------------------------------------
def test_durable_subscribers_hear_each_event_first_in_order_then_the_others():
    bus, heard = EventBus(), []
    bus.subscribe(lambda e: heard.append(("console", e.rig_time_s)))
    bus.subscribe(lambda e: heard.append(("sync", e.rig_time_s)), durable=True)
    bus.subscribe(lambda e: heard.append(("journal", e.rig_time_s)), durable=True, first=True)
    bus.subscribe(lambda e: heard.append(("notifier", e.rig_time_s)), kinds=("fault",))
    bus.publish(note(1))
    bus.publish(Fault(run_id=1, rig_time_s=2.0, message="pitch table: no answer"))
    assert heard == [("journal", 1.0), ("sync", 1.0), ("console", 1.0),
                     ("journal", 2.0), ("sync", 2.0), ("console", 2.0), ("notifier", 2.0)]


def test_a_failing_subscriber_is_logged_once_and_the_others_still_hear(caplog):
    bus, heard = EventBus(), []

    def away(event):
        raise ConnectionError("lab database server away")

    bus.subscribe(away)
    bus.subscribe(heard.append)
    with caplog.at_level(logging.WARNING, logger="labcal.run.events"):
        for i in range(3):
            bus.publish(note(i))
    assert [e.rig_time_s for e in heard] == [0.0, 1.0, 2.0]
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "lab database server away" in warnings[0].exc_text


def test_a_durable_subscriber_that_fails_stops_delivery_and_propagates():
    bus, heard = EventBus(), []

    def disk_full(event):
        raise OSError("disk full")

    bus.subscribe(disk_full, durable=True)
    bus.subscribe(heard.append)
    with pytest.raises(OSError, match="disk full"):
        bus.publish(note(1))
    assert heard == []  # nobody hears of what the journal does not have


def test_keyboard_interrupt_in_a_subscriber_is_never_swallowed():
    bus = EventBus()
    bus.subscribe(lambda e: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        bus.publish(note(1))


def test_an_unknown_kind_is_refused_when_subscribing():
    with pytest.raises(ValueError, match="unknown event kind"):
        EventBus().subscribe(print, kinds=("prompt", "remount"))


def test_an_event_reads_back_from_its_json_without_the_journals_payload():
    status = Status(run_id=3, rig_time_s=12.5, status="running", at="point", points_done=5, points_total=64,
                    mount=2, next_remount_in_s=40.0, eta_s=300.0)
    assert EVENTS.validate_json(status.model_dump_json()) == status
    record = PointRecord(7, 1, 0, 180, 30, 45, 30, 45, 1, "ok", 10.0, 12.0, 2, 0.1, 0.2, 0.3,
                         1e-5, 1e-5, 1e-5, None, 1.5, "settled")
    point = PointMeasured(run_id=3, rig_time_s=12.0, seq=7, replicate=1, mount=3, pitch_deg=30, roll_deg=45,
                          volts=(0.1, 0.2, 0.3), settle_s=1.5, ok=True, points_done=8, points_total=64,
                          record=record, samples=np.zeros((2, 4)))
    doc = json.loads(point.model_dump_json())
    assert "record" not in doc and "samples" not in doc and doc["kind"] == "point" and doc["mount"] == 3
    back = EVENTS.validate_json(point.model_dump_json())
    assert back.record is None and back.model_dump() == point.model_dump()
    assert not point.samples.flags.writeable
    with pytest.raises(Exception):  # noqa: B017 - frozen: pydantic's ValidationError
        status.points_done = 6  # type: ignore[misc]


def test_each_event_is_the_journal_row_it_always_was():
    """The events table's kind, message and data, as the sequencer journaled them before events
    existed (`labcal log`, the certificate's story and the lab database read them)."""
    at = {"run_id": 1, "rig_time_s": 5.0}
    rows = [
        (Answer(**at, what="mount", reply="n", meaning="not yet", outcome="open"),
         ("answer", "mount: 'n' (not yet; the prompt stays open)", None)),
        (Answer(**at, what="mount", reply="confirmed", meaning="confirmed", outcome="answered"),
         ("answer", "mount: confirmed", None)),
        (Answer(**at, what="pause", reply="declined", meaning="no answers left", outcome="declined"),
         ("answer", "pause: declined", {"reason": "no answers left"})),
        (Prompt(**at, what="pause", message="paused (Ctrl-C)", why="Ctrl-C", args=("Ctrl-C", "()")),
         ("prompt", "pause", {"args": ["Ctrl-C", "()"], "mount": None, "step": None, "n_steps": None,
                              "message": "paused (Ctrl-C)", "where": "", "note": "", "why": "Ctrl-C",
                              "may_be_moving": []})),
        (Paused(**at, why="Ctrl-C"), ("pause", "Ctrl-C", {"may_be_moving": []})),
        (Resumed(**at, why="operator resumed after the pause"),
         ("resume", "operator resumed after the pause", None)),
        (Fault(**at, message="point 3 failed: drift", policy="skip"),
         ("fault", "point 3 failed: drift", {"policy": "skip"})),
        (Fault(**at, message="wrong mount"), ("fault", "wrong mount", None)),
        (Stopped(**at, cause="Ctrl-C twice"), ("stop", "both tables stopped", {"cause": "Ctrl-C twice"})),
        (Stopped(**at, cause="x", failed="no reply", may_be_moving=("roll",)),
         ("stop", "stop failed: no reply", {"may_be_moving": ["roll"], "cause": "x"})),
        (Discarded(**at, seq=4, attempt=1, reason="pitch moving", faulted=False, volts=(1.0, 2.0, 3.0),
                   sd=(0.1, 0.1, 0.1), samples=((1.0, 2.0, 3.0, None),)),
         ("discarded", "point 4: readings discarded, measured again: pitch moving",
          {"seq": 4, "attempt": 1, "reason": "pitch moving", "volts": [1.0, 2.0, 3.0], "sd": [0.1, 0.1, 0.1],
           "samples": [[1.0, 2.0, 3.0, None]]})),
        (Note(**at, name="retry", message="point 2 did not settle"),
         ("retry", "point 2 did not settle", None)),
    ]
    for event, row in rows:
        assert event.journal_entry() == row
        assert list(event.journal_entry()[2] or {}) == list(row[2] or {})  # the JSON keeps its key order


def test_a_prompt_reads_back_by_name_and_from_an_older_journal_by_position():
    """A prompt journaled with its named fields and one journaled before them (positional ``args``
    only, an empty note left out) read back the same, and say the same to people."""
    from labcal.run.events import JournaledPrompt

    at = {"run_id": 1, "rig_time_s": 5.0}
    asked = Prompt(**at, what="mount", mount=2, step=2, n_steps=8, message="mount 2 of 8", where="y=0 u=90",
                   note="re-seat", args=("y=0 u=90", "2", "8", "re-seat"))
    kind, what, data = asked.journal_entry()
    named = JournaledPrompt.read(what, data)
    older = JournaledPrompt.read("mount", {"args": ["y=0 u=90", "2", "8", "re-seat"]})
    assert (named.where, named.step, named.n_steps, named.note) == ("y=0 u=90", 2, 8, "re-seat")
    assert named.text() == older.text() == "mount 2 of 8: y=0 u=90 (re-seat)"
    first = JournaledPrompt.read("mount", {"args": ["y=0 u=0", "1", "8", ""]})
    assert first.text() == "mount 1 of 8: y=0 u=0"
    paused = Prompt(**at, what="pause", message="paused (Ctrl-C)", why="Ctrl-C", may_be_moving=("roll",),
                    args=("Ctrl-C", "('roll',)"))
    assert JournaledPrompt.read("pause", paused.journal_entry()[2] or {}).text() == "paused: Ctrl-C"
    assert JournaledPrompt.read("pause", {"args": ["Ctrl-C", "()"]}).text() == "paused: Ctrl-C"
    assert JournaledPrompt.read("pause", {}).text() == "pause"


# --- a simulated run's events -----------------------------------------------------------------------
def sim_run(tmp_path, bus, plan_name="four-mount-64", seed=4):
    setup = sim_station(None, seed)
    plan, text = load_plan(plan_name)
    settings = SequencerSettings(settle=setup.settle)
    steps = schedule(plan, settings)
    est = estimate(plan, settings, setup.timing, steps)
    run_dir = tmp_path / "run"
    run_dir.mkdir(exist_ok=True)
    journal = Journal(tmp_path / "lab.sqlite")
    try:
        result = calibrate(plan, text, setup.station, setup.text, AutoOperator(quiet_console()), settings,
                           run_dir, journal, bus, steps=steps, forecast=est.forecast())
    finally:
        journal.close()
    return result, steps, est


ROOT = Path(__file__).resolve().parents[2]


def test_the_published_event_schema_is_the_one_the_models_generate():
    """Edit an event's model and not the published file (tools/schemas.py writes it): this fails."""
    assert json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8")) == json_schema()


def test_every_event_of_a_run_meets_the_published_schema_and_a_wrong_one_does_not(tmp_path):
    """Checked with the `jsonschema` library (a second implementation of the checks) on what a
    simulated run published, and on one event of each kind it did not (a fault, a pause ...)."""
    schema = json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    bus, events = EventBus(), []
    bus.subscribe(events.append)
    sim_run(tmp_path, bus, "one-mount-16")
    others = [Answer(run_id=1, rig_time_s=2.0, what="pause", reply="", meaning="operator stopped",
                     outcome="declined"),
              Fault(run_id=1, rig_time_s=3.0, message="DMM timeout", policy="skip"),
              Paused(run_id=1, rig_time_s=4.0, why="fault: DMM timeout", may_be_moving=("pitch",)),
              Resumed(run_id=1, rig_time_s=5.0, why="operator resumed"),
              Stopped(run_id=1, rig_time_s=6.0, cause="signal", failed="no answer", may_be_moving=("roll",)),
              Discarded(run_id=1, rig_time_s=7.0, seq=3, attempt=1, reason="not settled", faulted=False,
                        volts=(0.1, 0.2, 4.9), sd=(1e-5, 1e-5, 1e-5), samples=((0.1, 0.2, 4.9, None),)),
              note(8)]
    published = [json.loads(e.model_dump_json()) for e in [*events, *others]]
    assert {doc["kind"] for doc in published} == {"point", "prompt", "answer", "fault", "pause", "resume",
                                                  "stop", "discarded", "note", "status"}
    assert [list(validator.iter_errors(doc)) for doc in published] == [[]] * len(published)
    point = next(doc for doc in published if doc["kind"] == "point")
    assert list(validator.iter_errors({**point, "mount": 5})) != []  # Soto Table 3 has four mounts
    assert list(validator.iter_errors({**point, "kind": "points"})) != []
    assert list(validator.iter_errors({k: v for k, v in point.items() if k != "volts"})) != []


def test_the_event_stream_of_a_run_matches_its_journal_and_its_schedule(tmp_path):
    bus, events, chosen = EventBus(), [], []
    bus.subscribe(events.append)
    bus.subscribe(chosen.append, kinds=("point", "prompt", "status"))
    result, steps, est = sim_run(tmp_path, bus)
    with Journal(tmp_path / "lab.sqlite") as journal:
        points = journal.points(result.run_id)
        journaled = journal.events(result.run_id)
    assert {e.kind for e in chosen} == {"point", "prompt", "status"}
    assert [e for e in events if e.kind in ("point", "prompt", "status")] == chosen

    measured = [e for e in events if isinstance(e, PointMeasured)]
    assert [e.seq for e in measured] == [p.seq for p in points] == list(range(64))  # one per point, in order
    assert all(e.record == p and e.volts == (p.vx, p.vy, p.vz) for e, p in zip(measured, points, strict=True))
    assert [e.points_done for e in measured] == list(range(1, 65))

    # the mount prompts: Soto Table 3's numbers of the plan's mounts [[0,0],[180,0],[0,180],[180,180]]
    prompts = [e for e in events if e.kind == "prompt"]
    assert [(e.what, e.mount, e.step, e.n_steps) for e in prompts] == [("mount", 1, 1, 4), ("mount", 2, 2, 4),
                                                                       ("mount", 3, 3, 4), ("mount", 4, 4, 4)]
    # every journaled event but the statuses between milestones was published, in the same order
    assert [(e.kind, e.message) for e in journaled] == [
        e.journal_entry()[:2] for e in events if e.journal_entry() is not None]

    statuses = [e for e in events if isinstance(e, Status)]
    assert statuses[0].at == "start" and statuses[-1].at == "end"
    last = statuses[-1]
    assert (last.status, last.points_done, last.next_remount_in_s, last.eta_s) == ("complete", 64, None, 0.0)
    assert [e.data["at"] for e in journaled if e.kind == "status"] == ["mount"] * 4 + ["end"]

    # next remount after each point, by hand from the schedule: the rest of the mount's steps, then
    # the next mount's move to the load position (clamped); None once the last mount is on
    after_point = [e for e in statuses if e.at == "point"]
    assert len(after_point) == 64
    for i, status in enumerate(after_point):
        later = [s for s in steps[i + 1:] if s.block_start]
        if not later:
            assert status.next_remount_in_s is None
            continue
        j = later[0].seq
        expected = sum(est.per_step_s[s.seq] for s in steps[i + 1:j]) + est.prompt_s[j]
        assert status.next_remount_in_s == pytest.approx(expected, rel=1e-12)
        assert status.eta_s == pytest.approx(sum(est.per_step_s[s.seq] for s in steps[i + 1:]), rel=1e-12)
    for block in range(3):  # decreasing within each of the first three mounts, None in the last
        figures = [s.next_remount_in_s for s in after_point[16 * block:16 * block + 16]]
        assert all(b < a for a, b in zip(figures, figures[1:], strict=False))
    assert all(s.next_remount_in_s is None for s in after_point[48:])
    # and the estimate is what the rig then took, to within a few seconds (the estimate's own
    # model of a move and its settling; the rig's settle test may take a second window)
    for status in after_point[:48]:
        prompt = next(e for e in prompts if e.rig_time_s > status.rig_time_s)
        assert status.next_remount_in_s == pytest.approx(prompt.rig_time_s - status.rig_time_s, abs=15.0)


def test_a_failing_subscriber_never_stops_a_run(tmp_path, caplog):
    bus = EventBus()
    calls = []

    def notifier(event):
        calls.append(event.kind)
        raise RuntimeError("notification refused")

    bus.subscribe(notifier)
    with caplog.at_level(logging.WARNING, logger="labcal.run.events"):
        result, _, _ = sim_run(tmp_path, bus, "one-mount-16")
    with Journal(tmp_path / "lab.sqlite") as journal:
        assert [p.seq for p in journal.points(result.run_id, status="ok")] == list(range(16))
        assert journal.run(result.run_id).status == "complete"
    assert calls.count("point") == 16 and calls[-1] == "status"  # it heard everything, to the end
    assert sum("notification refused" in (r.exc_text or "") for r in caplog.records) == 1


def test_a_durable_subscriber_that_fails_stops_the_run_with_the_point_on_disk(tmp_path):
    bus, seen = EventBus(), []

    def mirror(event):  # a second durable copy that fails on the 5th point
        if isinstance(event, PointMeasured) and event.seq == 4:
            raise RuntimeError("mirror disk failed")

    bus.subscribe(mirror, durable=True)
    bus.subscribe(seen.append, kinds=("point", "status"))
    with pytest.raises(RuntimeError, match="mirror disk failed"):
        sim_run(tmp_path, bus, "one-mount-16")
    with Journal(tmp_path / "lab.sqlite") as journal:
        assert [p.seq for p in journal.points(1)] == [0, 1, 2, 3, 4]  # the journal heard it first
        assert journal.run(1).status == "stopped"
        assert [e.message for e in journal.events(1) if e.kind == "stop"] == ["both tables stopped"]
    assert [e.seq for e in seen if e.kind == "point"] == [0, 1, 2, 3]  # the others never heard of the 5th
    assert (seen[-1].kind, seen[-1].status) == ("status", "stopped")


# --- --pace ---------------------------------------------------------------------------------------
def run_json(capsys, tmp_path, name, *extra):
    argv = ["run", "--sim", "--plan", "one-mount-16", "--seed", "5", "--yes", "--no-report", "--json",
            "--out", str(tmp_path / name), "--db", str(tmp_path / "lab.sqlite"), *extra]
    start = time.monotonic()
    assert main(argv) == 0
    wall = time.monotonic() - start
    return json.loads(capsys.readouterr().out), wall


def test_a_paced_run_takes_at_least_its_rig_time_over_the_pace_and_measures_the_same(tmp_path, capsys):
    pace = 400.0
    paced, wall = run_json(capsys, tmp_path, "paced", "--pace", str(pace))
    rig = paced["simulated_rig_time_s"]
    assert rig > 400.0  # 16 points, a remount allowance: minutes on the rig's clock
    assert wall >= rig / pace and paced["wall_time_s"] >= rig / pace
    unpaced, wall = run_json(capsys, tmp_path, "unpaced")
    assert unpaced["simulated_rig_time_s"] == rig
    assert wall < rig  # not slowed: a rig run in real time would take its rig time
    readings = [(tmp_path / name / "readings.csv").read_bytes() for name in ("paced", "unpaced")]
    assert readings[0] == readings[1]


def test_an_unpaced_simulated_rig_never_sleeps(tmp_path, monkeypatch):
    import labcal.sim.clock as clock

    slept = []
    monkeypatch.setattr(clock.time, "sleep", slept.append)
    sim_run(tmp_path, EventBus(), "one-mount-16")
    assert slept == []


SIM_ONLY = "--pace paces the simulated rig (--sim)"


@pytest.mark.parametrize("argv, says", [
    (["run", "--sim", "--pace", "0"], "--pace: 0 is out of range"),
    (["run", "--sim", "--pace", "fast"], "--pace: 'fast' is not a number"),
    (["run", "--sim", "--pace", "-2"], "--pace: -2 is out of range"),
    (["run", "--pace", "2", "--station", "smc100-serial", "--emulate"], SIM_ONLY),
    (["run", "--pace", "2", "--station", "smc100-serial"], SIM_ONLY),
])
def test_a_wrong_pace_is_one_line(tmp_path, capsys, argv, says):
    assert main([*argv, "--db", str(tmp_path / "lab.sqlite")]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "lab.sqlite").exists()


def test_a_resumed_simulated_run_keeps_the_pace_asked_for(tmp_path, capsys):
    """An interrupted dry run, resumed with --pace: the rest of the run takes at least its rig time
    over the pace, and the run completes with every point."""
    bus = EventBus()

    def interrupt(event):
        if event.seq == 7:
            raise KeyboardInterrupt

    bus.subscribe(interrupt, kinds=("point",))
    with pytest.raises(KeyboardInterrupt):
        sim_run(tmp_path, bus, "one-mount-16")
    with Journal(tmp_path / "lab.sqlite") as journal:
        assert len(journal.points(1)) == 8
        rig_before = journal.rig_time(1)
    pace = 400.0
    start = time.monotonic()
    code = main(["resume", str(tmp_path / "run"), "--pace", str(pace), "--yes", "--no-report", "--json"])
    wall = time.monotonic() - start
    assert code == 0
    done = json.loads(capsys.readouterr().out)
    assert done["points"] == 16 and done["simulated_rig_time_s"] > rig_before + 100.0  # a remount's allowance
    assert wall >= (done["simulated_rig_time_s"] - rig_before) / pace
