"""The calibration report's files, and everything an issue writes: the certificate, its DCC, the
report (HTML and PDF) and the history entry, through one function.

The report shows what the certificate states and the evidence behind it, made of its tables
(`labcal.documents.report_tables`) and figures (`labcal.documents.report_figures`), each figure
drawn once and carried by the HTML page (`labcal.documents.report_html`) and the PDF
(`labcal.documents.report_pdf`) alike. The certificate itself is built by
`labcal.documents.issuing`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.fit import Fit
from labcal.config.files import write_atomic
from labcal.documents import history
from labcal.documents.certificate import Certificate, read_certificate, write_certificate
from labcal.documents.dcc import DCC_FILE, write_dcc
from labcal.documents.device_history import store_device_estimate
from labcal.documents.report_tables import Table
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.exports import run_fits
from labcal.store.record import RunRecord, load_run

if TYPE_CHECKING:
    from labcal.documents import device_report, report_figures, report_html, report_pdf
else:
    device_report = lazy("labcal.documents.device_report")  # start-up without scipy, numpy, pydantic
    # matplotlib and reportlab: a command that approves, lists or verifies draws no report
    report_figures = lazy("labcal.documents.report_figures")
    report_html = lazy("labcal.documents.report_html")
    report_pdf = lazy("labcal.documents.report_pdf")

CERTIFICATE = "certificate.json"
REPORT_HTML = "report.html"
REPORT_PDF = "report.pdf"


def write_report(directory: Path, cert: Certificate, record: RunRecord, fit: Fit,
                 device: DeviceFit | None = None) -> tuple[Path, Path]:
    """``device``: the device model's fit, where the plan identifies it (its tables and residuals are
    appended: `labcal.documents.device_report`). Each figure is drawn once, for the HTML and the PDF."""
    figures_drawn = report_figures.figures(cert, record, fit, device)
    extra: tuple[Table, ...] = ()
    if device is not None:
        extra = tuple(Table(*parts) for parts in device_report.device_rows(device))
        figures_drawn.append(("Residuals of the linear and of the device model",
                              device_report.residuals_side_by_side(device, record)))
    figs = [report_figures.draw(title, fig) for title, fig in figures_drawn]
    html_path, pdf_path = directory / REPORT_HTML, directory / REPORT_PDF
    # whole or not at all: a kill never cuts a report
    write_atomic(html_path, report_html.render_html(cert, figs, extra))
    write_atomic(pdf_path, report_pdf.render_pdf(cert, figs, extra))
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


def write_file(path: Path, cert: Certificate) -> Path:
    """The one place a certificate document is written (atomic replace; see write_certificate)."""
    return write_certificate(path, cert)


def write_documents(cert: Certificate, record: RunRecord, fit: Fit, device: DeviceFit | None,
                    db: str | Path | None = None) -> RunOutputs:
    """Every file an issue (or an approval) writes: certificate, report, history entry — through one
    function, so that making them one transaction changes one place. ``device``: the device model
    the certificate rests on (`fitted`), None where the linear model is used."""
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
