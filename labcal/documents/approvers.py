"""The people who may approve a certificate: name, role and Ed25519 public key, registered in the lab
database by a lab administrator.

A signature alone proves only that someone holding some key signed; the registry says whose key it
is. `certificate approve` signs only with a registered, unrevoked key under the name and role it is
registered with, and `labcal attitude --cert` / `certificate verify` accept an approved certificate
only when its key is registered and unrevoked and the name and role it states are the key's.

A registration is never deleted: revoking one keeps the row (with its time), so the registry still
says who held a key. A key is registered once, ever (a revoked key never comes back, and no key
signs under two names); a name has at most one active key.
"""

from __future__ import annotations

from dataclasses import astuple, dataclass
from datetime import UTC, datetime
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from labcal.analysis.attitude import Calibration, calibration_from_json
from labcal.analysis.packages import PackageCalibration
from labcal.config.files import read_text
from labcal.documents.approval import key_id, load_public_key, signature_holds, signed_certificate
from labcal.documents.certificate import (
    Certificate,
    ServerSignature,
    certificate_from_doc,
    is_certificate,
    parse_json,
)
from labcal.errors import LabcalError
from labcal.store import approvers as register
from labcal.store.journal import db_path
from labcal.store.labquery import Rows, records

COLUMNS = ", ".join(register.COLUMNS)
# The role a lab server's key is registered with: it signs only for an approver signed in to the
# server (`labcal.app.server_approval`), never as a person of its own.
SERVER_ROLE = "lab server"
APPROVER_USER_ROLE = "approver"  # the server users' role that may approve (`labcal.app.users`)


@dataclass(frozen=True)
class Approver:
    name: str
    role: str
    public_key_pem: str
    key_id: str
    added_utc: str
    revoked_utc: str | None

    @property
    def active(self) -> bool:
        return self.revoked_utc is None

    def public_key(self) -> Ed25519PublicKey:
        key = serialization.load_pem_public_key(self.public_key_pem.encode("ascii"))
        assert isinstance(key, Ed25519PublicKey)  # only Ed25519 keys are ever registered
        return key

    def to_json(self) -> dict:
        return {"name": self.name, "role": self.role, "key_id": self.key_id, "added_utc": self.added_utc,
                "revoked_utc": self.revoked_utc, "public_key": self.public_key_pem}


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def add(name: str, role: str, public_key_file: str | Path, db: str | Path | None = None) -> Approver:
    """Register ``name`` (``role``) with the public key in ``public_key_file``."""
    name, role = name.strip(), role.strip()
    if not name or not role:
        raise LabcalError("give the approver's name and {0} (neither may be empty)", "role")
    public = load_public_key(public_key_file)
    pem = public.public_bytes(serialization.Encoding.PEM,
                              serialization.PublicFormat.SubjectPublicKeyInfo).decode("ascii")
    kid = key_id(public)
    path = db_path(db)
    # the lab's registry (every bench's registrations, where the lab is a server) and this
    # bench's own, not yet sent
    for known in _lab(db, key_id=kid) + _lab(db, name=name, active=True) + \
            [Approver(*r) for r in register.same_key_or_active_name(path, kid, name)]:
        if known.key_id == kid:
            state = "registered" if known.active else f"revoked on {known.revoked_utc}"
            raise LabcalError(f"{public_key_file}: this key (id {kid[:12]}…) is already {state} for "
                              f"{known.name}; a key is registered once (make a new pair with `labcal "
                              "certificate keygen`)")
        raise LabcalError(f"{name}: already registered with key {known.key_id[:12]}…; `labcal "
                          f"certificate approvers revoke {name!r}` first to give them a new key")
    approver = Approver(name, role, pem, kid, _now(), None)
    if not register.insert(path, astuple(approver)):  # another administrator registered it meanwhile
        raise LabcalError(f"{name}: registered meanwhile by someone else; `labcal certificate approvers "
                          "list` says by whom")
    return approver


def revoke(name: str, db: str | Path | None = None) -> Approver:
    """Revoke ``name``'s active key: it approves and verifies nothing from now on. The revocation is
    journaled with the registration it revokes (registered at another bench: copied here first), so
    that the lab database receives it as it receives every record of this bench."""
    path = db_path(db)
    active = _lab(db, name=name, active=True) or [Approver(*r) for r in register.active(path, name)]
    if not active:
        names = [a.name for a in _lab(db, active=True)]
        raise LabcalError(f"{name}: no active approver of that name in {path}; active: "
                          f"{', '.join(names) if names else 'none'}")
    a = active[0]
    when = _now()
    register.revoke(path, astuple(a), when)
    return Approver(a.name, a.role, a.public_key_pem, a.key_id, a.added_utc, when)


@dataclass(frozen=True)
class Registry:
    """The registrations as read, and where: the lab database's name, the one line saying the bench
    read its own journal's copy because the lab could not be reached (None: the lab's own), and
    whether there was a database at all (a SQLite lab file not made yet holds none)."""

    approvers: list[Approver]
    shown: str
    stale: str | None
    exists: bool


def listed(db: str | Path | None = None) -> Registry:
    """Every registration, active and revoked, in the order they were made (a missing database:
    none, and nothing is created): the lab's, where the lab database is a server."""
    read = _read(db, {})
    return Registry([Approver(*row) for row in read.rows], read.source.shown, read.source.stale, read.exists)


def _read(db: str | Path | None, where: dict[str, str]) -> Rows:
    """The registry's rows equal to ``where``, in the order they were made, and where they were read
    (a missing database: none, and nothing is created)."""
    return records(db, "approvers", tuple(COLUMNS.split(", ")), where, ("id",), must_exist=False)


def by_key(kid: str, db: str | Path | None = None) -> Approver | None:
    """The registration of the key with id ``kid`` (active or revoked), if any, in the lab's registry."""
    found = _lab(db, key_id=kid)
    return found[0] if found else None


def _lab(db: str | Path | None, key_id: str | None = None, name: str | None = None, active: bool = False
         ) -> list[Approver]:
    """Registrations as the lab database holds them (`labcal.store.labquery`: a bench that cannot
    reach it reads its own journal's), optionally of one key or one name, or only the active ones."""
    where = {k: v for k, v in (("key_id", key_id), ("name", name)) if v is not None}
    found = [Approver(*row) for row in _read(db, where).rows]
    return [a for a in found if a.active] if active else found


def problems(kid: str, name: str, role: str, db: str | Path | None = None,
             server: ServerSignature | None = None, when: str | None = None) -> list[str]:
    """Why a key with id ``kid`` may not sign (or have signed) as ``name`` (``role``): not registered,
    revoked, registered to another name or another role. Empty: it may.

    With ``server`` (the approval says the lab server's key signed for ``name``), the key must be
    registered with the role `SERVER_ROLE` under the name ``server.signer``, and ``name`` must have
    been, at ``when`` (the approval's time, ISO 8601 UTC), an active user of the lab server with the
    role approver and the id ``server.user_id`` (`server_user_problems`). A key registered as the lab
    server's signs nothing without ``server``: it is nobody's own signature."""
    approver = by_key(kid, db)
    if approver is None:
        return [f"key {kid[:12]}… is not registered (a lab administrator registers it: `labcal certificate "
                "approvers add NAME --role ROLE --public-key FILE`)"]
    found = []
    if not approver.active:
        found.append(f"key {kid[:12]}… of {approver.name} was revoked on {approver.revoked_utc}")
    if server is None:
        if approver.role == SERVER_ROLE:
            found.append(f"key {kid[:12]}… is the lab server's ({approver.name!r}): it signs only for an "
                         "approver signed in to the lab server (`labcal serve`), never as a person")
            return found
        if approver.name != name.strip():
            found.append(f"key {kid[:12]}… is registered to {approver.name!r}, not {name.strip()!r}")
        if approver.role != role.strip():
            found.append(f"{approver.name}'s registered role is {approver.role!r}, not {role.strip()!r}")
        return found
    if approver.role != SERVER_ROLE:
        found.append(f"key {kid[:12]}… is registered to {approver.name!r} as a person ({approver.role!r}), "
                     f"not as the lab server's (--role {SERVER_ROLE!r}): it signs only as {approver.name!r}")
    elif approver.name != server.signer:
        found.append(f"key {kid[:12]}… is registered as {approver.name!r}, not {server.signer!r}")
    if role.strip() != APPROVER_USER_ROLE:
        found.append(f"a signature through the lab server is an approver's, not a {role.strip()!r}'s")
    found += server_user_problems(server.user_id, name.strip(), when, db)
    return found


def server_user_problems(user_id: int, name: str, when: str | None, db: str | Path | None = None
                         ) -> list[str]:
    """Why user ``user_id`` named ``name`` could not approve at ``when`` (None: now) through the lab
    server: no such user, another name, not an approver, added after or disabled before. A user's
    name and role never change and a user is never deleted (`labcal.app.users`), so the users table
    says what they were at any time."""
    found_rows = records(db, "users", ("name", "role", "created_utc", "disabled_utc"), {"id": user_id},
                         must_exist=False)
    if not found_rows.exists:
        return [f"no lab database at {found_rows.source.shown} to say who user {user_id} is"]
    row = found_rows.rows[0] if found_rows.rows else None
    if row is None:
        return [f"the lab server has no user {user_id} ({name!r})"]
    user, user_role, created, disabled = row
    at = _instant(when) if when is not None else datetime.now(UTC)
    found = []
    if user != name:
        found.append(f"the lab server's user {user_id} is {user!r}, not {name!r}")
    if user_role != APPROVER_USER_ROLE:
        found.append(f"{user!r} is a {user_role} of the lab server, not an approver")
    if _instant(created) > at:
        found.append(f"{user!r} became a user of the lab server on {created}, after {at.isoformat()}")
    if disabled is not None and _instant(disabled) <= at:
        found.append(f"{user!r} was disabled on {disabled}, before {at.isoformat()}")
    return found


def _instant(text: str) -> datetime:
    found = datetime.fromisoformat(text)
    return found if found.tzinfo is not None else found.replace(tzinfo=UTC)


def verify_registered(path: str | Path, db: str | Path | None = None) -> Certificate:
    """The certificate, if it is approved, its signature verifies with the key it names, and that key
    is registered in the lab database, unrevoked, to the name and role the certificate states;
    otherwise one line naming every reason."""
    source = str(path)
    doc, cert = signed_certificate(path)
    approval = cert.approval
    assert approval is not None
    registered = by_key(approval.key_id, db)
    if registered is not None:
        signature_holds(doc, cert, registered.public_key(), source)
    reasons = problems(approval.key_id, approval.by, approval.role, db, approval.server,
                       approval.approved_utc.isoformat())
    if reasons:
        raise LabcalError(f"{source}: signature not accepted: {'; '.join(reasons)}")
    return cert


def signed_note(cert: Certificate) -> str:
    """Who approved a verified certificate, and through what, in words."""
    a = cert.approval
    assert a is not None
    if a.server is None:
        return f"signed by {a.by} ({a.role}), a registered approver"
    return (f"approved by {a.by} (user {a.server.user_id} of the lab server, an approver; "
            f"{a.server.authentication}), signed with the lab server's registered key ({a.server.signer})")


# --- using a certificate ----------------------------------------------------------------------------
def calibration_in_use(path: str | Path, db: str | Path | None = None, unverified: bool = False
                       ) -> tuple[Calibration | PackageCalibration, dict | None]:
    """The calibration in a fit JSON or a certificate (a package's, `PackageCalibration`, where the
    certificate is of a sensor package), for converting voltages, and what the
    certificate's standing is (None: a fit JSON, no certificate). An approved certificate is used only
    if its signature is by a key registered in the lab database to the name and role it states
    (`verify_registered`); ``unverified`` uses it anyway, and the standing says so and why."""
    source = str(path)
    doc = parse_json(read_text(path, "calibration"), source)
    if not is_certificate(doc):
        return calibration_from_json(doc.get("fit", doc) if isinstance(doc, dict) else doc, path), None
    cert = certificate_from_doc(doc, source)  # schema and digest: an accident never converts a voltage
    standing = {"number": cert.number, "approved": cert.approval is not None, "verified": False,
                "note": "DRAFT: not approved"}
    if cert.approval is not None:
        try:
            verify_registered(path, db)
            standing.update(verified=True, note=signed_note(cert))
        except LabcalError as exc:
            if not unverified:
                raise
            standing["note"] = f"UNVERIFIED (used with --unverified): {exc}"
    return (cert.calibration() if cert.package is None else cert.package_calibration()), standing
