"""The lab's instruments: the register (`labcal instrument add|list|show|edit`), when each falls
due (`labcal due`, with a notification per instrument falling due), and the serial a run certifies,
checked before anything moves.

A serial is the instrument's name on every certificate and DCC, and the key of its history. So it
is cleaned once, here, before anything moves: surrounding whitespace is stripped with a note (a
copied serial often brings a trailing space, and no serial is meant to carry one — refusing would
only make the technician retype it), while a control character or a line break inside is refused
(that is not a slip to guess at). A serial that matches a registered one in another case takes the
register's spelling, so ``acc-0042`` cannot start a second history beside ``ACC-0042``.

Once the register holds any instrument, a serial it does not hold is asked about at the terminal,
and refused where nobody is asked (``--yes``, a script) unless the lab file says
``[instruments] allow_adhoc = true``; with an empty register a run takes any serial, as before.

Due dates: next due = the last calibration (the newest certificate that is not a dry run's) + the
instrument's interval; one never calibrated is due now. The suggested interval follows ILAC-G24:2007
("Guidelines for the determination of calibration intervals of measuring instruments"), method 1,
"automatic adjustment or staircase": after each calibration the interval is lengthened when the
instrument was found in tolerance and shortened when it was not. ILAC-G24 leaves the step sizes to
the lab; labcal's are `LENGTHEN` and `SHORTEN` (shortening harder than lengthening: an instrument
found out of tolerance has put every result since its last calibration in doubt, an early
calibration only costs a calibration). "In tolerance" is the certificate's conformity verdict; a
certificate without one (no tolerance given) is not judged, and suggests nothing. The history's drift
flags are not used as a verdict: they test each of the twelve coefficients at 95 %, so a perfectly
stable instrument shows at least one flag in about 1 − 0.95¹² ≈ 46 % of consecutive calibrations, and
the staircase would halve its interval on noise.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import date, timedelta
from typing import TYPE_CHECKING

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.documents.history import certificates_for
from labcal.errors import LabcalError
from labcal.run.notify import Message, lab_notifications
from labcal.store import instruments
from labcal.store.labdb import Unreachable

if TYPE_CHECKING:
    from labcal.app.labdatabase import LabDatabase
    from labcal.store.instruments import Instrument

STATUSES = ("active", "retired", "out-for-repair")
LENGTHEN = 1.25  # ILAC-G24 method 1: the interval after an in-tolerance calibration, × this
SHORTEN = 0.5  # … and after an out-of-tolerance one
DAYS_PER_MONTH = 365.25 / 12  # a month of an interval, on average over the Gregorian 4-year cycle
SERIAL_MAX = 64
_INTERVAL = re.compile(r"^\s*(\d+)\s*([dmy])\s*$", re.IGNORECASE)


def checked_serial(text: str) -> tuple[str, str | None]:
    """The serial as given, with surrounding whitespace stripped, and a note saying so (None: it was
    clean). Refused in one line: nothing left, longer than `SERIAL_MAX`, or a control character or
    line break inside."""
    serial = text.strip()
    if not serial:
        raise LabcalError("{0} is empty; give the instrument's serial as on its label", "serial")
    if not serial.isprintable():
        bad = next(c for c in serial if not c.isprintable())
        raise LabcalError(f"{{0}} {text!r} holds a control character ({bad!r}); give the serial on one "
                          "line, as on the instrument's label", "serial")
    if len(serial) > SERIAL_MAX:
        raise LabcalError(f"{{0}} {serial[:20]!r}…: a serial is at most {SERIAL_MAX} characters", "serial")
    note = (None if serial == text else
            f"serial {text!r}: surrounding whitespace removed, certified as {serial!r}")
    return serial, note


def interval_days(text: str, option: str = "--interval") -> int:
    """Days in an interval written ``365d``, ``12m`` or ``1y`` (a month is `DAYS_PER_MONTH` days, a year
    twelve months, rounded to whole days: ``12m`` and ``1y`` are 365 days)."""
    match = _INTERVAL.match(text)
    if not match or int(match.group(1)) == 0:
        raise LabcalError(f"{option} {text!r}: give a number of days, months or years, e.g. 365d, 12m, 1y")
    n, unit = int(match.group(1)), match.group(2).lower()
    return n if unit == "d" else round(n * DAYS_PER_MONTH * (12 if unit == "y" else 1))


def _status(status: str) -> str:
    if status not in STATUSES:
        raise LabcalError(f"{{0}} {status!r}: one of {', '.join(STATUSES)}", "status")
    return status


def _text(value: str, name: str) -> str:
    value = value.strip()
    if not value.isprintable():
        raise LabcalError(f"--{name} {value!r}: one line of printable text")
    return value


@dataclass(frozen=True)
class InstrumentFields:
    """What `add` and `edit` set; None: not given (add: empty; edit: unchanged)."""

    model: str | None = None
    manufacturer: str | None = None
    customer: str | None = None
    owner: str | None = None
    location: str | None = None
    interval: str | None = None  # 365d, 12m, 1y
    status: str | None = None
    notes: str | None = None

    def values(self) -> dict:
        """The register's columns for the fields given, each checked (one line if not)."""
        found: dict = {}
        for name in ("model", "manufacturer", "customer", "owner", "location", "notes"):
            value = getattr(self, name)
            if value is not None:
                found[name] = _text(value, name)
        if self.interval is not None:
            found["interval_days"] = interval_days(self.interval)
        if self.status is not None:
            found["status"] = _status(self.status)
        return found


def add(lab: LabDatabase, serial: str, fields: InstrumentFields) -> Instrument:
    """Register an instrument (one line if its serial is registered already, in any case)."""
    clean, _ = checked_serial(serial)
    return instruments.insert(lab.engine, clean, fields.values())


def edit(lab: LabDatabase, serial: str, fields: InstrumentFields) -> Instrument:
    values = fields.values()
    if not values:
        raise LabcalError("nothing to change: give {0}, {1}, {2}, {3}, … ", "model", "customer", "interval",
                          "status")
    found = instruments.change(lab.engine, checked_serial(serial)[0], values)
    if found is None:
        raise _unregistered(lab, serial)
    return found


def listed(lab: LabDatabase, search: str | None = None) -> list[Instrument]:
    return instruments.listed(lab.engine, search.strip() if search else None)


def _unregistered(lab: LabDatabase, serial: str) -> LabcalError:
    return LabcalError(f"{serial.strip()!r}: no such instrument in {lab.shown} (`labcal instrument list`; "
                       f"`labcal instrument add {serial.strip()}` registers it)")


def registered(lab: LabDatabase, serial: str) -> Instrument:
    found = instruments.find(lab.engine, checked_serial(serial)[0])
    if found is None:
        raise _unregistered(lab, serial)
    return found


# --- when each instrument is due -------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """One real calibration of the instrument, as its certificate states it."""

    certificate_id: str
    on: date  # the calibration's date (UTC)
    in_tolerance: bool | None  # the certificate's conformity verdict (None: no tolerance was given)

    def to_json(self) -> dict:
        return {"certificate_id": self.certificate_id, "date": self.on.isoformat(),
                "in_tolerance": self.in_tolerance}


def calibrations(serial: str, db: str | None, include_simulated: bool = False) -> list[Calibration]:
    """The instrument's real calibrations, oldest first, each judged in or out of tolerance (see the
    module). Read through the history's reader (`labcal.documents.history.certificates_for`), which
    verifies each certificate and leaves out replaced revisions and, unless ``include_simulated``, dry
    runs (a simulated calibration never makes an instrument current); none is an empty list."""
    try:
        certs = certificates_for(serial, db, include_simulated)
    except LabcalError:  # no certificate, or only dry runs': never calibrated
        return []
    return [Calibration(c.certificate_id, c.calibrated_utc.date(),
                        None if c.conformity is None else c.conformity.passed) for c in certs]


def suggested_interval(interval: int | None, history: list[Calibration]) -> int | None:
    """ILAC-G24 method 1 (staircase) from the current interval: one step for the newest calibration's
    result (`LENGTHEN` in tolerance, `SHORTEN` out); None without an interval or a judged result."""
    if interval is None or not history or history[-1].in_tolerance is None:
        return None
    return max(1, round(interval * (LENGTHEN if history[-1].in_tolerance else SHORTEN)))


@dataclass(frozen=True)
class Card:
    """`labcal instrument show`: the register's row, its last calibration and when it is next due."""

    instrument: Instrument
    history: list[Calibration]
    next_due: date | None  # None: no interval set
    suggested_days: int | None

    @property
    def last(self) -> Calibration | None:
        return self.history[-1] if self.history else None

    def to_json(self) -> dict:
        return {**self.instrument.to_json(),
                "last_calibration": None if self.last is None else self.last.to_json(),
                "next_due": None if self.next_due is None else self.next_due.isoformat(),
                "suggested_interval_days": self.suggested_days,
                "interval_method": "ILAC-G24:2007 method 1 (staircase)",
                "calibrations": [c.to_json() for c in self.history]}


def next_due(interval: int | None, history: list[Calibration], today: date) -> date | None:
    """The last calibration + the interval; never calibrated: today (due now); no interval: None."""
    if interval is None:
        return None
    return today if not history else history[-1].on + timedelta(days=interval)


def card(lab: LabDatabase, serial: str, db: str | None, today: date, include_simulated: bool = False) -> Card:
    found = registered(lab, serial)
    history = calibrations(found.serial, db, include_simulated)
    return Card(found, history, next_due(found.interval_days, history, today),
                suggested_interval(found.interval_days, history))


@dataclass(frozen=True)
class Due:
    """An instrument falling due: overdue (``days_left`` < 0) or due within the window."""

    card: Card
    due: date
    days_left: int

    @property
    def overdue(self) -> bool:
        return self.days_left < 0

    def to_json(self) -> dict:
        last = self.card.last
        return {"serial": self.card.instrument.serial, "customer": self.card.instrument.customer,
                "model": self.card.instrument.model, "location": self.card.instrument.location,
                "interval_days": self.card.instrument.interval_days,
                "last_calibration": None if last is None else last.on.isoformat(),
                "due": self.due.isoformat(), "days_left": self.days_left, "overdue": self.overdue}


def due(lab: LabDatabase, db: str | None, within: str, today: date, include_simulated: bool = False
        ) -> list[Due]:
    """The active instruments with an interval that are overdue or due within ``within`` (``30d``…)
    of ``today``, soonest first; one never calibrated is due today."""
    horizon = interval_days(within, "--within")
    found = []
    for instrument in listed(lab):
        if instrument.status != "active" or instrument.interval_days is None:
            continue
        history = calibrations(instrument.serial, db, include_simulated)
        when = next_due(instrument.interval_days, history, today)
        assert when is not None
        left = (when - today).days
        if left <= horizon:
            suggested = suggested_interval(instrument.interval_days, history)
            found.append(Due(Card(instrument, history, when, suggested), when, left))
    return sorted(found, key=lambda d: (d.due, d.card.instrument.serial))


def recall_text(item: Due) -> tuple[str, str]:
    """A due notification's title and body."""
    i = item.card.instrument
    who = f" ({i.customer})" if i.customer else ""
    state = (f"overdue by {-item.days_left} day(s)" if item.overdue else
             "due today" if item.days_left == 0 else f"due in {item.days_left} day(s)")
    last = item.card.last
    since = "never calibrated" if last is None else f"last calibrated {last.on.isoformat()}"
    where = f"; at {i.location}" if i.location else ""
    return (f"labcal: {i.serial} {state}",
            f"Instrument {i.serial}{who}, {i.model or 'model not registered'}: calibration {state} "
            f"(due {item.due.isoformat()}; {since}; interval {i.interval_days} days{where}).")


def notify_due(items: list[Due], warn: Callable[[str], None]) -> tuple[int, int]:
    """One notification per instrument falling due, through the lab's apprise URLs (the runs' own
    sender, `labcal.run.notify`); (sent, failed). Refused in one line where no URL is configured."""
    with lab_notifications(warn) as notifications:
        if not notifications.urls:
            raise LabcalError("no notification URLs: set notify = [\"URL\", …] in the lab file or "
                              "$LABCAL_NOTIFY (apprise URLs) to send recalls")
        for item in items:
            title, body = recall_text(item)
            notifications.send(Message(f"recall {item.card.instrument.serial}", title, body))
    sent = len(notifications.sent)
    return sent, len(items) - sent


# --- the serial a run certifies --------------------------------------------------------------------


@dataclass(frozen=True)
class RunSerial:
    serial: str  # as the run certifies it
    notes: list[str] = field(default_factory=list)
    unregistered: bool = False  # the register holds instruments, not this one


def serial_for_run(serial: str, db: str | None) -> RunSerial:
    """The serial a run certifies (see the module): cleaned, in the register's spelling where it is
    registered, and whether the register (when it holds any instrument) lacks it."""
    clean, note = checked_serial(serial)
    notes = [note] if note else []
    try:
        lab = open_lab(OpenLab(db, must_exist=False))
    except Unreachable as exc:  # a run goes on without the lab's server; its journal is local
        return RunSerial(clean, [*notes, f"the instrument register was not checked: {exc}"])
    try:
        if instruments.count(lab.engine) == 0:
            return RunSerial(clean, notes)
        found = instruments.find(lab.engine, clean)
    finally:
        lab.close()
    if found is None:
        return RunSerial(clean, notes, unregistered=True)
    if found.serial != clean:
        notes.append(f"serial {clean!r} is registered as {found.serial!r}: certified as {found.serial!r}")
    if found.status != "active":
        notes.append(f"{found.serial} is marked {found.status} in the register")
    return RunSerial(found.serial, notes)
