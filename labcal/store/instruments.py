"""The instrument register's rows in the lab database (`labcal.store.schema.instruments`): the only
SQL the register has. An instrument is found by its serial whatever its case: ``serial_key`` is the
serial case-folded (`serial_key`), unique, so ``acc-0042`` and ``ACC-0042`` are one row, kept under
the spelling it was registered with.

The rules on what a serial, an interval or a status may be are the use cases' (`labcal.app.instruments`);
this module stores and reads what they hand it. Works on SQLite and PostgreSQL alike (SQLAlchemy
Core on the engine `labcal.store.labdb.lab_engine` gives).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError

from labcal.errors import LabcalError
from labcal.store.schema import instruments

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

FIELDS = ("model", "manufacturer", "customer", "owner", "location", "interval_days", "status", "notes")


def serial_key(serial: str) -> str:
    """What makes two serials the same instrument: the serial case-folded (``ACC-0042``, ``acc-0042``)."""
    return serial.casefold()


@dataclass(frozen=True)
class Instrument:
    serial: str  # the register's spelling
    model: str
    manufacturer: str
    customer: str
    owner: str
    location: str
    interval_days: int | None  # None: no calibration interval set
    status: str
    notes: str
    created_utc: str
    updated_utc: str

    def to_json(self) -> dict:
        return {"serial": self.serial, "model": self.model, "manufacturer": self.manufacturer,
                "customer": self.customer, "owner": self.owner, "location": self.location,
                "interval_days": self.interval_days, "status": self.status, "notes": self.notes,
                "created_utc": self.created_utc, "updated_utc": self.updated_utc}


COLUMNS = (instruments.c.serial, *(instruments.c[name] for name in FIELDS), instruments.c.created_utc,
           instruments.c.updated_utc)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _row(row: tuple) -> Instrument:
    serial, model, manufacturer, customer, owner, location, interval, status, notes, created, updated = row
    return Instrument(serial, model, manufacturer, customer, owner, location, interval, status, notes,
                      created, updated)


def insert(engine: Engine, serial: str, values: dict) -> Instrument:
    """Register ``serial`` with ``values`` (the `FIELDS` given); one line if it is registered already,
    under any case."""
    now = _now()
    try:
        with engine.begin() as conn:
            held = found_in(conn, serial)
            if held is not None:
                raise LabcalError(f"{serial}: already registered as {held.serial} "
                                  f"(`labcal instrument edit {held.serial} …` changes it)")
            conn.execute(instruments.insert().values(serial=serial, serial_key=serial_key(serial),
                                                     created_utc=now, updated_utc=now, **values))
    except IntegrityError:  # registered meanwhile by someone else
        raise LabcalError(f"{serial}: registered meanwhile by someone else (`labcal instrument show "
                          f"{serial}`)") from None
    got = find(engine, serial)
    assert got is not None
    return got


def found_in(conn, serial: str) -> Instrument | None:
    row = conn.execute(select(*COLUMNS).where(instruments.c.serial_key == serial_key(serial))).first()
    return None if row is None else _row(tuple(row))


def find(engine: Engine, serial: str) -> Instrument | None:
    """The instrument registered under ``serial`` in any case, else None."""
    with engine.connect() as conn:
        return found_in(conn, serial)


def change(engine: Engine, serial: str, values: dict) -> Instrument | None:
    """Set ``values`` (some of `FIELDS`) on the instrument ``serial`` (any case); None: not registered."""
    with engine.begin() as conn:
        done = conn.execute(update(instruments).where(instruments.c.serial_key == serial_key(serial))
                            .values(updated_utc=_now(), **values))
        if done.rowcount != 1:
            return None
        return found_in(conn, serial)


def listed(engine: Engine, search: str | None = None) -> list[Instrument]:
    """Every instrument by serial, or those whose serial, customer or model holds ``search`` (any case)."""
    query = select(*COLUMNS).order_by(instruments.c.serial_key)
    if search:
        pattern = "%" + search.casefold().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
        query = query.where(or_(*(func.lower(column).like(pattern, escape="\\") for column in
                                  (instruments.c.serial, instruments.c.customer, instruments.c.model))))
    with engine.connect() as conn:
        return [_row(tuple(r)) for r in conn.execute(query)]


def count(engine: Engine) -> int:
    """How many instruments are registered (none: a run takes any serial, as before the register)."""
    with engine.connect() as conn:
        return int(conn.execute(select(func.count()).select_from(instruments)).scalar_one())
