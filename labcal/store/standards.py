"""The reference standards' rows in the lab database (`labcal.store.schema.standards`) and the overrides
approvers record for an overdue one (`labcal.store.schema.standard_overrides`): the only SQL of either.

A standard is found by its serial whatever its case (``serial_key``, the serial case-folded, as the
instrument register's `labcal.store.instruments.serial_key`). An override row is appended, never
changed: the lab keeps who allowed what, and why. The rules on what a standard's fields may be, and
whether an override holds (its signature, its approver), are the use cases' (`labcal.app.standards`).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, date, datetime
from typing import TYPE_CHECKING

from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError, SQLAlchemyError

from labcal.errors import LabcalError
from labcal.store.instruments import serial_key
from labcal.store.schema import standard_overrides, standards

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection, Engine

FIELDS = ("kind", "model", "manufacturer", "certificate", "issued_by", "calibrated_on", "due_on", "bench",
          "status", "notes")


@dataclass(frozen=True)
class Standard:
    serial: str  # the register's spelling
    kind: str
    model: str
    manufacturer: str
    certificate: str  # the number of its calibration certificate
    issued_by: str
    calibrated_on: date
    due_on: date
    bench: str  # the station that uses it ('' none)
    status: str
    notes: str
    created_utc: str
    updated_utc: str

    @property
    def identity(self) -> str:
        """Manufacturer, model and serial, as a certificate's traceability names equipment."""
        return " ".join(p for p in (self.manufacturer, self.model, f"serial {self.serial}") if p)

    def to_json(self) -> dict:
        return {"serial": self.serial, "kind": self.kind, "model": self.model,
                "manufacturer": self.manufacturer,
                "certificate": self.certificate, "issued_by": self.issued_by,
                "calibrated_on": self.calibrated_on.isoformat(), "due_on": self.due_on.isoformat(),
                "bench": self.bench, "status": self.status, "notes": self.notes,
                "created_utc": self.created_utc, "updated_utc": self.updated_utc}


@dataclass(frozen=True)
class OverrideRow:
    """An approver's override as stored; whether it holds is `labcal.app.standards`' to say."""

    standard_key: str
    due_on: date  # the standard's due date it was recorded against
    valid_until: date
    reason: str
    approver: str
    role: str
    key_id: str
    signature: str  # hex Ed25519 signature of `labcal.app.standards.override_payload`
    recorded_utc: str


COLUMNS = (standards.c.serial, *(standards.c[name] for name in FIELDS), standards.c.created_utc,
           standards.c.updated_utc)
OVERRIDE_COLUMNS = tuple(standard_overrides.c[name] for name in (
    "standard_key", "due_on", "valid_until", "reason", "approver", "role", "key_id", "signature",
    "recorded_utc"))


def now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _row(row: tuple) -> Standard:
    (serial, kind, model, manufacturer, certificate, issued_by, calibrated, due, bench, status, notes,
     created, updated) = row
    return Standard(serial, kind, model, manufacturer, certificate, issued_by, date.fromisoformat(calibrated),
                    date.fromisoformat(due), bench, status, notes, created, updated)


def _stored(values: dict) -> dict:
    """Dates as ISO text (the column type both SQLite and PostgreSQL keep alike)."""
    return {k: v.isoformat() if isinstance(v, date) else v for k, v in values.items()}


def found_in(conn: Connection, serial: str) -> Standard | None:
    row = conn.execute(select(*COLUMNS).where(standards.c.serial_key == serial_key(serial))).first()
    return None if row is None else _row(tuple(row))


def find(engine: Engine, serial: str) -> Standard | None:
    """The standard registered under ``serial`` in any case, else None."""
    with engine.connect() as conn:
        return found_in(conn, serial)


def insert(engine: Engine, serial: str, values: dict) -> Standard:
    """Register ``serial`` with ``values`` (the `FIELDS` given, kind, certificate and dates among them)."""
    now = now_utc()
    try:
        with engine.begin() as conn:
            held = found_in(conn, serial)
            if held is not None:
                raise LabcalError(f"{serial}: already registered as {held.serial} "
                                  f"(`labcal standard edit {held.serial} …` changes it)")
            conn.execute(standards.insert().values(serial=serial, serial_key=serial_key(serial),
                                                   created_utc=now, updated_utc=now, **_stored(values)))
    except IntegrityError:  # registered meanwhile by someone else
        raise LabcalError(f"{serial}: registered meanwhile by someone else (`labcal standard show "
                          f"{serial}`)") from None
    got = find(engine, serial)
    assert got is not None
    return got


def change(engine: Engine, serial: str, values: dict) -> Standard | None:
    """Set ``values`` (some of `FIELDS`) on the standard ``serial`` (any case); None: not registered."""
    with engine.begin() as conn:
        done = conn.execute(update(standards).where(standards.c.serial_key == serial_key(serial))
                            .values(updated_utc=now_utc(), **_stored(values)))
        if done.rowcount != 1:
            return None
        return found_in(conn, serial)


def listed(engine: Engine, bench: str | None = None) -> list[Standard]:
    """Every standard by serial, or those a bench uses (its name, any case)."""
    query = select(*COLUMNS).order_by(standards.c.serial_key)
    if bench is not None:
        query = query.where(func.lower(standards.c.bench) == bench.casefold())
    with engine.connect() as conn:
        return [_row(tuple(r)) for r in conn.execute(query)]


def named(engine: Engine, serials: list[str], bench: str) -> tuple[list[Standard], list[str]]:
    """The standards ``bench`` uses and those named by ``serials`` (any case), by serial; and the
    serials named that are not registered."""
    keys = {serial_key(s): s for s in serials}
    query = select(*COLUMNS).where(or_(func.lower(standards.c.bench) == bench.casefold(),
                                       standards.c.serial_key.in_(list(keys)))).order_by(standards.c.serial_key)
    with engine.connect() as conn:
        found = [_row(tuple(r)) for r in conn.execute(query)]
    held = {serial_key(s.serial) for s in found}
    return found, [s for k, s in keys.items() if k not in held]


class WriteRefused(LabcalError):
    """The lab database refused the write (a bench's role on the lab's server may not make it); the
    message is the database's first line."""


def add_override(engine: Engine, row: OverrideRow) -> None:
    try:
        with engine.begin() as conn:
            conn.execute(standard_overrides.insert().values(
                standard_key=row.standard_key, due_on=row.due_on.isoformat(),
                valid_until=row.valid_until.isoformat(), reason=row.reason, approver=row.approver,
                role=row.role, key_id=row.key_id, signature=row.signature, recorded_utc=row.recorded_utc))
    except SQLAlchemyError as exc:
        raise WriteRefused(str(getattr(exc, "orig", exc)).strip().splitlines()[0]) from exc


def overrides(engine: Engine, serial: str) -> list[OverrideRow]:
    """Every override recorded for the standard ``serial`` (any case), oldest first."""
    query = (select(*OVERRIDE_COLUMNS).where(standard_overrides.c.standard_key == serial_key(serial))
             .order_by(standard_overrides.c.id))
    with engine.connect() as conn:
        return [OverrideRow(key, date.fromisoformat(due), date.fromisoformat(until), reason, approver, role,
                            kid, signature, recorded)
                for key, due, until, reason, approver, role, kid, signature, recorded in conn.execute(query)]
