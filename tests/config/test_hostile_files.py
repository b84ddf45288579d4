"""Every file parser against hostile files (hypothesis): accepted, or refused in one line.

Deep nesting, numbers beyond a float, subnormal and infinite settings, huge strings, wrong types
and truncation, applied to a valid plan, station, rig, fit JSON, certificate, run.json and
readings CSV (`hostile_files` says how). A parser that raises anything but a one-line
`LabcalError` fails.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from hostile_files import mutate_csv, mutate_json, mutate_toml, one_line_or_accepted
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from labcal.cli import main
from labcal.config.emulation import load_rig_config
from labcal.config.plans import load_plan
from labcal.config.readings_csv import read_readings
from labcal.config.station import load_certificate_settings, load_station
from labcal.documents.certificate import load_calibration, read_certificate
from labcal.store.rundir import open_run

STATIONS = Path(__file__).parent.parent.parent / "stations"
STATIC_LAB = Path(__file__).parent.parent / "data" / "rig_static_lab.toml"
MUTATION = dict(choice=st.integers(0, 100), depth=st.integers(1, 1200), where=st.integers(0, 10**6))
FUZZ = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def files():
    """One finished simulated run's files (plan, readings, fit, certificate, run.json) to start from."""
    folder = Path(tempfile.mkdtemp(prefix="labcal-hostile-"))
    db = folder / "lab.sqlite"
    assert main(["run", "--sim", "--yes", "--plan", "one-mount-16", "--out", str(folder / "run"),
                 "--db", str(db)]) == 0
    yield folder / "run"
    shutil.rmtree(folder, ignore_errors=True)


def _open_run(path: Path):
    _, journal, _ = open_run(path.parent)
    journal.close()


TOML_PARSERS = {
    "plan": (lambda run: (run / "plan.toml").read_text(), lambda p: load_plan(str(p))),
    "station": (lambda run: (STATIONS / "lab-example.toml").read_text(), load_station),
    "station [certificate]": (lambda run: (STATIONS / "lab-example.toml").read_text(),
                              load_certificate_settings),
    "rig": (lambda run: STATIC_LAB.read_text(), load_rig_config),
}
JSON_PARSERS = {
    "fit JSON": ("fit.json", load_calibration),
    "certificate": ("certificate.json", read_certificate),
    "certificate as calibration": ("certificate.json", load_calibration),
    "run.json": ("run.json", _open_run),
}


@pytest.mark.parametrize("kind", list(TOML_PARSERS))
@FUZZ
@given(**MUTATION)
@example(choice=0, depth=500, where=0)  # the reported 500-deep TOML
@example(choice=2, depth=1, where=10)  # a 400-digit integer
def test_toml_files(files, tmp_path, kind, choice, depth, where):
    original, parse = TOML_PARSERS[kind]
    path = tmp_path / "hostile.toml"
    path.write_text(mutate_toml(original(files), choice, depth, where), encoding="utf-8")
    one_line_or_accepted(parse, path)


@pytest.mark.parametrize("kind", list(JSON_PARSERS))
@FUZZ
@given(**MUTATION)
@example(choice=0, depth=1000, where=0)  # the reported 1000-deep JSON
@example(choice=2, depth=1, where=5)  # a 400-digit integer
def test_json_files(files, tmp_path, kind, choice, depth, where):
    name, parse = JSON_PARSERS[kind]
    folder = tmp_path / "case"
    folder.mkdir(exist_ok=True)
    path = folder / name
    path.write_text(mutate_json((files / name).read_text(), choice, depth, where), encoding="utf-8")
    one_line_or_accepted(parse, path)


@FUZZ
@given(**MUTATION)
def test_readings_csv(files, tmp_path, choice, depth, where):
    path = tmp_path / "hostile.csv"
    path.write_text(mutate_csv((files / "readings.csv").read_text(), choice, depth, where), encoding="utf-8")
    one_line_or_accepted(read_readings, path)


def test_the_reported_hostile_settings_are_refused_naming_the_field(files, tmp_path, capsys):
    plan = tmp_path / "tiny.toml"
    text = (files / "plan.toml").read_text()
    plan.write_text(text.replace("replicates", "angle_step_deg = 5e-324\nreplicates", 1))
    station = tmp_path / "inf.toml"
    station.write_text((STATIONS / "az-modbus-rtu.toml").read_text().replace("steps_per_degree = 1000",
                                                                           "steps_per_degree = inf", 1))
    for args, words in ((["plan", "show", str(plan)], "angle_step_deg"),
                        (["station", "check", str(station)], "steps_per_degree")):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert words in err and str(args[2]) in err and len(err.strip().splitlines()) == 1, err
