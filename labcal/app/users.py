"""The lab server's users: who may read, who may approve; the use cases of `labcal user` and of the
server's sign-in (add, list, disable; authenticate a password, resolve an API token).

Each user has a role — ``viewer`` reads, ``technician`` reads (and runs at the bench, which the
server does not do), ``approver`` reads and approves certificates — a password for the web login and
an API token for programs (``Authorization: Bearer TOKEN``).

Neither is kept in clear (`labcal.store.schema.users`):

- the password under argon2id (argon2-cffi, its default cost: 64 MiB, 3 passes), because people
  choose guessable passwords and a stolen table must make each guess expensive;
- the token as the SHA-256 of 32 random bytes (`secrets.token_urlsafe`). A slow hash buys nothing
  there: a guess must find one of 2²⁵⁶ values, which no speed of hashing makes feasible, and the fast
  hash lets the server find the user by the token's hash with one indexed lookup per request instead
  of trying every user's argon2 hash. The token is shown once, when the user is added.

A user is never deleted: ``disable`` keeps the row with its time (it names who approved what), and a
disabled user's password, token and open web sessions stop working at once.
"""

from __future__ import annotations

import hashlib
import logging
import os
import secrets
import threading
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from functools import cache
from pathlib import Path

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

from labcal.app import audit
from labcal.app.labdatabase import LabDatabase
from labcal.errors import LabcalError
from labcal.store import users as accounts

LOG = logging.getLogger("labcal.server")
ROLES = ("technician", "approver", "viewer")
APPROVER = "approver"
VIEWER = "viewer"
NAME_MAX = 64
# OWASP ASVS 4.0.3 V2.1: a length floor and no common password, no composition rules. 12 characters
# for every account (V2.1.1): a viewer's password opens the lab's readings, an approver's signs them.
MIN_LENGTH = 12
COMMON = Path(__file__).with_name("common_passwords.txt")
TOKEN_DAYS = 365  # an API token older than this no longer works (`labcal user token` issues a new one)


@dataclass(frozen=True)
class User:
    id: int
    name: str
    role: str
    created_utc: str
    disabled_utc: str | None

    @property
    def active(self) -> bool:
        return self.disabled_utc is None

    @property
    def may_approve(self) -> bool:
        return self.active and self.role == APPROVER

    def to_json(self) -> dict:
        return {"name": self.name, "role": self.role, "created_utc": self.created_utc,
                "disabled_utc": self.disabled_utc, "active": self.active}


def _hasher():
    return PasswordHasher()


def token_hash(token: str) -> str:
    """What the database keeps of an API token: its SHA-256, hex."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _valid_name(name: str) -> str:
    name = name.strip()
    if not name or len(name) > NAME_MAX or not name.isprintable():
        raise LabcalError(f"{name!r}: a user name is 1 to {NAME_MAX} printable characters")
    return name


@cache
def _common() -> frozenset[str]:
    lines = COMMON.read_text(encoding="utf-8").splitlines()
    return frozenset(line.casefold() for line in lines if line and not line.startswith("#"))


def password_problem(password: str, role: str, name: str) -> str | None:
    """Why ``password`` may not be ``name``'s (a ``role``), or None."""
    if len(password) < MIN_LENGTH:
        article = "an" if role[0] in "aeiou" else "a"
        return f"a password of {article} {role} has at least {MIN_LENGTH} characters"
    if password.casefold() in _common() or password.casefold() == name.strip().casefold():
        return "that password is among the most common ones (or is the name): choose another"
    return None


def _valid_role(role: str) -> str:
    if role not in ROLES:
        raise LabcalError(f"{role!r}: the role is one of {', '.join(ROLES)}")
    return role




@dataclass(frozen=True)
class AddUser:
    name: str
    role: str  # one of ROLES
    password: str  # for the web login (never stored: its argon2id hash is)

    def __post_init__(self) -> None:
        """Refused when made, before any database is opened (or created)."""
        _valid_name(self.name)
        _valid_role(self.role)
        if not self.password:
            raise LabcalError("the password may not be empty")
        problem = password_problem(self.password, self.role, self.name)
        if problem:
            raise LabcalError(f"{problem}; nothing was added")


@dataclass(frozen=True)
class AddedUser:
    user: User
    token: str  # the API token: not kept, shown this once


def add(lab: LabDatabase, request: AddUser) -> AddedUser:
    """Add the user; returns them with their API token, which is not kept and cannot be shown again."""
    name, role, password = _valid_name(request.name), _valid_role(request.role), request.password
    token = secrets.token_urlsafe(32)  # 32 random bytes
    with _HASHING:
        hashed = _hasher().hash(password)
    now = _now()
    row = {"name": name, "role": role, "password_hash": hashed, "token_hash": token_hash(token),
           "created_utc": now, "disabled_utc": None, "token_utc": now}
    try:
        user_id = accounts.insert(lab.engine, row)
    except accounts.NameTaken as taken:
        if taken.meanwhile:  # added meanwhile by someone else
            raise LabcalError(f"{name}: added meanwhile by someone else (`labcal user list`)") from None
        raise LabcalError(f"{name}: already a user (`labcal user list`); a user is never re-added "
                          "(choose another name)") from None
    audit.record(lab, audit.by_command(audit.USER_ADDED, name, f"role {role}"))
    return AddedUser(User(int(user_id), name, role, row["created_utc"], None), token)


def listed(lab: LabDatabase) -> list[User]:
    """Every user, active and disabled, in the order they were added."""
    return [User(*r) for r in accounts.every(lab.engine)]


def named(lab: LabDatabase, name: str) -> User | None:
    row = accounts.named(lab.engine, name)
    return None if row is None else User(*row)


def disable(lab: LabDatabase, name: str) -> User:
    """Disable ``name``: their password, token and sessions stop working; the row stays."""
    when = _now()
    done, disabled, known = accounts.disable(lab.engine, name, when)
    if not done:
        if disabled is not None:
            raise LabcalError(f"{name}: already disabled on {disabled}")
        raise LabcalError(f"{name}: no such user; users: {', '.join(known) if known else 'none'}")
    audit.record(lab, audit.by_command(audit.USER_DISABLED, name))
    found = named(lab, name)
    assert found is not None
    return found


def by_token(lab: LabDatabase, token: str, days: float = TOKEN_DAYS) -> User | None:
    """The active user whose API token this is, if it was issued less than ``days`` ago; else None."""
    if not token:
        return None
    row = accounts.with_token(lab.engine, token_hash(token))
    if row is None:
        return None
    user = User(*row[0])
    issued = datetime.fromisoformat(row[1] or user.created_utc)
    if datetime.now(UTC) - issued > timedelta(days=days):
        return None
    return user if user.active else None


def _existing(lab: LabDatabase, name: str) -> User:
    found = named(lab, name)
    if found is None:
        raise LabcalError(f"{name}: no such user (`labcal user list`)")
    return found


def change_password(lab: LabDatabase, name: str, password: str) -> User:
    """Give ``name`` a new password (by the command line): the policy holds, the old one stops
    working, and the account's run of failures (and a lockout) ends."""
    user = _existing(lab, name)
    problem = password_problem(password, user.role, name)
    if problem:
        raise LabcalError(f"{problem}; the password is unchanged")
    with _HASHING:
        hashed = _hasher().hash(password)
    accounts.change(lab.engine, name, password_hash=hashed)
    audit.record(lab, audit.by_command(audit.PASSWORD_CHANGED, name))
    return user


def new_token(lab: LabDatabase, name: str) -> AddedUser:
    """Issue ``name`` a new API token (by the command line); the old one stops working at once."""
    user = _existing(lab, name)
    if not user.active:
        raise LabcalError(f"{name}: disabled on {user.disabled_utc}; a disabled user gets no token")
    token = secrets.token_urlsafe(32)
    accounts.change(lab.engine, name, token_hash=token_hash(token), token_utc=_now())
    audit.record(lab, audit.by_command(audit.TOKEN_ISSUED, name, "the previous token no longer works"))
    return AddedUser(user, token)


# A hash of a password nobody has: a name that does not exist costs the same argon2 verification as
# one that does, so the login's timing does not tell which names exist.
_DUMMY: list[str] = []
# argon2id at its default cost holds 64 MiB while it runs: at most this many at once in a process,
# so that a crowd of sign-ins cannot take the server's memory (40 at once took 2.6 GiB) nor every
# worker thread, and half the cores stay free for everyone else (argon2 releases the GIL and takes a
# core while it runs); the others are told to come back (`Busy`) rather than queued.
HASHES_AT_ONCE = max(1, (os.cpu_count() or 2) // 2)
_HASHING = threading.BoundedSemaphore(HASHES_AT_ONCE)


class Busy(LabcalError):
    """Every password-hashing slot is in use: try again in a moment."""


def by_password(lab: LabDatabase, name: str, password: str) -> User | None:
    """The active user ``name`` if ``password`` is theirs, else None; `Busy` when `HASHES_AT_ONCE`
    hashes are already running. No throttling: the server asks `check_password`."""
    hasher = _hasher()
    row = accounts.with_password(lab.engine, name.strip())
    if not _HASHING.acquire(blocking=False):
        raise Busy("the server is checking other passwords; try again in a moment")
    try:
        if not _DUMMY:
            _DUMMY.append(hasher.hash(secrets.token_hex(16)))
        stored = _DUMMY[0] if row is None else row[-1]
        hasher.verify(stored, password)
    except (VerificationError, InvalidHashError):
        return None
    finally:
        _HASHING.release()
    user = None if row is None else User(*row[0])
    return user if user is not None and user.active else None


@dataclass(frozen=True)
class PasswordCheck:
    name: str
    password: str
    client: str | None  # where the attempt comes from (for the audit trail)
    signature: bool = False  # the password given again to sign an approval (not a sign-in)


@dataclass(frozen=True)
class Checked:
    user: User | None  # None: refused
    locked: bool = False  # refused unheard: the account is locked (`labcal user unlock`)
    wait_s: float = 0.0  # the account must wait this long before its next guess
    heard: bool = False  # the password was checked (and was wrong, when there is no user)


def check_password(lab: LabDatabase, request: PasswordCheck) -> Checked:
    """A password checked for a sign-in or a signature, throttled per account: after
    `audit.FREE_FAILURES` consecutive failures each guess must wait (doubling), after
    `audit.LOCK_AFTER` the account is locked until an administrator unlocks it. A refused guess is
    not hashed at all. Every check is in the audit trail; failures are also logged."""
    account = request.name.strip()
    state = audit.account_state(lab, account)
    if state.locked:
        return Checked(None, locked=True)
    if state.wait_s > 0:
        return Checked(None, wait_s=state.wait_s)
    user = by_password(lab, account, request.password)
    what = "signature" if request.signature else "sign-in"
    if user is not None:
        audit.record(lab, audit.Entry(audit.SIGNATURE_GIVEN if request.signature else audit.SIGNED_IN,
                                      account, account, request.client))
        return Checked(user, heard=True)
    failures = state.failures + 1
    kind = audit.SIGNATURE_FAILED if request.signature else audit.SIGN_IN_FAILED
    audit.record(lab, audit.Entry(kind, account, None, request.client, f"failure {failures} in a row"))
    LOG.warning("%s of %r from %s failed (%d in a row)", what, account, request.client, failures)
    if failures >= audit.LOCK_AFTER:
        audit.record(lab, audit.Entry(audit.LOCKED, account, None, request.client,
                                      f"{failures} failed password checks in a row"))
        LOG.warning("%r locked out after %d failed password checks in a row", account, failures)
        return Checked(None, locked=True, heard=True)
    return Checked(None, wait_s=audit.wait_after(failures), heard=True)


def unlock(lab: LabDatabase, name: str) -> audit.AccountState:
    """Lift ``name``'s lockout (and forget their run of failures), by the command line; their state
    before."""
    _existing(lab, name)
    before = audit.account_state(lab, name)
    audit.record(lab, audit.by_command(audit.UNLOCKED, name, "was locked" if before.locked
                                       else f"after {before.failures} failures in a row"))
    return before
