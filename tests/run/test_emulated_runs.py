"""Whole calibrations through the real drivers against the emulators (`labcal run --station
--emulate`): the simulated truth comes back, faults end the way they promise, nothing is lost."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import time

import numpy as np
import pytest
from cli import LABCAL, cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.emulation import default_instrument

pytestmark = pytest.mark.long(seconds=45)  # whole runs through the drivers: handed out first

EMULATE = ["--emulate", "--time-scale", str(TIME_SCALE), "--no-report"]  # the certificate is not the subject
QUICK = "timeout_s = 0.1\nreconnect_s = 1"  # faults cost timeouts: keep them short


def readings(run_dir) -> list[dict]:
    with (run_dir / "readings.csv").open() as f:
        return list(csv.DictReader(f))


def faults(*tables: str) -> str:
    return "".join(f"\n[[emulation.faults]]\n{t}\n" for t in tables)


def run_with_a_fault(capsys, tmp_path, station: str, fault: str, answers: str) -> tuple[int, str]:
    """`labcal run` into tmp_path/run, with one fault injected and the operator's answers from a file."""
    script = tmp_path / "answers.txt"
    script.write_text(answers)
    code, _, err = cli(capsys, "run", "--station", str(private_file(station, tmp_path, faults(fault), QUICK)),
                       *EMULATE, "--answers", str(script), "--out", str(tmp_path / "run"))
    return code, err


@pytest.mark.slow
@pytest.mark.parametrize("station", ["az-modbus-tcp", "smc100-serial"])
def test_a_four_mount_calibration_through_the_drivers_recovers_the_truth(station, tmp_path, capsys, no_leaks):  # noqa: F811
    """64 points, 4 mounts, one table protocol each (Modbus TCP; SMC100 ASCII on a pty with homing
    and soft limits), the DMM on TCP or a pty: the fit is the emulated instrument's truth to
    0.1 mV, as for the simulated rig (arcsec misalignments, drift and a temperature swing)."""
    run_dir = tmp_path / "run"
    t0 = time.perf_counter()
    path = private_file(station, tmp_path)
    code, out, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--yes",
                         "--out", str(run_dir), "--json")
    wall = time.perf_counter() - t0
    assert code == 0, err
    summary = json.loads(out)
    meta = json.loads((run_dir / "run.json").read_text())
    truth = np.array(meta["simulated_truth"]["coefficients"])
    X = np.array(summary["fit"]["coefficients"])
    assert summary["points"] == 64 and summary["points_failed"] == 0 and meta["status"] == "complete"
    assert np.max(np.abs(X - truth)) < 1e-4
    # the DMM's >10 GΩ input is declared; a 10 MΩ one on the 5 kΩ outputs would
    # make every sensitivity 10e6/(10e6 + 5e3) - 1 = -500 ppm off (the 1e-4 V/g above is 20 ppm)
    assert np.max(np.abs(np.diag(X[1:]) / np.diag(truth[1:]) - 1)) < 50e-6
    assert err.count("(--yes: confirmed)") == 4 and "preparing the pitch table" in err
    rig_s = summary["simulated_rig_time_s"]  # the emulation's scaled clock: moves, settling, scans
    # A 64-point, 4-mount calibration is tens of minutes of rig time. No upper bound: the emulation's
    # clock runs at TIME_SCALE × the wall clock, so a loaded machine's stalls add rig time too.
    assert rig_s > 600, rig_s
    # The time scale is in force: run at TIME_SCALE (1000x), the ~50 min of rig time take 3-4 s. Only
    # an emulation slower than 20x would fail (1x, if the scale were ignored): the bound (~150 s)
    # leaves a ~40-fold margin over the 3-4 s for a loaded 2-core CI.
    assert wall < rig_s / 20, (wall, rig_s)
    rows = readings(run_dir)
    assert len(rows) == 64 and {(r["y_deg"], r["u_deg"]) for r in rows} == {("0", "0"), ("180", "0"),
                                                                            ("0", "180"), ("180", "180")}


def test_transient_faults_are_absorbed_without_a_pause(tmp_path, capsys, no_leaks):  # noqa: F811
    """Lost, garbled and late replies and a gateway that drops off for 0.3 s: retried and
    reconnected by the drivers; the run completes with every point and no fault in the journal."""
    extra = faults('device = "pitch"\nkind = "close-port"\nafter = 40\nreopen_s = 0.3',
                   'device = "roll"\nkind = "garbled"\ncount = 2\nafter = 100',
                   'device = "dmm"\nkind = "no-reply"\nmatch = "FETC"\nafter = 30',
                   'device = "dmm"\nkind = "late-reply"\nmatch = "OPC"\nafter = 60\ndelay_s = 0.3')
    station = private_file("az-modbus-tcp", tmp_path, extra, QUICK)
    code, out, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--yes",
                         "--out", str(tmp_path / "run"), "--json")
    assert code == 0, err
    assert json.loads(out)["points"] == 64 and "Fault" not in err


def test_a_port_that_never_comes_back_pauses_safely_and_resume_finishes(tmp_path, capsys, no_leaks):  # noqa: F811
    """The DMM's port closes for good mid-run: the driver gives up after its reconnect budget, the
    sequencer stops the tables and pauses with the driver's one-line message; the operator aborts.
    Every reading taken is on disk, and `labcal resume` (emulators restarted) finishes the run
    without changing one of them."""
    run_dir, answers = tmp_path / "run", tmp_path / "answers.txt"
    closes = 'device = "dmm"\nkind = "close-port"\nafter = 40\nmatch = "FETC"'
    code, err = run_with_a_fault(capsys, tmp_path, "smc100-tcp", closes, "y\ny\ny\na\n")
    assert code == 1, err
    assert "Fault:" in err and "dmm (Keysight 34970A, tcp 127.0.0.1:" in err and "kept trying for 1 s" in err
    assert "continue with: labcal resume" in err.strip().splitlines()[-1] and "Traceback" not in err
    before = readings(run_dir)
    assert 16 < len(before) < 64
    meta = json.loads((run_dir / "run.json").read_text())
    assert meta["status"] == "stopped" and meta["points_recorded"] == len(before)

    answers.write_text("y\ny\ny\n")  # confirm the mount to resume, then the remaining mount(s)
    code, out, err = cli(capsys, "resume", str(run_dir), "--answers", str(answers), "--json", "--no-report")
    assert code == 0, err
    after = readings(run_dir)
    assert len(after) == 64 and json.loads(out)["points"] == 64
    kept = {(r["y_deg"], r["u_deg"], r["pitch_deg"], r["roll_deg"]): r for r in before}
    again = {(r["y_deg"], r["u_deg"], r["pitch_deg"], r["roll_deg"]): r for r in after}
    assert all(again[key] == row for key, row in kept.items())  # not one reading changed


def test_a_drive_alarm_stops_both_tables_and_pauses(tmp_path, capsys, no_leaks):  # noqa: F811
    """The roll drive raises alarm 10h mid-run: the run stops the tables and pauses with the
    alarm's meaning and what to do; aborting keeps every reading and exits 1 (resumable)."""
    code, err = run_with_a_fault(capsys, tmp_path, "az-modbus-rtu",
                                 'device = "roll"\nkind = "alarm"\ncode = 16\nafter = 150', "y\ny\ny\ny\na\n")
    assert code == 1, err
    assert "roll table (Oriental Motor AZ, unit 2 on" in err
    assert "alarm 10h (excessive position deviation)" in err
    assert "--reset-alarms" in err
    rows = readings(tmp_path / "run")
    assert 0 < len(rows) < 64
    assert json.loads((tmp_path / "run" / "run.json").read_text())["points_recorded"] == len(rows)


def test_limits_refuse_a_plan_before_anything_moves(tmp_path, capsys, no_leaks):  # noqa: F811
    """A pitch table limited to [-10°, 100°] cannot reach 180° or 270°: refused before homing or
    any move, exit 2, one line."""
    station = private_file("smc100-serial", tmp_path).read_text().replace("limits_deg = [-100, 280]",
                                                                          "limits_deg = [-10, 100]")
    path = tmp_path / "limited.toml"
    path.write_text(station)
    code, out, err = cli(capsys, "run", "--station", str(path), *EMULATE, "--yes",
                         "--out", str(tmp_path / "run"))
    assert code == 2 and out == "" and err.strip().count("\n") == 0, err
    assert "plan refused before any motion: pitch" in err and "180° is outside the soft limits" in err
    assert not (tmp_path / "run").exists()


def test_a_run_on_hardware_served_by_another_process(tmp_path, capsys):
    """The real-hardware path: `labcal run --station` (no --emulate: the system clock, no hooks into
    the rig) against `labcal sim serve` in another process, as against a bench. One mount, since
    nobody remounts the emulated instrument; a fixed dwell, since the system clock is not scaled."""
    station = private_file("smc100-tcp", tmp_path)
    serve = subprocess.Popen([LABCAL, "sim", "serve", str(station), "--time-scale", "500", "--json"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert json.loads("".join(iter(serve.stdout.readline, "}\n")) + "}")["time_scale"] == 500
        code, out, err = cli(capsys, "run", "--station", str(station), "--plan", "one-mount-16", "--yes",
                             "--no-report", "--fixed-dwell", "0.05", "--out", str(tmp_path / "run"), "--json")
    finally:
        serve.send_signal(signal.SIGINT)
        serve.communicate(timeout=20)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["points"] == 16 and "preparing the pitch table" in err
    S, truth = np.array(summary["fit"]["coefficients"])[1:], default_instrument().X[1:]
    assert np.max(np.abs(np.diag(S) - np.diag(truth))) < 1e-3  # one mount: only ~1e-5 leaks into the diagonal
    assert serve.returncode == 0


def test_lost_scan_starts_are_measured_again_not_journaled_stale(tmp_path, capsys, no_leaks):  # noqa: F811
    """Issue 22 item 6, end to end: the DMM loses the INIT of three scans mid-run (once right after a
    move), so FETC? would give the previous window or point again. The driver discards each stale
    scan (the same first time stamp as the last) and scans again: the run completes with every
    point and the fit is still the truth to 0.1 mV (a stale point, taken at another attitude, is
    off by up to 10 V)."""
    lost = faults(*(f'device = "dmm"\nkind = "lost-request"\nmatch = "^INIT"\nafter = {n}'
                    for n in (20, 40, 60)))  # a run takes 68 scans at least: 64 points, 4 mount checks
    station = private_file("az-modbus-tcp", tmp_path, lost, QUICK)
    run_dir = tmp_path / "run"
    code, out, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--yes", "--out", str(run_dir),
                         "--json")
    assert code == 0, err
    summary = json.loads(out)
    truth = np.array(json.loads((run_dir / "run.json").read_text())["simulated_truth"]["coefficients"])
    assert summary["points"] == 64 and summary["points_failed"] == 0
    assert np.max(np.abs(np.array(summary["fit"]["coefficients"]) - truth)) < 1e-4
    log = cli(capsys, "log", str(run_dir), "--json")[1]
    assert log.count("the INIT was lost") == 3, log


def recovered_run(capsys, station, run_dir) -> str:
    """An emulated run that must complete every point with the fit at the truth to 0.1 mV, despite
    its injected fault; returns its journal as `labcal log --json` prints it."""
    code, out, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--yes", "--out", str(run_dir),
                         "--json")
    assert code == 0, err
    summary = json.loads(out)
    truth = np.array(json.loads((run_dir / "run.json").read_text())["simulated_truth"]["coefficients"])
    assert summary["points"] == 64 and summary["points_failed"] == 0 and "Fault" not in err
    assert np.max(np.abs(np.array(summary["fit"]["coefficients"]) - truth)) < 1e-4
    return cli(capsys, "log", str(run_dir), "--json")[1]


@pytest.mark.parametrize("station", ["smc100-serial", "az-modbus-tcp"])
def test_a_power_cycled_dmm_is_recovered_and_the_run_completes(station, tmp_path, capsys, no_leaks):  # noqa: F811
    """Issue 22 item 5, end to end: the DMM is switched off and on mid-run (on RS-232 it is then deaf
    until SYST:REM; on TCP its connection drops) and comes back with its power-on defaults: no scan
    list, 10 MΩ input. The driver re-sends SYST:REM and the configuration and reads it back; the
    run completes with every point, and the fit is the truth to 0.1 mV (a 10 MΩ input alone would
    put the sensitivities 500 ppm, 2.5 mV/g, off). Before, the run paused on "no reply" for good."""
    cycle = faults('device = "dmm"\nkind = "power-cycle"\nmatch = "FETC"\nafter = 40')
    path = private_file(station, tmp_path, cycle, QUICK)
    log = recovered_run(capsys, path, tmp_path / "run")
    assert "it was powered off and on (*ESR? power-on bit); configuring it again" in log


def test_resume_names_the_runs_own_journal(tmp_path, capsys, no_leaks):  # noqa: F811
    """Issue 22 item 9: a run journaled in `--db elsewhere/lab.sqlite` stops at a fault (the DMM's
    port closes for good) and is aborted; `labcal resume RUN_DIR` without --db goes on in the
    journal its run.json names, and says that one, not the default ($LABCAL_DB here)."""
    db = tmp_path / "elsewhere" / "lab.sqlite"
    db.parent.mkdir()
    run_dir, answers = tmp_path / "run", tmp_path / "answers.txt"
    answers.write_text("y\na\n")
    station = private_file("smc100-tcp", tmp_path, faults('device = "dmm"\nkind = "close-port"\nafter = 10\n'
                                                          'match = "FETC"'), QUICK)  # mid-run: 17+ scans
    code, _, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--plan", "one-mount-16",
                       "--answers", str(answers), "--db", str(db), "--out", str(run_dir))
    assert code == 1, err
    answers.write_text("y\n")
    code, out, err = cli(capsys, "resume", str(run_dir), "--answers", str(answers), "--no-report")
    assert code == 0, err
    said = "".join(out.split())  # whatever the console's width folded
    assert f"journal{db}" in said and "labcal.sqlite" not in said.replace(str(db), ""), out


def test_a_dmm_reset_while_the_operator_remounts_is_found_at_the_mount(tmp_path, capsys, no_leaks):  # noqa: F811
    """Issue 22 item 5: the DMM is switched off and on while the operator remounts the instrument
    for the second mount (on RS-232: back in local, its defaults, no scan list). The check of its
    declared configuration at the mount finds it (the power-on bit), configures it again, and the
    run completes with every point and the truth to 0.1 mV."""
    # the *ESR? of the second mount's check (the first mount's goes through)
    at_mount = faults('device = "dmm"\nkind = "power-cycle"\nmatch = "^\\\\*ESR"\nafter = 1')
    path = private_file("smc100-serial", tmp_path, at_mount, QUICK)
    log = recovered_run(capsys, path, tmp_path / "run")
    assert "at the mount: it was powered off and on (*ESR? power-on bit); configuring it again" in log, log


def test_a_reading_short_of_a_byte_is_not_kept_and_the_window_is_taken_again(tmp_path, capsys, no_leaks):  # noqa: F811
    """End to end on RS-232: one byte of a mid-run FETC? reply is lost, the
    first reading's 8th significant digit, leaving a number that still parses. Before, it was kept.
    Now every reading is checked against the width the unit writes it in: the scan is taken again,
    the run completes with every point and the fit is the truth to 0.1 mV."""
    dropped = faults('device = "dmm"\nkind = "dropped-byte"\nmatch = "FETC"\nafter = 30')
    log = recovered_run(capsys, private_file("smc100-serial", tmp_path, dropped, QUICK), tmp_path / "run")
    assert log.count("is not as the unit writes it") == 1, log


def test_an_smc100_power_cycled_mid_run_is_homed_after_one_r(tmp_path, capsys, no_leaks):  # noqa: F811
    """The pitch SMC100 is switched off and on as its sixth move command (PA) reaches it, mid-run
    (that command is lost): it comes back NOT REFERENCED (0Ah) and refuses PA (error H). The
    trigger counts moves, which a plan fixes, not status requests, whose number depends on how
    fast the machine polls: the 60th status request came after the last point on a busy machine.
    The run stops the tables and pauses; the pause says the pitch table lost its reference and
    that resuming homes it. One "r" (the answers' second line) homes it and the run completes with
    every point. Before, "r" moved again, was refused, and the run paused for good."""
    cycle = faults('device = "pitch"\nkind = "power-cycle"\nmatch = "^1PA"\nafter = 5')
    station = private_file("smc100-serial", tmp_path, cycle, QUICK)
    answers = tmp_path / "answers.txt"
    answers.write_text("y\nr\n")
    run_dir = tmp_path / "run"
    code, out, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--plan", "one-mount-16",
                         "--answers", str(answers), "--out", str(run_dir), "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["points"] == 16 and summary["points_failed"] == 0
    flat = " ".join(err.split())
    assert "the pitch table lost its reference: resuming homes it first" in flat, err
    log = cli(capsys, "log", str(run_dir), "--json")[1]
    assert log.count("homing the pitch table, which had lost its reference") == 1, log
    assert log.count("NOT REFERENCED from reset (0Ah)") >= 1


def test_an_overloaded_scan_is_journaled_with_its_readings_before_the_pause(tmp_path, capsys, no_leaks):  # noqa: F811
    """The DMM reads channel 101 as an overload (+9.90000000E+37, the 34970A's overload reading) in
    one scan: the run pauses on it, and the journal keeps that window as discarded with its samples,
    the overload value among them, as it keeps every window it does not use."""
    import sqlite3
    from contextlib import closing

    code, err = run_with_a_fault(capsys, tmp_path, "smc100-serial",
                                 'device = "dmm"\nkind = "alarm"\nmatch = "FETC"\nafter = 6', "y\na\n")
    assert code == 1, err
    assert "overloaded (+9.9E+37)" in err
    journal = json.loads((tmp_path / "run" / "run.json").read_text())["journal"]
    with closing(sqlite3.connect(journal)) as db:
        found = [json.loads(data) for (data,) in db.execute(
            "SELECT data FROM events WHERE kind = 'discarded' AND message LIKE '%overloaded%'")]
    assert len(found) == 1
    samples = np.array(found[0]["samples"], dtype=float)
    assert samples.shape[0] >= 1 and samples.shape[1] >= 3
    assert np.any(samples[:, 0] >= 9.9e37) and np.all(np.abs(samples[:, 1:3]) < 10)  # only x overloaded
