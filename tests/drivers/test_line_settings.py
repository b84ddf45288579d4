"""Serial line settings the operating system refuses: one line naming the device,
the port and the setting, exit 2, no traceback; the port is not reopened for the reconnect budget
(it would be refused the same way)."""

from __future__ import annotations

import time

import pytest
from cli import cli
from emulators import no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import load_station
from labcal.drivers.errors import SettingsRefused
from labcal.drivers.transport import open_serial
from labcal.sim.emulation import Emulation


def test_a_parity_the_pty_refuses_is_one_line_naming_the_device_and_the_setting(tmp_path, capsys,
                                                                                   no_leaks):  # noqa: F811
    """The DMM's RS-232 link is a pty (`labcal sim serve`), which carries no parity: a station file
    that asks for parity E on it. `labcal run`'s pre-run checklist asks the DMM, whose port is refused:
    exit 2, one line naming the DMM, its port and `parity = "E"`, within far less than the
    reconnect budget (30 s here). Before, termios.error escaped as a traceback."""
    served = private_file("az-modbus-rtu", tmp_path)
    wrong = tmp_path / "parity-e.toml"
    wrong.write_text(served.read_text().replace("[dmm]\n", '[dmm]\nparity = "E"\nreconnect_s = 30\n'))
    with Emulation(load_station(served)[0], time_scale=1000):
        t0 = time.monotonic()
        code, out, err = cli(capsys, "run", "--station", str(wrong), "--yes", "--no-report", "--plan",
                             "one-mount-16", "--fixed-dwell", "0.01", "--out", str(tmp_path / "run"))
        took = time.monotonic() - t0
    line = err.strip().splitlines()[-1]
    assert code == 2 and out == "" and "Traceback" not in err, err
    # the pre-run checklist asks the DMM first, before anything moves, and names the DMM's own line
    assert line.startswith(f"labcal: error: pre-run checklist: DMM: dmm (Keysight 34970A, {tmp_path}/dmm): "
                           f'{tmp_path}/dmm does not keep parity = "E" (it reads back other line '
                           "settings)"), line
    assert line.endswith("; nothing was moved")
    assert took < 15, took


def test_the_refused_setting_is_named_among_the_accepted_ones(tmp_path, no_leaks):  # noqa: F811
    """Of 57600 Bd, 8 data bits, parity E, 1 stop bit and XON/XOFF on a pty, only parity is refused.
    Linux takes parity on a pty once without a word and drops it (read back, it is not there);
    every later setting of the pty is then refused outright (termios: EINVAL): each setting is
    tried alone on the port at 9600 8N1 to name the one."""
    served = private_file("az-modbus-rtu", tmp_path)
    with Emulation(load_station(served)[0], time_scale=1000):
        for said in ('does not keep parity = "E" (it reads back',
                     'refuses parity = "E" (the operating system says: Invalid argument)'):
            with pytest.raises(SettingsRefused) as refused:
                open_serial(str(tmp_path / "dmm"), baudrate=57600, bytesize=8, parity="E", stopbits=1,
                            xonxoff=True, timeout=0.02)
            assert f"{tmp_path}/dmm {said}" in str(refused.value)
        assert "baudrate" not in str(refused.value) and "xonxoff" not in str(refused.value)
        open_serial(str(tmp_path / "dmm"), baudrate=57600, parity="N", timeout=0.02).close()  # N is fine
