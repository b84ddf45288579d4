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
"""

from __future__ import annotations

import json
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from labcal.errors import LabcalError

SCHEMA_FILE = "schemas/run-metadata.schema.json"


class RunMetadata(BaseModel):
    """A run's metadata: the journaled fields in the order they are written, then those the journal's
    row and run.json add on reading."""

    model_config = ConfigDict(extra="allow", validate_assignment=True)

    # --- journaled by the run's creator (in this order: the stored text keeps it) ---
    station: str | None = None  # the station's description (a dry run: "simulated rig")
    station_file: str | None = None  # the station file the run started from
    simulated_truth: dict[str, Any] | None = None  # a dry run's true coefficients and misalignments
    package: dict[str, Any] | None = None  # how a simulated package other than three-axis is used
    unregistered_serial: str | None = None  # why a serial the register lacks was certified
    ambient: dict[str, float | str] | None = None  # the conditions the operator entered at the start
    standards: list[dict[str, Any]] | None = None  # the registered reference standards the run used
    standard_overrides: list[dict[str, Any]] | None = None  # an approver's override for an overdue one
    estimated_rig_time_s: float | None = None  # the estimate, beside the actual in run.json
    checklist: dict[str, Any] | None = None  # the pre-run checklist, and who went on past an unmet item
    device_identity: dict[str, dict[str, Any]] | None = None  # role → what the device reported of itself
    # --- the journal's row, stated over the rest on reading ---
    status: str | None = None
    reason: str | None = None
    started_utc: str | None = None
    ended_utc: str | None = None
    settings: dict[str, Any] | None = None  # the sequencer settings the run used
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
        return json.dumps(self.model_dump(exclude_unset=True))

    def journaled(self) -> dict[str, Any]:
        """The document a run's creator journals (`stored` is its text): a key the model does not
        name is refused here (a misspelling: an attribute set that is no field), where reading keeps
        it (a newer journal's)."""
        if self.model_extra:
            raise TypeError(f"run metadata has no field {', '.join(sorted(self.model_extra))}")
        return self.model_dump(exclude_unset=True)

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
    tools/run_metadata_schema.py)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            **RunMetadata.model_json_schema(mode="validation"), "title": "labcal run metadata"}
