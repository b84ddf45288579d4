"""The certificate's PDF, read back by a reader labcal did not write (pypdf): the text is there and
searchable, nothing is under 8 pt, long identification wraps instead of shrinking, fonts are subset
and embedded, every page says "page X of Y" and DRAFT until approved."""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np
from PIL import Image
from pypdf import PdfReader

from labcal.documents.typeset import CertificateDocument, render


@dataclass
class T:
    title: str
    header: list[str]
    rows: list[list[str]]
    caption: str = ""
    emphasis: set[tuple[int, int]] = field(default_factory=set)


@dataclass
class F:
    title: str
    size_in: tuple[float, float]
    png: bytes


LONG_ADDRESS = ("Calibration Laboratory for Inertial Sensors, Building 42, Room 3.117, "
                "Physikalisch-Technische Allee 100, 38116 Braunschweig-Nord, Federal Republic of Germany")


def _png(h: int = 300, w: int = 400) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(1).integers(0, 256, (h, w, 3), dtype=np.uint8)).save(buf, "png")
    return buf.getvalue()


def document(draft: bool = True, rows: int = 3, typed: str = "ACC-0042") -> CertificateDocument:
    ident = T("Identification", ["item", "value"],
              [["laboratory", LONG_ADDRESS], ["customer", typed], ["serial", typed]])
    coeffs = T("Coefficients", ["row", "x (V)", "y (V)", "z (V)"],
               [[f"S{i}", "+4.987150 ± 0.000019", "σ_prec ν_eff U95 ≤ 0.5″ Xᵀ −1.5e-06 µV", "±2°"]
                for i in range(rows)], caption="U = k·u with k = t₀.₉₇₅(ν_eff).", emphasis={(0, 1)})
    return CertificateDocument(
        heading="Calibration certificate", number="LC-2026-0001 rev. 1",
        status="DRAFT — not approved" if draft else "approved by A. Signer (metrologist) on 2026-11-26",
        draft=draft, first_lines=["PASS: within tolerance"], alerts=["Reference standard DMM was overdue"],
        tables=[ident, coeffs], paragraphs=["Method: Soto 2020, Tripp & Tcheng 1999."],
        figures=[F("Residuals", (8.0, 6.0), _png())], signature=[("Approved by", "not yet approved")],
        title=f"Calibration certificate {typed}", subject=f"instrument {typed}")


def sizes_and_text(pdf: bytes) -> list[tuple[list[float], str]]:
    """Per page, the effective size (pt) of every piece of text drawn, and the page's text."""
    pages = []
    for page in PdfReader(io.BytesIO(pdf)).pages:
        found: list[float] = []

        def visitor(text, cm, tm, font_dict, font_size, found=found):
            if text.strip():
                scale = float(np.hypot(tm[0], tm[1])) * float(np.hypot(cm[0], cm[1]))
                found.append(font_size * scale)
        text = page.extract_text(visitor_text=visitor)
        pages.append((found, text))
    return pages


def test_every_page_is_numbered_marked_draft_and_no_text_is_under_8_pt():
    pdf = render(document(rows=120))  # a long table: it runs over several pages and repeats its header
    pages = sizes_and_text(pdf)
    assert len(pages) >= 3
    for n, (sizes, text) in enumerate(pages, start=1):
        assert f"page {n} of {len(pages)}" in text
        assert "DRAFT" in text and "LC-2026-0001 rev. 1" in text
        assert min(sizes) >= 8.0 - 1e-6, (n, min(sizes))
    assert sum(text.count("x (V)") for _, text in pages[:-1]) >= 2  # the header row repeats


def test_long_identification_wraps_at_full_size_and_reads_back_whole():
    sizes, text = sizes_and_text(render(document()))[0]
    assert min(sizes) >= 8.0 - 1e-6
    joined = " ".join(text.split())
    assert " ".join(LONG_ADDRESS.split()) in joined  # every word, in order, though it wraps
    assert "σ_prec ν_eff U95 ≤ 0.5″ Xᵀ −1.5e-06 µV" in joined  # the font has the certificate's characters


def test_fonts_are_embedded_subsets_and_an_approved_certificate_has_no_draft_mark():
    pdf = render(document(draft=False))
    reader = PdfReader(io.BytesIO(pdf))
    fonts = set()
    for page in reader.pages:
        for font in page["/Resources"]["/Font"].values():
            font = font.get_object()
            fonts.add(str(font["/BaseFont"]))
            descendant = font["/DescendantFonts"][0].get_object() if "/DescendantFonts" in font else font
            descriptor = descendant.get("/FontDescriptor")
            assert descriptor is not None and any(k in descriptor.get_object() for k in
                                                  ("/FontFile2", "/FontFile", "/FontFile3")), font
    assert fonts and all("+" in f for f in fonts)  # "ABCDEF+Name": a subset (ISO 32000-1 §9.6.4)
    assert not any("DRAFT" in page.extract_text() for page in reader.pages)
    assert len(pdf) < len(_png()) + 150_000  # subset fonts: the PNG is most of it


def test_the_figure_is_on_its_own_page_at_its_aspect():
    reader = PdfReader(io.BytesIO(render(document())))
    (image,) = reader.pages[-1].images
    assert image.image.size == (400, 300)
    assert "Residuals" in reader.pages[-1].extract_text()


def test_what_people_type_cannot_break_the_document():
    """Names and serials go in as typed: markup characters, PDF delimiters, characters the font lacks."""
    typed = "O'Brien <b>(tech)</b> & \\ $x$ % <> 李 🙂 end"
    reader = PdfReader(io.BytesIO(render(document(typed=typed))))
    text = reader.pages[0].extract_text()
    assert "O'Brien <b>(tech)</b> & \\ $x$ % <>" in text and "end" in text
    assert reader.metadata.title == f"Calibration certificate {typed}"
