"""The station snapshot a run journals is read once into its model (`labcal.config.snapshot`): every
journal the tests keep parses, old ones included, and "is this run simulated" is one rule."""

import json
import sqlite3
from pathlib import Path

import pytest

from labcal.config.run_metadata import RunMetadata
from labcal.config.snapshot import (
    SimulatedRigSnapshot,
    StationFileSnapshot,
    is_simulated,
    output_units,
    parse_snapshot,
)

DATA = Path(__file__).parent.parent / "data"


def journaled_snapshots() -> list[tuple[str, str]]:
    """Every station snapshot in the journals kept under tests/data, by journal and run."""
    found = []
    for journal in sorted(DATA.rglob("*.sqlite")):
        with sqlite3.connect(journal) as db:
            found += [(f"{journal.relative_to(DATA)} run {run}", text)
                      for run, text in db.execute("SELECT id, station_text FROM runs")]
    return found


def test_the_tests_keep_at_least_one_journal():
    assert journaled_snapshots(), "no journal under tests/data: the test below would check nothing"


@pytest.mark.parametrize(("where", "text"), journaled_snapshots(), ids=lambda x: x if " run " in x else "")
def test_every_journaled_snapshot_parses_into_its_model(where, text):
    """The first labcal's journal (before fields were added to the rig) reads as the simulated rig
    it ran on, with its seed, and today's rig model validates its settings (defaults filling in)."""
    doc = json.loads(text)
    snapshot = parse_snapshot(text)
    assert isinstance(snapshot, SimulatedRigSnapshot), where
    assert snapshot.seed == doc["seed"] and snapshot.rig == doc["rig"]
    assert snapshot.rig_config().device.index_arcsec == doc["rig"]["device"]["index_arcsec"]
    assert snapshot.simulated and output_units(snapshot) == "V"


def test_a_station_file_snapshot_parses_with_what_it_ran_on():
    """A station file's snapshot as a run journals it: the file's settings, on its emulators or not."""
    from labcal.config.station import load_station

    station, _ = load_station("lab-example")
    settings = station.model_dump(mode="json")
    on_hardware = parse_snapshot(json.dumps({"kind": "station", "station": settings, "emulate": False}))
    assert isinstance(on_hardware, StationFileSnapshot)
    assert not on_hardware.simulated and on_hardware.simulator_rig() is None
    assert on_hardware.config == station
    emulated = parse_snapshot(json.dumps({"kind": "station", "station": settings, "emulate": True,
                                          "time_scale": 20.0, "seed": 7}))
    assert isinstance(emulated, StationFileSnapshot)
    assert emulated.simulated and (emulated.time_scale, emulated.seed) == (20.0, 7)
    assert emulated.simulator_rig() == (settings.get("emulation") or {}).get("rig", {})


def test_text_that_is_not_a_snapshot_is_none():
    """A run journaled before snapshots were kept, or with text of its own: no snapshot, not simulated."""
    for text in ("", None, "[station]\nname = 'x'", "[]", json.dumps({"kind": "bench"})):
        assert parse_snapshot(text) is None
    assert not is_simulated(RunMetadata(), None)


def test_a_run_is_simulated_by_its_metadata_or_its_snapshot():
    rig = parse_snapshot(json.dumps({"kind": "simulated rig", "seed": 1, "rig": {}}))
    real = parse_snapshot(json.dumps({"kind": "station", "station": {}, "emulate": False}))
    assert is_simulated(RunMetadata(), rig) and not is_simulated(RunMetadata(), real)
    assert is_simulated(RunMetadata(simulated_truth=None), real)  # the metadata alone is enough, recorded


def test_no_module_but_the_snapshot_model_decodes_the_journaled_station_text():
    """Parse once, read by attribute: a ``json.loads`` of ``station_text`` anywhere else would be a
    second reader of the snapshot's keys, free to drift from the model."""
    import ast

    import labcal

    package = Path(labcal.__file__).parent
    decoders = []
    for module in sorted(package.rglob("*.py")):
        if module.name == "snapshot.py" and module.parent.name == "config":
            continue
        for node in ast.walk(ast.parse(module.read_text(encoding="utf-8"))):
            called = node.func if isinstance(node, ast.Call) else None
            decodes = isinstance(called, ast.Attribute) and called.attr == "loads"
            if decodes and "station_text" in ast.unparse(node):
                decoders.append(f"{module.relative_to(package)}:{node.lineno}")
    assert decoders == []


def test_a_journaled_stations_devices_read_by_attribute_none_where_an_older_journal_is_silent():
    """The settings the documents and the run's checks name, as the station file journaled them (a
    trimmed copy of an emulated az-modbus-tcp run's snapshot); a setting it lacks reads None, and
    what it says beyond the named ones is kept as journaled."""
    station = {"pitch": {"driver": "oriental-az", "unit": 1, "tcp": "127.0.0.1:0", "port": None,
                         "in_position_arcsec": 5.0, "speed_dps": 20.0},
               "roll": {"driver": "newport-smc100", "address": 2, "port": "/dev/ttyUSB0"},
               "dmm": {"driver": "keysight-34970a", "tcp": "10.0.0.5:5025", "range_v": 10.0, "nplc": 1.0}}
    snapshot = parse_snapshot(json.dumps({"kind": "station", "station": station, "emulate": False}))
    assert isinstance(snapshot, StationFileSnapshot)
    pitch, roll, dmm = (snapshot.device(role) for role in ("pitch", "roll", "dmm"))
    assert (pitch.driver, pitch.unit, pitch.tcp or pitch.port, pitch.in_position_arcsec) == (
        "oriental-az", 1, "127.0.0.1:0", 5.0)
    assert (roll.address, roll.unit, roll.tcp or roll.port, roll.in_position_arcsec) == (
        2, None, "/dev/ttyUSB0", None)
    assert (dmm.range_v, dmm.nplc) == (10.0, 1.0)
    assert pitch.model_extra == {"speed_dps": 20.0}
    assert snapshot.device("thermometer").driver is None  # a role the station does not have
