"""What a run records about itself (its metadata), typed: built by its creator, parsed once where the
run is read, read by attribute.

The journal keeps, as JSON in the run's row, what the run's creator knew before the first move: the
station's description and file, a dry run's true coefficients, the package's use, the serial's note,
the ambient conditions, the estimate, the checklist and the devices' identities. Reading the run, the
row's own columns (dates, status, serial, operator, sequencer settings) and run.json's keys join them
(`labcal.store.record.run_record`); one model holds them all, each unset field None.

Journals written by an older labcal hold keys no longer written (``station_time_s``,
``wall_time_s``) and a newer one may hold keys this labcal does not know: they are kept as extra
fields (``extra="allow"``), so that every journal still parses and nothing it holds is lost. A key
the creator misspells fails at write time: the run is started with `RunMetadata.journaled`, which
refuses a key the model does not name.

The stored text is unchanged for every key written before the model: `stored` dumps only the fields
set, in the order the creator always wrote them (the station first), so that a run's manifest —
whose digest begins the run's chain — is the same text it always was.

Each value the creator journals is a model of its own (below), strict where labcal is the only
writer (an unknown key or a wrong type fails at write time), open where a device or an older journal
may say more (a device's identity). The sequencer's settings and a dry run's simulated truth are the
certificate's own sections (`labcal.documents.certificate`), the same models, so that a run's record
and its certificate read them by one rule. Every model dumps its fields in the order the creator
always wrote them, and leaves out a field the document did not carry, so that the stored text of
every run written before the models is still the text `stored` writes.
"""

from __future__ import annotations

import json
from datetime import date
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    SerializationInfo,
    SerializerFunctionWrapHandler,
    ValidationError,
    model_serializer,
)

from labcal.errors import LabcalError

SCHEMA_FILE = "schemas/run-metadata.schema.json"


# --- the certificate's records of the run (its station section) -------------------------------
class Strict(BaseModel):
    """A record labcal alone writes (a certificate's section, a value of a run's metadata): no unknown
    field, immutable, no NaN or infinity (JSON has none)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Recorded(Strict):
    """A record as its producer wrote it: an optional field the document does not carry (it was
    written before the field existed, or its producer had nothing to say) is left out when written
    again, so its bytes do not change."""

    @model_serializer(mode="wrap")
    def _as_recorded(self, handler: SerializerFunctionWrapHandler, info: SerializationInfo) -> Any:
        data = handler(self)
        fields = type(self).model_fields
        return {k: v for k, v in data.items()
                if k not in fields or fields[k].is_required() or k in self.model_fields_set}


# --- how the sequencer ran (station.sequencer_settings) ----------------------------------------------
class SettleRecord(Recorded):
    """`labcal.config.settings.SettleSettings` as the run's journal kept it (validated there)."""

    tau_s: float
    noise_v: float
    sensitivity_v_per_g: float
    samples: int
    k_sigma: float
    max_dwell_s: float
    fixed_dwell_s: float | None
    mode: str | None = None  # "detect" or "model" (absent: issued before model settling)
    pool: str | None = None  # whose step records model settling starts with (absent: before pools)
    instrument_type: str | None = None
    prior: str | None = None  # whose other instruments' records a new one's pool starts from
    prior_records: int | None = None
    leftover: float | None = None  # the transient a reading may keep, in σ/√N (absent: σ/√N)
    off_axis_arcsec: float | None = None  # gravity off the tables' axes the dead time allows for (absent: 0)


class SequencerRecord(Recorded):
    """`labcal.config.settings.SequencerSettings` as the run's journal kept it."""

    settle: SettleRecord
    order: str
    seed: int
    move_timeout_s: float
    position_tolerance_deg: float
    check_mount: bool
    on_failure: str
    speed_dps: float
    accel_dps2: float
    thermal_gate: dict[str, float] | None = None  # absent: no gate (or issued before it existed)


class Endpoint(Strict):
    """Where an emulator listened (`sim.emulation.Emulation.endpoints`)."""

    devices: list[str]
    protocol: str
    address: str


class SimulatedTruth(Recorded):
    """The simulated instrument and calibration device a dry run (or an emulated one) measured: the
    truth its results can be compared with."""

    coefficients: list[list[float]]
    misalignment_deg: dict[str, float]
    seed: int
    time_scale: float | None = None  # emulated runs: emulated seconds per wall second
    endpoints: list[Endpoint] | None = None


# --- what a run's creator journals, each value typed ----------------------------------------------
class PackageUse(Strict):
    """How a package other than three-axis is used, for its statement (Tripp & Tcheng §6): roll
    inferred from its own outputs, none (pitch at roll 0), or measured by the table or a sensor."""

    package: str  # two-axis-xy, two-axis-xz or single-axis (`labcal.config.station.InstrumentSettings`)
    roll_in_use: str | None  # inferred, none, table or sensor
    roll_sd_deg: float | None  # σ of the roll measured in use (None: inferred or none)


class Ambient(Recorded):
    """The environmental conditions the operator entered at the start (ISO/IEC 17025 §7.8.2.1 i),
    each left out where not entered."""

    temperature_c: float | None = None
    humidity_pct: float | None = None
    source: str  # where they come from ("entered at the start of the run")


class StandardUsed(Strict):
    """A registered reference standard the run used: the certificate's traceability entry
    (`labcal.config.uncertainty.Traceability`) with the register's serial and calibration date."""

    equipment: str
    identity: str
    certificate: str
    issued_by: str
    due: date
    serial: str
    calibrated_on: date


class StandardOverride(Strict):
    """An approver's signed override the run went on under, for an overdue reference standard."""

    serial: str
    due_on: date
    valid_until: date
    reason: str
    approver: str
    role: str
    key_id: str  # the approver's registered key that signed it
    recorded_utc: str  # when it was recorded, as the lab database keeps it


class ChecklistItem(Strict):
    """One line of the pre-run checklist (`labcal.bench.checklist.Item`)."""

    item: str
    status: Literal["ok", "warning", "fail"]
    message: str  # what was found, and what to do when it is not ok


class Checklist(Recorded):
    """The pre-run checklist as the run went on past it: its items, whether the operator went on
    past an unmet one, and what was said of the instrument's power (every run writes both; a
    checklist that does not say is read as nobody having said)."""

    items: list[ChecklistItem]
    went_on_regardless: bool
    powered_on: str | None = None  # when the instrument was switched on (local ISO time to the minute)
    warmed_up_stated: bool = False  # the operator said it had warmed up

    def overridden(self) -> list[ChecklistItem]:
        """The unmet items the operator went on regardless of (none when the run met its checklist)."""
        return [i for i in self.items if i.status == "fail"] if self.went_on_regardless else []


class DeviceIdentity(Recorded):
    """What a device reported of itself (a `labcal.bench.hardware.Bench`'s ``identities``): its model and
    identity line always, the rest as far as its manual documents one, each left out where it has
    none; anything more a device says is kept, as it said it."""

    model_config = ConfigDict(extra="allow")

    model: str
    identity: str
    maker: str | None = None
    stage: str | None = None  # an SMC100's stage (``ID?``)
    serial: str | None = None
    firmware: str | None = None


class RunMetadata(BaseModel):
    """A run's metadata: the journaled fields in the order they are written, then those the journal's
    row and run.json add on reading."""

    model_config = ConfigDict(extra="allow", validate_assignment=True)

    # --- journaled by the run's creator (in this order: the stored text keeps it) ---
    station: str | None = None  # the station's description (a dry run: "simulated rig")
    station_file: str | None = None  # the station file the run started from
    simulated_truth: SimulatedTruth | None = None  # a dry run's true coefficients and misalignments
    package: PackageUse | None = None  # how a package other than three-axis is used
    unregistered_serial: str | None = None  # why a serial the register lacks was certified
    ambient: Ambient | None = None  # the conditions the operator entered at the start
    standards: list[StandardUsed] | None = None  # the registered reference standards the run used
    standard_overrides: list[StandardOverride] | None = None  # an approver's override for an overdue one
    estimated_rig_time_s: float | None = None  # the estimate, beside the actual in run.json
    checklist: Checklist | None = None  # the pre-run checklist, and who went on past an unmet item
    device_identity: dict[str, DeviceIdentity] | None = None  # role → what the device reported of itself
    # --- the journal's row, stated over the rest on reading ---
    status: str | None = None
    reason: str | None = None
    started_utc: str | None = None
    ended_utc: str | None = None
    settings: SequencerRecord | None = None  # the sequencer settings the run used
    instrument_serial: str | None = None
    operator: str | None = None
    device_id: str | None = None  # the calibration device's id, where the run's writer recorded one
    # --- run.json's (`labcal.store.exports`) ---
    labcal_version: str | None = None
    journal: str | None = None
    run_uuid: str | None = None
    run_id: int | None = None
    plan: str | None = None
    plan_sha256: str | None = None
    points_recorded: int | None = None
    rig_time_s: float | None = None
    # --- administration, where a run's writer recorded it (the command line's values win) ---
    customer: str | None = None
    manufacturer: str | None = None
    model: str | None = None
    received: str | None = None
    instrument_description: str | None = None

    def stored(self) -> str:
        """The JSON the journal keeps: only the fields set, extras last, as `json.dumps` wrote the dict
        before the model."""
        return json.dumps(self.model_dump(mode="json", exclude_unset=True))

    def journaled(self) -> dict[str, Any]:
        """The document a run's creator journals (`stored` is its text): a key the model does not
        name is refused here (a misspelling: an attribute set that is no field), where reading keeps
        it (a newer journal's)."""
        if self.model_extra:
            raise TypeError(f"run metadata has no field {', '.join(sorted(self.model_extra))}")
        return self.model_dump(mode="json", exclude_unset=True)

    def with_station(self, description: str) -> RunMetadata:
        """This metadata with the station's description first, as the journal stores it."""
        return RunMetadata.model_validate({"station": description, **self.model_dump(exclude_unset=True)})


def parse_run_metadata(data: str | dict | None, where: str = "the run's metadata") -> RunMetadata:
    """A run's metadata from the journal's JSON text or an already decoded document (None or empty:
    nothing recorded); a value of the wrong type is one LabcalError line naming ``where``."""
    try:
        found = json.loads(data) if isinstance(data, str) else (data or {})
        return RunMetadata.model_validate(found)
    except (ValueError, ValidationError) as exc:
        first = exc.errors()[0] if isinstance(exc, ValidationError) else None
        said = f"{'.'.join(map(str, first['loc']))}: {first['msg']}" if first else str(exc)
        raise LabcalError(f"{where} does not read as run metadata ({said})") from None


def listed_metadata(text: str | None) -> RunMetadata:
    """A run's metadata as a list of the lab's runs reads it: one that no longer reads (not JSON, a
    value of the wrong type) is read as nothing recorded, so that the list still shows every run."""
    try:
        return parse_run_metadata(text)
    except LabcalError:
        return RunMetadata()


def json_schema() -> dict[str, Any]:
    """The published JSON Schema of a run's metadata (`SCHEMA_FILE`, written by
    tools/schemas.py)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            **RunMetadata.model_json_schema(mode="validation"), "title": "labcal run metadata"}
