"""The lab overview's state of a station, replayed from hand-built timelines: the events are the
sequencer's own (`labcal.run.events`), journaled as the journal writes them (`journal_entry`), at
wall times chosen here; every expected time and duration is worked out by hand in the test."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from labcal.app.station_state import Heard, Silence, State, replay
from labcal.run.events import Answer, Fault, Prompt, Resumed, RunEvent, Status

T0 = datetime(2026, 11, 27, 9, 0, 0, tzinfo=UTC)


def at(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


def journaled(event: RunEvent, wall_s: float) -> Heard:
    """The event as the journal keeps it (kind, message, data), stamped ``wall_s`` after T0."""
    entry = event.journal_entry()
    assert entry is not None
    kind, message, data = entry
    return Heard(at(wall_s), kind, message, data)


def point(wall_s: float, rig_s: float, y_deg: float = 0.0, u_deg: float = 0.0) -> Heard:
    return Heard(at(wall_s), "point", data={"t_end": rig_s, "y_deg": y_deg, "u_deg": u_deg})


def paced(n: int, start_wall: float = 0.0, wall_step: float = 2.0, rig_step: float = 40.0,
          start_rig: float = 0.0, y_deg: float = 0.0, u_deg: float = 0.0) -> list[Heard]:
    """``n`` points ``wall_step`` s apart on the wall clock, ``rig_step`` s apart on the rig's."""
    return [point(start_wall + i * wall_step, start_rig + i * rig_step, y_deg, u_deg) for i in range(n)]


def mount_prompt(step: int, mount: int) -> Prompt:
    return Prompt(run_id=1, rig_time_s=0, what="mount", mount=mount, step=step, n_steps=4, message="mount",
                  where=f"mount {mount}", args=(f"mount {mount}", str(step), "4"))


def answer(reply: str, meaning: str, outcome: str) -> Answer:
    return Answer(run_id=1, rig_time_s=0, what="mount", reply=reply, meaning=meaning, outcome=outcome)  # type: ignore[arg-type]


def test_a_bench_measuring_at_its_usual_pace_is_running_done_at_a_wall_clock_time():
    """Points 2 s apart on the wall and 40 s apart on the rig's clock (a simulated rig paced at 20 ×):
    the run's 400 rig seconds left are 400 / 20 = 20 wall seconds after its latest point."""
    timeline = paced(10)  # the latest point at 18 s
    view = replay("running", timeline, at(19), Silence(floor_s=60), eta_rig_s=400.0, remount_rig_s=120.0)
    assert view.state is State.RUNNING and view.label == "running"
    assert view.interval_s == pytest.approx(2.0)
    assert view.done_at == at(18 + 20)
    assert view.next_remount_at == at(18 + 6)
    assert view.mount == 1


def test_a_real_rig_whose_clock_is_the_walls_is_done_when_its_clock_says():
    timeline = paced(5, wall_step=30.0, rig_step=30.0)
    view = replay("running", timeline, at(125), eta_rig_s=600.0)
    assert view.done_at == at(120 + 600)


def test_a_remount_prompt_is_waiting_for_a_person_for_as_long_as_it_has_been_open():
    """Seven minutes at a remount prompt: waiting (not 'not heard from', however long the silence),
    420 s waited, no done-at or next remount (nobody knows when the person comes)."""
    timeline = [*paced(16), journaled(mount_prompt(2, 2), 31.0)]
    now = at(31 + 420)
    view = replay("running", timeline, now, Silence(floor_s=60), eta_rig_s=400.0, remount_rig_s=0.0)
    assert view.state is State.WAITING and view.label == "waiting for a person"
    assert view.waiting is not None and view.waiting.text == "mount 2 of 4: mount 2"
    assert view.waited_s(now) == 420.0
    assert view.done_at is None and view.next_remount_at is None


def test_an_answer_that_keeps_the_prompt_open_leaves_the_bench_waiting_since_the_prompt():
    timeline = [*paced(4), journaled(mount_prompt(2, 2), 10.0),
                journaled(answer("n", "not yet", "open"), 70.0)]
    view = replay("running", timeline, at(100))
    assert view.state is State.WAITING and view.waiting is not None
    assert view.waiting.utc == at(10)
    assert view.waited_s(at(100)) == 90.0


def test_a_confirmed_remount_is_the_mount_on_the_plate_before_its_first_point():
    """Mount 1's points, the prompt for mount 4 (y 180°, u 180°), confirmed, and the status milestone
    that follows: the overview's mount is 4 although no point has been measured on it."""
    confirmed = Status(run_id=1, rig_time_s=0, status="running", at="mount", points_done=16, points_total=64,
                       mount=4, next_remount_in_s=600.0, eta_s=1800.0)
    timeline = [*paced(16), journaled(mount_prompt(2, 4), 31.0),
                journaled(answer("confirmed", "confirmed", "answered"), 50.0), journaled(confirmed, 50.5)]
    view = replay("running", timeline, at(52))
    assert view.state is State.RUNNING
    assert view.mount == 4


def test_a_point_on_a_new_mount_is_that_mount():
    timeline = [*paced(3), *paced(3, start_wall=20.0, start_rig=200.0, y_deg=180.0, u_deg=0.0)]
    assert replay("running", timeline, at(25)).mount == 2  # Soto Table 3: y 180°, u 0°


def test_a_pause_on_a_fault_is_the_fault_state_until_resumed_and_then_the_fault_is_cleared():
    fault = Fault(run_id=1, rig_time_s=0, message="roll table: alarm 10h (excessive position deviation)")
    pause = Prompt(run_id=1, rig_time_s=0, what="pause", message="paused", why=f"fault: {fault.message}",
                   args=(f"fault: {fault.message}",))
    timeline = [*paced(5), journaled(fault, 9.0), journaled(pause, 9.1)]
    now = at(9.1 + 180)
    view = replay("running", timeline, now)
    assert view.state is State.FAULT and view.label == "paused on a fault"
    assert view.waited_s(now) == pytest.approx(180.0)
    assert view.fault is not None and view.fault.cleared_utc is None
    go_on = Answer(run_id=1, rig_time_s=0, what="pause", reply="r", meaning="resume", outcome="answered")
    resumed = [*timeline, journaled(go_on, 200.0),
               journaled(Resumed(run_id=1, rig_time_s=0, why="operator resumed after the pause"), 200.1)]
    view = replay("running", resumed, at(201))
    assert view.state is State.RUNNING
    assert view.fault is not None and view.fault.cleared_utc == at(200.1)


def test_a_pause_after_ctrl_c_is_a_person_waited_for_not_a_fault():
    pause = Prompt(run_id=1, rig_time_s=0, what="pause", message="paused", why="Ctrl-C", args=("Ctrl-C",))
    view = replay("running", [*paced(5), journaled(pause, 9.0)], at(70))
    assert view.state is State.WAITING
    assert view.waiting is not None and view.waiting.text == "paused: Ctrl-C"


def test_a_fault_the_run_went_past_is_cleared_by_its_next_point():
    """A point that did not settle under the skip policy: the fault, then the next point."""
    fault = Fault(run_id=1, rig_time_s=0, message="point 4 failed: not settled", policy="skip")
    timeline = [*paced(5), journaled(fault, 8.5), point(10.0, 200.0)]
    view = replay("running", timeline, at(11))
    assert view.state is State.RUNNING
    assert view.fault is not None and view.fault.cleared_utc == at(10)


@pytest.mark.parametrize(("silent_s", "state"), [(59.0, State.RUNNING), (61.0, State.SILENT)])
def test_a_bench_silent_past_the_floor_is_not_heard_from(silent_s, state):
    """Points 2 s apart: five intervals are 10 s, so the floor (60 s) is the limit."""
    timeline = paced(10)
    view = replay("running", timeline, at(18 + silent_s), Silence(floor_s=60, factor=5), eta_rig_s=400.0)
    assert view.state is state
    assert view.silent_after_s == 60.0


@pytest.mark.parametrize(("silent_s", "state"), [(99.0, State.RUNNING), (101.0, State.SILENT)])
def test_a_slow_bench_is_allowed_several_of_its_own_intervals(silent_s, state):
    """Points 20 s apart on the wall: five intervals are 100 s, above the 60 s floor."""
    timeline = paced(10, wall_step=20.0, rig_step=20.0)
    view = replay("running", timeline, at(180 + silent_s), Silence(floor_s=60, factor=5))
    assert view.state is state


def test_a_bench_not_heard_from_states_no_done_at():
    view = replay("running", paced(10), at(18 + 3600), Silence(floor_s=60), eta_rig_s=400.0)
    assert view.state is State.SILENT and view.label == "not heard from"
    assert view.done_at is None and view.next_remount_at is None
    assert view.silent_s(at(18 + 3600)) == 3600.0


def test_the_usual_interval_is_the_median_gap_so_a_remount_wait_does_not_stretch_it():
    """Eight points 2 s apart, a 10-minute remount wait, eight more: the median gap is still 2 s."""
    timeline = [*paced(8), *paced(8, start_wall=14 + 600, start_rig=400)]
    view = replay("running", timeline, at(614 + 14 + 61), Silence(floor_s=60))
    assert view.interval_s == 2.0
    assert view.state is State.SILENT


def test_a_move_heard_after_the_latest_point_counts_as_heard():
    view = replay("running", paced(10), at(18 + 61), Silence(floor_s=60), last_heard=at(18 + 30))
    assert view.state is State.RUNNING


@pytest.mark.parametrize(("status", "state"), [("complete", State.COMPLETE), ("stopped", State.IDLE),
                                               ("failed", State.IDLE), ("interrupted", State.IDLE),
                                               (None, State.IDLE)])
def test_a_bench_with_no_run_going_on_is_complete_or_idle(status, state):
    """However long ago it last journaled, and with a prompt left open by a stopped run."""
    timeline = [] if status is None else [*paced(3), journaled(mount_prompt(2, 2), 6.0)]
    view = replay(status, timeline, at(86400))
    assert view.state is state
    assert view.done_at is None and view.waiting is None
