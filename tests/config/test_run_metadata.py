"""A run's metadata, typed: every journal written before still parses, the text a run stores is the
text it always stored, a misspelt key fails when the run is written, and the published JSON Schema
is the one the model generates (checked on real metadata with the `jsonschema` library, a second
implementation of the checks)."""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path

import jsonschema
import pytest
from pydantic import ValidationError

from labcal.cli import main
from labcal.config.run_metadata import SCHEMA_FILE, RunMetadata, json_schema, parse_run_metadata
from labcal.config.snapshot import is_simulated
from labcal.errors import LabcalError

ROOT = Path(__file__).resolve().parents[2]
V0 = Path(__file__).parent.parent / "data" / "v0"


def stored_rows(db: Path, tmp_path: Path) -> list[str]:
    """The metadata text of every run a journal holds (read from a copy: even a read-only connection
    to a WAL database leaves files beside it)."""
    kept = Path(shutil.copy(db, tmp_path / db.name))
    connection = sqlite3.connect(kept)
    try:
        return [text for (text,) in connection.execute("SELECT metadata FROM runs ORDER BY id")]
    finally:
        connection.close()


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    schema = json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    """A dry run journaled by this labcal (one mount, no report: quick)."""
    base = tmp_path_factory.mktemp("fresh")
    assert main(["run", "--sim", "--yes", "--plan", "one-mount-16", "--no-report", "--ambient-temp", "21.5",
                 "--out", str(base / "run"), "--db", str(base / "lab.sqlite")]) == 0
    return base / "lab.sqlite"


def test_the_published_schema_is_the_one_the_model_generates():
    """Edit the model and not the published file (tools/run_metadata_schema.py writes it): this fails."""
    assert json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8")) == json_schema()


def test_every_run_of_the_version_0_journal_parses_and_stores_back_to_its_text(tmp_path, validator):
    rows = stored_rows(V0 / "labcal.sqlite", tmp_path)
    assert len(rows) == 2  # the complete run and the stopped one
    for text in rows:
        written = json.loads(text)
        meta = parse_run_metadata(text)
        assert meta.simulated_truth == written["simulated_truth"]
        assert is_simulated(meta, None)
        assert meta.stored() == text  # the very text the digest chain and the journal hold
        assert list(validator.iter_errors(written)) == []


@pytest.mark.parametrize("run", ["complete", "stopped"])
def test_a_version_0_run_json_parses_keeping_the_keys_no_longer_written(run, validator):
    """run.json's keys join the journal's in a run's record (`labcal.store.record.run_record`)."""
    written = json.loads((V0 / run / "run.json").read_text(encoding="utf-8"))
    meta = parse_run_metadata(written)
    assert meta.plan == written["plan"] and meta.points_recorded == written["points_recorded"]
    assert meta.settings == written["settings"]
    # keys an older labcal wrote and this one does not (the complete run's times): kept, not lost
    assert meta.model_extra == {k: written[k] for k in ("station_time_s", "wall_time_s") if k in written}
    assert meta.model_dump(exclude_unset=True) == written
    assert list(validator.iter_errors(written)) == []


def test_a_fresh_dry_run_journals_metadata_that_parses_and_keeps_its_text(fresh, tmp_path, validator):
    (text,) = stored_rows(fresh, tmp_path)
    written = json.loads(text)
    meta = parse_run_metadata(text)
    assert list(written)[0] == "station"  # the station first, as it was always written
    assert meta.station == "simulated rig" and meta.ambient == written["ambient"]
    assert written["ambient"]["temperature_c"] == 21.5
    assert meta.estimated_rig_time_s == written["estimated_rig_time_s"] > 0
    assert meta.checklist == written["checklist"]
    assert meta.stored() == text
    assert list(validator.iter_errors(written)) == []


def test_keys_a_newer_labcal_writes_survive_reading():
    text = json.dumps({"station": "bench 2", "overrides": [{"item": "power", "by": "ana"}]})
    meta = parse_run_metadata(text)
    assert meta.model_extra == {"overrides": [{"item": "power", "by": "ana"}]}
    assert meta.stored() == text


def test_a_misspelt_key_fails_when_the_run_is_written():
    creator = RunMetadata(station_file="bench.toml")
    creator.ambeint = {"temperature_c": 21.0}  # type: ignore[attr-defined]  # the misspelling under test
    with pytest.raises(TypeError, match="no field ambeint"):
        creator.with_station("bench 2").journaled()
    with pytest.raises(ValidationError):  # and a mistyped value, as it is set
        RunMetadata().estimated_rig_time_s = "an hour"  # type: ignore[assignment]


def test_the_creator_journals_its_fields_in_the_order_they_were_always_written():
    """The dict the creator built before the model, in its order (the runner put the station first),
    written here by hand: the model's text is its `json.dumps`, byte for byte."""
    before = {"station": "bench 2", "station_file": "bench.toml", "simulated_truth": {"seed": 3},
              "unregistered_serial": "not in the register", "ambient": {"temperature_c": 21.0},
              "estimated_rig_time_s": 512.5, "checklist": {"items": []},
              "device_identity": {"dmm": {"model": "34970A"}}}
    creator = RunMetadata(station_file="bench.toml", simulated_truth={"seed": 3})
    creator.unregistered_serial = "not in the register"
    creator.ambient = {"temperature_c": 21.0}
    creator.estimated_rig_time_s = 512.5
    creator.checklist = {"items": []}
    creator.device_identity = {"dmm": {"model": "34970A"}}
    assert json.dumps(creator.with_station("bench 2").journaled()) == json.dumps(before)


def test_a_wrong_type_read_is_one_line_naming_the_field():
    with pytest.raises(LabcalError, match=r"^run 7's metadata does not read as run metadata "
                                          r"\(estimated_rig_time_s: .*\)$"):
        parse_run_metadata('{"estimated_rig_time_s": "an hour"}', "run 7's metadata")
    with pytest.raises(LabcalError, match="does not read as run metadata"):
        parse_run_metadata("{not json")


def test_wrong_types_fail_the_published_schema_too(validator):
    assert list(validator.iter_errors({"station": "bench 2", "ambient": {"temperature_c": 21.0}})) == []
    assert list(validator.iter_errors({"estimated_rig_time_s": "an hour"})) != []
    assert list(validator.iter_errors({"device_identity": {"dmm": "HP 34401A"}})) != []


def test_the_complete_version_0_run_keeps_its_times_as_extra_fields():
    written = json.loads((V0 / "complete" / "run.json").read_text(encoding="utf-8"))
    assert set(parse_run_metadata(written).model_extra or {}) == {"station_time_s", "wall_time_s"}
