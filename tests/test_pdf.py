"""The report's PDF writer, read back by a reader labcal did not write (pypdf, with PIL for pixels)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image
from pypdf import PdfReader

from labcal.documents.pdf import RED, Page, Text, pdf_document, png_image


def _png(pixels: np.ndarray, mode: str = "RGB") -> bytes:
    buf = io.BytesIO()
    Image.fromarray(pixels).convert(mode).save(buf, format="png")
    return buf.getvalue()


def test_text_reads_back_as_written_unicode_included():
    lines = "σ_prec (V)  ν_eff  U95 ≤ 0.5″  Xᵀ — −1.5e-06 µV … ±2°\nsecond line, same font"
    pdf = pdf_document([Page((11.69, 8.27), [Text(0.03, 0.97, "heading — page 1 of 1", 9, bold=True,
                                                  colour=RED),
                                             Text(0.03, 0.93, lines, 6.4),
                                             Text(0.5, 0.5, "DRAFT", 90, va="center", ha="center",
                                                  rotation_deg=30, opacity=0.15)])],
                       "Calibration certificate Ω-1", "instrument S/N ü")
    reader = PdfReader(io.BytesIO(pdf))
    text = reader.pages[0].extract_text()
    assert "heading — page 1 of 1" in text and lines.splitlines()[0] in text
    assert "second line, same font" in text and "DRAFT" in text
    assert reader.metadata.title == "Calibration certificate Ω-1"
    assert reader.metadata.subject == "instrument S/N ü"
    assert [float(v) for v in reader.pages[0].mediabox] == pytest.approx([0, 0, 11.69 * 72, 8.27 * 72])


def test_a_png_is_carried_as_it_is_and_decodes_to_the_same_pixels():
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)  # noise: every PNG row filter is exercised
    pixels[:10] = 255
    png = _png(pixels)
    pdf = pdf_document([Page((5.3, 3.7), [Text(0.01, 0.001, "caption", 7, va="bottom")], png)], "t", "s")
    assert png_image(png)[2] in pdf  # the PNG's own compressed rows, not a re-encoding
    (image,) = PdfReader(io.BytesIO(pdf)).pages[0].images
    assert np.array_equal(np.asarray(image.image.convert("RGB")), pixels)


def test_a_line_too_wide_for_the_page_is_set_smaller_to_fit():
    wide = "x" * 400
    pdf = pdf_document([Page((11.69, 8.27), [Text(0.03, 0.93, wide, 6.4, max_width=0.94)])], "t", "s")
    words: list[tuple[float, float]] = []

    def visitor(text, cm, tm, font_dict, font_size):
        if text.strip():
            words.append((tm[4], tm[0] * font_size))
    PdfReader(io.BytesIO(pdf)).pages[0].extract_text(visitor_text=visitor)
    (x, size), = words
    # DejaVu Sans Mono advances 0.602 em per character (1233 of 2048 units)
    assert x + len(wide) * 0.602 * size == pytest.approx(0.97 * 11.69 * 72, rel=1e-3)


def test_only_rgb_pngs_are_taken():
    with pytest.raises(ValueError, match="8-bit RGB"):
        png_image(_png(np.zeros((4, 4, 3), np.uint8), "RGBA"))
    with pytest.raises(ValueError, match="not a PNG"):
        png_image(b"GIF89a")


def test_what_people_type_cannot_break_the_document():
    """Names and serials go into the PDF as typed: PDF's own delimiters and characters the font
    lacks (a box is drawn) leave a document that still reads back."""
    typed = "O'Brien (tech) \\ $x$ % <> 李 🙂 \t end"
    pdf = pdf_document([Page((8.27, 11.69), [Text(0.1, 0.9, typed, 9)])], typed, typed)
    reader = PdfReader(io.BytesIO(pdf))
    text = reader.pages[0].extract_text()
    assert "O'Brien (tech) \\ $x$ % <>" in text and "end" in text
    assert reader.metadata.title == typed
