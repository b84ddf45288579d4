"""A certificate approved through the lab server: the signed-in approver's decision, the lab's key.

The server holds one private key (`labcal serve --key FILE`, or the lab file's ``server_key``),
registered in the lab database like an approver's. Two registrations are possible, and the server
signs accordingly:

- **the lab server's key** (``labcal certificate approvers add "lab server" --role "lab server"
  --public-key FILE.pub``, `labcal.documents.approvers.SERVER_ROLE`): the server signs *for* the
  approver who is signed in. The certificate names that approver (``by``: their name; ``role``:
  "approver", their role among the server's users) and says how: ``approval.server`` holds the
  server key's registered name, the approver's user id, the meaning of the signature ("approved")
  and how the approver authenticated for this signing ("password re-entered" on the page, or "API
  token"). 21 CFR Part 11 §11.50 asks a signed record to show the signer's printed name, the date
  and time, and the meaning: the first two are ``by`` and ``approved_utc``, the third
  ``server.meaning``; §11.200 asks that the signature be the signer's own — here the signer is
  identified by the server's authentication, and the key only attests that the server saw it.
  Verifying accepts such a signature only while the key is registered and unrevoked with the role
  "lab server", and only when the user it names was, at the time stated, an active server user with
  the role approver (`labcal.documents.approvers.problems`). Several approvers share one server key.
- **a person's key** (registered under their name and job title): the server signs as that person
  only, as `labcal certificate approve --key` would; any other approver is refused with the
  registry's reason (a key never signs under a name it is not registered to).

On SQLite, approving is `labcal.app.certificates.approve_certificate` on the run's folder — the
use case of `labcal certificate approve`: it rebuilds what it signs from the journal, refuses a
simulated run, an edited draft, a journal whose chain of digests does not hold (`labcal.store.chain`),
a run journaled before digests, an unregistered or revoked key, and writes the certificate, DCC and
report again.

On PostgreSQL the lab database is the record: the server signs the lab database's own copy of the
run the approver named (its runs, points and events rows and the draft its bench synced; never a
folder), recomputes the lab's chain of digests, and keeps the signed certificate, its DCC and its
report in the lab database in one transaction (`labcal.app.approving.approve_lab_run`); the
bench's folder receives them on its next `labcal sync` or `labcal export RUN`.

On SQLite the lab database is one machine, one trust domain: the server approves only from a file
(and folder) that only its owner may write, since whoever may write it may add a user or an approver.
The run's folder must be reachable from the server (the same path, on a shared disk); otherwise the
answer says where to approve instead. Approvals are serialised: two approvers pressing the button at
once produce one approval and one "already approved".
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.app.certificates import ApproveCertificate, Authentication, SignedFor, approve_certificate
from labcal.app.desk import MEDIA
from labcal.app.lab import run_folder
from labcal.app.labdatabase import LabDatabase
from labcal.app.users import User
from labcal.config.lab import load_lab_config
from labcal.documents.approval import key_id, load_private_key
from labcal.documents.approvers import SERVER_ROLE, by_key
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.lab_certificates import approved_files
from labcal.store.labdb import others_may_write

if TYPE_CHECKING:
    from labcal.app import approving
else:
    approving = lazy("labcal.app.approving")  # start-up without matplotlib, scipy, numpy, …

CERTIFICATE = "certificate.json"
_ONE_AT_A_TIME = threading.Lock()


class NotHere(LabcalError):
    """The approval cannot be made by this server (folder not reachable, no key, a SQLite file others
    may write)."""


@dataclass(frozen=True)
class ApproveAsUser:
    run_id: int
    user: User  # the authenticated user (the server has checked they are an active approver)
    key: Path | None  # the server's signing key
    authentication: Authentication  # how the user authenticated for this signing


@dataclass(frozen=True)
class ServerApproved:
    number: str
    by: str
    role: str
    approved_utc: str
    certificate: str
    signed_by: str  # whose key signed: the approver's own, or the lab server's for them

    def to_json(self) -> dict[str, Any]:
        return {"number": self.number, "by": self.by, "role": self.role, "approved_utc": self.approved_utc,
                "certificate": self.certificate, "signed_by": self.signed_by}


def server_key(given: str | None) -> Path | None:
    """The server's signing key — ``given`` (--key), else the lab file's ``server_key``, else none —
    checked now rather than at the first approval (one line for a missing, unreadable or too-open
    key)."""
    path = Path(given) if given is not None else load_lab_config().server_key()
    if path is not None:
        load_private_key(path)
    return path


def _cannot(lab: LabDatabase, run_dir: str, key: Path | None, name: str) -> str | None:
    """Why this server cannot approve the run whose folder is ``run_dir`` (None: it can try; the
    approval itself may still refuse, naming its reasons). On PostgreSQL the lab database's own copy
    of the run is what is signed, so where its folder is does not matter."""
    where = (f"approve it where its folder is: labcal certificate approve {run_dir} --by {name!r} "
             "--role ROLE --key KEYFILE")
    if lab.server is None and not (Path(run_dir) / CERTIFICATE).is_file():
        return f"{run_dir}: the run's folder (its {CERTIFICATE}) is not reachable from this server; {where}"
    if key is None:
        return (f"this server has no signing key (start it with labcal serve --key FILE, or set server_key "
                f"in the lab file); {where}")
    if lab.file is None:
        return None
    loose = others_may_write(lab.file)
    if loose is not None:  # whoever may write the file may write its users, approvers and journal
        return (f"{lab.file}: others may write this SQLite lab database, so its users, approvers and "
                f"readings are not the lab's to vouch for; the server signs nothing from it: {loose}")
    return None


def approval_refused(lab: LabDatabase, run_id: int, key: Path | None, name: str) -> str | None:
    """Why this server cannot approve run ``run_id`` for ``name``, in one line, or None when it can
    try: a page offers its approval form only where approval can succeed."""
    run_dir = run_folder(lab, run_id)
    return None if run_dir is None else _cannot(lab, run_dir, key, name)


def approve_as_user(lab: LabDatabase, request: ApproveAsUser) -> ServerApproved | None:
    """Approve the run's certificate for the authenticated approver with the server's key (None: no
    such run); one line on any refusal."""
    run_dir = run_folder(lab, request.run_id)
    if run_dir is None:
        return None
    user, key = request.user, request.key
    why = _cannot(lab, run_dir, key, user.name)
    if why is not None:
        raise NotHere(why)
    assert key is not None  # else `_cannot` says why
    db = str(lab.file) if lab.server is None else lab.server.url
    registered = by_key(key_id(load_private_key(key).public_key()), db)
    if registered is not None and registered.role == SERVER_ROLE:
        role, signed_for = user.role, SignedFor(user.id, request.authentication)
    else:  # a person's key (or none registered: the approval says so)
        role, signed_for = (registered.role if registered is not None else user.role), None
    with _ONE_AT_A_TIME:
        if lab.server is not None:  # the lab's own copy of the run, and the files kept there
            server = None if signed_for is None else (signed_for.user_id, signed_for.authentication)
            cert = approving.approve_lab_run(lab.server, request.run_id, user.name, role, key, server)
            where = f"{lab.shown} (run {request.run_id}'s {CERTIFICATE})"
        else:
            done = approve_certificate(ApproveCertificate(run_dir, user.name, role, str(key), db,
                                                          signed_for=signed_for))
            cert, where = done.outputs.certificate, str(done.outputs.certificate_path)
    approval = cert.approval
    assert approval is not None  # approve_run signs or refuses
    stated = cert.to_json()["approval"]  # the time as the certificate states it
    signer = (f"the lab server's key ({registered.name}) for {approval.by}"
              if signed_for is not None and registered is not None else f"{approval.by}'s own key")
    return ServerApproved(cert.number, approval.by, approval.role, stated["approved_utc"], where, signer)


def approved_file(lab: LabDatabase, run_id: int, name: str) -> tuple[str, bytes] | None:
    """A file of run ``run_id``'s certificate as the lab server approved it and the lab keeps it
    (the signed certificate.json, certificate.dcc.xml, report.pdf, report.html), with its media
    type; None: no such file, or none approved there."""
    if name not in MEDIA:
        return None
    content = approved_files(lab.engine, run_id).get(name)
    return None if content is None else (MEDIA[name], content)
