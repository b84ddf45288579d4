"""A run's metadata, typed: every journal written before still parses, the text a run stores is the
text it always stored, a misspelt key fails when the run is written, and the published JSON Schema
is the one the model generates (checked on real metadata with the `jsonschema` library, a second
implementation of the checks)."""

from __future__ import annotations

import json
import shutil
import sqlite3
from datetime import date
from pathlib import Path

import jsonschema
import pytest
from pydantic import ValidationError

from labcal.cli import main
from labcal.config.run_metadata import (
    SCHEMA_FILE,
    Ambient,
    Checklist,
    ChecklistItem,
    DeviceIdentity,
    PackageUse,
    RunMetadata,
    SimulatedTruth,
    StandardOverride,
    StandardUsed,
    json_schema,
    parse_run_metadata,
)
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
    """Edit the model and not the published file (tools/schemas.py writes it): this fails."""
    assert json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8")) == json_schema()


def test_every_run_of_the_version_0_journal_parses_and_stores_back_to_its_text(tmp_path, validator):
    rows = stored_rows(V0 / "labcal.sqlite", tmp_path)
    assert len(rows) == 2  # the complete run and the stopped one
    for text in rows:
        written = json.loads(text)
        meta = parse_run_metadata(text)
        truth = meta.simulated_truth
        assert truth is not None and truth.seed == written["simulated_truth"]["seed"]
        assert truth.coefficients == written["simulated_truth"]["coefficients"]
        assert is_simulated(meta, None)
        assert meta.stored() == text  # the very text the digest chain and the journal hold
        assert list(validator.iter_errors(written)) == []


@pytest.mark.parametrize("run", ["complete", "stopped"])
def test_a_version_0_run_json_parses_keeping_the_keys_no_longer_written(run, validator):
    """run.json's keys join the journal's in a run's record (`labcal.store.record.run_record`)."""
    written = json.loads((V0 / run / "run.json").read_text(encoding="utf-8"))
    meta = parse_run_metadata(written)
    assert meta.plan == written["plan"] and meta.points_recorded == written["points_recorded"]
    assert meta.settings is not None
    assert meta.settings.settle.samples == written["settings"]["settle"]["samples"]
    assert meta.settings.model_dump(mode="json") == written["settings"]  # no field the run lacked is added
    # keys an older labcal wrote and this one does not (the complete run's times): kept, not lost
    assert meta.model_extra == {k: written[k] for k in ("station_time_s", "wall_time_s") if k in written}
    assert meta.model_dump(mode="json", exclude_unset=True) == written
    assert list(validator.iter_errors(written)) == []


def test_a_fresh_dry_run_journals_metadata_that_parses_and_keeps_its_text(fresh, tmp_path, validator):
    (text,) = stored_rows(fresh, tmp_path)
    written = json.loads(text)
    meta = parse_run_metadata(text)
    assert list(written)[0] == "station"  # the station first, as it was always written
    assert meta.station == "simulated rig" and meta.ambient is not None
    assert meta.ambient.temperature_c == written["ambient"]["temperature_c"] == 21.5
    assert meta.ambient.humidity_pct is None and "humidity_pct" not in written["ambient"]  # not entered
    assert meta.estimated_rig_time_s == written["estimated_rig_time_s"] > 0
    assert meta.checklist is not None and len(meta.checklist.items) == len(written["checklist"]["items"]) > 0
    assert meta.checklist.went_on_regardless is written["checklist"]["went_on_regardless"] is False
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
    """The dict the creator built before the models, in its order (the runner put the station first;
    each value as its producer wrote it, nested keys in its order), written here by hand: the
    models' text is its `json.dumps`, byte for byte, whatever order the creator sets them in."""
    truth = {"coefficients": [[0.01, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0], [0.0, 0.0, 5.0]],
             "misalignment_deg": {"a": 0.01, "b": -0.005}, "seed": 3}
    smc = {"model": "Newport SMC100", "identity": "SMC100 unit 1 on /dev/ttyUSB0", "maker": "Newport",
           "stage": "URS100BCC", "firmware": "SMC_CC - v3.0"}
    idn = {"model": "Keysight Technologies 34970A", "identity": "Keysight Technologies,34970A,MY1,13-2-2",
           "maker": "Keysight Technologies", "serial": "MY1", "firmware": "13-2-2"}
    before = {
        "station": "bench 2", "station_file": "bench.toml", "simulated_truth": truth,
        "package": {"package": "two-axis-xz", "roll_in_use": "table", "roll_sd_deg": 0.002},
        "unregistered_serial": "not in the register",
        "ambient": {"temperature_c": 21.0, "source": "entered at the start of the run"},
        "standards": [{"equipment": "DMM", "identity": "Keysight 34970A serial MY1", "certificate": "C-1",
                       "issued_by": "Volt Lab", "due": "2026-12-01", "serial": "MY1",
                       "calibrated_on": "2025-12-01"}],
        "standard_overrides": [{"serial": "MY1", "due_on": "2026-12-01", "valid_until": "2026-12-05",
                                "reason": "booked", "approver": "Ann Lee", "role": "Technical manager",
                                "key_id": "ab12", "recorded_utc": "2026-12-02T08:00:00+00:00"}],
        "estimated_rig_time_s": 512.5,
        "checklist": {"items": [{"item": "warm-up", "status": "fail", "message": "on for 5 of 30 min"}],
                      "went_on_regardless": True, "powered_on": "2026-12-02T07:55+00:00",
                      "warmed_up_stated": False},
        "device_identity": {"pitch": smc, "dmm": idn}}
    creator = RunMetadata(station_file="bench.toml", simulated_truth=SimulatedTruth(**truth))
    creator.checklist = Checklist(items=[ChecklistItem(item="warm-up", status="fail",
                                                       message="on for 5 of 30 min")],
                                  went_on_regardless=True, powered_on="2026-12-02T07:55+00:00",
                                  warmed_up_stated=False)
    creator.unregistered_serial = "not in the register"
    creator.ambient = Ambient(temperature_c=21.0, source="entered at the start of the run")
    creator.package = PackageUse(package="two-axis-xz", roll_in_use="table", roll_sd_deg=0.002)
    creator.standard_overrides = [StandardOverride(
        serial="MY1", due_on=date(2026, 12, 1), valid_until=date(2026, 12, 5), reason="booked",
        approver="Ann Lee", role="Technical manager", key_id="ab12",
        recorded_utc="2026-12-02T08:00:00+00:00")]
    creator.standards = [StandardUsed(
        equipment="DMM", identity="Keysight 34970A serial MY1", certificate="C-1", issued_by="Volt Lab",
        due=date(2026, 12, 1), serial="MY1", calibrated_on=date(2025, 12, 1))]
    creator.estimated_rig_time_s = 512.5
    creator.device_identity = {"pitch": DeviceIdentity(**smc), "dmm": DeviceIdentity(**idn)}
    assert json.dumps(creator.with_station("bench 2").journaled()) == json.dumps(before)
    assert creator.with_station("bench 2").stored() == json.dumps(before)


def test_a_value_labcal_alone_writes_is_refused_with_a_key_it_does_not_know():
    """Strict where labcal is the only writer: a misspelt key in the checklist fails as it is written;
    a device's identity keeps whatever more the device said."""
    with pytest.raises(ValidationError, match="went_on_regardles"):
        Checklist.model_validate({"items": [], "went_on_regardles": True, "powered_on": None,
                                  "warmed_up_stated": False})
    said = DeviceIdentity.model_validate({"model": "HP 34401A", "identity": "HP,34401A,0,1", "options": 2})
    assert said.model_dump(mode="json") == {"model": "HP 34401A", "identity": "HP,34401A,0,1", "options": 2}


ROWS_BEFORE_THE_MODELS = Path(__file__).parent.parent / "data" / "run_metadata" / "rows-08d208e.json"


@pytest.mark.parametrize("run", ["dry-run", "dry-run-two-axis-xy-ambient", "dry-run-standards-override",
                                 "emulated-az-modbus-tcp"])
def test_a_row_journaled_before_the_nested_models_parses_and_stores_back_to_its_bytes(run, validator):
    """Rows of the runs table written by `labcal run` (--sim, --sim with a two-axis package and the
    ambient entered, --sim under a reference standard's override, --station az-modbus-tcp --emulate)
    before the metadata's values were typed (commit 08d208e): the same text, byte for byte (the
    manifest's digest begins the run's chain), and the published schema takes it."""
    [row] = [r for r in json.loads(ROWS_BEFORE_THE_MODELS.read_text(encoding="utf-8")) if r["run"] == run]
    meta = parse_run_metadata(row["metadata"])
    assert meta.stored() == row["metadata"]
    assert meta.model_extra == {}  # every key a model's field
    written = json.loads(row["metadata"])
    assert list(validator.iter_errors(written)) == []
    settings = parse_run_metadata({"settings": json.loads(row["settings"])}).settings
    assert settings is not None and settings.model_dump(mode="json") == json.loads(row["settings"])


def test_the_rows_before_the_models_read_by_attribute_as_they_were_written():
    rows = {r["run"]: json.loads(r["metadata"]) for r in json.loads(ROWS_BEFORE_THE_MODELS.read_text())}
    emulated = parse_run_metadata(rows["emulated-az-modbus-tcp"])
    assert emulated.device_identity is not None and emulated.device_identity["dmm"].serial == "MY00000001"
    assert emulated.device_identity["pitch"].serial is None  # an AZ drive states none
    assert emulated.simulated_truth is not None and emulated.simulated_truth.time_scale == 100.0
    assert [e.protocol for e in emulated.simulated_truth.endpoints or []] == [
        "Modbus TCP", "Keysight 34970A SCPI"]
    standards = parse_run_metadata(rows["dry-run-standards-override"])
    [used], [held] = standards.standards or [], standards.standard_overrides or []
    assert (used.serial, used.due, held.approver) == ("MY-DMM-7", date(2026, 11, 27), "Ann Lee")
    two_axis = parse_run_metadata(rows["dry-run-two-axis-xy-ambient"])
    assert two_axis.package is not None and (two_axis.package.package, two_axis.package.roll_sd_deg) == (
        "two-axis-xy", None)
    ambient = two_axis.ambient
    assert ambient is not None and (ambient.temperature_c, ambient.humidity_pct) == (21.5, 40.0)


def test_a_wrong_type_read_is_one_line_naming_the_field():
    with pytest.raises(LabcalError, match=r"^run 7's metadata does not read as run metadata "
                                          r"\(estimated_rig_time_s: .*\)$"):
        parse_run_metadata('{"estimated_rig_time_s": "an hour"}', "run 7's metadata")
    with pytest.raises(LabcalError, match="does not read as run metadata"):
        parse_run_metadata("{not json")


def test_wrong_types_fail_the_published_schema_too(validator):
    ambient = {"temperature_c": 21.0, "source": "entered at the start of the run"}
    assert list(validator.iter_errors({"station": "bench 2", "ambient": ambient})) == []
    assert list(validator.iter_errors({"ambient": {"temperature_c": 21.0}})) != []  # where it came from
    assert list(validator.iter_errors({"checklist": {"items": [], "went_on_regardless": "no"}})) != []
    assert list(validator.iter_errors({"estimated_rig_time_s": "an hour"})) != []
    assert list(validator.iter_errors({"device_identity": {"dmm": "HP 34401A"}})) != []


def test_the_complete_version_0_run_keeps_its_times_as_extra_fields():
    written = json.loads((V0 / "complete" / "run.json").read_text(encoding="utf-8"))
    assert set(parse_run_metadata(written).model_extra or {}) == {"station_time_s", "wall_time_s"}
