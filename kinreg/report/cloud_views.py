"""What the report shows of the point cloud itself, gathered while ``corrected.laz`` is written.

:class:`CloudViews` receives every chunk of points twice, as read and as corrected (``add``), and
keeps only rasters and per-cell moments (bounded memory, no extra pass over the cloud). At the end,
:meth:`CloudViews.finish` writes the PNG figures into ``DIR/figures/`` and returns the
``report.json`` entries:

- ``cloud.sections``: horizontal sections before and after, coloured by time
  (:mod:`kinreg.report.sections`), at ``[report] section_heights_m`` or one height chosen from the
  first chunk of points (:func:`~kinreg.report.sections.choose_heights`);
- ``cloud.vertical_section``: a vertical section before and after along the longest straight
  stretch of the (first run's) trajectory;
- ``cloud.thickness``: the plane-thickness map and the median ratio after/before over the cells
  planar in both (:mod:`kinreg.report.thickness`);
- ``cloud.per_point``: plan-view maps of the median per column of each point's 3D position sigma
  and of its correction length, the two extra-bytes dimensions of corrected.laz
  (:class:`ColumnMedians`);
- ``cloud.static_deviations`` (with ``--static``): signed distances of the kinematic points to the
  static cloud's local planes before and after (:mod:`kinreg.report.deviations`);
- ``crs``: the coordinate reference system of the input cloud (:mod:`kinreg.report.crs`).

The same entries are kept in ``DIR/figures/cloud.json``, with the seconds the views took
(``seconds``: ``gather`` while corrected.laz is written, ``figures`` in :meth:`CloudViews.finish`;
CPU seconds of the thread doing them, because the cloud's decoding and encoding run on other
threads alongside and would count in wall time; not in report.json, which holds only what does
not depend on how the run got there): a resumed run whose corrected cloud is still current (not
written again) shows them from there.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.config import ReportConfig
from kinreg.geometry import FloatArray
from kinreg.io.atomic import atomic_path
from kinreg.report.crs import describe_crs
from kinreg.report.deviations import Deviations, StaticPlanes
from kinreg.report.json import _clean
from kinreg.report.raster import (
    WHITE,
    Image,
    colour_map,
    draw_colour_bar,
    draw_label,
    draw_north_arrow,
    draw_scale_bar,
    encode_png,
    font_scale,
)
from kinreg.report.sections import (
    CorrectionMap,
    Grid,
    SectionRaster,
    VerticalPlane,
    choose_heights,
    crop,
    enlarge,
    longest_straight_stretch,
    render_time_image,
)
from kinreg.report.thickness import CellMoments, column_map, compare
from kinreg.survey import ReferencePlanes
from kinreg.types import Trajectory

log = logging.getLogger(__name__)

FIGURES_DIR = "figures"
SUMMARY_NAME = "cloud.json"
INSETS, INSET_M = 3, 3.0  # zoomed windows of the first section where the correction is largest, their size
MIN_CELL_POINTS = 50  # points of a planar cell (1 m cell at 5 mm noise: the thickness to ~10 %)
# At most about this many points enter the thickness map (every n-th beyond): hundreds per planar
# 1 m cell of a building; every 2nd to 4th point of a 20 M-point run moved the median ratio by
# 0.0005 at most (benchmarks/RESULTS.md), and the sums are most of the views' cost.
THICKNESS_POINTS = 8_000_000
BLOCK_POINTS = 1 << 16  # points per block of the rasters
PER_POINT_MAX_PX = 160  # columns per side of the per-point maps at most (coarser cells beyond)
# Bins of the per-point values' histograms [mm]: below the first edge, then geometric up to 100 m
# (a bin is 30 % wide: the median to +-15 %, enough for a colour map).
PER_POINT_LOW_MM, PER_POINT_BINS = 0.01, 64
_PER_POINT_FACTOR = (1e5 / PER_POINT_LOW_MM) ** (1.0 / (PER_POINT_BINS - 2))
PER_POINT_POINTS = 2_000_000
PER_POINT_MAPS = {"sigma_3d": "3D POSITION SIGMA", "correction": "CORRECTION LENGTH"}


class ColumnMedians:
    """The median of a per-point value [mm] over each column of a plan-view grid, from a histogram
    per column in :data:`PER_POINT_BINS` logarithmic bins (bounded memory: at most
    :data:`PER_POINT_MAX_PX` squared columns, 4 bytes per bin, whatever the number of points)."""

    def __init__(self, grid: Grid) -> None:
        self.grid = grid
        self.counts = np.zeros(grid.width * grid.height * PER_POINT_BINS, dtype=np.uint32)
        self.n_points = 0
        self.largest_mm = 0.0

    def add(self, xy: FloatArray, values_mm: FloatArray) -> None:
        """Points (n, >=2) in the plan and their values (n,) [mm]; non-finite values are left out."""
        index, inside = self.grid.flat_index(xy)
        inside &= np.isfinite(values_mm)
        if not inside.any():
            return
        values = np.maximum(np.asarray(values_mm, dtype=np.float64)[inside], PER_POINT_LOW_MM * 0.5)
        bins = np.floor(np.log(values / PER_POINT_LOW_MM) / math.log(_PER_POINT_FACTOR)).astype(np.int64) + 1
        np.clip(bins, 0, PER_POINT_BINS - 1, out=bins)
        flat = index[inside] * PER_POINT_BINS + bins
        # over the span of bins the chunk touches (a chunk is a few seconds of the walk: a small
        # part of the map), not a fresh array of every bin per chunk
        lo = int(flat.min())
        per_bin = np.bincount(flat - lo)
        span = self.counts[lo:lo + len(per_bin)]
        np.add(span, per_bin, out=span, casting="unsafe")
        self.n_points += len(flat)
        self.largest_mm = max(self.largest_mm, float(values.max()))

    def medians_mm(self) -> FloatArray:
        """(height, width): each column's median [mm] (the centre of its median bin, on the log
        scale); NaN for a column without points."""
        counts = self.counts.reshape(-1, PER_POINT_BINS).astype(np.int64)
        total = counts.sum(axis=1)
        median_bin = (np.cumsum(counts, axis=1) >= (total[:, None] + 1) // 2).argmax(axis=1)
        centre = PER_POINT_LOW_MM * _PER_POINT_FACTOR ** (median_bin - 0.5)
        centre[median_bin == 0] = 0.0
        centre[total == 0] = np.nan
        return centre.reshape(self.grid.height, self.grid.width)


class CloudViews:
    """Sections and plane thickness of a cloud before and after its correction (see the module).

    ``bounds_min``/``bounds_max``: the object-frame box of all points (the rasters cover it plus
    half a metre); ``t0_s``/``t1_s``: the time range that colours run from; ``crs``: the CRS
    entry of ``report.json`` (:func:`kinreg.report.crs.describe_crs`).
    """

    def __init__(self, config: ReportConfig, bounds_min: FloatArray, bounds_max: FloatArray, t0_s: float,
                 t1_s: float, crs: dict[str, Any] | None = None, static_planes: StaticPlanes | None = None,
                 vertical: VerticalPlane | None = None, n_points_total: int = 0) -> None:
        self.config = config
        # Every n-th point enters the thickness map: [report] thickness_stride, or more so that
        # about THICKNESS_POINTS of the n_points_total do.
        self.thickness_stride = max(config.thickness_stride, int(n_points_total) // THICKNESS_POINTS)
        self.grid = Grid.covering(bounds_min, bounds_max, config.section_pixel_m, config.section_max_px)
        self.t0_s, self.duration_s = float(t0_s), max(float(t1_s) - float(t0_s), 1e-9)
        self.heights: list[float] | None = list(config.section_heights_m) or None
        self.automatic = not config.section_heights_m
        self.rasters: dict[tuple[float, str], SectionRaster] = {}
        self.corrections = CorrectionMap(self.grid)  # of the first section's points
        self.vertical = vertical
        if vertical is not None:
            lo = np.array([-1.0, float(bounds_min[2]) - 0.3])
            hi = np.array([vertical.length_m + 1.0, float(bounds_max[2]) + 0.3])
            self.vertical_grid = Grid.covering(lo, hi, config.section_pixel_m, config.section_max_px, margin_m=0.0)
            self.vertical_rasters = {w: SectionRaster(self.vertical_grid) for w in ("before", "after")}
        origin = np.asarray(bounds_min, dtype=np.float64) - 1.0  # corrected points may leave the input's box
        extent = np.asarray(bounds_max, dtype=np.float64) + 1.0 - origin
        self.moments = {which: CellMoments(origin, config.thickness_cell_m, extent) for which in ("before", "after")}
        self.crs = crs or {}
        self.deviations = None if static_planes is None else Deviations(static_planes)
        # Columns of at least the thickness map's cell, coarser where the cloud is wide.
        map_grid = Grid.covering(bounds_min, bounds_max, config.thickness_cell_m, PER_POINT_MAX_PX)
        self.per_point = {name: ColumnMedians(map_grid) for name in PER_POINT_MAPS}
        # Every n-th point enters them: about PER_POINT_POINTS of the n_points_total (a median per
        # column of at most 160 x 160 needs far fewer than the thickness map's sums).
        self.per_point_stride = max(1, int(n_points_total) // PER_POINT_POINTS)
        self.n_points = 0
        self.seconds = {"gather": 0.0, "figures": 0.0}  # in add (while corrected.laz is written), in finish

    def add(self, xyz_before: FloatArray, xyz_after: FloatArray, stamps_s: FloatArray,
            sigma_mm: FloatArray | None = None, correction_mm: FloatArray | None = None) -> None:
        """One chunk: object-frame points (n, 3) as read and as corrected, their times (n,), and
        (optional) their 3D position sigmas and correction lengths (n,) [mm]."""
        if not self.config.cloud_views or len(stamps_s) == 0:
            return
        start = time.thread_time()
        if self.heights is None:
            self.heights = choose_heights(xyz_before[::7, 2], self.config.section_band_m)
        stamps_s = np.asarray(stamps_s, dtype=np.float64)
        # The rasters in blocks whose temporaries (the times in [0, 1] among them) stay in the cache
        # (fresh arrays of a whole chunk cost more than the arithmetic: the kernel maps and zeroes
        # their pages).
        for a in range(0, len(stamps_s), BLOCK_POINTS):
            block = slice(a, a + BLOCK_POINTS)
            time01 = ((stamps_s[block] - self.t0_s) / self.duration_s).astype(np.float32)
            self._add_to_rasters(xyz_before[block], xyz_after[block], time01)
        stride = self.thickness_stride
        for which, xyz in (("before", xyz_before), ("after", xyz_after)):
            self.moments[which].add(xyz[::stride] if stride > 1 else xyz)
            if self.deviations is not None:
                self.deviations.add(which, xyz)
        if sigma_mm is not None and correction_mm is not None:
            every = self.per_point_stride
            self.per_point["sigma_3d"].add(xyz_after[::every], sigma_mm[::every])
            self.per_point["correction"].add(xyz_after[::every], correction_mm[::every])
        self.n_points += len(stamps_s)
        self.seconds["gather"] += time.thread_time() - start

    def _add_to_rasters(self, xyz_before: FloatArray, xyz_after: FloatArray, time01: NDArray[np.float32]) -> None:
        """The sections, the correction map and the vertical section of one block of points."""
        half = 0.5 * self.config.section_band_m
        for which, xyz in (("before", xyz_before), ("after", xyz_after)):
            z_column = xyz[:, 2]
            for k, z in enumerate(self.heights or []):
                # The band's few points by index, gathered column by column (a boolean mask on an
                # (n, 3) array, taken again for each use, scans and gathers row by row).
                band = np.flatnonzero(np.abs(z_column - z) <= half)
                xy = np.column_stack([xyz[:, 0].take(band), xyz[:, 1].take(band)])
                raster = self.rasters.get((z, which))
                if raster is None:
                    raster = self.rasters[(z, which)] = SectionRaster(self.grid)
                raster.add(xy, time01.take(band))
                if k == 0 and which == "after":
                    dx = xy[:, 0] - xyz_before[:, 0].take(band)
                    dy = xy[:, 1] - xyz_before[:, 1].take(band)
                    self.corrections.add(xy, np.hypot(dx, dy))
            if self.vertical is not None:
                projected, inside = self.vertical.project(xyz)
                self.vertical_rasters[which].add(projected, time01[inside])

    def finish(self, out_dir: Path) -> dict[str, Any]:
        """Write the figures into ``out_dir/figures`` and return ``{"cloud": ..., "crs": ...}`` for
        ``report.json``. Without points (the corrected cloud was current and not written again),
        the entries of the previous run in ``figures/cloud.json``, if any."""
        figures = Path(out_dir) / FIGURES_DIR
        if not self.config.cloud_views:
            return {"crs": self.crs}
        if self.n_points == 0:
            return _previous(figures, self.crs)
        start = time.thread_time()
        figures.mkdir(parents=True, exist_ok=True)
        for old in figures.glob("*.png"):  # of an earlier run in this folder (other heights, other runs)
            old.unlink()
        sections = []
        for k, z in enumerate(self.heights or []):
            entry: dict[str, Any] = {"z_m": z, "band_m": self.config.section_band_m, "pixel_m": self.grid.pixel_m,
                                     "width_px": self.grid.width, "height_px": self.grid.height, "images": {}}
            places = self.corrections.largest(INSETS) if k == 0 else []
            for which in ("before", "after"):
                raster = self.rasters[(z, which)]
                name = f"section_{k + 1}_{which}.png"
                image = raster.render(f"{which.upper()} z={z:.2f} m", self.duration_s, places, INSET_M)
                _write_png(figures / name, image)
                entry["images"][which] = f"{FIGURES_DIR}/{name}"
                entry[f"n_points_{which}"] = raster.n_points
            entry["insets"] = [self._inset(figures, k, n, place) for n, place in enumerate(places)]
            sections.append(entry)
        cloud: dict[str, Any] = {
            "n_points": self.n_points,
            "time_range_s": [self.t0_s, self.t0_s + self.duration_s],
            "heights": "automatic" if self.automatic else "configured",
            "sections": sections,
            "thickness": self._thickness(figures),
            "per_point": self._per_point(figures),
        }
        if self.vertical is not None:
            cloud["vertical_section"] = self._vertical(figures)
        if self.deviations is not None:  # the kinematic noise: the corrected cloud's median plane thickness
            noise = cloud["thickness"].get("median_after_mm")
            cloud["static_deviations"] = self.deviations.figures(noise if noise and math.isfinite(noise) else 5.0)
        result = {"cloud": cloud, "crs": self.crs}
        self.seconds["figures"] = time.thread_time() - start
        # The seconds only here (report.json holds what does not depend on how the run got there).
        with atomic_path(figures / SUMMARY_NAME, overwrite=True) as tmp:
            tmp.write_text(json.dumps(_clean({**result, "seconds": self.seconds}), indent=1) + "\n", encoding="utf-8")
        return result

    def _inset(self, figures: Path, k: int, n: int, place: tuple[float, float, float]) -> dict[str, Any]:
        x, y, shift_m = place
        z = (self.heights or [])[k]
        entry: dict[str, Any] = {"x_m": x, "y_m": y, "size_m": INSET_M, "correction_mm": shift_m * 1000.0,
                                 "images": {}}
        for which in ("before", "after"):
            window = crop(self.rasters[(z, which)].mean_time(), self.grid, x, y, INSET_M)
            big, factor = enlarge(window, 600)
            image = render_time_image(big, self.grid.pixel_m / factor, f"{n + 1} {which.upper()}", self.duration_s)
            name = f"section_{k + 1}_inset_{n + 1}_{which}.png"
            _write_png(figures / name, image)
            entry["images"][which] = f"{FIGURES_DIR}/{name}"
        return entry

    def _vertical(self, figures: Path) -> dict[str, Any]:
        plane = self.vertical
        assert plane is not None
        entry: dict[str, Any] = {"start_xy": plane.start_xy.tolist(), "end_xy": plane.end_xy.tolist(),
                                 "length_m": plane.length_m, "azimuth_deg": plane.azimuth_deg, "band_m": plane.band_m,
                                 "pixel_m": self.vertical_grid.pixel_m, "images": {}}
        for which, raster in self.vertical_rasters.items():
            image = raster.render(f"{which.upper()} VERTICAL AZ {plane.azimuth_deg:.0f}", self.duration_s, north=False)
            name = f"vertical_{which}.png"
            _write_png(figures / name, image)
            entry["images"][which] = f"{FIGURES_DIR}/{name}"
            entry[f"n_points_{which}"] = raster.n_points
        return entry

    def _per_point(self, figures: Path) -> dict[str, Any]:
        """The plan-view maps of the per-point sigma and correction length (each on its own colour
        scale, 0 to the 95th percentile of its columns' medians)."""
        entry: dict[str, Any] = {"cell_m": next(iter(self.per_point.values())).grid.pixel_m,
                                 "stride": self.per_point_stride, "images": {}}
        for name, label in PER_POINT_MAPS.items():
            medians = self.per_point[name]
            if medians.n_points == 0:
                continue
            grid = medians.medians_mm()
            finite = grid[np.isfinite(grid)]
            vmax_mm = max(float(np.percentile(finite, 95)), 0.01)
            entry[f"{name}_map_max_mm"] = vmax_mm
            entry[f"{name}_median_mm"] = float(np.median(finite))
            image = _column_image(grid / 1000.0, medians.grid.pixel_m, vmax_mm / 1000.0, label)
            file_name = f"per_point_{name}.png"
            _write_png(figures / file_name, image)
            entry["images"][name] = f"{FIGURES_DIR}/{file_name}"
        return entry

    def _thickness(self, figures: Path) -> dict[str, Any]:
        result = compare(self.moments["before"], self.moments["after"], MIN_CELL_POINTS)
        entry: dict[str, Any] = dict(result.figures)
        entry["thickness_stride"] = self.thickness_stride
        cells = np.vstack([result.cells_before, result.cells_after])
        if len(cells) == 0:
            return entry
        i0, j0 = (int(v) for v in cells[:, :2].min(axis=0))
        i1, j1 = (int(v) for v in cells[:, :2].max(axis=0))
        width, height = i1 - i0 + 1, j1 - j0 + 1
        vmax = float(np.percentile(result.thickness_before_m, 95)) if len(result.thickness_before_m) else 0.01
        vmax = max(vmax, 1e-3)
        entry["map_max_mm"] = vmax * 1000.0
        entry["images"] = {}
        for which, c, t in (("before", result.cells_before, result.thickness_before_m),
                            ("after", result.cells_after, result.thickness_after_m)):
            grid = column_map(c, t, i0, j1, width, height)
            image = _column_image(grid, self.config.thickness_cell_m, vmax, f"THICKNESS {which.upper()}")
            name = f"thickness_{which}.png"
            _write_png(figures / name, image)
            entry["images"][which] = f"{FIGURES_DIR}/{name}"
        return entry


def _column_image(grid: FloatArray, cell_m: float, vmax_m: float, label: str) -> Image:
    """A column map [m] (NaN: no value) as an image: each cell a square of pixels, about 800 px
    wide, coloured 0 to ``vmax_m``."""
    w = grid.shape[1]
    px = int(max(2, min(40, 800 // max(w, 1))))
    big = np.kron(np.nan_to_num(grid, nan=-1.0), np.ones((px, px)))
    scale = font_scale(np.empty((big.shape[0], max(big.shape[1], 400), 0), dtype=np.uint8))
    top, bottom, side = 24 * scale, 18 * scale, 4 * scale  # title and north arrow above, bars below
    image = np.empty((big.shape[0] + top + bottom, max(big.shape[1] + 2 * side, 400), 3), dtype=np.uint8)
    image[:] = WHITE
    view = image[top:top + big.shape[0], side:side + big.shape[1]]
    full = big >= 0
    view[~full] = (235, 235, 235)
    view[full] = colour_map(big[full] / vmax_m, heat=True)
    draw_label(image, label)
    draw_scale_bar(image, cell_m / px)
    draw_north_arrow(image)
    vmax_mm = vmax_m * 1000
    draw_colour_bar(image, "0", f"{vmax_mm:.0f} mm" if vmax_mm >= 10 else f"{vmax_mm:.2g} mm", heat=True)
    return image


def _write_png(path: Path, image: Image) -> None:
    with atomic_path(path, overwrite=True) as tmp:
        tmp.write_bytes(encode_png(image))


def _previous(figures: Path, crs: dict[str, Any]) -> dict[str, Any]:
    try:
        result = json.loads((figures / SUMMARY_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {"crs": crs}
    if isinstance(result, dict) and isinstance(result.get("cloud"), dict):
        return {"cloud": result["cloud"], "crs": crs}
    return {"crs": crs}



def cloud_views_for_runs(config: ReportConfig, clouds: Sequence[Path], trajectories: Sequence[Trajectory],
                         references: ReferencePlanes | None = None, static: Path | None = None) -> CloudViews:
    """A :class:`CloudViews` over the header bounds of every cloud (mapped into the trajectories'
    frame by the references' ``[initial_transform]``, as corrected.laz is) and the time range of
    every trajectory; the CRS from the first cloud; with ``static`` (registered static scans, E57),
    the static cloud's local planes for the kinematic-vs-static deviations."""
    from kinreg.io.cloud import open_cloud
    from kinreg.io.las import read_las_crs

    T_obj_cloud = None if references is None else references.T_ref_traj
    stamps_s = [t.stamps_s for t in trajectories]

    lows, highs = [], []
    n_points = 0
    for path in clouds:
        with open_cloud(path, require_time=False) as cloud:
            n_points += cloud.info.n_points
            if cloud.info.bounds_min is None or cloud.info.bounds_max is None:
                continue
            lo, hi = np.asarray(cloud.info.bounds_min), np.asarray(cloud.info.bounds_max)
        if T_obj_cloud is not None:
            corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
            moved = T_obj_cloud.apply(corners)
            lo, hi = moved.min(axis=0), moved.max(axis=0)
        lows.append(lo)
        highs.append(hi)
    if lows:
        bounds_min, bounds_max = np.min(lows, axis=0), np.max(highs, axis=0)
    else:  # no header bounds (E57): the rasters cannot be placed
        bounds_min, bounds_max = np.zeros(3), np.ones(3)
        config = _without_views(config)
    t0 = min(float(np.min(s)) for s in stamps_s) if stamps_s else 0.0
    t1 = max(float(np.max(s)) for s in stamps_s) if stamps_s else 1.0
    crs = describe_crs(read_las_crs(clouds[0])) if clouds and Path(clouds[0]).suffix.lower() in (".las", ".laz") \
        else {}
    vertical = None
    if config.cloud_views and trajectories:  # along the longest straight stretch of the first run
        line = longest_straight_stretch(trajectories[0].stamps_s, trajectories[0].poses.t_xyz[:, :2])
        vertical = None if line is None else VerticalPlane(line[0], line[1], config.section_band_m)
    planes = None
    if static is not None and config.cloud_views:
        from kinreg.report.deviations import static_planes_from_e57

        planes = static_planes_from_e57(static, np.asarray(bounds_min) - 1.0)
    return CloudViews(config, bounds_min, bounds_max, t0, t1, crs, planes, vertical, n_points)


def _without_views(config: ReportConfig) -> ReportConfig:
    import dataclasses

    return dataclasses.replace(config, cloud_views=False)
