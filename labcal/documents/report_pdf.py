"""The certificate and report as a PDF, typeset by `labcal.documents.typeset` (reportlab) from the
same tables and figures as the HTML page.
"""

from __future__ import annotations

from labcal.config.dates import written_time_utc
from labcal.documents.certificate import Certificate
from labcal.documents.report_figures import DrawnFigure
from labcal.documents.report_tables import (
    SIMULATED_WORD,
    Table,
    overdue_standards,
    status_text,
    tables,
    verdict_text,
)
from labcal.documents.typeset import CertificateDocument, render


def render_pdf(cert: Certificate, figs: list[DrawnFigure], extra: tuple[Table, ...] = ()) -> bytes:
    """The certificate typeset (`labcal.documents.typeset`): identification and verdict first, every
    table, the method and statements, the signature block, then one page per figure (its PNG, as
    drawn for the HTML); every page says "page X of Y" and, until it is approved, DRAFT."""
    a = cert.approval
    signature = [("Approved by", f"{a.by} ({a.role})" if a else "not yet approved — DRAFT"),
                 ("Date", written_time_utc(a.approved_utc) if a else "—"),
                 ("Electronic signature", f"{a.algorithm}, key {a.key_id[:16]}…" if a else "—"),
                 *([("Signed through", f"the lab server's key ({a.server.signer}) for user "
                                      f"{a.server.user_id}, {a.server.authentication}; "
                                      f"meaning: {a.server.meaning}")]
                   if a is not None and a.server is not None else []),
                 ("Certificate content", f"sha256 {cert.digest.value}")]
    return render(CertificateDocument(
        heading=f"{SIMULATED_WORD} — Calibration certificate" if cert.notice else "Calibration certificate",
        number=cert.number, status=status_text(cert), draft=cert.draft,
        first_lines=[*([cert.notice] if cert.notice else []), verdict_text(cert)],
        alerts=overdue_standards(cert), tables=[*tables(cert), *extra],
        paragraphs=[cert.method, *cert.statements, *cert.fit.notes], figures=figs, signature=signature,
        title=f"Calibration certificate {cert.certificate_id}",
        subject=f"instrument {cert.instrument.serial}"))
