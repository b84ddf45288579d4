"""The 34970A driver through VISA (pyvisa with the pyvisa-py library that installs with labcal),
against the SCPI emulator over a raw TCPIP SOCKET and over a serial pty (ASRL), and what a station
that names a VISA resource or library that is not there gets: one line, exit 2."""

from __future__ import annotations

import json
import statistics
import termios
import time

import pytest
from cli import cli
from emulators import emulated, no_leaks, private_file  # noqa: F401 - fixture

from labcal.bench.hardware import Bench
from labcal.config.station import StationFile
from labcal.drivers.errors import LinkLost
from labcal.drivers.visa import VisaLink

QUICK = {"timeout_s": 0.5, "retries": 1, "reconnect_s": 0.0}


def through_visa(config: StationFile, resource: str) -> StationFile:
    dmm = config.dmm.model_copy(update={"visa": resource, "tcp": None, "port": None})
    return config.model_copy(update={"dmm": StationFile.model_validate(
        {**config.model_dump(), "dmm": dmm.model_dump()}).dmm})


@pytest.mark.parametrize("station", ["az-modbus-tcp", "smc100-serial"])
def test_the_same_driver_scans_through_pyvisa_py(station, tmp_path, no_leaks):  # noqa: F811
    with emulated(station, tmp_path, dmm=QUICK) as (emulation, _):
        dmm = emulation.station_config.dmm
        resource = (f"TCPIP0::{dmm.tcp.replace(':', '::')}::SOCKET" if dmm.tcp else f"ASRL{dmm.port}::INSTR")
        config = through_visa(emulation.station_config, resource)
        assert config.dmm.serial_line == (dmm.port is not None)
        with Bench(config, emulation.rig.clock) as bench:
            assert isinstance(bench.dmm.link, VisaLink) and bench.dmm.device.endswith(f"VISA {resource})")
            assert bench.dmm.identify().startswith("Keysight Technologies,34970A,")
            if dmm.port is not None:  # the station's XON/XOFF reaches the port itself
                instrument = bench.dmm.link._instrument
                port = instrument.visalib.sessions[instrument.session].interface
                iflag = termios.tcgetattr(port.fd)[0]
                assert config.dmm.xonxoff and iflag & termios.IXON and iflag & termios.IXOFF
            bench.dmm.configure()
            scan = bench.dmm.read(3)
            assert scan.volts.shape == (3, 3) and bench.dmm.errors() == []
            report = bench.check()[2]
            assert report["problem"] is None and report["identity"].startswith("Keysight")


def test_one_scan_through_visa_and_through_the_raw_socket(tmp_path, no_leaks):  # noqa: F811
    """The round trip of one scan (TRIG:COUN, INIT, *OPC?, FETC?, SYST:ERR?) through pyvisa-py
    against labcal's own socket link, on the same emulator; printed as a ratio (not asserted)."""
    with emulated("smc100-tcp", tmp_path, time_scale=1e5, dmm=QUICK) as (emulation, raw_bench):
        dmm = emulation.station_config.dmm
        config = through_visa(emulation.station_config, f"TCPIP0::{dmm.tcp.replace(':', '::')}::SOCKET")
        with Bench(config, emulation.rig.clock) as visa_bench:
            meters = {"socket": raw_bench.dmm, "visa": visa_bench.dmm}
            times: dict[str, list[float]] = {"socket": [], "visa": []}
            for meter in meters.values():
                meter.configure()
                meter.read(1)
            for _ in range(40):  # alternated, so that a busy machine slows both alike; medians
                for name, meter in meters.items():
                    t0 = time.perf_counter()
                    meter.read(1)
                    times[name].append(time.perf_counter() - t0)
        socket_s, visa_s = (statistics.median(times[name]) for name in ("socket", "visa"))
        print(f"one scan: raw socket {socket_s * 1e3:.2f} ms, pyvisa-py {visa_s * 1e3:.2f} ms "
              "(medians of 40), "
              f"ratio {visa_s / socket_s:.2f}")


def station_with(tmp_path, visa: str, library: str = "@py"):
    path = private_file("smc100-tcp", tmp_path)
    text = path.read_text()
    start = text.index("[dmm]")
    end = text.index("\n\n", start)
    text = text[:start] + ('[dmm]\ndriver = "keysight-34970a"\n'
                           f'visa = "{visa}"\nvisa_library = "{library}"\ntimeout_s = 0.2\n') + text[end:]
    path.write_text(text)
    return path


def dmm_problem(capsys, station) -> str:
    """`labcal station check --json`: exit 2, and the DMM's problem (the tables are not served)."""
    code, out, err = cli(capsys, "station", "check", str(station), "--json")
    assert code == 2 and "Traceback" not in err
    [dmm] = [r for r in json.loads(out)["devices"] if r["device"] == "dmm"]
    assert "identity" not in dmm and "\n" not in dmm["problem"]
    return dmm["problem"]


def test_a_visa_resource_that_is_not_there_is_one_line(tmp_path, capsys):
    problem = dmm_problem(capsys, station_with(tmp_path, "TCPIP0::127.0.0.1::1::SOCKET"))
    # pyvisa-py opens a socket resource without waiting for the connection: the first write fails
    assert problem.startswith("dmm (Keysight 34970A, VISA TCPIP0::127.0.0.1::1::SOCKET): ")
    assert "Connection refused" in problem and problem.endswith("check the cable and the port")


def test_a_missing_visa_library_is_one_line(tmp_path, capsys):
    library = str(tmp_path / "libvisa.so")
    problem = dmm_problem(capsys, station_with(tmp_path, "GPIB0::9::INSTR", library=library))
    assert f"cannot load the VISA library '{tmp_path / 'libvisa.so'}'" in problem
    assert 'visa_library = "@py"' in problem


def test_a_station_names_one_link_for_its_dmm(tmp_path, capsys):
    path = station_with(tmp_path, "GPIB0::9::INSTR")
    both = 'visa = "GPIB0::9::INSTR"\ntcp = "h:1"'
    path.write_text(path.read_text().replace('visa = "GPIB0::9::INSTR"', both))
    code, _, err = cli(capsys, "station", "check", str(path))
    assert code == 2 and "give exactly one of port" in err and err.count("\n") == 1


def test_an_unloadable_library_from_the_link_itself(tmp_path):
    link = VisaLink("GPIB0::9::INSTR", library=str(tmp_path / "nothing.so"), timeout_s=0.1, reconnect_s=0)
    with pytest.raises(LinkLost, match="cannot load the VISA library"):
        link.query("*IDN?")
