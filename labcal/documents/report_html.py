"""The report as one self-contained HTML file: inline CSS and inline PNG figures, so that it opens
offline and can be mailed alone. It carries the tables (`labcal.documents.report_tables`) and the
figures as drawn once (`labcal.documents.report_figures`).
"""

from __future__ import annotations

import base64
import html

from labcal.documents.certificate import Certificate
from labcal.documents.report_figures import DrawnFigure
from labcal.documents.report_tables import (
    SIMULATED_WORD,
    Table,
    status_text,
    tables,
    technician_notes,
    verdict_text,
)

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;max-width:1100px;margin:2em auto;color:#111;
line-height:1.4}
h1{font-size:1.5em;margin-bottom:0}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #bbb;padding:.25em .6em;text-align:right;font-variant-numeric:tabular-nums}
th:first-child,td:first-child{text-align:left}caption{caption-side:bottom;text-align:left;font-size:.85em;
color:#444;padding-top:.3em}td.fail{background:#fdd;font-weight:bold}
.verdict{font-size:1.3em;font-weight:bold;padding:.3em .6em;display:inline-block;border:2px solid}
.pass{color:#064;border-color:#064}.fail-v{color:#a00;border-color:#a00}.none{color:#555;border-color:#999}
img{max-width:100%}footer{margin-top:2em;font-size:.8em;color:#555;word-break:break-all}
@media print{h2{break-after:avoid}figure{break-inside:avoid}}
"""


def _html_table(t: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in t.header)
    fail = ' class="fail"'
    body = "".join(
        "<tr>" + "".join(f"<td{fail if (i, j) in t.emphasis else ''}>{html.escape(c)}</td>"
                         for j, c in enumerate(row)) + "</tr>"
        for i, row in enumerate(t.rows))
    caption = f"<caption>{html.escape(t.caption)}</caption>" if t.caption else ""
    return (f"<h2>{html.escape(t.title)}</h2><table>{caption}<thead><tr>{head}</tr></thead>"
            f"<tbody>{body}</tbody></table>")


def _png(fig: DrawnFigure) -> str:
    return base64.b64encode(fig.png).decode("ascii")


def render_html(cert: Certificate, figs: list[DrawnFigure], extra: tuple[Table, ...] = ()) -> str:
    """One HTML file with inline CSS and inline PNG plots: it opens offline and can be mailed alone."""
    verdict = verdict_text(cert)
    css_class = "none" if cert.conformity is None else ("pass" if cert.conformity.passed else "fail-v")
    simulated = f"{SIMULATED_WORD} — " if cert.notice else ""
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{simulated}Calibration "
             f"certificate {html.escape(cert.certificate_id)}</title><style>{CSS}</style></head><body>",
             *([f"<p class=\"verdict fail-v\">{html.escape(cert.notice)}</p>"] if cert.notice else []),
             f"<h1>Calibration certificate and report</h1><p>{html.escape(cert.number)} · "
             f"instrument {html.escape(cert.instrument.serial)} · "
             f"<strong>{html.escape(status_text(cert))}</strong></p>"
             f"<p class=\"verdict {css_class}\">{html.escape(verdict)}</p>"]
    notes = technician_notes(cert)
    parts += [_html_table(t) for t in (*tables(cert), *extra, *([notes] if notes else []))]
    parts.append("<h2>Method</h2>" + "".join(f"<p>{html.escape(p)}</p>" for p in
                                             (cert.method, *cert.statements, *cert.fit.notes)))
    for fig in figs:
        title = fig.title
        parts.append(f"<h2>{html.escape(title)}</h2><figure><img alt=\"{html.escape(title)}\" "
                     f"src=\"data:image/png;base64,{_png(fig)}\"></figure>")
    parts.append(f"<footer>End of report {html.escape(cert.certificate_id)}. Certificate content sha256 "
                 f"{cert.digest.value} (certificate.json holds the full-precision values and covariances)."
                 "</footer></body></html>")
    return "\n".join(parts)
