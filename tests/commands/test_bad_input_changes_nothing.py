"""Bad input, second round: each gets one line naming the file or option, exit 2, and
changes nothing — a readings file that is not a regular file (a pipe with no writer or a stalling
one, a device), `simulate --out` onto an existing file, a receipt date in the future, an AZ
emulator whose port is taken, readings that make S singular."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from cli import cli, in_process, labcal
from emulators import free_port, no_leaks, private_file  # noqa: F401 - fixture

from labcal.cli import main
from labcal.config import streams
from labcal.config.station import load_station, tcp_address


def one_line_error(capsys, *args: str) -> str:
    code = main(list(args))
    captured = capsys.readouterr()
    assert code == 2, captured
    assert "Traceback" not in captured.err and len(captured.err.strip().splitlines()) == 1, captured.err
    return captured.err


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """A simulated readings file (four-mount-64, 0.1 mV noise), its fit and a voltages file."""
    folder = tmp_path_factory.mktemp("bad-input")
    readings, fit = folder / "readings.csv", folder / "fit.json"
    assert main(["simulate", "--noise", "1e-4", "--seed", "3", "--out", str(readings)]) == 0
    code, out, err = in_process("fit", str(readings), "--json")
    assert code == 0, err
    fit.write_text(out)
    volts = folder / "volts.csv"
    volts.write_text("vx,vy,vz\n0.5,0.5,0.7071067811865476\n0,0,1\n")
    return {"readings": readings, "fit": fit, "volts": volts}


def _writer(fifo: Path, text: str, hold: threading.Event | None = None,
            limit_s: float = 20.0) -> threading.Thread:
    """A thread that opens ``fifo``, writes ``text`` and closes it — or, given ``hold``, keeps it
    open until ``hold`` is set (a stalling writer; at most ``limit_s``, so a reader that waits for
    ever makes the test fail rather than hang)."""
    def write() -> None:
        with open(fifo, "w") as f:
            f.write(text)
            f.flush()
            if hold is not None:
                hold.wait(limit_s)
    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    return thread


# --- not a regular file ----------------------------------------------------------------------
@pytest.mark.parametrize("command", [["fit", "{path}"], ["attitude", "--cert", "{fit}", "--csv", "{path}"]])
@pytest.mark.parametrize("device", ["/dev/zero", "/dev/null"])
def test_a_device_given_as_readings_is_refused_at_once(files, command, device):
    if not os.path.exists(device):
        pytest.skip(f"no {device} here")
    start = time.monotonic()
    done = labcal(*(a.format(path=device, fit=files["fit"]) for a in command), timeout=10)
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.strip() == (f"labcal: error: {device}: a character device, not a "
                                   f"{'readings' if command[0] == 'fit' else 'voltages'} file; give the path "
                                   f"of a {'readings' if command[0] == 'fit' else 'voltages'} file")
    assert time.monotonic() - start < 10


def test_a_folder_given_as_readings_is_refused(tmp_path, capsys):
    assert f"{tmp_path}: a folder, not a readings file" in one_line_error(capsys, "fit", str(tmp_path))


def test_a_named_pipe_nobody_writes_to_is_refused_within_10_s(tmp_path):
    """With the shipped stall time, in a process of its own (nothing patched)."""
    fifo = tmp_path / "readings.csv"
    os.mkfifo(fifo)
    start = time.monotonic()
    done = labcal("fit", str(fifo), timeout=10)
    elapsed = time.monotonic() - start
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.strip() == (f"labcal: error: {fifo}: a pipe that delivered nothing for "
                                   f"{streams.STALL_S:g} s (no writer, or one that stalled); give a readings "
                                   "file, or write the whole file into the pipe")
    assert streams.STALL_S <= elapsed < 10


@pytest.mark.parametrize("command", [["fit", "{path}"], ["attitude", "--cert", "{fit}", "--csv", "{path}"]])
def test_a_writer_that_stalls_is_refused(files, tmp_path, capsys, monkeypatch, command):
    monkeypatch.setattr(streams, "STALL_S", 0.5)
    fifo = tmp_path / "readings.csv"
    os.mkfifo(fifo)
    lines = files["readings"].read_text().splitlines(keepends=True)
    hold = threading.Event()
    writer = _writer(fifo, "".join(lines[:10]), hold)  # a header and nine rows, then silence
    try:
        start = time.monotonic()
        message = one_line_error(capsys, *(a.format(path=fifo, fit=files["fit"]) for a in command))
        elapsed = time.monotonic() - start
    finally:
        hold.set()
        writer.join(5)
    assert f"{fifo}: a pipe that delivered nothing more for 0.5 s (no writer, or one that stalled)" in message
    assert 0.5 <= elapsed < 5


def test_attitude_and_fit_accept_a_pipe_that_delivers_its_data(files, tmp_path, capsys):
    """A pipe that delivers a whole file and closes reads as the file does (byte-equal output)."""
    fifo = tmp_path / "volts.csv"
    os.mkfifo(fifo)
    for command, source in ((["attitude", "--cert", str(files["fit"]), "--csv"], files["volts"]),
                            (["fit", "--json", "--model", "linear"], files["readings"])):
        assert main([*command, str(source)]) == 0
        expected = capsys.readouterr().out
        writer = _writer(fifo, source.read_text())
        assert main([*command, str(fifo)]) == 0
        writer.join(5)
        assert capsys.readouterr().out == expected


def test_standard_input_that_is_a_device_or_binary_is_refused(files):
    with open(os.devnull, "rb") as devnull:
        done = labcal("attitude", "--cert", str(files["fit"]), stdin=devnull, timeout=10)
    assert done.returncode == 2 and done.stderr.strip() == (
        "labcal: error: standard input is a character device, not a voltages file; give the path of a "
        "voltages file")
    endless_zeros = "import sys\nwhile True: sys.stdout.buffer.write(bytes(65536))"
    zeros = subprocess.Popen([sys.executable, "-c", endless_zeros], stdout=subprocess.PIPE)
    try:
        done = labcal("attitude", "--cert", str(files["fit"]), stdin=zeros.stdout, timeout=10)
    finally:
        zeros.kill()
        zeros.wait()
        zeros.stdout.close()
    assert done.returncode == 2 and done.stderr.strip() == (
        "labcal: error: standard input: binary data (a NUL byte), not a voltages file")


def test_standard_input_that_is_a_pipe_is_read(files, capsys):
    done = labcal("attitude", "--cert", str(files["fit"]), input=files["volts"].read_text(), timeout=30)
    code, by_file, err = cli(capsys, "attitude", "--cert", str(files["fit"]), "--csv", str(files["volts"]))
    assert code == 0, err
    assert done.returncode == 0 and done.stdout == by_file and done.stdout.count("\n") == 3


# --- simulate --out, --received ----------------------------------------------------------------
def test_simulate_onto_an_existing_file_is_refused_unless_forced(tmp_path, capsys):
    target = tmp_path / "readings.csv"
    target.write_text("keep me")
    message = one_line_error(capsys, "simulate", "--out", str(target))
    assert message.strip() == (f"labcal: error: {target}: exists; choose another --out, or give --force to "
                               "replace it")
    assert target.read_text() == "keep me"
    assert main(["simulate", "--out", str(target), "--force"]) == 0
    assert target.read_text().startswith("replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz")


def test_a_receipt_date_in_the_future_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    message = one_line_error(capsys, "report", "somewhere", "--received", "2099-01-01")
    assert "argument --received: 2099-01-01 is in the future (today is " in message
    assert "give the date the item was received" in message
    assert not any(tmp_path.iterdir())


# --- an emulator's port taken ----------------------------------------------------------------
@pytest.mark.parametrize("station", ["az-modbus-tcp", "mixed-rtu-socket"])
@pytest.mark.parametrize("command", [["sim", "serve"], ["run", "--emulate", "--yes", "--no-report"]])
def test_an_az_emulator_whose_port_is_taken_is_one_line(tmp_path, capsys, no_leaks, station,  # noqa: F811
                                                         command):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        held = taken.getsockname()[1]
        private = private_file(station, tmp_path)  # free ports, ptys under tmp_path
        text, pitch = private.read_text(), load_station(private)[0].pitch
        port = tcp_address(pitch.tcp or str(pitch.port).removeprefix("socket://"))[1]
        text = text.replace(f"127.0.0.1:{port}", f"127.0.0.1:{held}")  # the AZ drives' port, taken
        path = tmp_path / "station.toml"
        path.write_text(text)
        db = tmp_path / "lab.sqlite"
        extra = ["--db", str(db), "--out", str(tmp_path / "run")] if command[0] == "run" else []
        message = one_line_error(capsys, *command, *([str(path)] if command[0] == "sim" else
                                                     ["--station", str(path)]), *extra)
    assert (f"pitch{', roll' if station == 'az-modbus-tcp' else ''}: cannot serve "
            f"{'tcp' if station == 'az-modbus-tcp' else 'socket://'}" in message)
    assert f"127.0.0.1:{held} (Address already in use); is another emulator" in message
    assert not (tmp_path / "run").exists() and not db.exists()  # nothing journaled, no folder made


# --- readings that make S singular ---------------------------------------------------------------
def _edited(files, tmp_path, edit) -> str:
    import csv

    rows = list(csv.reader(files["readings"].read_text().splitlines()))
    for row in rows[1:]:
        edit(row)
    path = tmp_path / "edited.csv"
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return str(path)


SINGULAR = ("the sensitivity matrix S is singular (the voltages do not follow gravity in three independent "
            "directions")


@pytest.mark.parametrize("edit", [
    lambda r: r.__setitem__(slice(5, 8), ["0.1", "0.2", "0.3"]),  # identical volts on every row
    lambda r: r.__setitem__(slice(5, 8), ["0", "0", "0"]),  # a dead meter
    lambda r: r.__setitem__(7, r[5]),  # vz wired to the x sensor
    lambda r: r.__setitem__(6, "2.5"),  # a constant channel
], ids=["identical", "zero", "copied", "constant"])
@pytest.mark.parametrize("model", [[], ["--model", "linear"], ["--model", "device"], ["--model", "coning"]])
def test_readings_that_make_s_singular_are_one_line_naming_the_file(files, tmp_path, capsys, edit, model):
    path = _edited(files, tmp_path, edit)
    assert f"{path}: {SINGULAR}" in one_line_error(capsys, "fit", path, *model)


def test_a_constant_temperature_with_the_temperature_extension_is_one_line(files, tmp_path, capsys):
    path = _edited(files, tmp_path, lambda r: r.append("20.0"))
    Path(path).write_text(Path(path).read_text().replace("vz\n", "vz,temp_c\n", 1))
    code = main(["fit", path, "--extend", "temperature", "--json"])
    captured = capsys.readouterr()
    assert code == 0 and "Traceback" not in captured.err
    import json

    doc = json.loads(captured.out)
    assert any("left out" in note for note in doc["notes"])  # the zero column is named, not fitted
