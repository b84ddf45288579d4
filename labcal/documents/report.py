"""The calibration report's files, and everything an issue writes: the certificate, its DCC, the
report (HTML and PDF) and the history entry, through one function.

The report shows what the certificate states and the evidence behind it, made of its tables
(`labcal.documents.report_tables`) and figures (`labcal.documents.report_figures`), each figure
drawn once and carried by the HTML page (`labcal.documents.report_html`) and the PDF
(`labcal.documents.report_pdf`) alike. The certificate itself is built by
`labcal.documents.issuing`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.fit import Fit
from labcal.config.files import write_atomic
from labcal.config.settings import CertificateSettings
from labcal.documents.administration import ItemGiven
from labcal.documents.certificate import Certificate, read_certificate, write_certificate
from labcal.documents.device_history import store_device_estimate
from labcal.documents.issuing import build_certificate, changed_fields, identification, kept_identification
from labcal.documents.report_figures import draw, figures
from labcal.documents.report_html import render_html
from labcal.documents.report_pdf import render_pdf
from labcal.documents.report_tables import Table
from labcal.documents.uncertainty import bench_section, type_b_inputs
from labcal.errors import LabcalError
from labcal.run.exports import run_fits
from labcal.run.record import RunRecord, load_run

CERTIFICATE = "certificate.json"
REPORT_HTML = "report.html"
REPORT_PDF = "report.pdf"


def write_report(directory: Path, cert: Certificate, record: RunRecord, fit: Fit,
                 device: DeviceFit | None = None) -> tuple[Path, Path]:
    """``device``: the device model's fit, where the plan identifies it (its tables and residuals are
    appended: `labcal.documents.device_report`). Each figure is drawn once, for the HTML and the PDF."""
    figures_drawn = figures(cert, record, fit, device)
    extra: tuple[Table, ...] = ()
    if device is not None:
        from labcal.documents.device_report import device_rows, residuals_side_by_side

        extra = tuple(Table(*parts) for parts in device_rows(device))
        figures_drawn.append(("Residuals of the linear and of the device model",
                              residuals_side_by_side(device, record)))
    figs = [draw(title, fig) for title, fig in figures_drawn]
    html_path, pdf_path = directory / REPORT_HTML, directory / REPORT_PDF
    write_atomic(html_path, render_html(cert, figs, extra))  # whole or not at all: a kill never cuts a report
    write_atomic(pdf_path, render_pdf(cert, figs, extra))
    return html_path, pdf_path


# --- what a run leaves behind ------------------------------------------------------------------
@dataclass(frozen=True)
class RunOutputs:
    certificate: Certificate
    certificate_path: Path
    html_path: Path
    pdf_path: Path
    database: Path
    notes: tuple[str, ...] = ()  # what checking the run folder against the journal repaired
    dcc_path: Path | None = None
    compared_with: str | None = None  # the certificate this issue replaced in the run directory
    changes: tuple[str, ...] = ()  # its identification fields that differ, in words


def write_run_outputs(run_dir: str | Path, settings: CertificateSettings | None = None, *,
                      serial: str | None = None, operator: str | None = None,
                      db: str | Path | None = None, station: str | Path | None = None,
                      monte_carlo: int = 0, item: ItemGiven | None = None,
                      record: RunRecord | None = None) -> RunOutputs:
    """Certificate, report and history entry of a finished run (called at the end of `labcal run`
    and by `labcal report`); ``db`` None means $LABCAL_DB or the lab file's database. The Type B
    inputs come from ``station`` (a station file), else the station the run was journaled with;
    ``monte_carlo`` trials check the budget by JCGM 101. ``record``: the run as `load_run` read it
    just before (the end of a run: read once for the device's estimate and for this, not fitted twice)."""
    record = record or load_run(run_dir)
    if record.fit is not None and len(record.fit.sensors) < 3:
        raise LabcalError(f"{run_dir}: a package of the {', '.join(record.fit.sensors)} sensor(s) only: its "
                          "statement is package.json (written at the end of its run), not the three-axis "
                          "certificate, whose attitude budget needs three sensors")
    fit, device, model_note = fitted(record)
    if device is None:  # a plan that corrects for the device: not from a correction the run saw move
        from labcal.documents.device_history import refuse_if_moved

        refuse_if_moved(record, fit)
    section = bench_section(record, station)
    inputs = type_b_inputs(section, record, device)
    revision, replaced = 1, None
    previous = _issued(record.directory / CERTIFICATE)
    if previous is not None and previous.approval is not None:
        # An approved certificate is never changed: what follows is a correction, a new revision
        # naming the one it replaces; the approved one stays beside it and in the history.
        revision, replaced = (previous.revision or 1) + 1, previous
        write_file(record.directory / f"certificate.rev{previous.revision or 1}.json", previous)
    elif previous is not None and (previous.revision or 1) > 1:
        # a revision's draft reported again is still that revision, replacing the same approved one
        revision, replaced = previous.revision or 1, replaced_by(record.directory, previous)
    item, serial, operator = kept_identification(previous, item or ItemGiven(), serial, operator)
    from labcal.documents.numbering import lab_number

    number = (previous.lab_number if previous is not None and previous.lab_number else
              lab_number(record, serial, db))  # a run keeps its number through reissues and revisions
    cert = build_certificate(record, fit, settings, serial=serial, operator=operator, inputs=inputs,
                             monte_carlo=monte_carlo, revision=revision,
                             replaces=None if replaced is None else replaced.number, section=section,
                             item=item, device=device, model_note=model_note, replaced=replaced,
                             lab_number=number)
    outputs = write_documents(cert, record, fit, device, db)
    if previous is None:
        return outputs
    return replace(outputs, compared_with=previous.number,
                   changes=tuple(changed_fields(identification(previous), identification(cert))))


def replaced_by(directory: Path, cert: Certificate) -> Certificate | None:
    """The approved certificate a revision replaces, as kept beside it in the run directory
    (``certificate.revN.json``); None for a first issue."""
    if not cert.replaces:
        return None
    path = directory / f"certificate.rev{(cert.revision or 1) - 1}.json"
    kept = read_certificate(path) if path.is_file() else None
    if kept is None or kept.number != cert.replaces:
        raise LabcalError(f"{path}: the certificate {cert.number} replaces ({cert.replaces}) is not kept "
                          "there")
    return kept


def fitted(record: RunRecord) -> tuple[Fit, DeviceFit | None, str]:
    """The linear fit, the device model where the points identify it, and the note saying which of
    them the run's fit.json holds: those `load_run` derived fit.json from, else fitted here."""
    if record.fit is not None:
        return record.fit, record.device, record.model_note
    return run_fits(record.readings, record.plan_text, record.station)


def _issued(path: Path) -> Certificate | None:
    """The certificate already in the run directory, if one is there and reads back intact."""
    if not path.is_file():
        return None
    try:
        return read_certificate(path)
    except LabcalError:
        return None  # a damaged draft is replaced; an approved one would have read back


def write_file(path: Path, cert: Certificate) -> Path:
    """The one place a certificate document is written (atomic replace; see write_certificate)."""
    return write_certificate(path, cert)


def write_documents(cert: Certificate, record: RunRecord, fit: Fit, device: DeviceFit | None,
                    db: str | Path | None = None) -> RunOutputs:
    """Every file an issue (or an approval) writes: certificate, report, history entry — through one
    function, so that making them one transaction changes one place. ``device``: the device model
    the certificate rests on (`fitted`), None where the linear model is used."""
    from labcal.documents import history
    from labcal.documents.dcc import DCC_FILE, write_dcc

    dcc_path = write_dcc(record.directory / DCC_FILE, cert)  # validated first: a bad one stops it all
    html_path, pdf_path = write_report(record.directory, cert, record, fit, device)
    # The history entry and the certificate file go together: the entry is committed first and the
    # file is the entry's document, so a kill between them leaves a history entry without its file
    # (`outputs_in_place` sees it; resume or report writes it again), never a certificate that
    # history does not know.
    database = history.store(cert, db)
    if device is not None:
        store_device_estimate(record, device, db)
    cert_path = write_file(record.directory / CERTIFICATE, cert)
    return RunOutputs(cert, cert_path, html_path, pdf_path, database, notes=record.notes, dcc_path=dcc_path)


def outputs_in_place(run_dir: str | Path, db: str | Path | None = None) -> bool:
    """Whether a complete run's certificate, its report and its history entry are all there and
    are of the run's current readings (after a kill during `labcal report` one may be missing)."""
    from labcal.documents import history
    from labcal.documents.dcc import DCC_FILE

    run_dir = Path(run_dir)
    if not all((run_dir / name).is_file() for name in (CERTIFICATE, DCC_FILE, REPORT_HTML, REPORT_PDF)):
        return False
    try:
        cert = read_certificate(run_dir / CERTIFICATE)
        record = load_run(run_dir)
    except LabcalError:
        return False
    return (cert.data.readings_sha256 == record.readings_sha256
            and history.stored_digest(cert.certificate_id, db) == cert.digest.value)
