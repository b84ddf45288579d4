"""The instrument's sensor package in the station file (Tripp & Tcheng §6): validated, judged by
`plan audit --station` over the certificate's usage envelope, refused by `labcal run` before
anything moves where it cannot be used, and read by the DMM through one channel per sensor."""

from __future__ import annotations

import json
import re

import pytest
from pydantic import ValidationError

from labcal.cli import main
from labcal.config.station import InstrumentSettings, load_station, shipped_stations

# one DMM channel per sensor of the package, in x, y, z order
CHANNELS = {"single-axis": "[101]", "two-axis-xy": "[101, 102]", "two-axis-xz": "[101, 103]"}


def station_with(tmp_path, instrument: str, certificate: str = "", channels: str | None = None) -> str:
    """lab-example with extra [instrument] settings (and [certificate] ones), its DMM's channel list
    the package's unless ``channels`` gives another."""
    text = shipped_stations()["lab-example"].read_text(encoding="utf-8")
    assert "[instrument]" in text and "channels = [101, 102, 103]" in text
    package = re.search(r'package = "([^"]+)"', instrument)
    channels = channels or CHANNELS.get(package[1] if package else "", "[101, 102, 103]")
    text = text.replace("channels = [101, 102, 103]", f"channels = {channels}", 1)
    text = text.replace("[instrument]", "[instrument]\n" + instrument, 1)
    if certificate:
        text = text.replace("[certificate]", "[certificate]\n" + certificate, 1) if "[certificate]" in text \
            else text + "\n[certificate]\n" + certificate + "\n"
    path = tmp_path / "bench.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def test_existing_stations_stay_three_axis_inferring_roll():
    config, _ = load_station("lab-example")
    assert config.instrument.package == "three-axis" and config.instrument.roll_source == "inferred"


@pytest.mark.parametrize("settings,message", [
    ({"package": "single-axis"}, "cannot infer roll"),
    ({"package": "single-axis", "roll_in_use": "sensor"}, "needs roll_sd_deg"),
    ({"package": "two-axis-xy", "roll_in_use": "none"}, "is for a single-axis package"),
    ({"package": "three-axis", "roll_sd_deg": 0.1}, "roll_sd_deg is for a roll measured"),
    ({"package": "four-axis"}, "three-axis"),
])
def test_package_settings_are_validated(settings, message):
    with pytest.raises(ValidationError, match=message):
        InstrumentSettings(**settings)


def test_single_axis_at_a_measured_roll_is_accepted():
    inst = InstrumentSettings(package="single-axis", roll_in_use="sensor", roll_sd_deg=0.05)
    assert inst.roll_source == "sensor" and inst.roll_sd_deg == 0.05


def test_plan_audit_says_why_an_x_y_package_cannot_be_used_over_full_roll(tmp_path, capsys):
    """The default envelope spans roll ±180°, through the x–y package's singular R = ±90° (eq. 86)."""
    station = station_with(tmp_path, 'package = "two-axis-xy"')
    assert main(["plan", "audit", "four-mount-64", "--station", station, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["package"]["axes"] == ["x", "y"] and "singular near" in doc["package"]["problem"]
    assert "roll -90°" in doc["package"]["problem"] or "roll 90°" in doc["package"]["problem"]


def test_plan_audit_accepts_an_x_y_package_within_its_usable_roll(tmp_path, capsys):
    station = station_with(tmp_path, 'package = "two-axis-xy"', "usage_roll_deg = [-60, 60]")
    assert main(["plan", "audit", "four-mount-64", "--station", station]) == 0
    out = capsys.readouterr().out
    assert "two-axis-xy (x, y)" in out and "refused" not in out


def test_run_refuses_a_package_before_anything_moves(tmp_path, capsys):
    """The station's devices do not exist here: reaching them would be another error. The refusal is
    the package's, one line, exit 2, and no run directory is made."""
    station = station_with(tmp_path, 'package = "two-axis-xz"')
    out = tmp_path / "runs"
    code = main(["run", "--station", station, "--plan", "four-mount-64", "--out", str(out), "--no-report"])
    err = capsys.readouterr().err
    assert code == 2 and "two-axis-xz package cannot infer pitch and roll" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_run_estimates_a_usable_single_axis_package_on_a_stations_devices(tmp_path, capsys):
    """A single sensor at a measured roll passes the start-up checks of a station's run (the dry run
    opens no device): the DMM reads its one channel."""
    station = station_with(tmp_path, 'package = "single-axis"\nroll_in_use = "table"\nroll_sd_deg = 0.01')
    code = main(["run", "--station", station, "--plan", "four-mount-64", "--dry-run"])
    assert code == 0, capsys.readouterr().err


@pytest.mark.parametrize(("package", "channels"), [("single-axis", "[101, 102, 103]"),
                                                   ("two-axis-xy", "[101]"), ("three-axis", "[101, 102]")])
def test_a_station_whose_channel_list_does_not_match_its_package_is_refused_in_one_line(
        tmp_path, capsys, package, channels):
    """A channel per sensor: a list longer than the package's sensors would scan an output nobody
    journals, a shorter one would leave a sensor unread. Refused as the file is read, before anything
    moves, naming both counts."""
    roll = '\nroll_in_use = "table"\nroll_sd_deg = 0.01' if package == "single-axis" else ""
    station = station_with(tmp_path, f'package = "{package}"{roll}', "usage_roll_deg = [-60, 60]", channels)
    out = tmp_path / "runs"
    code = main(["run", "--station", station, "--plan", "four-mount-64", "--out", str(out), "--no-report"])
    err = capsys.readouterr().err
    n = channels.count(",") + 1
    assert code == 2 and f"[dmm] channels lists {n} channel(s)" in err and f"the {package} package has" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_another_package_on_the_same_channels_is_another_bench_for_a_resume(tmp_path):
    """Channels 101 and 102 reading an x–y package are not the same channels reading an x–z one: a
    resume on such a file is refused naming the package (its channels alike, they go unnamed)."""
    xy, _ = load_station(station_with(tmp_path, 'package = "two-axis-xy"', "usage_roll_deg = [-60, 60]"))
    xz, _ = load_station(station_with(tmp_path, 'package = "two-axis-xz"\nroll_in_use = "table"\n'
                                      "roll_sd_deg = 0.01", channels="[101, 102]"))
    assert xy.identity_differences(xz, "new.toml") == [
        "instrument.package: two-axis-xy in the run, two-axis-xz in new.toml"]
