"""The PDF's running header stays on the page whatever the serial's length: each line drawn at the top
of every page, measured with reportlab's own font metrics at the position and size the PDF draws it,
ends inside the page's right margin, and none of the certificate number is lost."""

from __future__ import annotations

import io
from dataclasses import replace

from pypdf import PdfReader
from reportlab.lib.pagesizes import A4
from reportlab.lib.units import mm
from reportlab.pdfbase.pdfmetrics import stringWidth
from test_typeset import document

from labcal.documents.typeset import MARGIN_MM, _fonts, render

LONG_SERIAL = "ACC-" + "7" * 60  # the longest serial labcal takes (64 characters)


def header_lines(pdf: bytes) -> list[list[tuple[float, float, float, str]]]:
    """Per page, every piece of text drawn above the body's frame: (x, y, size, text)."""
    page_h = A4[1]
    pages = []
    for page in PdfReader(io.BytesIO(pdf)).pages:
        found: list[tuple[float, float, float, str]] = []

        def visitor(text, cm, tm, font_dict, font_size, found=found):
            x, y = tm[4] * cm[0] + cm[4], tm[5] * cm[3] + cm[5]
            if text.strip() and y > page_h - MARGIN_MM * mm:
                found.append((x, y, font_size * tm[0] * cm[0], text.strip()))
        page.extract_text(visitor_text=visitor)
        pages.append(found)
    return pages


def test_a_long_serials_running_header_ends_inside_the_right_margin_on_every_page():
    number = f"{LONG_SERIAL}-20261127T211232Z-b2174f32 rev. 1"
    doc = replace(document(rows=120, typed=LONG_SERIAL), number=number)
    _, bold = _fonts()
    right_edge = A4[0] - MARGIN_MM * mm
    pages = header_lines(render(doc))
    assert len(pages) >= 3
    for found in pages:
        assert found, "no header drawn"
        for x, _, size, text in found:
            assert size >= 8.0 - 1e-6  # wrapped, never shrunk below the document's smallest text
            end = x + stringWidth(text, bold, size)
            assert end <= right_edge + 0.5, (text, end, right_edge)  # half a point: the PDF's rounding
        drawn = "".join(text for *_, text in sorted(found, key=lambda f: -f[1]))  # top line first
        assert number.replace(" ", "") in drawn.replace(" ", "")
