"""Horizontal sections of the cloud before and after the drift correction, coloured by time.

A section is a band of ``band_m`` around a height ``z``; every point in it is binned into a raster
of the horizontal plane (row 0 at the largest y: north up in a projected frame). Each pixel keeps
the number of points and the sum of their relative times, so a wall seen twice, minutes apart and
shifted by the drift, shows as two lines of two colours before the correction and one line after.
Memory is the rasters only (8 bytes per pixel), whatever the number of points.
"""

from __future__ import annotations

import dataclasses
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

    def render(self, title: str, duration_s: float) -> Image:
        """The section as an RGB image: points coloured by time, with the title, a scale bar, a
        north arrow (+y up) and the time colour bar."""
        return render_time_image(self.mean_time(), self.grid.pixel_m, title, duration_s)


def render_time_image(mean_time: FloatArray, pixel_m: float, title: str, duration_s: float) -> Image:
    """An RGB image of relative times in [0, 1] (NaN: empty, white) with its furniture."""
    h, w = mean_time.shape
    scale = font_scale(np.empty((h, w, 0), dtype=np.uint8))
    top, bottom = 12 * scale, 16 * scale  # strips for the title and for the scale and colour bars
    image = np.empty((h + top + bottom, w, 3), dtype=np.uint8)
    image[:] = WHITE
    full = np.isfinite(mean_time)
    image[top:top + h][full] = colour_map(mean_time[full])
    draw_label(image, title)
    draw_scale_bar(image, pixel_m)
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
