"""The administrative contents of a certificate (ISO/IEC 17025 §7.8.2.1) that a run alone does not
hold: the laboratory from the lab file, the customer and the item with its receipt date, the
equipment used with its identities, and the reference standards behind it (the station file's
``[[traceability]]`` entries).

Device identities: a run journals what each device reported in its metadata (``device_identity``,
role → the fields the bench read: maker, model, serial, firmware where the device reports them), and
a resume journals them again as a ``device_identity`` event (the devices may have been swapped while
the run was paused): the latest wins. Where nothing was read, the certificate names the device by
its station-file settings and says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import date

from labcal.config.lab import load_lab_config
from labcal.config.run_metadata import Ambient, DeviceIdentity, RunMetadata
from labcal.config.snapshot import StationFileSnapshot
from labcal.config.station import CertificateSection
from labcal.documents.certificate import Administration, Equipment, Item, LaboratoryRecord, TraceabilityRecord
from labcal.store.record import RunRecord

NOT_READ = "not read from the device"


@dataclass(frozen=True)
class ItemGiven:
    """What the command line says of the customer and the item (each may also be in the run's
    metadata; the run's value wins when the command line is silent)."""

    customer: str | None = None
    manufacturer: str | None = None
    model: str | None = None
    received: date | None = None


def journaled_identities(record: RunRecord) -> dict[str, DeviceIdentity]:
    """Role → the identity the run journaled last (at the start, then at each resume's
    ``device_identity`` event, which journals the same documents)."""
    found = dict(record.meta.device_identity or {})
    for event in record.events:
        if event.kind == "device_identity":
            found.update({role: DeviceIdentity.model_validate(said) for role, said in event.values.items()})
    return found


def _identified(role: str, description: str, said: DeviceIdentity | None) -> Equipment:
    if said is None:
        return Equipment(role=role, description=description, identity=NOT_READ)
    maker, model = said.maker or None, said.model
    if maker and model.startswith(maker):
        model = model[len(maker):].strip()
    if said.stage:
        model += f" with stage {said.stage}"
    return Equipment(role=role, description=description, identity=said.identity or NOT_READ,
                     maker=maker, model=model or None, serial=said.serial or None,
                     firmware=said.firmware or None)


def _equipment(record: RunRecord) -> list[Equipment]:
    identities = journaled_identities(record)
    if not isinstance(record.station, StationFileSnapshot):
        return [Equipment(role="calibration device and DMM", description="simulated rig (a dry run)",
                          identity=None)]
    found = []
    for role in ("pitch", "roll", "dmm"):
        device = record.station.device(role)
        where = device.tcp or device.port
        address = next((f"{k} {n}" for k, n in (("unit", device.unit), ("address", device.address))
                        if n is not None), "")
        settings = f", range {device.range_v:g} V, {device.nplc:g} PLC" if role == "dmm" else ""
        description = f"{device.driver or '?'} {address} on {where}{settings}"
        found.append(_identified("DMM" if role == "dmm" else f"{role} table", description,
                                 identities.get(role)))
    return found


def _ambient(recorded: Ambient | None) -> str | None:
    """The run's ambient conditions in words (`labcal run --ambient-temp --humidity` journals them)."""
    if recorded is None:
        return None
    t, rh = recorded.temperature_c, recorded.humidity_pct
    if t is None and rh is None:
        return None
    text = (f"air temperature {'not recorded' if t is None else f'{t:g} °C'}, relative humidity "
            f"{'not recorded' if rh is None else f'{rh:g} %'}")
    return text + (f" ({recorded.source})" if recorded.source else "")


def _registered_standards(meta: RunMetadata) -> list[TraceabilityRecord]:
    """The lab's registered reference standards the run used, as it journaled them
    (`labcal.app.standards.traceability_entry`)."""
    return [TraceabilityRecord(**s.model_dump(include=set(TraceabilityRecord.model_fields)))
            for s in meta.standards or []]


def administration(record: RunRecord, section: CertificateSection, given: ItemGiven, serial: str
                   ) -> Administration:
    meta = record.meta
    lab = load_lab_config().laboratory
    received = given.received or meta.received
    ambient = _ambient(meta.ambient) or (
        "not recorded; the instrument's own temperature is under Environment"
        if record.readings.temp_c is not None else "not recorded")
    return Administration(
        laboratory=LaboratoryRecord(name=lab.name, address=lab.address,
                                    accreditation_id=lab.accreditation_id, country_code=lab.country_code),
        customer=given.customer or meta.customer,
        item=Item(manufacturer=given.manufacturer or meta.manufacturer or "",
                  model=given.model or meta.model or "", serial=serial,
                  received=date.fromisoformat(received) if isinstance(received, str) else received),
        equipment=_equipment(record),
        traceability=[*(TraceabilityRecord(**t.model_dump()) for t in section.traceability),
                      *_registered_standards(meta)],
        ambient=str(ambient))
