"""The lab server's audit trail: sign-ins and their failures, lockouts and unlocks, refusals (401,
403), approvals, and every change to the users and the approvers — what happened, to which account,
who did it, when and from where — in the lab database (`labcal.store.schema.audit`).

Tamper-evident: each row's ``digest`` is the SHA-256 of the previous row's digest (``prev``) and of
the row's own fields, so changing, removing or inserting a row breaks the chain from there on
(`verify` names the first row that does not follow). ``prev`` is unique: two writers appending at
once cannot both follow the same row — the second one's insert fails and it appends again after
the first. This shows an edit by someone who cannot recompute every later digest unnoticed; it does
not stop the database's owner from rewriting the whole chain (for that, copy the newest digest
somewhere else now and then).

It also decides the throttling of password guesses per account (`account_state`): the failures
since the account's last success or unlock are counted here, so the count survives a restart of
the server, holds across several servers on one lab database, and an administrator lifts a lockout
with a row of their own (`labcal user unlock`).
"""

from __future__ import annotations

import getpass
import socket
from dataclasses import dataclass
from datetime import UTC, datetime

from labcal.app.labdatabase import LabDatabase
from labcal.errors import LabcalError
from labcal.store import audit as trail
from labcal.store.chain import append_audit, audit_digest

# What a row records (``kind``)
SIGNED_IN = "signed in"
SIGN_IN_FAILED = "sign-in failed"
SIGNATURE_GIVEN = "signature password given"  # the approval form's password re-entry
SIGNATURE_FAILED = "signature password wrong"
LOCKED = "locked out"
UNLOCKED = "unlocked"
REFUSED = "refused"  # a 401 or 403
APPROVED = "approved"
USER_ADDED = "user added"
USER_DISABLED = "user disabled"
PASSWORD_CHANGED = "password changed"
TOKEN_ISSUED = "token issued"
APPROVER_CHANGED = "approver changed"

FAILURES = (SIGN_IN_FAILED, SIGNATURE_FAILED)
RESETS = (SIGNED_IN, SIGNATURE_GIVEN, UNLOCKED, PASSWORD_CHANGED)  # the end of a run of failures

FREE_FAILURES = 3  # consecutive failures an account may have before it must wait
MAX_WAIT_S = 300.0  # the longest wait between two guesses, before the lockout
LOCK_AFTER = 6  # consecutive failures that lock the account until an administrator unlocks it


@dataclass(frozen=True)
class Entry:
    kind: str
    account: str | None = None  # the account concerned (as typed, at a failed sign-in)
    actor: str | None = None  # who did it (None: an anonymous visitor)
    client: str | None = None  # from where: an IP address, or the command line's user and host
    detail: str | None = None


@dataclass(frozen=True)
class Row:
    id: int
    utc: str
    kind: str
    account: str | None
    actor: str | None
    client: str | None
    detail: str | None
    prev: str
    digest: str

    def to_json(self) -> dict:
        return {"id": self.id, "utc": self.utc, "kind": self.kind, "account": self.account,
                "actor": self.actor, "client": self.client, "detail": self.detail, "digest": self.digest}


def digest_of(prev: str, utc: str, entry: Entry) -> str:
    """SHA-256 (hex) of the previous digest and this row's fields, as canonical JSON."""
    return audit_digest(prev, utc, entry.kind, entry.account, entry.actor, entry.client, entry.detail)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def by_command(kind: str, account: str | None, detail: str | None = None) -> Entry:
    """A change made with the command line: by the local account, from this host."""
    try:
        who = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (a container)
        who = "?"
    return Entry(kind, account, f"{who} (command line)", socket.gethostname(), detail)


def record(lab: LabDatabase, entry: Entry) -> str:
    """Append ``entry`` after the newest row; its digest."""
    try:
        with lab.engine.begin() as conn:
            digest = append_audit(conn, _now(), entry.kind, entry.account, entry.actor, entry.client,
                                  entry.detail)
    except RuntimeError:
        raise LabcalError(f"the audit trail is being written by too many at once; {entry.kind} not recorded"
                          ) from None
    assert digest is not None  # a row of no origin is always appended
    return digest


def _row(r) -> Row:
    return Row(*r)


def newest(lab: LabDatabase, limit: int = 200, before: int | None = None) -> list[Row]:
    """The newest ``limit`` rows (before the row id ``before``), newest first."""
    return [_row(r) for r in trail.newest(lab.engine, limit, before)]


def count(lab: LabDatabase) -> int:
    return trail.count(lab.engine)


def verify(lab: LabDatabase) -> int | None:
    """The id of the first row that does not follow from the one before it (None: the chain holds)."""
    prev = ""
    for r in trail.in_order(lab.engine):
        row = _row(r)
        entry = Entry(row.kind, row.account, row.actor, row.client, row.detail)
        if row.prev != prev or row.digest != digest_of(prev, row.utc, entry):
            return row.id
        prev = row.digest
    return None


@dataclass(frozen=True)
class AccountState:
    """An account's run of failed password checks since its last success or unlock."""

    failures: int
    locked: bool
    wait_s: float  # how long before the next guess is heard (0: now)


def wait_after(failures: int) -> float:
    """Seconds an account waits after ``failures`` consecutive failures: none for the first
    `FREE_FAILURES` (people mistype), then doubling from 1 s, at most `MAX_WAIT_S`."""
    return 0.0 if failures < FREE_FAILURES else min(2.0 ** (failures - FREE_FAILURES), MAX_WAIT_S)


def account_state(lab: LabDatabase, account: str, now: datetime | None = None) -> AccountState:
    """``account``'s consecutive failures, whether it is locked and how long its next guess waits."""
    kinds = (*FAILURES, *RESETS, LOCKED)
    # locked until a reset follows the lock: a wrong guess heard after the lock (one that began before
    # it, in parallel) does not lift it
    rows, last_lock_or_reset = trail.account_rows(lab.engine, account, kinds, LOCK_AFTER + 1,
                                                  (*RESETS, LOCKED))
    locked = last_lock_or_reset == LOCKED
    if locked:
        return AccountState(LOCK_AFTER, True, 0.0)
    failures = 0
    for kind, _ in rows:
        if kind in RESETS:
            break
        failures += kind in FAILURES
    if failures == 0:
        return AccountState(0, False, 0.0)
    since = ((now or datetime.now(UTC)) - datetime.fromisoformat(rows[0][1])).total_seconds()
    return AccountState(failures, False, max(0.0, wait_after(failures) - since))
