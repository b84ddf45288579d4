"""Stops that always reach the tables and say so: a second Ctrl-C, SIGTERM and SIGHUP stop both
tables and mark the run interrupted in the journal; a stop that fails is printed, journaled, and
the pause prompt names the table that may still be moving. Signals go to a real `labcal run`."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import threading
import time
from pathlib import Path

import pytest
from cli import LABCAL, cli
from conftest import quiet_console
from emulators import TIME_SCALE, emulated, no_leaks, private_file  # noqa: F401 - fixture

from labcal.bench.setup import prepare
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.run.operator import AutoOperator
from labcal.run.runner import calibrate
from labcal.store.journal import Journal


def committed(db: Path) -> int:
    try:
        with sqlite3.connect(db) as con:
            return con.execute("SELECT COUNT(*) FROM points").fetchone()[0]
    except sqlite3.OperationalError:  # not created yet
        return 0


def journal_of(db: Path) -> tuple[str, str, list[tuple[str, str, dict]]]:
    """The run's status, reason and events (kind, message, data)."""
    with sqlite3.connect(db) as con:
        status, reason = con.execute("SELECT status, reason FROM runs").fetchone()
        events = [(k, m, json.loads(d) if d else {}) for k, m, d in
                  con.execute("SELECT kind, message, data FROM events ORDER BY id")]
    return status, reason, events


class Run:
    """`labcal run` in a child process; its stderr collected as it comes."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen([LABCAL, "run", *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.err: list[str] = []
        self._reader = threading.Thread(target=lambda: self.err.extend(self.proc.stderr), daemon=True)
        self._reader.start()

    def wait_for(self, condition, what: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert self.proc.poll() is None, f"the run ended before {what}: {''.join(self.err)}"
            assert time.monotonic() < deadline, f"no {what} within {timeout} s: {''.join(self.err)}"
            time.sleep(0.01)

    def saw(self, text: str) -> bool:
        return text in "".join(self.err)

    def end(self) -> tuple[int, str]:
        self.proc.stdin.close()
        code = self.proc.wait(timeout=60)
        self._reader.join(timeout=10)
        return code, "".join(self.err)


@pytest.mark.parametrize(("signals", "reason", "code"), [
    ((signal.SIGTERM,), "SIGTERM", 128 + signal.SIGTERM),
    ((signal.SIGHUP,), "SIGHUP", 128 + signal.SIGHUP),
    ((signal.SIGINT, signal.SIGINT), "Ctrl-C", 130),
])
def test_a_stop_signal_mid_run_stops_both_tables_and_marks_the_run_interrupted(tmp_path, lab_database,
                                                                                signals, reason, code):
    """Mid-run (20 replicates: far more points than are measured before the signal lands), each
    way of stopping labcal from outside stops both tables, journals it, and leaves the run
    'interrupted' with the signal as its reason, resumable; the readings are kept. Before, SIGTERM
    and SIGHUP ended the process with no stop sent and the run 'running', and no stop was
    journaled at all."""
    run = Run("--sim", "--yes", "--no-report", "--replicates", "20", "--out", str(tmp_path / "run"))
    run.wait_for(lambda: committed(lab_database) >= 20, "20 points")
    run.proc.send_signal(signals[0])
    if len(signals) > 1:  # the second only once the first is seen (a pending signal is not counted twice)
        run.wait_for(lambda: run.saw("pausing after this point"), "the first Ctrl-C's message")
        run.proc.send_signal(signals[1])
    exit_code, err = run.end()
    assert exit_code == code, err
    assert "Traceback" not in err and "tables stopped" in err and "continue with: labcal resume" in err
    status, why, events = journal_of(lab_database)
    assert status == "interrupted" and why.startswith(reason), (status, why)
    stops = [(m, d) for k, m, d in events if k == "stop"]
    assert len(stops) == 1 and stops[0][0] == "both tables stopped", stops
    assert stops[0][1]["cause"].startswith(reason)
    run_json = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run_json["status"] == "interrupted" and run_json["points_recorded"] == committed(lab_database)


def test_sigterm_at_a_remount_prompt_stops_and_marks_the_run_interrupted(tmp_path, lab_database):
    """A service manager or a closing session may end labcal while it waits for the operator."""
    run = Run("--sim", "--no-report", "--out", str(tmp_path / "run"))
    run.proc.stdin.write("y\n")  # mount 1; mount 2's prompt is left waiting
    run.proc.stdin.flush()
    run.wait_for(lambda: run.saw("Mount 2 of 4"), "the second remount prompt")
    run.proc.send_signal(signal.SIGTERM)
    exit_code, err = run.end()
    assert exit_code == 128 + signal.SIGTERM and "Traceback" not in err, err
    status, why, events = journal_of(lab_database)
    assert (status, why) == ("interrupted", "SIGTERM")
    assert [m for k, m, _ in events if k == "stop"] == ["both tables stopped"]
    assert committed(lab_database) == 16


def test_a_stop_that_fails_is_printed_journaled_and_named_at_the_pause_prompt(tmp_path, capsys, no_leaks):  # noqa: F811
    """The pitch drive's link dies for good mid-run: the move fails, the stop cannot reach the
    pitch table (the roll table takes its stop). That is said at once, journaled, the pause
    prompt says the pitch table may still be moving instead of "the tables are still", and the
    last line says the stop failed instead of "tables stopped"."""
    answers = tmp_path / "answers.txt"
    answers.write_text("y\ny\ny\ny\na\n")
    dies = '\n[[emulation.faults]]\ndevice = "pitch"\nkind = "close-port"\nafter = 60\n'
    station = private_file("mixed-rtu-socket", tmp_path, dies, "timeout_s = 0.1\nreconnect_s = 0.5")
    log = tmp_path / "labcal.log"
    code, _, err = cli(capsys, "--log-file", str(log), "run", "--station", str(station), "--emulate",
                       "--time-scale", str(TIME_SCALE), "--no-report", "--answers", str(answers),
                       "--out", str(tmp_path / "run"))
    assert code == 1, err
    flat = " ".join(err.split())
    assert "STOP FAILED: the stop did not reach the pitch table" in flat
    assert "The stop did not reach the pitch table: it may still be moving" in flat
    assert "The tables are still" not in flat
    assert "STOP FAILED" in err.strip().splitlines()[-1] and "Traceback" not in err
    status, _, events = journal_of(tmp_path / "labcal.sqlite")
    assert status == "stopped"
    stops = [d for k, _, d in events if k == "stop"]
    assert stops and all(d["may_be_moving"] == ["pitch"] for d in stops), stops
    pauses = [d for k, _, d in events if k == "pause"]
    assert pauses and pauses[0]["may_be_moving"] == ["pitch"]
    failed = [line for line in log.read_text().splitlines()
              if " WARNING labcal.run.sequencer: STOP FAILED" in line]
    assert len(failed) == len(stops), failed


def test_sigterm_while_the_tables_are_homed_stops_them_and_says_so(tmp_path, lab_database):
    """Before the run proper begins, the SMC100 stages are homed (a move). SIGTERM then used to end
    labcal at once, the stage moving on; now it raises like Ctrl-C, the bench's stop is sent, the
    emulators are shut down, and labcal ends with 128 + 15 and one line."""
    station = private_file("smc100-serial", tmp_path)
    run = Run("--station", str(station), "--emulate", "--time-scale", "1", "--yes", "--no-report",
              "--out", str(tmp_path / "run"))
    run.wait_for(lambda: run.saw("preparing the pitch table"), "homing")
    run.proc.send_signal(signal.SIGTERM)
    exit_code, err = run.end()
    assert exit_code == 128 + signal.SIGTERM, err
    assert "interrupted" in err.splitlines()[-1] and "Traceback" not in err
    assert "stopping the tables failed" not in err and committed(lab_database) == 0


@pytest.mark.parametrize("station", ["az-modbus-tcp", "smc100-serial"])
def test_sigterm_mid_move_reaches_the_drives_through_the_drivers(station, tmp_path, no_leaks):  # noqa: F811
    """SIGTERM while the pitch table swings to the mount check: through the real drivers the
    emulated drives get their stop, the table halts short of where it was going (it is not moving
    afterwards, and its move ended before the end it was planned to have), and the journal says
    both tables stopped. The emulators keep the truth the drivers cannot fake."""
    plan, text = load_plan("one-mount-16")
    with emulated(station, tmp_path, time_scale=2.0) as (emulation, bench):
        rig, clock = emulation.rig.rig, emulation.rig.clock
        station_ = bench.station(**emulation.hooks())
        prepare(bench, station_, say=lambda text: None)
        planned: list[float] = []

        def signal_mid_move() -> None:  # the first move with > 1.5 s of rig time (0.75 s of wall) left:
            deadline = time.monotonic() + 30  # the stop's deceleration (0.5 s from full speed) leaves 1 s
            while time.monotonic() < deadline:
                left = rig.pitch.motion_end - clock.now()
                if 1.5 < left < 1e6:
                    planned.append(rig.pitch.motion_end)
                    os.kill(os.getpid(), signal.SIGTERM)
                    return
                time.sleep(0.001)

        def unhandled(signum, frame):  # what the run must replace while it runs (else pytest dies)
            pytest.fail("the run left SIGTERM to its default: the process would have died mid-move")

        watcher = threading.Thread(target=signal_mid_move)
        watcher.start()
        run_dir = tmp_path / "run"
        run_dir.mkdir()
        before = signal.signal(signal.SIGTERM, unhandled)
        try:
            with Journal(tmp_path / "j.sqlite") as journal, pytest.raises(KeyboardInterrupt) as stopped:
                calibrate(plan, text, station_, "test", AutoOperator(quiet_console()),
                          SequencerSettings(settle=bench.config.sequencer.settle), run_dir, journal)
        finally:
            watcher.join()
            signal.signal(signal.SIGTERM, before)
        assert planned and getattr(stopped.value, "reason", None) == "SIGTERM"
        now = clock.now()
        assert rig.pitch.motion_end <= now and rig.roll.motion_end <= now  # neither table moves
        assert rig.pitch.motion_end < planned[0] - 0.5  # cut short by the stop, by most of a second
    status, why, events = journal_of(tmp_path / "j.sqlite")
    assert (status, why) == ("interrupted", "SIGTERM")
    assert [m for k, m, _ in events if k == "stop"] == ["both tables stopped"]


def test_a_signal_while_the_tables_are_being_stopped_is_kept_for_after_the_stop():
    """Ctrl-C or SIGTERM during a stop must neither cut it short (the second table would not get
    its stop) nor be lost (after a fault's stop comes a pause prompt that would wait for ever):
    it is raised at the next critical section's end."""
    from labcal.run.interrupts import Interrupts, StopSignal

    reached = []
    with Interrupts() as interrupts:
        with interrupts.stopping():
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)
            reached.append("roll told to stop")
        with pytest.raises(StopSignal) as stop, interrupts.critical():
            reached.append("fault journaled")
    assert reached == ["roll told to stop", "fault journaled"] and stop.value.reason == "SIGTERM"


def test_a_stop_cuts_the_wait_for_a_reply_short_but_never_a_request():
    """Inside an exchange a stop is deferred while the request goes out (a frame cut in half would
    be garbage on a shared line) and raised at once where the exchange only waits for its reply
    (`critical(awaiting_reply=True)`): a dead controller no longer holds the stop for its timeout.
    While the tables are being stopped, even the wait for a reply keeps it for later."""
    from labcal.run.interrupts import Interrupts, StopSignal

    reached = []
    with Interrupts() as interrupts:
        with pytest.raises(StopSignal) as stop, interrupts.critical():
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("request written")
            with interrupts.critical(awaiting_reply=True):
                reached.append("reply awaited")  # never: the deferred stop is raised on entering
        with pytest.raises(StopSignal), interrupts.critical(), interrupts.critical(awaiting_reply=True):
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("reply read")  # never: raised at once, mid-wait
        with interrupts.stopping(), interrupts.critical(awaiting_reply=True):
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("stop confirmed")
        with pytest.raises(StopSignal), interrupts.critical():
            reached.append("journaled")
    assert reached == ["request written", "stop confirmed", "journaled"] and stop.value.reason == "SIGTERM"
