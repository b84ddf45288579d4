"""A finished run's certificate: issue it (with its report, DCC and history entry), approve (sign)
it, verify a signature; and the register of those who may approve, and their keys.

Issuing and approving write into the run folder (certificate.json, certificate.dcc.xml,
report.html, report.pdf) and the lab database's history, and nothing else: readings.csv, fit.json,
plan.toml and run.json are left as they are. The certificate is built from the journal, whose
readings it names by digest, so it is true whatever those files say; a folder whose exports are
missing, stale or edited is *reported* in the notes (`labcal export RUN_DIR` rebuilds it), never
silently rewritten. Verifying and listing only read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import date, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from labcal.app import audit
from labcal.app.approving import approve_run, journal_verdict
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.app.run_documents import write_run_outputs
from labcal.documents import approval as documents_approval
from labcal.documents import approvers as documents_approvers
from labcal.documents.administration import ItemGiven
from labcal.documents.approval import check_dcc, load_public_key, verify
from labcal.documents.approvers import signed_note, verify_registered
from labcal.documents.certificate import read_certificate as read
from labcal.documents.dcc import DCC_FILE
from labcal.documents.issuing import load_settings
from labcal.documents.report_tables import (
    attitude_table,
    budget_table,
    coefficients_with_expanded_uncertainty,
    conformity_table,
)
from labcal.errors import LabcalError
from labcal.store.journal import db_path
from labcal.store.sync import send_now

Authentication = Literal["password re-entered", "API token"]  # as labcal.documents.certificate's
SERVER_ROLE = "lab server"  # as labcal.documents.approvers.SERVER_ROLE, without importing it at start-up

if TYPE_CHECKING:
    from labcal.documents.approvers import Approver
    from labcal.documents.certificate import Certificate
    from labcal.documents.report import RunOutputs
    from labcal.documents.report_tables import Table


@dataclass(frozen=True)
class IssueCertificate:
    """Certificate, report, DCC and history entry of a complete run. Tolerances: the lab file's,
    the station file's [certificate] over them, these over both (None: not given)."""

    run_dir: str
    db: str | None = None
    station: str | None = None  # the station file for the Type B inputs (default: the journaled one)
    tolerance_deg: float | None = None
    bias_max_v: float | None = None
    usage_pitch: tuple[float, float] | None = None
    usage_roll: tuple[float, float] | None = None
    monte_carlo: int = 0  # JCGM 101 trials checking the budget (0: none)
    serial: str | None = None
    operator: str | None = None
    customer: str | None = None
    manufacturer: str | None = None
    model: str | None = None
    received: date | None = None
    in_use_samples: int | None = None  # samples a reading in use averages (None: the calibration's window)


@dataclass(frozen=True)
class Issued:
    outputs: RunOutputs
    tables: tuple[Table, ...] = ()  # coefficients, attitude, budget and conformity, as the report has them
    changed: str | None = None  # "identification changed from …" / "kept from …" when one was replaced

    @property
    def notes(self) -> tuple[str, ...]:
        """The outputs' notes, and the lack-of-fit or drift test's statement where either is flagged:
        the technician reads it at the console, not only in the certificate."""
        budget = self.outputs.certificate.uncertainty_budget
        check = None if budget is None else budget.fit_check
        flagged = (check.statement,) if check is not None and (check.lack_of_fit or check.drift) else ()
        return self.outputs.notes + flagged

    def to_json(self) -> dict[str, Any]:
        result, cert = self.outputs, self.outputs.certificate
        check = None if cert.uncertainty_budget is None else cert.uncertainty_budget.fit_check
        return {
            "fit_check": None if check is None else check.model_dump(mode="json"),
            "certificate_id": cert.certificate_id, "serial": cert.instrument.serial,
            "certificate": str(result.certificate_path), "report_html": str(result.html_path),
            "report_pdf": str(result.pdf_path), "database": str(result.database),
            "dcc": None if result.dcc_path is None else str(result.dcc_path),
            "passed": None if cert.conformity is None else cert.conformity.passed,
            "conformity": None if cert.conformity is None else cert.conformity.model_dump(mode="json"),
            "attitude": cert.attitude.model_dump(mode="json"),
            "coefficients": cert.fit.coefficients, "U": cert.expanded_uncertainty.U,
            "k": cert.expanded_uncertainty.k, "digest": cert.digest.value,
            "uncertainty_budget": None if cert.uncertainty_budget is None
            else cert.uncertainty_budget.model_dump(mode="json"),
            "replaces": cert.replaces, "compared_with": result.compared_with,
            "identification_changed": list(result.changes),
        }


def issue_certificate(request: IssueCertificate) -> Issued:
    """Issue (or issue again) a complete run's certificate and report; one line for a run that is
    not complete, not this journal's, or settings that are wrong."""
    if request.monte_carlo and not 100 <= request.monte_carlo <= 1_000_000:
        raise LabcalError(f"{{0}} {request.monte_carlo}: give 100 … 1000000 trials (10000 gives U95 "
                          "to about 1 %), or leave it out", "monte_carlo")
    settings = load_settings(request.station, attitude_u95_max_deg=request.tolerance_deg,
                             bias_max_v=request.bias_max_v, usage_pitch_deg=request.usage_pitch,
                             usage_roll_deg=request.usage_roll, in_use_samples=request.in_use_samples)
    result = write_run_outputs(request.run_dir, settings, serial=request.serial, operator=request.operator,
                               db=request.db, station=request.station, monte_carlo=request.monte_carlo,
                               item=ItemGiven(request.customer, request.manufacturer, request.model,
                                              request.received))
    cert = result.certificate
    changed = None
    if result.compared_with is not None:
        changed = (f"identification changed from {result.compared_with}: {'; '.join(result.changes)}"
                   if result.changes else f"identification kept from {result.compared_with}")
    tables = tuple(make(cert) for make in (coefficients_with_expanded_uncertainty, attitude_table,
                                           budget_table, conformity_table))
    return Issued(result, tables, changed)


@dataclass(frozen=True)
class SignedFor:
    """The key is the lab server's, signing for an approver signed in to it (`labcal.app.server_approval`)."""

    user_id: int  # the approver among the server's users
    authentication: Authentication  # how they authenticated for this signing


@dataclass(frozen=True)
class ApproveCertificate:
    run_dir: str
    by: str
    role: str
    key: str  # the approver's private key (PEM), or the lab server's (``signed_for``)
    db: str | None = None
    station: str | None = None  # the station file the certificate was issued with, if not the journaled
    signed_for: SignedFor | None = None
    unchained: bool = False  # a run journaled before digests may be signed (the approver was told)


@dataclass(frozen=True)
class Approved:
    outputs: RunOutputs

    def to_json(self) -> dict[str, Any]:
        result, cert = self.outputs, self.outputs.certificate
        approval = cert.approval
        assert approval is not None  # approve_run signs or refuses
        return {"certificate": str(result.certificate_path), "number": cert.number,
                "approved_by": approval.by, "role": approval.role, "key_id": approval.key_id,
                "dcc": None if result.dcc_path is None else str(result.dcc_path),
                "dcc_sha256": approval.dcc_sha256, "report_pdf": str(result.pdf_path)}


def approve_certificate(request: ApproveCertificate) -> Approved:
    """Sign the run's draft certificate and its DCC, write the report without DRAFT and store the
    approved certificate; one line naming every reason it may not be signed."""
    signed_for = (None if request.signed_for is None
                  else (request.signed_for.user_id, request.signed_for.authentication))
    return Approved(approve_run(request.run_dir, request.by, request.role, request.key, request.db,
                                request.station, signed_for, request.unchained))


@dataclass(frozen=True)
class VerifyCertificate:
    file: str  # a certificate.json
    public_key: str | None = None  # verify against this key instead of the lab database's register
    dcc: str | None = None  # the DCC to check against the signed digest (default: the one beside FILE)
    db: str | None = None


@dataclass(frozen=True)
class Verified:
    file: str
    number: str
    approved_by: str
    role: str
    approved_utc: datetime
    verified_against: str
    dcc: str | None
    signed: str  # who approved and through what, in words (`labcal.documents.approvers.signed_note`)
    through_server: dict[str, Any] | None  # the lab server's signature for the approver (None: their own key)
    journal: str = ""  # what the run's journal says: its chain holds up to the signed head, or why unchecked

    def to_json(self) -> dict[str, Any]:
        return {"file": self.file, "valid": True, "number": self.number, "approved_by": self.approved_by,
                "role": self.role, "approved_utc": self.approved_utc.isoformat(),
                "verified_against": self.verified_against, "dcc": self.dcc, "signed": self.signed,
                "through_server": self.through_server, "journal": self.journal}


def verify_certificate(request: VerifyCertificate) -> Verified:
    """A certificate's signature checked (and its DCC's digest), and its run's journal recomputed up
    to the chain's head it states; one line when either fails. A read."""
    cert = (verify_registered(request.file, request.db) if request.public_key is None
            else verify(request.file, load_public_key(request.public_key)))
    approval = cert.approval
    assert approval is not None  # verify refuses an unapproved certificate
    dcc = (Path(request.dcc) if request.dcc else
           Path(request.file).with_name(DCC_FILE) if approval.dcc_sha256 else None)
    if dcc is not None:
        check_dcc(cert, dcc)
    journal = journal_verdict(cert, request.db, request.file)
    against = "the registered key" if request.public_key is None else "the given public key"
    return Verified(request.file, cert.number, approval.by, approval.role, approval.approved_utc,
                    against, None if dcc is None else str(dcc), signed_note(cert),
                    None if approval.server is None else approval.server.model_dump(), journal)


@dataclass(frozen=True)
class MakeKeys:
    out: str  # writes OUT.key (readable by its owner only) and OUT.pub


@dataclass(frozen=True)
class Keys:
    private_key: Path
    public_key: Path
    key_id: str


def make_keys(request: MakeKeys) -> Keys:
    private, public = documents_approval.keygen(request.out)
    return Keys(private, public, documents_approval.key_id(documents_approval.load_public_key(public)))


@dataclass(frozen=True)
class AddApprover:
    name: str
    role: str
    public_key: str
    db: str | None = None


@dataclass(frozen=True)
class RevokeApprover:
    name: str
    db: str | None = None


@dataclass(frozen=True)
class ListApprovers:
    db: str | None = None


@dataclass(frozen=True)
class Approvers:
    approvers: tuple[Approver, ...] = field(default_factory=tuple)
    database: str = ""  # where they were read
    stale: str | None = None  # the bench read its journal's copy: the lab could not be reached
    exists: bool = True  # False: no lab database there yet


def add_approver(request: AddApprover) -> Approver:
    added = documents_approvers.add(request.name, request.role, request.public_key, request.db)
    _audited(request.db, f"registered as {request.role} with key {added.key_id[:16]}", request.name)
    return added


def revoke_approver(request: RevokeApprover) -> Approver:
    revoked = documents_approvers.revoke(request.name, request.db)
    _audited(request.db, f"key {revoked.key_id[:16]} revoked", request.name)
    return revoked


def _audited(db: str | None, detail: str, name: str) -> None:
    """A change to the register of approvers, in the audit trail of the file that holds the register
    (the SQLite lab database, or the station's journal)."""
    lab = open_lab(OpenLab(str(db_path(db)), must_exist=True))
    try:
        audit.record(lab, audit.by_command(audit.APPROVER_CHANGED, name, detail))
    finally:
        lab.close()


def list_approvers(request: ListApprovers) -> Approvers:
    """Every registration, active and revoked (a missing database: none, and nothing is created)."""
    read = documents_approvers.listed(request.db)
    return Approvers(tuple(read.approvers), read.shown, read.stale, read.exists)


def read_certificate(path: str | Path) -> Certificate:
    """A certificate.json as its typed model, checked against its schema and its digest. A read."""
    return read(path)


def share_with_lab(db: str | None) -> str | None:
    """What this bench has just recorded (a registration, a revocation, an approved certificate) sent
    to the lab's server now, so that every bench sees it at once; None when it is there (or when the
    lab database is a SQLite file, this bench's own), else the one line saying it waits for
    ``labcal sync`` (nothing is lost: the journal keeps it)."""
    return send_now(db)
