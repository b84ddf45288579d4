"""Station files and the commands around them: `labcal station list|check`, `labcal sim serve`,
and what a bad station file or an absent device looks like (one line, exit code 2)."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest
from cli import LABCAL, cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import load_station, shipped_stations

EMULATED = [name for name in shipped_stations() if name != "lab-example"]


def test_every_example_station_is_valid_and_listed(capsys):
    code, out, _ = cli(capsys, "station", "list", "--json")
    listed = {s["name"]: s for s in json.loads(out)["stations"]}
    assert code == 0 and set(listed) == set(shipped_stations()) and len(EMULATED) == 6
    assert (listed["mixed-rtu-socket"]["pitch"], listed["mixed-rtu-socket"]["roll"]) == ("oriental-az",
                                                                                        "newport-smc100")
    config, text = load_station("lab-example")
    assert config.dmm.tcp == "192.168.10.20:5025" and text.count("#") >= 15  # a commented example


@pytest.mark.parametrize("station", EMULATED)
def test_check_every_emulated_station(station, tmp_path, capsys, no_leaks):  # noqa: F811
    """Each example's devices answer through the real drivers: identity, status, position, a scan."""
    code, out, err = cli(capsys, "station", "check", str(private_file(station, tmp_path)), "--emulate",
                         "--time-scale", str(TIME_SCALE), "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["ok"] and [d["device"] for d in report["devices"]] == ["pitch", "roll", "dmm"]
    tables, dmm = report["devices"][:2], report["devices"][2]
    assert all(d["problem"] is None and d["position_deg"] == 0.0 for d in tables)
    assert dmm["identity"].startswith("Keysight Technologies,34970A")
    volts = dmm["volts"]  # level at home: z reads 1 g (5 V/g), x none
    if station == "single-axis-tcp":  # its one sensor, along x; null for the y and z it lacks
        assert volts[1:] == [None, None] and abs(volts[0]) < 0.05
    else:
        assert abs(volts[2] - 5.0) < 0.05
    for table in tables:  # an SMC100 powers up unreferenced: not a problem, the run homes it
        assert table["status"] in ("READY IN-POS", "NOT REFERENCED from reset (0Ah) (a run homes it first)")


def test_check_says_plainly_what_does_not_answer(tmp_path, capsys):
    station = tmp_path / "absent.toml"
    station.write_text('[pitch]\ndriver = "oriental-az"\ntcp = "127.0.0.1:1"\nsteps_per_degree = 50\n'
                       f'[roll]\ndriver = "newport-smc100"\nport = "{tmp_path}/no-such-port"\n'
                       '[dmm]\ndriver = "keysight-34970a"\ntcp = "127.0.0.1:2"\n')
    code, out, err = cli(capsys, "station", "check", str(station))
    assert code == 2
    assert "kept trying" not in err  # one attempt per device, not the 5 s reconnect budget of a run
    lines = err.strip().splitlines()
    assert lines[-1] == "labcal: error: 3 of 3 devices failed the check (pitch, roll, dmm); see the lines " \
                        "above"
    assert "pitch table (Oriental Motor AZ, unit 1 on tcp 127.0.0.1:1): cannot open tcp 127.0.0.1:1" in err
    assert "no-such-port (No such file or directory); check the cable, the port name" in err
    assert "Traceback" not in err and "pitch" in out


def test_a_silent_device_is_named(tmp_path, capsys, no_leaks):  # noqa: F811
    """The port opens but nothing answers at that address: say so, after the timeout and retries."""
    path = private_file("smc100-tcp", tmp_path, link="timeout_s = 0.1")
    text = path.read_text().replace("address = 2", "address = 7")  # asks for 7; the chain has 1 and 2
    emulated_file = tmp_path / "emu.toml"
    emulated_file.write_text(path.read_text())
    path.write_text(text)
    from labcal.config.station import load_station as load
    from labcal.sim.emulation import Emulation

    with Emulation(load(emulated_file)[0], time_scale=TIME_SCALE):
        code, _, err = cli(capsys, "station", "check", str(path))
    assert code == 2
    assert "roll table (Newport SMC100, address 7 on tcp 127.0.0.1:" in err and "no reply within 0.1 s" in err
    assert err.strip().splitlines()[-1].endswith("1 of 3 devices failed the check (roll); see the lines "
                                                 "above")


def table(driver: str, tcp: str, *lines: str) -> str:
    return "\n".join([f'driver = "{driver}"', f'tcp = "{tcp}"', *lines]) + "\n"


AZ, SMC = "oriental-az", "newport-smc100"
ROLL = "[roll]\n" + table(SMC, "h:3", "address = 2")
DMM = '[dmm]\ndriver = "keysight-34970a"\ntcp = "h:2"\n'


def with_pitch(pitch: str, dmm_extra: str = "") -> str:
    return "[pitch]\n" + pitch + ROLL + DMM + dmm_extra


BAD = [
    ("[pitch\n", "malformed TOML"),
    (with_pitch('driver = "zaber"\n'), "pitch: Input tag 'zaber' found using 'driver' does not match"),
    (with_pitch(table(AZ, "h:1", 'port = "/dev/x"', "steps_per_degree = 1")),
     "give exactly one of port (a serial device or URL) and tcp (host:port)"),
    (with_pitch(table(AZ, "no-port", "steps_per_degree = 1")), "'no-port' is not host:port"),
    (with_pitch(table(AZ, "h:1", "steps_per_degree = 1", "limits_deg = [0, 90]")), "a wrapping table has no"),
    (with_pitch(table(AZ, "h:1", "steps_per_degree = 1.001")),
     "steps_per_degree × 360 = 360.36 is not a whole number of steps per turn"),
    (with_pitch(table(SMC, "h:1", "limits_deg = [90, 0]")), "low < high"),
    (with_pitch(table(SMC, "h:1", "colour = 1")),
     "pitch.colour: unknown key; the valid keys here are accel_dps2, address,"),
    (with_pitch(table(SMC, "h:3", "address = 2")), "pitch and roll share tcp h:3 and address 2"),
    (with_pitch(table(AZ, "h:3", "steps_per_degree = 1")), "share tcp h:3 but not a driver"),
    (with_pitch(table(AZ, "h:2", "steps_per_degree = 1")), "the DMM cannot share tcp h:2 with a table"),
    (with_pitch(table(SMC, "h:1"), "nplc = 3\n"), "dmm.nplc: nplc must be one of 0.02, 0.2, 1, 2, 10"),
]


@pytest.mark.parametrize("text,expected", BAD)
def test_bad_station_files(text, expected, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    code, out, err = cli(capsys, "station", "check", str(path))
    assert code == 2 and out == "" and err.strip().count("\n") == 0, err
    assert expected in err and str(path) in err


@pytest.mark.parametrize("args,expected", [
    (["station", "check", "nowhere"], "unknown station 'nowhere'; give a station file (.toml) or one of"),
    (["station", "check", "missing.toml"], "missing.toml: no such station file"),
    (["station", "check", "lab-example", "--emulate"], "pitch: /dev/serial/by-id/usb-FTDI_USB-RS485_Cable_"
     "FT1ABCDE-if00-port0 is a real device; emulators link their ptys elsewhere"),
    (["sim", "serve", "az-modbus-tcp", "--time-scale", "-1"],
     "argument --time-scale: -1 is out of range; expected a number x with 0 < x ≤ 100000"),
    (["run", "--station", "az-modbus-tcp", "--sim"], "give --sim (the simulated rig) or --station FILE, not"),
    (["run", "--sim", "--emulate"], "--emulate needs --station FILE"),
])
def test_bad_arguments(args, expected, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = cli(capsys, *args)
    assert code == 2 and out == "" and expected in err and err.strip().count("\n") == 0, err


def test_a_pty_cannot_carry_parity(tmp_path, capsys):
    path = private_file("az-modbus-rtu", tmp_path)
    path.write_text(path.read_text().replace('parity = "N"', 'parity = "E"'))
    code, _, err = cli(capsys, "station", "check", str(path), "--emulate")
    assert code == 2 and 'pitch: a pty cannot carry parity E; set parity = "N" to emulate it on a pty' in err


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("started", ["from a terminal", "with SIGINT ignored (cmd & in a script)"])
def test_sim_serve_until_ctrl_c(started, tmp_path, capsys):
    """`labcal sim serve` in its own process: prints where it listens, answers `station check`
    from another process, takes console commands, and on Ctrl-C stops and removes its ptys — also
    when it was started with SIGINT ignored, as `cmd &` in a non-interactive shell starts it."""
    station = private_file("smc100-serial", tmp_path)
    proc = subprocess.Popen([LABCAL, "sim", "serve", str(station), "--json", "--time-scale", "200"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_ignore_sigint if "ignored" in started else None)
    try:
        doc = json.loads("".join(iter(proc.stdout.readline, "}\n")) + "}")
        assert doc["time_scale"] == 200
        assert [e["devices"] for e in doc["endpoints"]] == [["pitch", "roll"], ["dmm"]]
        assert doc["endpoints"][0]["address"] == f"pty {tmp_path}/smc100"
        assert Path(tmp_path / "smc100").is_symlink() and Path(tmp_path / "dmm").is_symlink()
        code, out, err = cli(capsys, "station", "check", str(station), "--json")
        assert code == 0, err
        report = json.loads(out)
        assert report["devices"][0]["status"] == "NOT REFERENCED from reset (0Ah) (a run homes it first)"
        assert report["devices"][2]["problem"] is None and len(report["devices"][2]["volts"]) == 3
        proc.stdin.write("mount 180 0\nstatus\nfrob\n")
        proc.stdin.flush()
        seen = ""  # stderr up to the reply to "frob", the last command: then all three were served
        for line in iter(proc.stderr.readline, ""):
            seen += line
            if seen.count("commands: mount Y U") == 2:  # once when it started, once for "frob"
                break
        proc.send_signal(signal.SIGINT)
        _, rest = proc.communicate(timeout=20)
        err = seen + rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "instrument remounted: top side of the plate, x sensor pointing backward" in err
    assert "mount y=180°, u=0°" in err and "commands: mount Y U" in err  # status, and help for "frob"
    assert err.strip().endswith("emulators stopped") and "Traceback" not in err
    assert not (tmp_path / "smc100").exists() and not (tmp_path / "dmm").exists()


def test_check_reports_a_drive_alarm_and_resets_it_on_request(tmp_path, capsys, no_leaks):  # noqa: F811
    alarm = '\n[[emulation.faults]]\ndevice = "pitch"\nkind = "alarm"\ncode = 16\n'
    station = str(private_file("az-modbus-tcp", tmp_path, alarm))
    code, _, err = cli(capsys, "station", "check", station, "--emulate", "--time-scale", str(TIME_SCALE))
    assert code == 2 and "alarm 10h (excessive position deviation); clear the cause, then" in err
    assert "`labcal station check STATION --reset-alarms`" in err
    code, out, err = cli(capsys, "station", "check", station, "--emulate", "--time-scale", str(TIME_SCALE),
                         "--reset-alarms", "--json")
    pitch = json.loads(out)["devices"][0]
    assert code == 0 and pitch["alarm_reset"] and pitch["status"] == "READY IN-POS", err


def test_check_warns_of_an_overdue_reference_standard(tmp_path, capsys, no_leaks):  # noqa: F811
    """A station file's [[traceability]] entry due before today: one warning line naming the
    standard, its certificate and due date (and in --json); one due in 2999 is not named. The
    devices answer, so the check still passes."""
    from datetime import date

    standards = ('\n[[traceability]]\nequipment = "reference DMM"\nidentity = "Keysight 34970A, serial '
                 'MY1"\ncertificate = "CAL-OLD-7"\nissued_by = "a lab"\ndue = 2020-01-01\n'
                 '\n[[traceability]]\nequipment = "index tables"\nidentity = "T-1"\ncertificate = '
                 '"ANG-NEW-1"\nissued_by = "a lab"\ndue = 2999-12-31\n')
    station = private_file("smc100-tcp", tmp_path, extra=standards)
    day = date.today()  # as people write dates (%B: the C locale's English month)
    expected = ("Reference standard reference DMM (Keysight 34970A, serial MY1, certificate CAL-OLD-7) is "
                f"overdue for calibration: due 1 January 2020, today {day.day} {day:%B %Y}.")
    code, out, err = cli(capsys, "station", "check", str(station), "--emulate", "--time-scale",
                         str(TIME_SCALE), "--json")
    assert code == 0, err
    assert json.loads(out)["overdue_standards"] == [
        {"equipment": "reference DMM", "identity": "Keysight 34970A, serial MY1", "certificate": "CAL-OLD-7",
         "due": "2020-01-01", "message": expected}]
    code, out, err = cli(capsys, "station", "check", str(station), "--emulate", "--time-scale",
                         str(TIME_SCALE))
    assert code == 0, err
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert [" ".join(w.split()) for w in warnings] == [f"warning: {expected}"]
    assert "ANG-NEW-1" not in err + out
