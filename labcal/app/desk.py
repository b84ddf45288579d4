"""The approver's desk: the certificates waiting for approval with what needs an approver's eye, and
what a finished run's certificate states, as the lab server's pages show them; pure reads.

An approver must not sign blind. The queue lists every complete run of the lab whose certificate is
not approved yet, each with what stands out in how it was measured and what it states: the checklist
items it went on regardless of, an overdue or unnamed reference standard, an unregistered serial
and, from the journal and the certificate, faults during the run, a device correction used in place
of remounts, and a conformity verdict that failed. That is one rule, `run_attention`, read from the
lab record: `labcal runs --attention` applies the same.

A run's results are its certificate's own: the model the certificate rests on (the device model
where the plan identifies it, else the linear fit), its coefficients ± U (95 %), the attitude U95 over
the usage envelope, the verdict, who approved it and when, and every revision's documents. The
residuals shown beside them are recomputed from the lab database's own copy of the run under that
same model (`labcal.documents.report.fitted`, the fit the certificate was issued from): a page that
showed the linear fit's residuals next to a device-model certificate would show a scatter forty
times larger than the certificate's.

Documents per revision: the certificate JSON as the lab database holds it; the DCC and the report as
the lab server kept them when it approved (PostgreSQL), else the run folder's where it is reachable
and its certificate is this very revision (same digest) — a DCC there only if it is the one an
approval signed (its SHA-256); the DCC is otherwise written from the JSON
(`labcal.documents.dcc.dcc_document`, a function of the certificate alone), and checked against the
digest an approval signed for it.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from labcal.analysis.fit import ROW_NAMES
from labcal.app.lab import _summary, simulated
from labcal.app.labdatabase import LabDatabase
from labcal.app.residuals import certified_residuals, residual_png
from labcal.config.run_metadata import RunMetadata, listed_metadata
from labcal.documents.certificate import Certificate, certificate_from_doc, format_result
from labcal.documents.overrides import STANDARD_OVERRIDE_EVENT, checklist_overrides, run_overrides
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import lab_certificates, lab_view
from labcal.store.lab_certificates import approved_runs

if TYPE_CHECKING:
    from labcal.documents import dcc, report_figures
    from labcal.store.handles import Connection
    from labcal.store.journal import EventRow
else:
    dcc = lazy("labcal.documents.dcc")  # start-up without scipy, numpy, pydantic, …
    report_figures = lazy("labcal.documents.report_figures")  # matplotlib: not to list runs

CERTIFICATE, DCC, PDF, HTML = "certificate.json", "certificate.dcc.xml", "report.pdf", "report.html"
MEDIA = {CERTIFICATE: "application/json", DCC: "application/xml", PDF: "application/pdf",
         HTML: "text/html; charset=utf-8"}
DOCUMENTS = (PDF, DCC, CERTIFICATE)  # what a revision offers, in the order a page lists them


# --- reading certificates -------------------------------------------------------------------------
def parsed_certificate(document: str | bytes, where: str) -> Certificate | None:
    """A stored certificate verified (schema and digest); None where it is not one that reads back."""
    try:
        return certificate_from_doc(json.loads(document), where)
    except (LabcalError, ValueError):
        return None


def _states_run(cert: Certificate, run_uuid: str) -> bool:
    return cert.data.journal is not None and cert.data.journal.run_uuid == run_uuid


def run_revisions(conn: Connection, run_uuid: str) -> list[Certificate]:
    """Every certificate the lab holds for the run (each revision, and its approved form where the
    server approved on PostgreSQL), oldest issue first; one per certificate id, the approved one
    where both are held."""
    found: dict[str, Certificate] = {}
    for cid, document in lab_certificates.run_documents(conn, run_uuid):
        cert = parsed_certificate(document, f"certificate {cid}")
        if cert is None or not _states_run(cert, run_uuid):
            continue
        held = found.get(cert.certificate_id)
        if held is None or (held.approval is None and cert.approval is not None):
            found[cert.certificate_id] = cert
    return sorted(found.values(), key=lambda c: (c.issued_utc, c.revision or 1))


def _current(revisions: list[Certificate]) -> Certificate | None:
    """The revision in force: the newest that no other replaces."""
    replaced = {c.replaces for c in revisions if c.replaces}
    live = [c for c in revisions if c.number not in replaced] or revisions
    return live[-1] if live else None


# --- what needs an approver's eye ------------------------------------------------------------------
def checklist_attention(metadata: RunMetadata, resumed: Iterable[EventRow] = ()) -> tuple[str, ...]:
    """What the run's journaled metadata says an approver must know of how it was measured: the
    checklist items it went on regardless of (as the certificate states them, `checklist_overrides`),
    a reference standard the checklist found overdue or unnamed, an overdue registered standard used
    under an approver's override (at the start, or on resuming: the ``resumed`` override events),
    and a serial the instrument register did not hold."""
    checklist = metadata.checklist
    found = [f"went on regardless: {item}" for item in checklist_overrides(checklist)]
    if checklist is not None:
        found += [f"{i.item}: {i.message}" for i in checklist.items
                  if i.item == "reference standards" and i.status == "warning"]
    found += [o.sentence() for o in run_overrides(metadata, resumed) if o.kind == "reference standard"]
    if metadata.unregistered_serial:
        found.append(f"serial {metadata.unregistered_serial}")
    return tuple(found)


def needs_attention(metadata: RunMetadata, faults: Iterable[str], cert: Certificate | None,
                    resumed: Iterable[EventRow] = ()) -> tuple[str, ...]:
    """What an approver must know before signing, in this order: the metadata's (`checklist_attention`:
    overrides, reference standards, serial), then the run's faults, a device correction used, a
    failed verdict."""
    found = list(checklist_attention(metadata, resumed))
    faults = list(faults)
    if faults:
        found.append(f"{len(faults)} fault(s) during the run: " + "; ".join(faults[:3])
                     + ("; …" if len(faults) > 3 else ""))
    if cert is not None and cert.device_correction is not None:
        found.append("a device correction was used in place of the remounts that identify the device")
    if cert is not None and cert.conformity is not None and not cert.conformity.passed:
        failed = [c for c in cert.conformity.checks if not c.passed]
        found.append("out of tolerance: " + "; ".join(
            f"{c.quantity} {c.value:.3g} {c.unit} > {c.limit:.3g} {c.unit}" for c in failed))
    return tuple(found)


def run_attention(conn: Connection, run_id: int, run_uuid: str | None, metadata: str | None,
                  revisions: list[Certificate] | None = None) -> tuple[str, ...]:
    """The one rule for what needs an approver's eye in a run, read from the lab record on ``conn``
    (the run's row ``run_id``, its journaled metadata, its fault events, its current certificate):
    what the desk's queue and run page show and what `labcal runs --attention` lists. ``revisions``:
    the run's certificates where the caller has read them already (`run_revisions`)."""
    if revisions is None:
        revisions = run_revisions(conn, run_uuid) if run_uuid else []
    resumed = lab_view.events_of_kind(conn, run_id, STANDARD_OVERRIDE_EVENT)
    return needs_attention(listed_metadata(metadata), lab_view.faults(conn, run_id), _current(revisions),
                           resumed)




@dataclass(frozen=True)
class Waiting:
    """A complete run whose certificate nobody has approved yet, as the queue lists it."""

    run: dict  # the run as the API states it (`labcal.app.lab`)
    number: str | None  # the certificate's number with its revision (None: no certificate issued yet)
    issued_utc: str | None
    attention: tuple[str, ...]


@dataclass(frozen=True)
class Queue:
    waiting: tuple[Waiting, ...]  # oldest run first: the one waiting longest
    dry_runs: int  # complete dry runs, never approved (listed only when asked)


def queue(lab: LabDatabase, dry_runs: bool = False) -> Queue:
    """The complete runs whose certificate is not approved, oldest first; dry runs (never approved)
    counted, and listed too when ``dry_runs``. A run the lab holds an approved certificate of
    (`labcal.store.lab_certificates.approved_runs`, the revision in force: read, not verified — its
    page verifies what it shows) is passed over before any certificate is verified, all of them found
    in a fixed number of statements, so the queue costs what is waiting, not a search per run."""
    waiting, dry = [], 0
    with lab.engine.connect() as conn:
        rows = lab_view.complete_runs(conn)
        counts = lab_view.counts(conn, [r.id for r in rows])
        approved = approved_runs(conn, [r.uuid for r in rows if r.uuid])
        for row in rows:
            if row.uuid in approved:
                continue
            revisions = run_revisions(conn, row.uuid) if row.uuid else []
            cert = _current(revisions)
            if cert is not None and cert.approval is not None:
                continue
            metadata = listed_metadata(row.metadata)
            if simulated(metadata, row.station_text):
                dry += 1
                if not dry_runs:
                    continue
            run = _summary(row, counts.get(row.id, (0, 0, None)))
            waiting.append(Waiting(run, None if cert is None else cert.number,
                                   None if cert is None else cert.issued_utc.isoformat(),
                                   run_attention(conn, row.id, row.uuid, row.metadata, revisions)))
    return Queue(tuple(waiting), dry)


# --- a run's results, as its certificate states them -----------------------------------------------
@dataclass(frozen=True)
class Revision:
    certificate_id: str
    number: str
    issued_utc: str
    approval: dict | None  # by, role, approved_utc (None: a draft)
    replaced: bool  # another revision replaces it
    documents: tuple[str, ...]  # the names the lab can give of it (`DOCUMENTS`)


@dataclass(frozen=True)
class Results:
    """What a finished run's certificate states, and its model's residuals recomputed."""

    number: str
    model: str  # "device model" or "linear model …"
    equation: str
    unit: str  # the outputs' unit
    coefficients: tuple[tuple[str, tuple[str, ...]], ...]  # (row, per sensor "value ± U")
    residual_se: tuple[str, ...]  # the certificate's residual standard error per sensor
    residual_rms: tuple[str, ...] | None  # the shown residuals' RMS per sensor (None: not recomputed)
    residual_ratio: tuple[float, ...] | None  # shown RMS / the certificate's residual standard error
    pitch_u95: str  # the attitude's U95 over the usage envelope (max)
    roll_u95: str | None
    verdict: str | None  # None: no tolerance given, no statement of conformity
    passed: bool | None
    attention: tuple[str, ...]
    approval: dict | None
    revisions: tuple[Revision, ...]
    sensors: tuple[str, ...] = ("x", "y", "z")  # the columns: a package's sensors (Tripp & Tcheng §6)


def _in_unit(value: float, unit: str) -> str:
    return report_figures.in_volts(value, unit)


def _verdict(cert: Certificate) -> tuple[str | None, bool | None]:
    if cert.conformity is None:
        return None, None
    checks = "; ".join(f"{c.quantity} {c.value:.3g} {c.unit} (limit {c.limit:.3g} {c.unit}): "
                       f"{'pass' if c.passed else 'FAIL'}" for c in cert.conformity.checks)
    return ("PASS" if cert.conformity.passed else "FAIL") + f" — {checks}", cert.conformity.passed


def documents_of(conn: Connection, cert: Certificate, run_dir: str | None) -> tuple[str, ...]:
    names = lab_certificates.kept_names(conn, cert.certificate_id)
    if run_dir and _folder_holds(Path(run_dir), cert):
        names |= {n for n in (PDF, DCC) if (Path(run_dir) / n).is_file()}
    names |= {CERTIFICATE, DCC}  # the JSON is held; the DCC is written from it
    return tuple(n for n in DOCUMENTS if n in names)


def _folder_holds(run_dir: Path, cert: Certificate) -> bool:
    """The run folder's certificate is this revision, as issued (its digest), so its report is too."""
    try:
        doc = json.loads((run_dir / CERTIFICATE).read_bytes())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and (doc.get("digest") or {}).get("value") == cert.digest.value \
        and doc.get("certificate_id") == cert.certificate_id


def approval_of(cert: Certificate) -> dict | None:
    if cert.approval is None:
        return None
    stated = cert.to_json()["approval"]
    return {"by": stated["by"], "role": stated["role"], "approved_utc": stated["approved_utc"]}


def run_results(lab: LabDatabase, run_id: int) -> Results | None:
    """A complete run's certificate as the lab holds it (None: no run, or no certificate yet)."""
    with lab.engine.connect() as conn:
        row = lab_view.run_place(conn, run_id=run_id)
        if row is None or row.uuid is None:
            return None
        revisions = run_revisions(conn, row.uuid)
        cert = _current(revisions)
        if cert is None:
            return None
        replaced = {c.replaces for c in revisions if c.replaces}
        listed = tuple(Revision(c.certificate_id, c.number, c.issued_utc.isoformat(), approval_of(c),
                                c.number in replaced, documents_of(conn, c, row.run_dir))
                       for c in reversed(revisions))
        noted = run_attention(conn, run_id, row.uuid, row.metadata, revisions)
        shown = certified_residuals(conn, run_id, cert)
    unit = cert.output_unit
    X, U = cert.coefficients, cert.U
    sensors = cert.sensors
    rows = tuple((ROW_NAMES[i], tuple(format_result(float(X[i, j]), float(U[i, j]))
                                      for j in range(len(sensors))))
                 for i in range(min(len(ROW_NAMES), X.shape[0])))
    se = np.array(cert.fit.residual_standard_error, dtype=float)
    rms = ratio = None
    if shown is not None:
        values = np.sqrt(np.mean(shown.residuals ** 2, axis=0))
        rms = tuple(_in_unit(float(v), unit) for v in values)
        ratio = tuple(float(v / s) if s > 0 else float("inf") for v, s in zip(values, se, strict=True))
    name, equation = (shown.model, shown.equation) if shown is not None else (
        "device model" if cert.fit.model == "device" else "linear model", "")
    verdict, passed = _verdict(cert)
    roll = cert.attitude.roll_U95_max_deg
    return Results(cert.number, name, equation, unit, rows, tuple(_in_unit(float(s), unit) for s in se),
                   rms, ratio, f"{cert.attitude.pitch_U95_max_deg * 3600:.3g}″",
                   None if roll is None else f"{roll * 3600:.3g}″", verdict, passed,
                   noted, approval_of(cert), listed, sensors)


# --- a revision's documents --------------------------------------------------------------------------
def certificate_document(lab: LabDatabase, certificate_id: str, name: str) -> tuple[str, bytes] | None:
    """One document of one certificate revision, with its media type (None: no such revision, or the
    lab cannot give that document of it; see the module for where each comes from)."""
    if name not in MEDIA:
        return None
    with lab.engine.connect() as conn:
        stored = lab_certificates.kept_file(conn, certificate_id, name)
        if stored is not None:
            return MEDIA[name], stored
        document = lab_certificates.certificate_text(conn, certificate_id)
        cert = None if document is None else parsed_certificate(document, f"certificate {certificate_id}")
        if cert is None:
            return None
        journal = cert.data.journal
        place = None if journal is None else lab_view.run_place(conn, uuid=journal.run_uuid)
        run_dir = None if place is None else place.run_dir
    if name == CERTIFICATE:
        return MEDIA[name], str(document).encode("utf-8")
    # an approval binds its DCC by digest: a folder's DCC edited since is not the one approved
    signed = cert.approval.dcc_sha256 if cert.approval is not None else None
    if run_dir and _folder_holds(Path(run_dir), cert) and (Path(run_dir) / name).is_file():
        found = (Path(run_dir) / name).read_bytes()
        if name != DCC or signed is None or hashlib.sha256(found).hexdigest() == signed:
            return MEDIA[name], found
    if name == DCC:
        written = dcc.dcc_document(cert)
        if signed is None or hashlib.sha256(written).hexdigest() == signed:
            return MEDIA[name], written
    return None


def residual_plot(lab: LabDatabase, run_id: int) -> bytes | None:
    """PNG of the run's residuals under its certificate's model (`labcal.app.residuals`; the readings
    so far under the linear fit while it has none); None: too few readings to fit."""
    with lab.engine.connect() as conn:
        place = lab_view.run_place(conn, run_id=run_id)
        uuid = None if place is None else place.uuid
        cert = _current(run_revisions(conn, uuid)) if uuid else None
        return residual_png(conn, run_id, cert)
