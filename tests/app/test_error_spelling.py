"""A refusal below the front ends names the value to give by its field; each front end spells it as
its user types it: ``--out`` at the command line, ``out=`` from Python, ``out`` on the server."""

from __future__ import annotations

import subprocess
import sys

import pytest

import labcal.api
from labcal.errors import LabcalError


def test_a_field_is_spelled_as_each_front_end_types_it():
    error = LabcalError("give {0} and {1} together", "certfile", "in_use_samples")
    assert str(error) == "give --certfile and --in-use-samples together"
    assert str(error.spelled("python")) == "give certfile= and in_use_samples= together"
    assert str(error.spelled("web")) == "give certfile and in_use_samples together"
    assert error.options == ("certfile", "in_use_samples")


def test_a_message_without_fields_is_left_exactly_as_written_braces_and_all():
    assert str(LabcalError("C:/runs/{0}: no such folder")) == "C:/runs/{0}: no such folder"
    assert str(LabcalError("{x}: exists; give another {0}", "out")) == "{x}: exists; give another --out"


def test_the_python_api_asks_for_the_keyword_argument_not_the_option(tmp_path):
    taken = tmp_path / "taken"
    taken.write_text("not a folder", encoding="utf-8")
    with pytest.raises(LabcalError) as refused:
        labcal.api.run(sim=True, plan="one-mount-16", out=str(taken))
    assert refused.value.options == ("out",)
    assert "out=" in str(refused.value) and "--out" not in str(refused.value)
    assert taken.read_text(encoding="utf-8") == "not a folder"  # nothing written over


def test_the_command_line_asks_for_the_option(tmp_path):
    taken = tmp_path / "taken"
    taken.write_text("not a folder", encoding="utf-8")
    command = ["run", "--sim", "--plan", "one-mount-16", "--yes", "--out", str(taken)]
    done = subprocess.run([sys.executable, "-m", "labcal.cli", *command], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "--out" in done.stderr and "out=" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(("options", "fields"), [
    ({}, ("sim", "station", "emulate")),
    ({"sim": True, "station": "bench.toml"}, ("sim", "station")),
    ({"emulate": True, "sim": True}, ("emulate", "station")),
], ids=["no station", "both", "emulate without a station"])
def test_each_refusal_before_a_run_names_keyword_arguments_from_python(options, fields):
    """The start-up refusals a script meets first say ``sim=``/``station=``, never ``--sim``."""
    with pytest.raises(LabcalError) as refused:
        labcal.api.run(**options)
    assert refused.value.options == fields
    assert "--" not in str(refused.value)
    assert all(f"{field}=" in str(refused.value) for field in fields)


def test_pace_on_a_station_names_the_keyword_arguments_from_python():
    """--pace is the simulated rig's: from Python the refusal says pace=, sim= and time_scale=."""
    with pytest.raises(LabcalError) as refused:
        labcal.api.run(station="bench.toml", pace=2.0)
    assert refused.value.options == ("pace", "sim", "time_scale")
    said = str(refused.value)
    assert "pace= paces the simulated rig (sim=) only" in said and "--" not in said
