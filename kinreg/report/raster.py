"""Raster figures without a plotting library: a PNG encoder (numpy + zlib), a time colour map,
a 5x7 bitmap font, scale bar, north arrow and colour bar drawn into RGB arrays.

The images of :mod:`kinreg.report.sections` and :mod:`kinreg.report.thickness` are made here;
everything works on ``(height, width, 3)`` uint8 arrays, row 0 at the top.
"""

from __future__ import annotations

import struct
import zlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

Image = NDArray[np.uint8]

WHITE = (255, 255, 255)
BLACK = (0, 0, 0)

# Anchors of a perceptually ordered colour map (viridis-like: dark blue, teal, green, yellow),
# early times dark, late times bright; a wall seen twice shows in two clearly different colours.
_ANCHORS = np.array([
    (68, 1, 84), (59, 82, 139), (33, 145, 140), (94, 201, 98), (253, 231, 37),
], dtype=np.float64)
# Sequential map for thickness (light yellow to dark red).
_HEAT = np.array([(255, 255, 204), (254, 217, 118), (253, 141, 60), (227, 26, 28), (128, 0, 38)], dtype=np.float64)


def colour_map(values: NDArray[np.floating[Any]], heat: bool = False) -> Image:
    """RGB (n, 3) uint8 for ``values`` in [0, 1] (clipped; NaN as 0).

    >>> colour_map(np.array([0.0, 1.0])).tolist()
    [[68, 1, 84], [253, 231, 37]]
    """
    anchors = _HEAT if heat else _ANCHORS
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64)), 0.0, 1.0) * (len(anchors) - 1)
    k = np.minimum(v.astype(np.int64), len(anchors) - 2)
    f = (v - k)[:, None]
    return np.round(anchors[k] * (1 - f) + anchors[k + 1] * f).astype(np.uint8)


def encode_png(image: Image) -> bytes:
    """PNG bytes (8-bit RGB, no interlace) of an ``(h, w, 3)`` uint8 array."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    h, w, channels = image.shape
    if channels != 3:
        raise ValueError("encode_png expects an (h, w, 3) RGB array")
    raw = np.zeros((h, 1 + 3 * w), dtype=np.uint8)  # filter byte 0 (none) before each row
    raw[:, 1:] = image.reshape(h, 3 * w)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))


# 5x7 glyphs, one string of 7 rows of 5 bits per character.
_FONT = {
    "0": "01110 10001 10011 10101 11001 10001 01110", "1": "00100 01100 00100 00100 00100 00100 01110",
    "2": "01110 10001 00001 00010 00100 01000 11111", "3": "11110 00001 00001 01110 00001 00001 11110",
    "4": "00010 00110 01010 10010 11111 00010 00010", "5": "11111 10000 11110 00001 00001 10001 01110",
    "6": "00110 01000 10000 11110 10001 10001 01110", "7": "11111 00001 00010 00100 01000 01000 01000",
    "8": "01110 10001 10001 01110 10001 10001 01110", "9": "01110 10001 10001 01111 00001 00010 01100",
    ".": "00000 00000 00000 00000 00000 01100 01100", "-": "00000 00000 00000 11111 00000 00000 00000",
    "=": "00000 00000 11111 00000 11111 00000 00000", " ": "00000 00000 00000 00000 00000 00000 00000",
    "m": "00000 00000 11010 10101 10101 10101 10101", "s": "00000 00000 01111 10000 01110 00001 11110",
    "z": "00000 00000 11111 00010 00100 01000 11111", "t": "01000 01000 11100 01000 01000 01001 00110",
    "A": "01110 10001 10001 11111 10001 10001 10001", "B": "11110 10001 10001 11110 10001 10001 11110",
    "C": "01110 10001 10000 10000 10000 10001 01110", "E": "11111 10000 10000 11110 10000 10000 11111",
    "F": "11111 10000 10000 11110 10000 10000 10000", "H": "10001 10001 10001 11111 10001 10001 10001",
    "I": "01110 00100 00100 00100 00100 00100 01110", "K": "10001 10010 10100 11000 10100 10010 10001",
    "N": "10001 11001 10101 10011 10001 10001 10001", "O": "01110 10001 10001 10001 10001 10001 01110",
    "R": "11110 10001 10001 11110 10100 10010 10001", "S": "01111 10000 10000 01110 00001 00001 11110",
    "T": "11111 00100 00100 00100 00100 00100 00100", "V": "10001 10001 10001 10001 10001 01010 00100",
    "L": "10000 10000 10000 10000 10000 10000 11111", "D": "11100 10010 10001 10001 10001 10010 11100",
    "P": "11110 10001 10001 11110 10000 10000 10000", "U": "10001 10001 10001 10001 10001 10001 01110",
    "W": "10001 10001 10001 10101 10101 10101 01010", "G": "01110 10001 10000 10111 10001 10001 01111",
    "M": "10001 11011 10101 10101 10001 10001 10001", "Y": "10001 10001 01010 00100 00100 00100 00100",
    "X": "10001 10001 01010 00100 01010 10001 10001", "Z": "11111 00001 00010 00100 01000 10000 11111",
    "J": "00111 00010 00010 00010 00010 10010 01100", "Q": "01110 10001 10001 10001 10101 10010 01101",
}
_GLYPHS = {c: np.array([[b == "1" for b in row] for row in rows.split()], dtype=bool) for c, rows in _FONT.items()}


def text_size(text: str, scale: int) -> tuple[int, int]:
    """(width, height) in pixels of ``text`` drawn with :func:`draw_text` at ``scale``."""
    return (6 * len(text) - 1) * scale, 7 * scale


def draw_text(image: Image, text: str, x: int, y: int, scale: int = 2, colour: tuple[int, int, int] = BLACK,
              box: bool = True) -> None:
    """``text`` with its top left corner at pixel (x, y); on a white box unless ``box`` is False.
    Characters without a glyph are drawn as spaces; pixels outside the image are skipped."""
    w, h = text_size(text, scale)
    if box:
        fill_rect(image, x - scale, y - scale, x + w + scale, y + h + scale, WHITE)
    for k, char in enumerate(text):
        glyph = _GLYPHS.get(char, _GLYPHS[" "])
        big = np.kron(glyph, np.ones((scale, scale), dtype=bool))
        x0 = x + 6 * k * scale
        _paint(image, big, x0, y, colour)


def _paint(image: Image, mask: NDArray[np.bool_], x0: int, y0: int, colour: tuple[int, int, int]) -> None:
    h, w = image.shape[:2]
    mh, mw = mask.shape
    xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + mw, w), min(y0 + mh, h)
    if xa >= xb or ya >= yb:
        return
    part = mask[ya - y0:yb - y0, xa - x0:xb - x0]
    image[ya:yb, xa:xb][part] = colour


def fill_rect(image: Image, x0: int, y0: int, x1: int, y1: int, colour: tuple[int, int, int]) -> None:
    """Fill the pixels x0 <= x < x1, y0 <= y < y1 (clipped to the image)."""
    h, w = image.shape[:2]
    ya, yb, xa, xb = (min(max(v, 0), limit) for v, limit in ((y0, h), (y1, h), (x0, w), (x1, w)))
    if ya < yb and xa < xb:
        image[ya:yb, xa:xb] = colour


def nice_length(target: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``target`` (a scale bar's length).

    >>> nice_length(7.3), nice_length(0.3), nice_length(120.0)
    (5.0, 0.2, 100.0)
    """
    if not target > 0:
        return 1.0
    exponent = np.floor(np.log10(target))
    for step in (5.0, 2.0, 1.0):
        if step * 10**exponent <= target * (1 + 1e-9):
            return float(step * 10**exponent)
    return float(10**exponent)


def font_scale(image: Image) -> int:
    """Glyph scale so that labels stay readable when the image is shown about 600 px wide."""
    return max(2, min(6, round(max(image.shape[:2]) / 330)))


def draw_scale_bar(image: Image, pixel_m: float) -> None:
    """A black and white bar of a round length (about a fifth of the width) in the bottom left."""
    h, w = image.shape[:2]
    scale = font_scale(image)
    length_m = nice_length(0.2 * w * pixel_m)
    length_px = max(round(length_m / pixel_m), 1)
    thick = 3 * scale
    x0, y1 = 4 * scale, h - 4 * scale
    fill_rect(image, x0 - scale, y1 - thick - 11 * scale, x0 + length_px + scale, y1 + scale, WHITE)
    fill_rect(image, x0, y1 - thick, x0 + length_px, y1, BLACK)
    fill_rect(image, x0 + length_px // 2, y1 - thick + scale, x0 + length_px - scale, y1 - scale, WHITE)
    label = f"{length_m:g} m"
    draw_text(image, label, x0, y1 - thick - 9 * scale, scale, box=False)


def draw_north_arrow(image: Image) -> None:
    """An arrow pointing up (+y of the frame) with an ``N`` to its left, in the top right corner."""
    w = image.shape[1]
    scale = font_scale(image)
    size = 9 * scale
    cx, top = w - 4 * scale - size // 2, 2 * scale
    fill_rect(image, cx - size // 2 - 8 * scale, top - scale, cx + size // 2 + scale, top + size + scale, WHITE)
    for r in range(size):  # a filled triangle, one pixel row at a time
        hw = r * (size // 2) // max(size - 1, 1)
        fill_rect(image, cx - hw, top + r, cx + hw + 1, top + r + 1, BLACK)
    draw_text(image, "N", cx - size // 2 - 7 * scale, top + size - 7 * scale, scale, box=False)


def draw_colour_bar(image: Image, left: str, right: str, heat: bool = False) -> None:
    """A horizontal colour bar with its two end labels in the bottom right corner."""
    h, w = image.shape[:2]
    scale = font_scale(image)
    length = max(w // 5, text_size(left, scale)[0] + text_size(right, scale)[0] + 4 * scale)
    length = min(length, w - 8 * scale)  # a narrow image: as wide as it allows
    if length < 2:
        return
    x0, y1 = w - 4 * scale - length, h - 4 * scale
    bar_h = 3 * scale
    fill_rect(image, x0 - scale, y1 - bar_h - 11 * scale, w - 3 * scale, y1 + scale, WHITE)
    colours = colour_map(np.linspace(0.0, 1.0, length), heat=heat)
    image[max(y1 - bar_h, 0):max(y1, 0), x0:x0 + length] = colours[None, :, :]
    draw_text(image, left, x0, y1 - bar_h - 9 * scale, scale, box=False)
    tw, _ = text_size(right, scale)
    draw_text(image, right, x0 + length - tw, y1 - bar_h - 9 * scale, scale, box=False)


def draw_label(image: Image, text: str) -> None:
    """A title in the top left corner."""
    scale = font_scale(image)
    draw_text(image, text, 4 * scale, 4 * scale, scale)
