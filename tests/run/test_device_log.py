"""`labcal --log-file FILE --log-level LEVEL`, and the drivers' warnings (retries, reconnects) as
events of the run in the journal, so that a degrading line leaves a record."""

from __future__ import annotations

import re
import sqlite3
import subprocess

from cli import LABCAL, cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z (DEBUG|INFO|WARNING|ERROR) (\S+): (.*)$")


def test_retries_and_reconnects_are_journaled_and_logged(tmp_path, capsys, lab_database, no_leaks):  # noqa: F811
    """A reply lost by the DMM and the tables' gateway dropping off for 0.3 s are absorbed by the
    drivers, as before; now each retry and reconnect is a WARNING in the log file and the same
    record, word for word, an event of the run in the journal."""
    faults = ('\n[[emulation.faults]]\ndevice = "pitch"\nkind = "close-port"\nafter = 40\nreopen_s = 0.3\n'
              '\n[[emulation.faults]]\ndevice = "dmm"\nkind = "no-reply"\nmatch = "FETC"\nafter = 30\n')
    station = private_file("az-modbus-tcp", tmp_path, faults, "timeout_s = 0.1\nreconnect_s = 1")
    log = tmp_path / "labcal.log"
    code, _, err = cli(capsys, "--log-file", str(log), "--log-level", "warning", "run", "--station",
                       str(station), "--emulate", "--time-scale", str(TIME_SCALE), "--no-report", "--yes",
                       "--out", str(tmp_path / "run"))
    assert code == 0, err
    lines = log.read_text(encoding="utf-8").splitlines()
    assert lines and all(LOG_LINE.match(line) for line in lines), lines
    records = [LOG_LINE.match(line).groups() for line in lines]
    logged = [text for level, name, text in records
              if level == "WARNING" and name.startswith("labcal.drivers.")]
    with sqlite3.connect(lab_database) as con:
        journaled = [m for (m,) in con.execute("SELECT message FROM events WHERE kind='link' ORDER BY id")]
    assert journaled == logged and len(journaled) >= 2, (journaled, logged)
    assert any("retry 1 of" in m for m in journaled) and any("no reply" in m for m in journaled)


def test_a_log_file_that_cannot_be_opened_is_one_line_and_exit_2(tmp_path):
    for where in (tmp_path / "missing" / "labcal.log", tmp_path):
        done = subprocess.run([LABCAL, "--log-file", str(where), "run", "--sim", "--yes", "--out",
                               str(tmp_path / "run")], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and done.stdout == "", done.stderr
        assert done.stderr.count("\n") == 1 and f"--log-file {where}: cannot open it" in done.stderr
        assert not (tmp_path / "run").exists()  # refused before anything started


def test_a_log_level_without_a_file_logs_to_stderr_for_the_command_only(capsys):
    import logging

    from labcal.commands.logfile import logging_to

    bad = subprocess.run([LABCAL, "--log-level", "loud", "plan", "list"], capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and "invalid choice: 'loud'" in bad.stderr
    driver = logging.getLogger("labcal.drivers.transport")
    with logging_to(None, "info"):
        driver.debug("tcp 127.0.0.1:502 > 01 03 00 cc 00 02")
        driver.warning("tcp 127.0.0.1:502: retry 1 of 2 after: no reply within 0.1 s")
    driver.warning("after the command: not printed")
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and LOG_LINE.match(lines[0]).groups() == (
        "WARNING", "labcal.drivers.transport", "tcp 127.0.0.1:502: retry 1 of 2 after: no reply within 0.1 s")
