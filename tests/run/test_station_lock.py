"""One run per station at a time: across processes, for serial and TCP links,
held while the run waits at a prompt; a second run is one line naming the station and who holds it;
a lock left by a killed process is taken over with a note; an address another emulator serves is
one line, not pymodbus's traceback."""

from __future__ import annotations

import errno
import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest
from cli import LABCAL, cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import load_station
from labcal.sim.emulation import Emulation
from labcal.store.lock import StationLock, link_key, station_locks

EMULATE = ["--emulate", "--time-scale", str(TIME_SCALE), "--no-report"]


def first_run_waiting_at_a_prompt(station: Path, db: Path, tmp_path: Path) -> subprocess.Popen:
    """`labcal run` in another process, holding the station while it waits at the first remount
    prompt (its stdin stays open and silent); returns once its station lock names its run."""
    first = subprocess.Popen([LABCAL, "run", "--station", str(station), *EMULATE, "--db", str(db),
                              "--out", str(tmp_path / "first")], stdin=subprocess.PIPE,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    folder = station_locks(db)[0]
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        held = [json.loads(p.read_text() or "{}") for p in folder.glob("*.lock")] if folder.exists() else []
        if held and all(h.get("run_id") == 1 for h in held):
            return first
        assert first.poll() is None, "the first run ended"
        time.sleep(0.05)
    first.kill()
    raise AssertionError("the first run never held the station")


@pytest.mark.parametrize(("name", "second_db"), [("az-modbus-tcp", "lab.sqlite"),
                                               ("smc100-serial", "lab.sqlite"),
                                               ("az-modbus-tcp", "another-lab.sqlite")])
def test_a_second_run_on_the_same_links_is_refused_in_one_line(name, second_db, tmp_path, capsys):
    """Two `labcal run --station … --emulate` on one station, Modbus TCP or serial ports (the second
    through another station file naming the same links, journaling into the same lab database or
    another one: the user's runtime folder holds the locks too): the second exits 2 with one line naming
    the station, a link, and who holds it (run 1, the first process's pid, this host) before it
    starts anything. Before, the second crashed with pymodbus's "Could not start listen"
    traceback (or, on a real bench, drove the tables the first run held)."""
    station = private_file(name, tmp_path, link="timeout_s = 0.1\nreconnect_s = 1")
    other = tmp_path / "same-bench-other-name.toml"
    (tmp_path / "by-id").mkdir()
    other.write_text(station.read_text().replace("127.0.0.1:", "localhost:")  # the same links, spelt
                     .replace(f"{tmp_path}/", f"{tmp_path}/by-id/../"))  # otherwise
    db = tmp_path / "lab.sqlite"
    first = first_run_waiting_at_a_prompt(station, db, tmp_path)
    try:
        code, out, err = cli(capsys, "run", "--station", str(other), *EMULATE, "--yes", "--db",
                             str(tmp_path / second_db), "--out", str(tmp_path / "second"))
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=30)
    assert code == 2 and out == "" and err.strip().count("\n") == 0, err
    assert f"station {other}: {'tcp localhost:' if name.startswith('az') else tmp_path}" in err
    assert f"is in use by run 1, pid {first.pid} on {socket.gethostname()}" in err, err
    assert "Traceback" not in err and "Could not start listen" not in err
    assert not (tmp_path / "second").exists()


def test_a_lock_left_by_a_killed_run_is_taken_over_with_a_note(tmp_path, capsys, no_leaks):  # noqa: F811
    """The first run is killed (-9) at a prompt: the kernel drops its flock, its lock file still
    names it. The next run on the station takes the lock over, says so, and completes."""
    station = private_file("az-modbus-tcp", tmp_path, link="timeout_s = 0.1\nreconnect_s = 1")
    db = tmp_path / "lab.sqlite"
    first = first_run_waiting_at_a_prompt(station, db, tmp_path)
    first.kill()
    first.communicate(timeout=30)
    code, out, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--yes", "--db", str(db),
                         "--plan", "one-mount-16", "--out", str(tmp_path / "second"), "--json")
    assert code == 0, err
    assert f"locked by run 1, pid {first.pid} on {socket.gethostname()}" in err
    assert "which is no longer running; lock taken over" in err
    assert json.loads(out)["points"] == 16
    assert all(p.read_text() == "" for folder in station_locks(db) for p in folder.glob("*.lock"))  # released


def test_an_address_another_emulator_serves_is_one_line(tmp_path, capsys, no_leaks):  # noqa: F811
    """`labcal sim serve` (which takes no station lock) already listens on the station's Modbus TCP
    address: `labcal run --emulate` says so in one line, exit 2, instead of pymodbus's traceback."""
    station = private_file("az-modbus-tcp", tmp_path)
    text = station.read_text()
    port = int(text.split('tcp = "127.0.0.1:')[1].split('"')[0])  # the tables' gateway
    with socket.create_server(("127.0.0.1", port)):
        code, out, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--yes",
                             "--out", str(tmp_path / "run"))
    assert code == 2 and err.strip().count("\n") == 0, err
    assert f"cannot serve tcp 127.0.0.1:{port} ({os.strerror(errno.EADDRINUSE)})" in err
    assert "Traceback" not in err and "is another emulator" in err


def test_two_spellings_of_one_link_are_one_lock(tmp_path):
    """By hand: a by-id symlink and the port it points at, localhost and 127.0.0.1, a pyserial socket
    URL and a VISA raw socket resource and a TCP address, an ASRL resource and its port."""
    port = tmp_path / "ttyUSB0"
    port.touch()
    alias = tmp_path / "usb-FTDI-if00-port0"
    alias.symlink_to(port)
    assert link_key(f"port:{alias}") == link_key(f"port:{port}") == f"port:{port.resolve()}"
    assert link_key("tcp:localhost:502") == link_key("tcp:127.0.0.1:502") == "tcp:127.0.0.1:502"
    assert link_key("port:socket://127.0.0.1:4001") == link_key("visa:TCPIP0::127.0.0.1::4001::SOCKET") \
        == link_key("tcp:127.0.0.1:4001") == "tcp:127.0.0.1:4001"
    assert link_key(f"visa:ASRL{alias}::INSTR") == f"port:{port.resolve()}"
    assert link_key("visa:gpib0::9::instr") == link_key("visa:GPIB0::9::INSTR") == "visa:GPIB0::9::INSTR"
    assert link_key("tcp:10.0.0.5:502") != link_key("tcp:10.0.0.5:503")
    assert os.path.exists(port)


def test_two_emulated_runs_of_one_example_station_at_once_both_complete(tmp_path, lab_database):
    """The example stations let the emulators choose free ports (``127.0.0.1:0``) and ptys of
    their own: two `labcal run --station az-modbus-tcp --emulate` at once, journaling into one lab
    database (so one set of station locks), both complete. Before, the example's fixed ports made
    the second one fail (its lock, or its emulator's listen). Each served its own addresses."""
    runs = [subprocess.Popen([LABCAL, "run", "--station", "az-modbus-tcp", *EMULATE, "--yes",
                              "--out", str(tmp_path / name)], stdin=subprocess.DEVNULL,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for name in "ab"]
    outputs = [run.communicate(timeout=300) for run in runs]
    assert [run.returncode for run in runs] == [0, 0], outputs
    served = [json.loads((tmp_path / name / "run.json").read_text())["simulated_truth"]["endpoints"]
              for name in "ab"]
    addresses = [e["address"] for endpoints in served for e in endpoints]
    assert len(set(addresses)) == 4 and not any(a.endswith(":0") for a in addresses), served


def test_the_lock_of_an_emulated_run_holds_the_addresses_its_emulators_chose(tmp_path, capsys,
                                                                             lab_database):
    """While an emulated run of the example station (free ports) waits at a prompt, a run through
    another station file that names the address its emulators chose is refused in one line naming
    run 1: the lock holds the chosen address, not "port 0"."""
    first = first_run_waiting_at_a_prompt(Path("az-modbus-tcp"), lab_database, tmp_path)
    try:
        deadline = time.monotonic() + 60
        while not (tmp_path / "first" / "run.json").exists():
            assert time.monotonic() < deadline, "the first run wrote no run.json"
            time.sleep(0.05)
        endpoints = json.loads((tmp_path / "first" / "run.json").read_text())["simulated_truth"]["endpoints"]
        gateway = next(e["address"] for e in endpoints if "pitch" in e["devices"]).removeprefix("tcp ")
        station = private_file("az-modbus-tcp", tmp_path)  # fixed free ports of its own...
        own = load_station(station)[0].pitch.tcp
        same = station.read_text().replace(f'"{own}"', f'"{gateway}"')  # ...but the first's gateway
        (tmp_path / "same-gateway.toml").write_text(same)
        code, out, err = cli(capsys, "run", "--station", str(tmp_path / "same-gateway.toml"), "--no-report",
                             "--out", str(tmp_path / "second"))
        assert code == 2
        assert f"tcp {gateway} is in use by run 1" in err, err
    finally:
        first.kill()
        first.wait(timeout=30)


@pytest.mark.parametrize("name", ["az-modbus-tcp", "smc100-tcp"])
def test_a_refused_run_sends_nothing_to_the_devices_of_a_lan_bench(name, tmp_path, no_leaks):  # noqa: F811
    """A LAN bench (emulators served at fixed addresses, as `labcal sim serve` serves them) held by
    another run: a second `labcal run` on it is refused in one line, and the emulators' own logs of
    every request they heard (Modbus frames on the gateway, command lines on the SMC100 chain and
    the DMM) hold nothing from it: the lock is taken before any device is opened or written."""
    station = private_file(name, tmp_path, link="timeout_s = 0.2\nreconnect_s = 0")
    config = load_station(station)[0]
    db = tmp_path / "lab.sqlite"
    links = {settings.bus: settings.where for settings in config.devices().values()}
    with Emulation(config, time_scale=TIME_SCALE) as emulation, \
            StationLock(station_locks(db), links, str(station)):  # the run holding the station
        servers = [server for _, _, server in emulation.servers.values()]
        assert len(servers) == 2  # the tables' bus and the DMM's link
        second = subprocess.run([LABCAL, "run", "--station", str(station), "--no-report", "--yes", "--db",
                                 str(db), "--out", str(tmp_path / "second")],
                                capture_output=True, text=True, timeout=120)
        heard = {server.address: list(server.received) for server in servers}
    assert second.returncode == 2 and second.stdout == "", second.stdout
    assert second.stderr.count("\n") == 1 and "one run per station at a time" in second.stderr, second.stderr
    assert heard == {server.address: [] for server in servers}


def test_a_run_refused_before_any_table_moved_writes_nothing_to_the_tables(tmp_path, no_leaks):  # noqa: F811
    """A run on a LAN bench (emulators served at fixed addresses) whose DMM refuses its configuration
    as the run prepares (the checklist's went through: SCPI -222 the second time): refused in one
    line. Before, it then stopped the tables it had never moved, with two broadcast STOP frames
    (function 06 to address 0) and each drive's stop and release on the gateway, which stop tables
    another process drives (one whose station lock this one cannot see: another computer). Now the
    gateway hears only the reads of the checklist and of the preparation: no write at all."""
    refused = ('\n[[emulation.faults]]\ndevice = "dmm"\nkind = "exception"\nmatch = "^CONF:VOLT"\n'
               'after = 1\ncount = 5\ncode = -222\n')
    station = private_file("az-modbus-tcp", tmp_path, refused, "timeout_s = 0.2\nreconnect_s = 0")
    with Emulation(load_station(station)[0], time_scale=TIME_SCALE) as emulation:
        gateway = next(server for _, _, server in emulation.servers.values() if hasattr(server, "drives"))
        second = subprocess.run([LABCAL, "run", "--station", str(station), "--no-report", "--yes", "--db",
                                 str(tmp_path / "lab.sqlite"), "--out", str(tmp_path / "run")],
                                capture_output=True, text=True, timeout=120)
        heard = [function for _, _, function, _ in gateway.received]
    assert second.returncode == 2, second.stderr
    assert second.stderr.strip().splitlines()[-1].startswith("labcal: error: dmm (Keysight 34970A")
    assert 'SCPI error -222 "Data out of range"' in second.stderr
    assert heard and set(heard) == {0x03}, heard  # reads (function 03) only: no 06, no 10h
