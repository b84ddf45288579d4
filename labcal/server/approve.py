"""A certificate approved through the lab server: the signed-in approver's decision, the lab's key.

The server holds one private key (`labcal serve --key FILE`), registered in the lab database like an
approver's (`labcal certificate approvers add NAME --role ROLE --public-key FILE.pub`). Approving is
`labcal.documents.approving.approve_run` on the run's folder — the same use case as `labcal
certificate approve`: it rebuilds what it signs from the journal, refuses a simulated run, an edited
draft, an unregistered or revoked key, and writes the certificate, DCC and report again. The approval
names the authenticated user (``by``), the meaning ("approved": the certificate's approval block),
the time, and the role the key is registered with.

Because the approvers' registry ties a key to one name (`labcal.documents.approvers.problems`), the
server's key must be registered under the name of the approver who signs through it; a key
registered to somebody else is refused with the registry's own reason, so a certificate never names
an approver the registry does not vouch for.

The run's folder must be reachable from the server (the same path, on a shared disk); otherwise the
answer says where to approve instead. Approvals are serialised: two approvers pressing the button at
once produce one approval and one "already approved".
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

from labcal.errors import LabcalError

CERTIFICATE = "certificate.json"
_ONE_AT_A_TIME = threading.Lock()


class NotHere(LabcalError):
    """The approval cannot be made by this server (folder not reachable, no key, no SQLite lab file)."""


@dataclass(frozen=True)
class Approved:
    number: str
    by: str
    role: str
    approved_utc: str
    certificate: str


def approve(run_dir: str, user: str, key: Path | None, db_file: Path | None) -> Approved:
    """Approve the run's certificate as ``user`` with the server's key; one line on any refusal."""
    from labcal.documents.approval import key_id, load_private_key
    from labcal.documents.approvers import by_key
    from labcal.documents.approving import approve_run

    where = (f"approve it where its folder is: labcal certificate approve {run_dir} --by {user!r} "
             "--role ROLE --key KEYFILE")
    if not (Path(run_dir) / CERTIFICATE).is_file():
        raise NotHere(f"{run_dir}: the run's folder (its {CERTIFICATE}) is not reachable from this server; "
                      f"{where}")
    if key is None:
        raise NotHere(f"this server has no signing key (start it with labcal serve --key FILE); {where}")
    if db_file is None:
        raise NotHere(f"this server approves only on a SQLite lab database for now; {where}")
    registered = by_key(key_id(load_private_key(key).public_key()), db_file)
    role = registered.role if registered is not None else "approver"  # unregistered: approve_run says so
    with _ONE_AT_A_TIME:
        result = approve_run(run_dir, user, role, key, db_file)
    approval = result.certificate.approval
    assert approval is not None  # approve_run signs or refuses
    stated = result.certificate.to_json()["approval"]  # the time as the certificate states it
    return Approved(result.certificate.number, approval.by, approval.role, stated["approved_utc"],
                    str(result.certificate_path))
