"""The report's PDF, written directly: pages of monospaced text and pages carrying a PNG as drawn.

matplotlib's PDF backend laid out and embedded every character of the report's text pages glyph by
glyph (most of a report's cost after the figures), and re-encoded each figure's pixels. Here the
text is one embedded TrueType font (DejaVu Sans Mono, which ships with matplotlib and covers the
report's σ, ν, ″, ᵀ, −, …) addressed by glyph id with a ToUnicode map, so the text is searchable
and copyable; and a figure's PNG goes in as it is — PDF's Flate filter with the PNG predictor reads
the PNG's own compressed rows (ISO 32000-1 §7.4.4.4), so nothing is encoded twice.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

POINTS_PER_INCH = 72.0
LINE_SPACING = 1.2  # baseline to baseline, in font sizes (matplotlib's default for multi-line text)
BOLD_STROKE = 0.03  # outline width, in font sizes, that makes the one font read as bold
RED = (0.839, 0.153, 0.157)  # matplotlib's tab:red
BLACK = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Text:
    """Lines of text at (x, y) in fractions of the page, anchored like matplotlib's text: ``va``
    "top" (the first line's top at y), "bottom" (the last line's bottom) or "center"."""

    x: float
    y: float
    text: str
    size: float
    va: str = "top"
    ha: str = "left"
    colour: tuple[float, float, float] = BLACK
    bold: bool = False
    rotation_deg: float = 0.0
    opacity: float = 1.0
    max_width: float | None = None  # fraction of the page width; a longer text gets a smaller size


@dataclass
class Page:
    """One page: its size in inches, an optional PNG filling it, and text on top."""

    size_in: tuple[float, float]
    texts: list[Text] = field(default_factory=list)
    png: bytes | None = None


@dataclass(frozen=True)
class Font:
    path: Path
    data: bytes
    glyphs: dict[int, int]  # code point -> glyph id
    advance: int  # per 1000 units of the font size (an integer, as PDF's /DW): the font is monospaced
    ascent: float
    descent: float
    bbox: tuple[float, float, float, float]
    name: str


@cache
def monospace() -> Font:
    import matplotlib
    from matplotlib.ft2font import FT2Font

    path = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSansMono.ttf"
    font = FT2Font(str(path))
    scale = 1000.0 / font.units_per_EM
    x0, y0, x1, y1 = (v * scale for v in font.bbox)
    return Font(path, path.read_bytes(), {int(c): int(g) for c, g in font.get_charmap().items()},
                round(font.max_advance_width * scale), font.ascender * scale, font.descender * scale,
                (x0, y0, x1, y1), font.postscript_name)


def png_image(png: bytes) -> tuple[int, int, bytes]:
    """Width, height and the concatenated IDAT data of an 8-bit RGB, non-interlaced PNG."""
    if png[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG")
    pos, idat, header = 8, bytearray(), None
    while pos < len(png):
        length, kind = struct.unpack(">I4s", png[pos:pos + 8])
        body = png[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    if header is None or header[2:5] != (8, 2, 0) or header[6] != 0:
        raise ValueError("the PDF carries 8-bit RGB non-interlaced PNGs only")
    return header[0], header[1], bytes(idat)


def _string(text: str) -> bytes:
    """A PDF text string (document information): UTF-16BE with its byte order mark, in hex."""
    return b"<FEFF" + text.encode("utf-16-be").hex().upper().encode() + b">"


def _number(x: float) -> bytes:
    return f"{x:.3f}".rstrip("0").rstrip(".").encode()


class _Writer:
    def __init__(self) -> None:
        self.objects: list[bytes] = []

    def add(self, body: bytes) -> int:
        self.objects.append(body)
        return len(self.objects)

    def stream(self, data: bytes, entries: bytes = b"", compress: bool = True) -> int:
        if compress:
            data = zlib.compress(data, 6)
            entries += b" /Filter /FlateDecode"
        return self.add(b"<< /Length %d%s >>\nstream\n%s\nendstream" % (len(data), entries, data))

    def reserve(self) -> int:
        return self.add(b"")

    def set(self, number: int, body: bytes) -> None:
        self.objects[number - 1] = body

    def document(self, root: int, info: int) -> bytes:
        out = bytearray(b"%PDF-1.7\n%\xe2\xe3\xcf\xd3\n")
        offsets = []
        for n, body in enumerate(self.objects, start=1):
            offsets.append(len(out))
            out += b"%d 0 obj\n%s\nendobj\n" % (n, body)
        xref = len(out)
        out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(self.objects) + 1)
        out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
        out += b"trailer\n<< /Size %d /Root %d 0 R /Info %d 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (
            len(self.objects) + 1, root, info, xref)
        return bytes(out)


def _text_ops(t: Text, width: float, height: float, font: Font, used: set[tuple[int, int]]) -> bytes:
    """The operators that draw ``t``; the (glyph, code point) pairs it uses are added to ``used``."""
    lines = t.text.split("\n")
    columns = max(len(line) for line in lines)
    size = t.size if t.max_width is None or columns == 0 else min(
        t.size, t.max_width * width / (columns * font.advance / 1000))
    leading = size * LINE_SPACING
    ascent, descent = font.ascent * size / 1000, -font.descent * size / 1000
    block = ascent + descent + leading * (len(lines) - 1)
    # the first baseline, below the block's top by the ascent; the anchor as matplotlib places it
    top = {"top": 0.0, "center": block / 2, "bottom": block}[t.va]
    widest = columns * font.advance * size / 1000
    left = {"left": 0.0, "center": widest / 2, "right": widest}[t.ha]
    ax, ay = t.x * width, t.y * height
    c, s = math.cos(math.radians(t.rotation_deg)), math.sin(math.radians(t.rotation_deg))
    dx, dy = -left, top - ascent  # from the anchor to the first baseline, in the text's own frame
    x0, y0 = ax + c * dx - s * dy, ay + s * dx + c * dy
    r, g, b = (_number(v) for v in t.colour)
    ops = [b"q", b"/GS%d gs" % round(t.opacity * 100) if t.opacity < 1 else b"",
           b"%s %s %s rg %s %s %s RG" % (r, g, b, r, g, b), b"BT", b"/F1 %s Tf" % _number(size),
           b"%s TL" % _number(leading),
           b"2 Tr %s w" % _number(BOLD_STROKE * size) if t.bold else b"0 Tr",
           b"%s %s %s %s %s %s Tm" % tuple(_number(v) for v in (c, s, -s, c, x0, y0))]
    for n, line in enumerate(lines):
        ids = [font.glyphs.get(ord(ch), 0) for ch in line]
        used.update((gid, ord(ch)) for gid, ch in zip(ids, line, strict=True))
        ops.append(b"%s<%s> Tj" % (b"T* " if n else b"", "".join(f"{i:04X}" for i in ids).encode()))
    ops += [b"ET", b"Q"]
    return b"\n".join(op for op in ops if op)


def _to_unicode(used: set[tuple[int, int]]) -> bytes:
    pairs = sorted(dict(used).items())
    chunks = [pairs[i:i + 100] for i in range(0, len(pairs), 100)]  # at most 100 per bfchar block
    body = "".join(f"{len(chunk)} beginbfchar\n" + "".join(
        f"<{gid:04X}> <{chr(cp).encode('utf-16-be').hex().upper()}>\n" for gid, cp in chunk) + "endbfchar\n"
        for chunk in chunks)
    return ("/CIDInit /ProcSet findresource begin 12 dict begin begincmap\n"
            "/CIDSystemInfo << /Registry (Adobe) /Ordering (UCS) /Supplement 0 >> def\n"
            "/CMapName /Adobe-Identity-UCS def /CMapType 2 def\n"
            "1 begincodespacerange <0000> <FFFF> endcodespacerange\n"
            f"{body}endcmap CMapName currentdict /CMap defineresource pop end end\n").encode()


def pdf_document(pages: list[Page], title: str, subject: str) -> bytes:
    """The whole PDF: every page's PNG as an image filling it, its texts on top."""
    font, w = monospace(), _Writer()
    catalog, tree, font_ref = w.reserve(), w.reserve(), w.reserve()
    used: set[tuple[int, int]] = set()
    opacities = sorted({round(t.opacity * 100) for p in pages for t in p.texts if t.opacity < 1})
    states = b" ".join(b"/GS%d << /ca %s /CA %s >>" % (o, _number(o / 100), _number(o / 100))
                       for o in opacities)
    kids = []
    for page in pages:
        width, height = (v * POINTS_PER_INCH for v in page.size_in)
        ops, xobjects = [], b""
        if page.png is not None:
            columns, rows, data = png_image(page.png)
            # the PNG's own zlib stream; /Predictor 15 undoes its rows' filters
            image = w.stream(data, b" /Type /XObject /Subtype /Image /Width %d /Height %d /ColorSpace "
                             b"/DeviceRGB /BitsPerComponent 8 /Filter /FlateDecode /DecodeParms << "
                             b"/Predictor 15 /Colors 3 /BitsPerComponent 8 /Columns %d >>"
                             % (columns, rows, columns), compress=False)
            xobjects = b" /XObject << /Im1 %d 0 R >>" % image
            ops.append(b"q %s 0 0 %s 0 0 cm /Im1 Do Q" % (_number(width), _number(height)))
        ops += [_text_ops(t, width, height, font, used) for t in page.texts]
        content = w.stream(b"\n".join(ops))
        kids.append(w.add(b"<< /Type /Page /Parent %d 0 R /MediaBox [0 0 %s %s] /Contents %d 0 R /Resources "
                          b"<< /Font << /F1 %d 0 R >>%s%s >> >>" % (
                              tree, _number(width), _number(height), content, font_ref, xobjects,
                              b" /ExtGState << %s >>" % states if states else b"")))
    references = b" ".join(b"%d 0 R" % k for k in kids)
    w.set(tree, b"<< /Type /Pages /Kids [%s] /Count %d >>" % (references, len(kids)))
    w.set(catalog, b"<< /Type /Catalog /Pages %d 0 R >>" % tree)
    file = w.stream(font.data, b" /Length1 %d" % len(font.data))
    bbox = b" ".join(_number(v) for v in font.bbox)
    descriptor = w.add(b"<< /Type /FontDescriptor /FontName /%s /Flags 33 /FontBBox [%s] /ItalicAngle 0 "
                       b"/Ascent %s /Descent %s /CapHeight %s /StemV 80 /FontFile2 %d 0 R >>" % (
                           font.name.encode(), bbox, _number(font.ascent), _number(font.descent),
                           _number(font.ascent), file))
    cid = w.add(b"<< /Type /Font /Subtype /CIDFontType2 /BaseFont /%s /CIDSystemInfo << /Registry (Adobe) "
                b"/Ordering (Identity) /Supplement 0 >> /FontDescriptor %d 0 R /DW %d "
                b"/CIDToGIDMap /Identity >>" % (font.name.encode(), descriptor, font.advance))
    unicode = w.stream(_to_unicode(used))
    w.set(font_ref, b"<< /Type /Font /Subtype /Type0 /BaseFont /%s /Encoding /Identity-H /DescendantFonts "
                    b"[%d 0 R] /ToUnicode %d 0 R >>" % (font.name.encode(), cid, unicode))
    info = w.add(b"<< /Title %s /Subject %s /Producer (labcal) >>" % (_string(title), _string(subject)))
    return w.document(catalog, info)
