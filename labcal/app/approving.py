"""Approving a run's certificate: the use case behind `labcal certificate approve`.

What is signed must be what the journal says. The draft in the run folder is a file anybody with
access can edit, and its SHA-256 digest can be recomputed by whoever edits it, so approval does not
trust it: it rebuilds the certificate from the journal with the draft's own issuing choices (the
usage envelope, the tolerances, the item's details, the Monte Carlo trials, the issue time and
revision) and the Type B inputs of the run's station (or of ``--station``, as `labcal report` took
them), and signs only a draft that the rebuild reproduces. Everything a draft states that comes
from the measurement — fit, uncertainties, budget, conformity, story — is recomputed, so an edited
value shows as a difference whatever the editor did to the digest.

The journal itself is checked too: its chain of digests (`labcal.store.chain`) is recomputed, in the
station's journal and in the lab server's copy of the run, and must hold up to the head the draft
states, which the signature then covers; a run journaled before digests is approved only when the
approver says so (``--unchained``).

A simulated run is never approved, a key must be registered, unrevoked, and registered to the name
and role given (`labcal.documents.approvers`). Every reason that applies is named in one line, so
the approver learns at once everything that stands in the way.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from labcal.config.files import write_atomic
from labcal.config.lab import ServerDatabase
from labcal.config.settings import CertificateSettings
from labcal.documents import approvers
from labcal.documents.administration import ItemGiven
from labcal.documents.approval import approve, key_id, load_private_key
from labcal.documents.certificate import Authentication, Certificate, ServerSignature, read_certificate
from labcal.documents.dcc import DCC_FILE, write_dcc
from labcal.documents.issuing import build_certificate
from labcal.documents.report import (
    CERTIFICATE,
    REPORT_HTML,
    REPORT_PDF,
    RunOutputs,
    fitted,
    replaced_by,
    write_documents,
    write_file,
    write_report,
)
from labcal.documents.uncertainty import bench_section, type_b_inputs
from labcal.errors import LabcalError
from labcal.store import lab_certificates, labdb
from labcal.store.chain import UNCHAINED, copies
from labcal.store.record import RunRecord, load_run

RELATIVE = 1e-9  # numbers a rebuild reproduces agree to rounding; an edit is far larger
SIMULATED = ("the run is simulated (a dry run on the simulated rig or its emulators): its readings are not a "
             "calibration of the instrument and are never approved")


def issue_settings(draft: Certificate) -> CertificateSettings:
    """The certificate settings the draft was issued with, as it states them."""
    checks = draft.conformity.checks if draft.conformity else []
    return CertificateSettings(
        laboratory=draft.laboratory,
        attitude_u95_max_deg=next((c.limit for c in checks if c.unit == "°"), None),
        bias_max_v=next((c.limit for c in checks if c.unit == "V"), None),
        usage_pitch_deg=draft.attitude.usage_pitch_deg, usage_roll_deg=draft.attitude.usage_roll_deg,
        grid_step_deg=draft.attitude.grid_step_deg, in_use_samples=_stated_in_use(draft))


def _stated_in_use(draft: Certificate) -> int | None:
    """The in-use averaging the draft states where it was stated for it (None: the calibration's)."""
    in_use = draft.uncertainty_budget.in_use if draft.uncertainty_budget else None
    return in_use.samples if in_use is not None and in_use.stated else None


def rebuild(record: RunRecord, draft: Certificate, station: str | Path | None = None) -> Certificate:
    """The certificate `labcal report` makes of the journal's run with the draft's issuing choices
    (the journal's chain stated over as many records as the draft's: records journaled after the
    draft was issued leave what it states true)."""
    fit, device, model_note = fitted(record)
    section = bench_section(record, station)
    admin = draft.administration
    item = ItemGiven() if admin is None else ItemGiven(admin.customer, admin.item.manufacturer or None,
                                                       admin.item.model or None, admin.item.received)
    checks = draft.uncertainty_budget.monte_carlo if draft.uncertainty_budget else None
    return build_certificate(
        record, fit, issue_settings(draft), serial=draft.instrument.serial, operator=draft.operator,
        issued_utc=draft.issued_utc, inputs=type_b_inputs(section, record, device),
        monte_carlo=checks[0].trials if checks else 0, revision=draft.revision or 1, replaces=draft.replaces,
        section=section, item=item, device=device, model_note=model_note,
        replaced=replaced_by(record.directory, draft),
        journal_records=draft.data.journal.records if draft.data.journal is not None else None,
        lab_number=draft.lab_number)


def differences(a: object, b: object, path: str = "") -> list[str]:
    """Where two JSON documents differ (numbers to `RELATIVE`), as dotted paths."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in differences(a.get(k), b.get(k), f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in differences(x, y, f"{path}[{i}]")]
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and bool not in (type(a), type(b)):
        return [] if math.isclose(a, b, rel_tol=RELATIVE, abs_tol=1e-300) else [path.lstrip(".")]
    return [] if a == b else [path.lstrip(".")]


def _sections(paths: list[str]) -> str:
    """The differing top-level sections, each with its first differing field."""
    first: dict[str, str] = {}
    for p in paths:
        first.setdefault(p.split(".")[0].split("[")[0], p)
    return ", ".join(first.values())


def chain_reasons(record: RunRecord, draft: Certificate | None, db: str | Path | None,
                  unchained: bool = False) -> list[str]:
    """Why the run's journal does not stand behind the draft (`labcal.store.chain`): a record of the
    station's journal, or of the lab server's copy of the run, that differs from the chain; a chain
    whose head is not the draft's; a run journaled before digests, unless ``unchained`` (the
    approver has been told, and the certificate then states no chain)."""
    check = record.chain
    if check is None:
        return []
    if not check.chained:
        return [] if unchained else [
            f"{check.run} was {UNCHAINED}: nothing shows its readings unedited (give --unchained to "
            "approve it all the same, or measure it again)"]
    stated = None if draft is None or draft.data.journal is None else draft.data.journal.model_dump()
    problem = check.problem if stated is None else check.against(stated)
    reasons = [] if problem is None else [problem]
    if stated is not None and not reasons:
        for where, copy in copies(db, check.run_uuid):  # the lab's copy too, where it has one
            elsewhere = copy.against(stated)
            if elsewhere is not None:
                reasons.append(f"{where}: {elsewhere}")
    return reasons


def approve_run(run_dir: str | Path, by: str, role: str, key_path: str | Path, db: str | Path | None = None,
                station: str | Path | None = None, signed_for: tuple[int, Authentication] | None = None,
                unchained: bool = False) -> RunOutputs:
    """Sign the run's draft certificate and write every document again, or one line naming every
    reason it may not be signed: a simulated run, a journal whose chain of digests does not hold or
    is not the draft's, a draft the journal does not reproduce, a key that is not registered,
    revoked, or registered to another name or role.

    ``signed_for``: (user id, how they authenticated) — the key is the lab server's, signing for
    ``by``, an approver signed in to it (`labcal.app.server_approval`); the approval says so.
    ``unchained``: a run journaled before digests may be signed (never through the server)."""
    key = load_private_key(key_path)  # before anything is read or written
    server = None
    if signed_for is not None:
        registered = approvers.by_key(key_id(key.public_key()), db)
        server = ServerSignature(signer=registered.name if registered is not None else "(unregistered)",
                                 user_id=signed_for[0], meaning="approved", authentication=signed_for[1])
    record = load_run(run_dir)
    path = Path(run_dir) / CERTIFICATE
    draft: Certificate | None = None
    unreadable = None
    try:
        draft = read_certificate(path)
    except LabcalError as exc:
        unreadable = f"certificate.json cannot be signed ({str(exc).removeprefix(f'{path}: ')})"
    chained = chain_reasons(record, draft, db, unchained)
    cert = _sign(record, draft, unreadable, chained, by, role, key, db, station, server, str(run_dir),
                 f"`labcal report {run_dir}` issues it again")
    fit, device, _ = fitted(record)
    return write_documents(cert, record, fit, device, db)


def _sign(record: RunRecord, draft: Certificate | None, unreadable: str | None, chained: list[str], by: str,
          role: str, key: Ed25519PrivateKey, db: str | Path | None, station: str | Path | None,
          server: ServerSignature | None, where: str, reissue: str) -> Certificate:
    """The draft signed, or one line naming every reason it may not be (``chained``: the chain's,
    said already): the rule both a folder's approval and the lab server's approval follow."""
    reasons = [SIMULATED] if record.simulated else []
    if unreadable is not None:
        reasons.append(unreadable)
    if draft is not None and draft.approval is not None:
        raise LabcalError(f"certificate {draft.number} is already approved by {draft.approval.by}; a change "
                          "is a new revision (`labcal report` issues it)")
    reasons += chained
    if draft is not None:
        try:
            rebuilt = rebuild(record, draft, station)
        except LabcalError as exc:
            reasons.append(f"the certificate cannot be rebuilt from the journal ({exc})")
        else:
            found = differences({k: v for k, v in draft.to_json().items() if k != "digest"},
                                {k: v for k, v in rebuilt.to_json().items() if k != "digest"})
            if chained:  # said above, record by record
                found = [f for f in found if not f.startswith("data.journal")]
            if found:
                reasons.append(f"certificate.json is not what the journal gives (differs in "
                               f"{_sections(found)}): edited after issue, or issued with another "
                               f"station file (give it with --station) or another labcal; {reissue}")
    reasons += approvers.problems(key_id(key.public_key()), by, role, db, server)
    if reasons:
        raise LabcalError(f"{where}: not approved: " + "; ".join(reasons))
    assert draft is not None
    return approve(draft, by, role, key, server=None if server is None else server.model_dump())


def approve_lab_run(server: ServerDatabase, run_id: int, by: str, role: str, key_path: str | Path,
                    signed_for: tuple[int, Authentication] | None = None) -> Certificate:
    """Sign run ``run_id`` of a PostgreSQL lab database from the lab's own copy of it — its runs,
    points and events rows and the draft its bench synced, never a folder — and keep the signed
    certificate, its DCC and its report there, all in one transaction: a server stopped anywhere
    in between leaves the draft as it was and nothing of the approval. The same refusals as a
    folder's approval (`approve_run`), the lab's chain of digests recomputed and held to the head
    the draft states; a run journaled before digests is never approved here."""
    key = load_private_key(key_path)  # before anything is read or written
    db = str(server.url)
    server_signature = None
    if signed_for is not None:
        registered = approvers.by_key(key_id(key.public_key()), db)
        server_signature = ServerSignature(
            signer=registered.name if registered is not None else "(unregistered)", user_id=signed_for[0],
            meaning="approved", authentication=signed_for[1])
    where = lab_certificates.lab_label(run_id)
    engine = labdb.open_server(server)
    try:
        with engine.begin() as connection, tempfile.TemporaryDirectory(prefix="labcal-approve-") as folder:
            lab_certificates.lock_run(connection, run_id)
            record = lab_certificates.lab_record(connection, run_id, Path(folder))
            check = record.chain
            assert check is not None  # the lab's copy is always checked
            done = lab_certificates.approved_by(connection, run_id)
            if done is not None:
                raise LabcalError(f"{where} is already approved by {done.get('by')} "
                                  f"({done.get('approved_utc')}); a change is a new revision")
            text = lab_certificates.draft_document(connection, record.meta.instrument_serial,
                                                   check.run_uuid, lock=True)
            draft, unreadable = None, None
            if text is None:
                unreadable = ("no draft certificate of it has reached the lab database (`labcal report` at "
                              "its bench issues it, `labcal sync` sends it)")
            else:
                try:
                    draft = Certificate.model_validate_json(text)
                except ValueError as exc:
                    unreadable = f"the lab's draft cannot be read ({str(exc).splitlines()[0]})"
            if draft is not None and draft.replaces:  # the approved revision it replaces, kept beside it
                kept = lab_certificates.replaced_document(connection, check.run_uuid, draft.replaces)
                if kept is not None:
                    write_atomic(Path(folder) / f"certificate.rev{(draft.revision or 1) - 1}.json", kept)
            chained = chain_reasons(record, draft, None) if check.chained else [
                f"{check.run} was {UNCHAINED}: the lab server approves only a chained run (approve it at its "
                "bench with labcal certificate approve --unchained)"]
            cert = _sign(record, draft, unreadable, chained, by, role, key, db, None, server_signature, where,
                         "`labcal report` at its bench issues it again and `labcal sync` sends it")
            fit, device, _ = fitted(record)
            folder_path = Path(folder)
            write_dcc(folder_path / DCC_FILE, cert)
            write_report(folder_path, cert, record, fit, device)
            write_file(folder_path / CERTIFICATE, cert)
            files = {name: (folder_path / name).read_bytes()
                     for name in (DCC_FILE, REPORT_HTML, REPORT_PDF, CERTIFICATE)}
            lab_certificates.store_files(connection, cert.certificate_id, check.run_uuid, files)
            lab_certificates.replace_draft(connection, cert.certificate_id, cert.instrument.serial,
                                           cert.calibrated_utc.isoformat(), cert.issued_utc.isoformat(),
                                           cert.digest.value, cert.model_dump_json(indent=2))
    finally:
        engine.dispose()
    return cert


def journal_verdict(cert: Certificate, db: str | Path | None, source: str) -> str:
    """What the journal says of a signed certificate's run, in one clause (`certificate verify`):
    its chain recomputed in every database here that holds the run, up to the head the certificate
    states. A record that differs, or a head that is not the stated one, is one LabcalError line
    naming it; a run journaled before digests is said to be so, neither passed nor failed."""
    stated = cert.data.journal
    if stated is None:
        return f"its run was {UNCHAINED}"
    found = copies(db, stated.run_uuid)
    for where, check in found:
        problem = check.against(stated.model_dump())
        if problem is not None:
            raise LabcalError(f"{source}: {where}: {problem}")
    if not found:
        return (f"its journal was not checked: no database here holds its run {stated.run_uuid} (--db names "
                "the lab database)")
    return "; ".join(f"{where}: {check.run}'s journal holds up to the signed head ({stated.records} records, "
                     f"{stated.head[:16]}…)" for where, check in found)
