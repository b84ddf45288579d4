"""The certificate's PDF, typeset by reportlab's platypus: a document a national laboratory would
sign, not a terminal dump.

Why reportlab and not WeasyPrint (which would print the HTML report as it is): reportlab is pure
Python with wheels on PyPI, so `pip install labcal` is all a station needs; WeasyPrint needs the
system's Pango, HarfBuzz and fontconfig libraries (a station's package manager, not pip) and lays
out through CSS at several times the cost. The HTML report stays the on-screen document; the PDF
is typeset here from the same tables, paragraphs and figures.

Layout: A4 portrait, DejaVu Sans (it ships with matplotlib and has every character the certificate
uses: σ, ν, ″, ᵀ, −, …), subset-embedded by reportlab; no text under 8 pt; table cells are
paragraphs, so long values (an address, a customer's name, a path) wrap within their column instead
of shrinking; every page has a header with the certificate number and status (wrapped onto more
lines where a long serial makes it wider than the page, never shrunk) and a footer "page X of Y";
a draft carries DRAFT across every page; the last text page ends with the signature block.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Protocol
from xml.sax.saxutils import escape

import matplotlib
from reportlab import rl_config
from reportlab.lib.colors import HexColor
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.pdfbase import pdfmetrics
from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.pdfbase.ttfonts import TTFont
from reportlab.pdfgen.canvas import Canvas
from reportlab.platypus import (
    Image,
    KeepTogether,
    PageBreak,
    Paragraph,
    SimpleDocTemplate,
    Spacer,
    Table,
    TableStyle,
)

BODY_PT = 9.0  # body text and table cells
SMALL_PT = 8.0  # captions, header and footer: the smallest text on any page
MARGIN_MM = 16.0
RED = "#b3261e"
GRID = "#9a9a9a"
SHADE = "#eceff3"


class TableLike(Protocol):
    @property
    def title(self) -> str: ...
    @property
    def header(self) -> list[str]: ...
    @property
    def rows(self) -> list[list[str]]: ...
    @property
    def caption(self) -> str: ...
    @property
    def emphasis(self) -> set[tuple[int, int]]: ...


class FigureLike(Protocol):
    @property
    def title(self) -> str: ...
    @property
    def size_in(self) -> tuple[float, float]: ...
    @property
    def png(self) -> bytes: ...


@dataclass(frozen=True)
class CertificateDocument:
    """What the PDF says, in reading order; the report module fills it from the certificate."""

    heading: str  # "Calibration certificate"
    number: str  # the certificate number with its revision
    status: str  # "DRAFT — not approved" or "approved by … on …"
    draft: bool
    first_lines: list[str]  # said at the top of page 1, in bold (a simulated run, a verdict)
    alerts: list[str]  # said on page 1 in red (an overdue reference standard)
    tables: Sequence[TableLike]
    paragraphs: list[str]
    figures: Sequence[FigureLike]
    signature: list[tuple[str, str]]  # (label, value) of the signature block
    title: str  # the PDF's metadata
    subject: str


@cache
def _fonts() -> tuple[str, str]:
    """Register DejaVu Sans and its bold from matplotlib's data folder (no font of the system is
    assumed); reportlab embeds the subset of glyphs a document uses."""
    folder = Path(matplotlib.get_data_path()) / "fonts" / "ttf"
    pdfmetrics.registerFont(TTFont("LabcalSans", str(folder / "DejaVuSans.ttf")))
    pdfmetrics.registerFont(TTFont("LabcalSans-Bold", str(folder / "DejaVuSans-Bold.ttf")))
    pdfmetrics.registerFontFamily("LabcalSans", normal="LabcalSans", bold="LabcalSans-Bold",
                                  italic="LabcalSans", boldItalic="LabcalSans-Bold")
    return "LabcalSans", "LabcalSans-Bold"


def _styles() -> dict[str, Any]:
    regular, bold = _fonts()
    return {
        "body": ParagraphStyle("body", fontName=regular, fontSize=BODY_PT, leading=BODY_PT * 1.3,
                               spaceAfter=4),
        "h1": ParagraphStyle("h1", fontName=bold, fontSize=16, leading=20, spaceAfter=2),
        "h2": ParagraphStyle("h2", fontName=bold, fontSize=11, leading=14, spaceBefore=10, spaceAfter=4,
                             keepWithNext=True),
        "lead": ParagraphStyle("lead", fontName=bold, fontSize=10.5, leading=14, spaceAfter=3),
        "alert": ParagraphStyle("alert", fontName=bold, fontSize=BODY_PT, leading=BODY_PT * 1.3,
                                textColor=HexColor(RED), spaceAfter=3),
        "cell": ParagraphStyle("cell", fontName=regular, fontSize=SMALL_PT, leading=SMALL_PT * 1.25),
        "head": ParagraphStyle("head", fontName=bold, fontSize=SMALL_PT, leading=SMALL_PT * 1.25),
        "caption": ParagraphStyle("caption", fontName=regular, fontSize=SMALL_PT, leading=SMALL_PT * 1.3,
                                  textColor=HexColor("#444444"), spaceBefore=2, spaceAfter=6),
    }


def _text(value: str) -> str:
    """Plain text as a platypus paragraph's markup: escaped, line breaks kept."""
    return escape(value).replace("\n", "<br/>")


def _column_widths(t: TableLike, width: float, styles: dict[str, Any]) -> list[float]:
    """Each column at least as wide as its longest word (a word is never broken inside), at most as
    wide as its longest cell; what is left of the frame goes to the columns whose text wraps, in
    proportion to what more they would take. Only a table whose words alone overflow the frame is
    scaled down to fit (and then breaks words)."""
    pad = 6.0  # left + right padding of a cell

    def measure(text: str, font: str) -> tuple[float, float]:
        words = text.split() or [""]
        return (max(stringWidth(w, font, SMALL_PT) for w in words) + pad,
                max(stringWidth(line, font, SMALL_PT) for line in text.splitlines() or [""]) + pad)

    cells = [[measure(h, styles["head"].fontName) for h in t.header]]
    cells += [[measure(row[j] if j < len(row) else "", styles["cell"].fontName) for j in range(len(t.header))]
              for row in t.rows]
    least = [max(c[j][0] for c in cells) for j in range(len(t.header))]
    most = [max(c[j][1] for c in cells) for j in range(len(t.header))]
    if sum(most) <= width:
        return most
    if sum(least) >= width:
        return [width * w / sum(least) for w in least]
    more = [m - lo for m, lo in zip(most, least, strict=True)]
    spare = width - sum(least)
    return [lo + spare * m / sum(more) for lo, m in zip(least, more, strict=True)]


def _table(t: TableLike, width: float, styles: dict[str, Any]) -> list[Any]:
    """A table whose cells wrap at word boundaries within the frame (`_column_widths`)."""
    ncol = len(t.header)
    rows = [[Paragraph(_text(h), styles["head"]) for h in t.header]]
    rows += [[Paragraph(_text(row[j]) if j < len(row) else "", styles["cell"]) for j in range(ncol)]
             for row in t.rows]
    widths = _column_widths(t, width, styles)
    style = [("FONT", (0, 0), (-1, -1), styles["cell"].fontName, SMALL_PT),
             ("GRID", (0, 0), (-1, -1), 0.4, HexColor(GRID)),
             ("BACKGROUND", (0, 0), (-1, 0), HexColor(SHADE)),
             ("VALIGN", (0, 0), (-1, -1), "TOP"),
             ("TOPPADDING", (0, 0), (-1, -1), 2), ("BOTTOMPADDING", (0, 0), (-1, -1), 2),
             ("LEFTPADDING", (0, 0), (-1, -1), 3), ("RIGHTPADDING", (0, 0), (-1, -1), 3)]
    style += [("BACKGROUND", (j, i + 1), (j, i + 1), HexColor("#f9d6d5")) for i, j in t.emphasis]
    table = Table(rows, colWidths=widths, repeatRows=1, style=TableStyle(style), hAlign="LEFT")
    parts: list[Any] = [Paragraph(_text(t.title), styles["h2"]), table]
    if t.caption:
        parts.append(Paragraph(_text(t.caption), styles["caption"]))
    return [KeepTogether(parts)] if len(t.rows) <= 12 else parts


def _figure(fig: FigureLike, width: float, height: float, styles: dict[str, Any]) -> list[Any]:
    w_in, h_in = fig.size_in
    scale = min(width / w_in, (height - 40) / h_in)
    return [KeepTogether([Paragraph(_text(fig.title), styles["h2"]),
                          Image(io.BytesIO(fig.png), width=w_in * scale, height=h_in * scale)])]


def render(doc: CertificateDocument) -> bytes:
    """The PDF's bytes, typeset once: each page's "of Y" is written when the document is saved and
    its number of pages known (`_counting_canvas`), not by typesetting everything twice."""
    styles = _styles()
    regular, bold = _fonts()
    page_w, page_h = A4
    margin = MARGIN_MM * mm
    frame_w, frame_h = page_w - 2 * margin, page_h - 2 * margin - 10 * mm

    def story() -> list[Any]:  # made anew for each pass: platypus consumes its flowables
        flowables: list[Any] = [Paragraph(_text(doc.heading), styles["h1"]),
                                Paragraph(_text(f"{doc.number} · {doc.status}"), styles["body"])]
        flowables += [Paragraph(_text(line), styles["lead"]) for line in doc.first_lines]
        flowables += [Paragraph(_text(line), styles["alert"]) for line in doc.alerts]
        for t in doc.tables:
            flowables += _table(t, frame_w, styles)
        flowables.append(Paragraph("Method and statements", styles["h2"]))
        flowables += [Paragraph(_text(p), styles["body"]) for p in doc.paragraphs]
        flowables.append(Spacer(1, 6 * mm))
        block = Table([[Paragraph(_text(label), styles["head"]), Paragraph(_text(value), styles["cell"])]
                       for label, value in doc.signature], colWidths=[frame_w * 0.28, frame_w * 0.72],
                      style=TableStyle([("FONT", (0, 0), (-1, -1), regular, SMALL_PT),
                                        ("BOX", (0, 0), (-1, -1), 0.8, HexColor("#333333")),
                                        ("LINEBELOW", (0, 0), (-1, -2), 0.3, HexColor(GRID)),
                                        ("VALIGN", (0, 0), (-1, -1), "TOP")]), hAlign="LEFT")
        flowables += [Paragraph("Signature", styles["h2"]), block]
        for fig in doc.figures:
            flowables += [PageBreak(), *_figure(fig, frame_w, frame_h, styles)]
        return flowables

    def page_of(canvas: Any, total: int) -> None:
        canvas.saveState()
        canvas.setFont(regular, SMALL_PT)
        canvas.setFillColor(HexColor("#000000"))
        canvas.drawRightString(page_w - margin, margin - 8 * mm, f"page {canvas.getPageNumber()} of {total}")
        canvas.restoreState()

    def decorate() -> Any:
        def on_page(canvas: Any, template: Any) -> None:
            canvas.saveState()
            canvas.setFont(bold, SMALL_PT)
            canvas.setFillColor(HexColor(RED) if doc.draft else HexColor("#000000"))
            lines = wrapped(f"{doc.heading} {doc.number} — {doc.status}", bold, SMALL_PT, page_w - 2 * margin)
            for k, line in enumerate(reversed(lines)):  # upwards from the header's line, into the margin
                canvas.drawString(margin, page_h - margin + 2 * mm + k * SMALL_PT * 1.25, line)
            canvas.setFont(regular, SMALL_PT)
            canvas.setFillColor(HexColor("#000000"))
            canvas.drawString(margin, margin - 8 * mm, doc.subject)
            if doc.draft:
                canvas.setFillColor(HexColor(RED), alpha=0.13)
                canvas.setFont(bold, 110)
                canvas.translate(page_w / 2, page_h / 2)
                canvas.rotate(35)
                canvas.drawCentredString(0, -40, "DRAFT")
            canvas.restoreState()
        return on_page

    out = io.BytesIO()
    template = SimpleDocTemplate(out, pagesize=A4, leftMargin=margin, rightMargin=margin,
                                 topMargin=margin + 4 * mm, bottomMargin=margin, title=doc.title,
                                 subject=doc.subject, author="labcal", creator="labcal",
                                 initialFontName=regular, initialFontSize=BODY_PT)  # no Helvetica
    ascii85 = rl_config.useA85
    rl_config.useA85 = 0  # binary streams: ASCII85 (reportlab's default, in pure Python without its
    try:  # optional C accelerator) makes the file a quarter larger and took half a second per report
        template.build(story(), onFirstPage=decorate(), onLaterPages=decorate(),
                       canvasmaker=_counting_canvas(page_of))
    finally:
        rl_config.useA85 = ascii85
    return out.getvalue()


def wrapped(text: str, font: str, size: float, width: float) -> list[str]:
    """``text`` in lines no wider than ``width`` points in ``font`` at ``size`` (reportlab's metrics), broken
    at spaces, and within a word longer than a line (a long serial, a certificate number) between
    characters."""
    def fits(line: str) -> bool:
        return stringWidth(line, font, size) <= width

    lines: list[str] = []
    line = ""
    for word in text.split(" "):
        candidate = f"{line} {word}" if line else word
        if fits(candidate):
            line = candidate
            continue
        if line:
            lines.append(line)
        line = ""
        while not fits(word):  # break the word itself: as many characters as fit on each line
            cut = next((n for n in range(len(word), 0, -1) if fits(word[:n])), 1)
            lines.append(word[:cut])
            word = word[cut:]
        line = word
    return [*lines, line] if line or not lines else lines


def _counting_canvas(finish_page: Callable[[Any, int], None]) -> type:
    """A reportlab canvas that holds each finished page until the document is saved, then lets
    ``finish_page(canvas, total)`` add what needs the number of pages (reportlab's own recipe for
    "page x of y" in one pass)."""
    class CountingCanvas(Canvas):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._held: list[dict[str, Any]] = []

        def showPage(self) -> None:  # noqa: N802 - reportlab's name
            self._held.append(dict(self.__dict__))
            self._startPage()

        def save(self) -> None:
            for state in self._held:
                self.__dict__.update(state)
                finish_page(self, len(self._held))
                super().showPage()
            super().save()

    return CountingCanvas
