"""Horizontal sections of the cloud before and after the drift correction, coloured by time.

A section is a band of ``band_m`` around a height ``z``; every point in it is binned into a raster
of the horizontal plane (row 0 at the largest y: north up in a projected frame). Each pixel keeps
the number of points and the sum of their relative times, so a wall seen twice, minutes apart and
shifted by the drift, shows as two lines of two colours before the correction and one line after.
Memory is the rasters only (8 bytes per pixel), whatever the number of points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import FloatArray
from kinreg.report.raster import (
    WHITE,
    Image,
    colour_map,
    draw_colour_bar,
    draw_label,
    draw_north_arrow,
    draw_scale_bar,
    font_scale,
)


@dataclasses.dataclass(frozen=True)
class Grid:
    """A horizontal raster: pixel (row, col) covers x in [x0 + col p, x0 + (col + 1) p) and
    y in (y1 - (row + 1) p, y1 - row p]."""

    x0: float
    y1: float
    pixel_m: float
    width: int
    height: int

    @classmethod
    def covering(cls, bounds_min: FloatArray, bounds_max: FloatArray, pixel_m: float, max_px: int,
                 margin_m: float = 0.5) -> Grid:
        """The raster over the horizontal bounds plus ``margin_m``, with pixels of ``pixel_m``
        or larger so that neither side exceeds ``max_px``."""
        lo, hi = np.asarray(bounds_min[:2], dtype=np.float64) - margin_m, np.asarray(bounds_max[:2]) + margin_m
        extent = np.maximum(hi - lo, pixel_m)
        pixel = max(pixel_m, float(np.max(extent)) / max_px)
        width, height = (int(v) for v in np.maximum(np.ceil(extent / pixel), 1))
        return cls(float(lo[0]), float(lo[1] + height * pixel), pixel, width, height)

    def flat_index(self, xy: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Flat pixel index of each point (n, >=2) and whether it falls inside the raster."""
        col = np.floor((xy[:, 0] - self.x0) / self.pixel_m).astype(np.int64)
        row = np.floor((self.y1 - xy[:, 1]) / self.pixel_m).astype(np.int64)
        inside = (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)
        return row * self.width + col, inside


class SectionRaster:
    """Point count and summed relative time (0: first point, 1: last) per pixel of one section."""

    def __init__(self, grid: Grid) -> None:
        self.grid = grid
        self.count = np.zeros(grid.width * grid.height, dtype=np.uint32)
        self.time_sum = np.zeros(grid.width * grid.height, dtype=np.float32)
        self.n_points = 0

    def add(self, xy: FloatArray, time01: NDArray[np.floating[Any]]) -> None:
        index, inside = self.grid.flat_index(xy)
        index, time01 = index[inside], time01[inside]
        if len(index) == 0:
            return
        pixels, inverse = np.unique(index, return_inverse=True)
        self.count[pixels] += np.bincount(inverse).astype(np.uint32)
        self.time_sum[pixels] += np.bincount(inverse, weights=time01).astype(np.float32)
        self.n_points += len(index)

    def mean_time(self) -> FloatArray:
        """Mean relative time per pixel (NaN where empty), shape (height, width)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.time_sum / self.count
        mean[self.count == 0] = np.nan
        return mean.reshape(self.grid.height, self.grid.width).astype(np.float64)

    def render(self, title: str, duration_s: float, places: Sequence[tuple[float, float, float]] = (),
               inset_m: float = 3.0, north: bool = True) -> Image:
        """The section as an RGB image: points coloured by time, the windows of ``places``
        outlined, with the title, a scale bar, a north arrow (+y up; none for a vertical section
        with ``north`` False) and the time colour bar."""
        def boxes(image: Image, top: int) -> None:
            draw_boxes(image, self.grid, top, places, inset_m)

        return render_time_image(self.mean_time(), self.grid.pixel_m, title, duration_s, boxes, north)


def title_strip_px(height: int, width: int) -> int:
    """Rows above the raster of :func:`render_time_image` (the title's strip; the bars get their own below)."""
    return 12 * font_scale(np.empty((height, width, 0), dtype=np.uint8))


def render_time_image(mean_time: FloatArray, pixel_m: float, title: str, duration_s: float,
                      overlay: Callable[[Image, int], None] | None = None, north: bool = True) -> Image:
    """An RGB image of relative times in [0, 1] (NaN: empty, white) with its furniture;
    ``overlay(image, top)`` draws onto the raster (starting ``top`` rows down) before the furniture."""
    h, w = mean_time.shape
    top, bottom = title_strip_px(h, w), 16 * font_scale(np.empty((h, w, 0), dtype=np.uint8))
    image = np.empty((h + top + bottom, w, 3), dtype=np.uint8)
    image[:] = WHITE
    full = np.isfinite(mean_time)
    image[top:top + h][full] = colour_map(mean_time[full])
    if overlay is not None:
        overlay(image, top)
    draw_label(image, title)
    draw_scale_bar(image, pixel_m)
    if north:
        draw_north_arrow(image)
    draw_colour_bar(image, "0 s", f"{duration_s:.0f} s")
    return image


def choose_heights(z: FloatArray, band_m: float) -> list[float]:
    """One section height where walls are most likely cut and little else: 1.0-1.5 m above the
    lowest floor, avoiding heights where a horizontal surface (table, stair) piles up points.

    The lowest floor is the lowest 5 cm bin holding at least a fifth of the fullest bin's points
    (floors and ceilings are the dense horizontal surfaces). Returns the middle of the cloud's
    height range when it is shorter than that.
    """
    z = np.asarray(z, dtype=np.float64)
    z = z[np.isfinite(z)]
    if len(z) == 0:
        return []
    lo, hi = (float(v) for v in np.percentile(z, [0.1, 99.9]))
    if hi - lo < 1.6:
        return [round(0.5 * (lo + hi), 2)]
    counts, edges = np.histogram(z, bins=np.arange(lo, hi + 0.05, 0.05))
    floor = float(edges[int(np.argmax(counts >= 0.2 * counts.max()))] + 0.025)
    candidates = floor + np.arange(1.0, 1.5001, 0.05)
    candidates = candidates[candidates < hi - band_m]
    if len(candidates) == 0:
        return [round(0.5 * (lo + hi), 2)]
    zs = np.sort(z)
    scores = (np.searchsorted(zs, candidates + band_m / 2) - np.searchsorted(zs, candidates - band_m / 2)).astype(float)
    scores[scores > 1.5 * np.median(scores)] = -1.0  # a horizontal surface in the band
    return [round(float(candidates[int(np.argmax(scores))]), 2)]


class CorrectionMap:
    """The mean horizontal correction of the section points per coarse cell (``cell_m``), to find
    the places where the correction is largest (the insets)."""

    def __init__(self, grid: Grid, cell_m: float = 1.0) -> None:
        factor = max(1, round(cell_m / grid.pixel_m))
        self.coarse = Grid(grid.x0, grid.y1, grid.pixel_m * factor, -(-grid.width // factor), -(-grid.height // factor))
        self.shift_sum = np.zeros(self.coarse.width * self.coarse.height)
        self.count = np.zeros(self.coarse.width * self.coarse.height)

    def add(self, xy_after: FloatArray, shift_m: FloatArray) -> None:
        index, inside = self.coarse.flat_index(xy_after)
        size = len(self.count)
        self.shift_sum += np.bincount(index[inside], weights=shift_m[inside], minlength=size)
        self.count += np.bincount(index[inside], minlength=size)

    def largest(self, n: int, min_points: int = 20, min_distance_m: float = 4.0) -> list[tuple[float, float, float]]:
        """Up to ``n`` places (x, y, mean correction [m]), largest first, ``min_distance_m`` apart."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(self.count >= min_points, self.shift_sum / self.count, -1.0)
        places: list[tuple[float, float, float]] = []
        for flat in np.argsort(mean)[::-1]:
            if mean[flat] < 0 or len(places) == n:
                break
            row, col = divmod(int(flat), self.coarse.width)
            x = self.coarse.x0 + (col + 0.5) * self.coarse.pixel_m
            y = self.coarse.y1 - (row + 0.5) * self.coarse.pixel_m
            if all(np.hypot(x - px, y - py) >= min_distance_m for px, py, _ in places):
                places.append((x, y, float(mean[flat])))
        return places


def crop(mean_time: FloatArray, grid: Grid, x: float, y: float, size_m: float) -> FloatArray:
    """The square window of ``size_m`` centred on (x, y) of a (height, width) raster, NaN outside."""
    half = round(size_m / grid.pixel_m / 2)
    col = int((x - grid.x0) / grid.pixel_m)
    row = int((grid.y1 - y) / grid.pixel_m)
    out = np.full((2 * half, 2 * half), np.nan)
    r0, c0 = row - half, col - half
    ra, rb = max(r0, 0), min(r0 + 2 * half, grid.height)
    ca, cb = max(c0, 0), min(c0 + 2 * half, grid.width)
    if ra < rb and ca < cb:
        out[ra - r0:rb - r0, ca - c0:cb - c0] = mean_time[ra:rb, ca:cb]
    return out


def enlarge(values: FloatArray, target_px: int) -> tuple[FloatArray, int]:
    """Each pixel repeated so that the larger side is about ``target_px``; returns the factor."""
    factor = max(1, target_px // max(values.shape))
    big = np.kron(values, np.ones((factor, factor))).astype(np.float64)
    return big, int(factor)


def draw_boxes(image: Image, grid: Grid, top_px: int, places: Sequence[tuple[float, float, float]],
               size_m: float) -> None:
    """Outline each inset's window on a section image (raster starting ``top_px`` below the top),
    numbered 1, 2, 3."""
    from kinreg.report.raster import BLACK, draw_text, fill_rect

    scale = font_scale(image)
    half = round(size_m / grid.pixel_m / 2)
    for k, (x, y, _) in enumerate(places):
        col = int((x - grid.x0) / grid.pixel_m)
        row = top_px + int((grid.y1 - y) / grid.pixel_m)
        x0, x1, y0, y1 = col - half, col + half, row - half, row + half
        for a, b, c, d in ((x0, y0, x1, y0 + scale), (x0, y1 - scale, x1, y1), (x0, y0, x0 + scale, y1),
                           (x1 - scale, y0, x1, y1)):
            fill_rect(image, a, b, c, d, (220, 0, 0))
        h, w = image.shape[:2]
        tx = min(max(x0 + 2 * scale, 2 * scale), w - 7 * scale)  # inside the box, inside the image
        ty = min(max(y0 + 2 * scale, 2 * scale), h - 9 * scale)
        draw_text(image, str(k + 1), tx, ty, scale, colour=BLACK)


def longest_straight_stretch(stamps_s: FloatArray, xy: FloatArray, tolerance_m: float = 0.3, step_s: float = 1.0,
                             min_length_m: float = 3.0) -> tuple[FloatArray, FloatArray] | None:
    """Start and end (x, y) of the longest stretch of the trajectory that stays within
    ``tolerance_m`` of the straight line between its ends (sampled every ``step_s``); ``None``
    when no stretch is ``min_length_m`` long."""
    if len(stamps_s) < 2:
        return None
    at = np.searchsorted(stamps_s, np.arange(stamps_s[0], stamps_s[-1], step_s))
    p = np.asarray(xy, dtype=np.float64)[np.clip(at, 0, len(stamps_s) - 1)]
    best, best_len = None, min_length_m
    for i in range(len(p) - 2):
        j = i + 2
        while j < len(p):
            chord = p[j] - p[i]
            length = float(np.hypot(chord[0], chord[1]))
            if length > 0:
                rel = p[i + 1:j] - p[i]
                off = np.abs(rel[:, 0] * chord[1] - rel[:, 1] * chord[0]) / length
                along = (rel @ chord) / length
                if off.max() > tolerance_m or along.min() < -tolerance_m or along.max() > length + tolerance_m:
                    break
                if length > best_len:
                    best, best_len = (p[i].copy(), p[j].copy()), length
            j += 1
    return best


@dataclasses.dataclass(frozen=True)
class VerticalPlane:
    """A vertical section: the line from ``start_xy`` to ``end_xy``, a band of ``band_m`` across it;
    its raster's x is the distance along the line, its y the height."""

    start_xy: FloatArray
    end_xy: FloatArray
    band_m: float

    @property
    def length_m(self) -> float:
        return float(np.hypot(*(self.end_xy - self.start_xy)))

    @property
    def azimuth_deg(self) -> float:
        """Direction of the line, clockwise from +y (north in a projected frame)."""
        d = self.end_xy - self.start_xy
        return float(np.degrees(np.arctan2(d[0], d[1])) % 360.0)

    def project(self, xyz: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(m, 2) (distance along the line, height) of the points inside the band, and which they are."""
        u = (self.end_xy - self.start_xy) / self.length_m
        x, y = xyz[:, 0] - self.start_xy[0], xyz[:, 1] - self.start_xy[1]  # contiguous columns: faster
        across = x * u[1]
        across -= y * u[0]
        inside = np.abs(across, out=across) <= 0.5 * self.band_m
        index = np.flatnonzero(inside)  # the band's few points, gathered column by column
        x, y = x.take(index), y.take(index)
        along = x * u[0] + y * u[1]
        return np.column_stack([along, xyz[:, 2].take(index)]), inside
