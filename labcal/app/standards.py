"""The lab's reference standards (`labcal standard add|list|show|edit`), the overrides an approver
records to run on an overdue one (`labcal standard override`), and the check a run makes before
anything moves.

A standard is the DMM or a table whose calibration certificate makes the results traceable (ISO/IEC
17025 §6.5): registered with that certificate's number, issuer, calibration date and due date, and
the bench that uses it. A run uses the standards registered to its bench (the station's name in the
lab database) and those its station file names (``standards = ["SERIAL", …]``). One that is overdue
on the day of the run stops the run before anything moves, unless an approver has recorded an
override for it: the approver's name, registered role and reason, signed with the approver's
registered Ed25519 key (the key `labcal certificate approve` signs with), valid against the due date
it was recorded for (a standard recalibrated and given a new date no longer needs it) and until a
day at most `MAX_OVERRIDE_DAYS` ahead. The signature, not who could write the row, makes an override
an approver's: a row anyone wrote into a SQLite file holds nothing; on PostgreSQL a bench's role
cannot write one at all (`labcal.store.roles`).

The standards a run used and the overrides it ran under are journaled in its metadata: the
certificate states both (`labcal.documents.overrides`).
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from datetime import date, timedelta
from typing import TYPE_CHECKING

from labcal.config.run_metadata import StandardOverride, StandardUsed
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.labdb import Unreachable, empty_in_file

if TYPE_CHECKING:
    from cryptography import exceptions

    from labcal.app import instruments, labdatabase
    from labcal.app.labdatabase import LabDatabase
    from labcal.documents import approval, approvers
    from labcal.store import instruments as store_instruments
    from labcal.store import standards
    from labcal.store.standards import OverrideRow, Standard
else:
    approval = lazy("labcal.documents.approval")  # start-up without scipy, numpy, pydantic, …
    approvers = lazy("labcal.documents.approvers")  # start-up without scipy, numpy, pydantic, …
    exceptions = lazy("cryptography.exceptions")  # start-up without cryptography
    instruments = lazy("labcal.app.instruments")  # start-up without matplotlib, scipy, numpy, …
    labdatabase = lazy("labcal.app.labdatabase")  # start-up without pydantic
    standards = lazy("labcal.store.standards")  # start-up without sqlalchemy
    store_instruments = lazy("labcal.store.instruments")  # start-up without sqlalchemy

KINDS = {"dmm": "DMM", "pitch-table": "pitch table", "roll-table": "roll table",
         "reference-level": "reference level", "other": "reference standard"}  # --kind: as equipment is named
STATUSES = ("active", "retired")
MAX_OVERRIDE_DAYS = 31  # an override bridges the wait for a recalibration; it never replaces one
DEFAULT_OVERRIDE_DAYS = 7


def _date(text: str, option: str) -> date:
    try:
        return date.fromisoformat(text.strip())
    except ValueError:
        raise LabcalError(f"{option} {text!r}: give a date as YYYY-MM-DD") from None


def _text(value: str, option: str) -> str:
    value = value.strip()
    if not value.isprintable():
        raise LabcalError(f"{option} {value!r}: one line of printable text")
    return value


@dataclass(frozen=True)
class StandardFields:
    """What `add` and `edit` set; None: not given (add: kind, certificate and both dates are required)."""

    kind: str | None = None
    model: str | None = None
    manufacturer: str | None = None
    certificate: str | None = None
    issued_by: str | None = None
    calibrated: str | None = None  # YYYY-MM-DD
    due: str | None = None  # YYYY-MM-DD
    bench: str | None = None
    status: str | None = None
    notes: str | None = None

    def values(self) -> dict:
        """The register's columns for the fields given, each checked (one line if not)."""
        found: dict = {}
        if self.kind is not None:
            if self.kind not in KINDS:
                raise LabcalError(f"--kind {self.kind!r}: one of {', '.join(KINDS)}")
            found["kind"] = self.kind
        for name in ("model", "manufacturer", "certificate", "issued_by", "bench", "notes"):
            value = getattr(self, name)
            if value is not None:
                found[name] = _text(value, "--" + name.replace("_", "-"))
        if self.calibrated is not None:
            found["calibrated_on"] = _date(self.calibrated, "--calibrated")
        if self.due is not None:
            found["due_on"] = _date(self.due, "--due")
        if self.status is not None:
            if self.status not in STATUSES:
                raise LabcalError(f"--status {self.status!r}: one of {', '.join(STATUSES)}")
            found["status"] = self.status
        return found


def _dates_in_order(calibrated: date, due: date) -> None:
    if due <= calibrated:
        raise LabcalError(f"--due {due.isoformat()} is not after --calibrated {calibrated.isoformat()}: a "
                          "standard falls due after it was calibrated")


def add(lab: LabDatabase, serial: str, fields: StandardFields) -> Standard:
    """Register a standard (one line if its serial is registered already, or a required field is missing)."""
    clean, _ = instruments.checked_serial(serial)
    values = fields.values()
    missing = [o for o, k in (("--kind", "kind"), ("--certificate", "certificate"),
                              ("--calibrated", "calibrated_on"), ("--due", "due_on")) if not values.get(k)]
    if missing:
        raise LabcalError(f"a standard is registered with its calibration: give {', '.join(missing)}")
    _dates_in_order(values["calibrated_on"], values["due_on"])
    return standards.insert(lab.engine, clean, values)


def registered(lab: LabDatabase, serial: str) -> Standard:
    found = standards.find(lab.engine, instruments.checked_serial(serial)[0])
    if found is None:
        raise LabcalError(f"{serial.strip()!r}: no such standard in {lab.shown} (`labcal standard list`; "
                          f"`labcal standard add {serial.strip()} …` registers it)")
    return found


def edit(lab: LabDatabase, serial: str, fields: StandardFields) -> Standard:
    values = fields.values()
    if not values:
        raise LabcalError("nothing to change: give --certificate, --calibrated, --due, --bench, … ")
    held = registered(lab, serial)
    _dates_in_order(values.get("calibrated_on", held.calibrated_on), values.get("due_on", held.due_on))
    changed = standards.change(lab.engine, held.serial, values)
    assert changed is not None  # found just now; a standard is never deleted
    return changed


def listed(lab: LabDatabase, bench: str | None = None) -> list[Standard]:
    return standards.listed(lab.engine, bench.strip() if bench else None)


# --- overrides -------------------------------------------------------------------------------------


def override_payload(serial_key: str, due_on: date, valid_until: date, reason: str, approver: str, role: str,
                     recorded_utc: str) -> bytes:
    """What an override's signature covers: canonical JSON (sorted keys, no spaces, UTF-8)."""
    return json.dumps({"standard": serial_key, "due_on": due_on.isoformat(),
                       "valid_until": valid_until.isoformat(), "reason": reason, "approver": approver,
                       "role": role, "recorded_utc": recorded_utc},
                      sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode("utf-8")


@dataclass(frozen=True)
class RecordOverride:
    serial: str
    reason: str
    by: str  # the approver's registered name
    role: str  # … and role
    key: str  # their private key (PEM)
    until: str | None = None  # YYYY-MM-DD (default: `DEFAULT_OVERRIDE_DAYS` from today)
    db: str | None = None


def record_override(request: RecordOverride, today: date) -> tuple[Standard, OverrideRow]:
    """An approver's override for the standard ``serial`` (see the module): refused in one line unless
    the key is an active approver's registered under that name and role, the reason is given, and the
    last day is today or later and within `MAX_OVERRIDE_DAYS`."""
    reason = _text(request.reason, "--reason")
    if len(reason) < 3:
        raise LabcalError("--reason: say why the run may use the overdue standard (the certificate "
                          "states it)")
    until = today + timedelta(days=DEFAULT_OVERRIDE_DAYS) if request.until is None else \
        _date(request.until, "--until")
    last = today + timedelta(days=MAX_OVERRIDE_DAYS)
    if not today <= until <= last:
        raise LabcalError(f"--until {until.isoformat()}: an override lasts from today to at most "
                          f"{MAX_OVERRIDE_DAYS} days ahead ({last.isoformat()}); "
                          "have the standard recalibrated")
    key = approval.load_private_key(request.key)
    kid = approval.key_id(key.public_key())
    by, role = request.by.strip(), request.role.strip()
    refused = approvers.problems(kid, by, role, request.db)
    if refused:
        raise LabcalError(f"only a registered approver records an override: {refused[0]}")
    lab = labdatabase.open_lab(labdatabase.OpenLab(request.db, must_exist=True))
    try:
        standard = registered(lab, request.serial)
        recorded = standards.now_utc()
        key_text = store_instruments.serial_key(standard.serial)
        signature = key.sign(override_payload(key_text, standard.due_on, until, reason, by, role, recorded))
        row = standards.OverrideRow(key_text, standard.due_on, until, reason, by, role, kid,
                                    base64.b64encode(signature).decode("ascii"), recorded)
        try:
            standards.add_override(lab.engine, row)
        except standards.WriteRefused as exc:  # a bench's role on the lab's server may not write one
            raise LabcalError(f"{lab.shown}: the override was not recorded ({exc}); record it as the "
                              "lab database's administrator, not a bench's role") from None
    finally:
        lab.close()
    return standard, row


def override_problem(row: OverrideRow, standard: Standard, today: date, db: str | None) -> str | None:
    """Why ``row`` does not let a run use ``standard`` today (None: it does): another due date than the
    standard's, expired, a signature that does not hold, or a key not an active approver's under the
    name and role the override states."""
    if row.due_on != standard.due_on:
        return (f"recorded against due date {row.due_on.isoformat()}, not the standard's "
                f"{standard.due_on.isoformat()}")
    if row.valid_until < today:
        return f"expired on {row.valid_until.isoformat()}"
    refused = approvers.problems(row.key_id, row.approver, row.role, db)
    if refused:
        return refused[0]
    approver = approvers.by_key(row.key_id, db)
    assert approver is not None  # problems() says so when it is not registered
    try:
        approver.public_key().verify(base64.b64decode(row.signature), override_payload(
            row.standard_key, row.due_on, row.valid_until, row.reason, row.approver, row.role,
            row.recorded_utc))
    except (exceptions.InvalidSignature, ValueError):
        return (f"its signature does not hold for {row.approver}'s key (the row was changed after it was "
                "signed)")
    return None


@dataclass(frozen=True)
class Card:
    """`labcal standard show`: the register's row, whether it is overdue, and its overrides, each with
    whether it holds."""

    standard: Standard
    today: date
    overrides: list[tuple[OverrideRow, str | None]]  # each with why it does not hold today (None: it holds)

    @property
    def overdue(self) -> bool:
        return self.standard.due_on < self.today

    def to_json(self) -> dict:
        return {**self.standard.to_json(), "on": self.today.isoformat(), "overdue": self.overdue,
                "overrides": [{**override_json(row), "holds": problem is None, "problem": problem}
                              for row, problem in self.overrides]}


def override_json(row: OverrideRow) -> dict:
    return {"due_on": row.due_on.isoformat(), "valid_until": row.valid_until.isoformat(),
            "reason": row.reason, "approver": row.approver, "role": row.role, "key_id": row.key_id,
            "recorded_utc": row.recorded_utc}


def card(lab: LabDatabase, serial: str, today: date, db: str | None) -> Card:
    found = registered(lab, serial)
    rows = standards.overrides(lab.engine, found.serial)
    return Card(found, today, [(row, override_problem(row, found, today, db)) for row in rows])


# --- the standards a run uses ----------------------------------------------------------------------


@dataclass(frozen=True)
class RunStandards:
    """What a run journals of its standards: each used, and each override it runs under."""

    used: list[StandardUsed] = field(default_factory=list)
    overrides: list[StandardOverride] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def traceability_entry(s: Standard) -> StandardUsed:
    """A used standard as the certificate's traceability states it (`labcal.config.uncertainty.Traceability`,
    with its serial and calibration date)."""
    return StandardUsed(equipment=KINDS.get(s.kind, s.kind), identity=s.identity, certificate=s.certificate,
                        issued_by=s.issued_by, due=s.due_on, serial=s.serial, calibrated_on=s.calibrated_on)


def standards_for_run(named: list[str], bench: str, db: str | None, today: date) -> RunStandards:
    """The standards a run on ``bench`` uses (registered to it, or ``named`` by its station file), checked
    before anything moves: a named serial the register lacks, and an overdue standard without an override
    that holds (`override_problem`), are refused in one line. A lab server out of reach is a note (a run
    never waits for it), as the instrument register's check is."""
    if not named and empty_in_file(db, "standards"):  # none registered in this lab file: none to check
        return RunStandards()
    try:
        lab = labdatabase.open_lab(labdatabase.OpenLab(db, must_exist=False))
    except Unreachable as exc:
        return RunStandards(notes=[f"the reference standards were not checked: {exc}"])
    try:
        found, unknown = standards.named(lab.engine, named, bench)
        if unknown:
            raise LabcalError(f"the station file names reference standard(s) {', '.join(unknown)}, not in "
                              f"{lab.shown} (nothing moved): register them with `labcal standard add SERIAL "
                              "--kind … --certificate … --calibrated … --due …`")
        used, held, blocked = [], [], []
        asked = {serial.casefold() for serial in named}
        for s in found:
            if s.status != "active" and s.serial.casefold() not in asked:
                continue  # a retired standard still registered to the bench is not in use
            used.append(traceability_entry(s))
            if s.due_on >= today:
                continue
            rows = standards.overrides(lab.engine, s.serial)
            holding = [row for row in reversed(rows) if override_problem(row, s, today, db) is None]
            if holding:
                held.append(StandardOverride(serial=s.serial, **override_json(holding[0])))
                continue
            why = f"; its override {override_problem(rows[-1], s, today, db)}" if rows else ""
            blocked.append(f"{KINDS.get(s.kind, s.kind)} {s.serial} (certificate {s.certificate}) was due "
                           f"{s.due_on.isoformat()}{why}")
    finally:
        lab.close()
    if blocked:
        more = f" (and {len(blocked) - 1} more)" if len(blocked) > 1 else ""
        raise LabcalError(f"reference standard overdue: {blocked[0]}{more}; nothing was moved. Have it "
                          "recalibrated (`labcal standard edit SERIAL --calibrated … --due …`), or an "
                          "approver records an override: `labcal standard override SERIAL --reason TEXT "
                          "--by NAME --role ROLE --key KEYFILE`")
    return RunStandards(used, held)
