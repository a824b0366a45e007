"""The report page's view of the point cloud: sections before/after and the plane-thickness map.

The PNGs written by :class:`kinreg.report.cloud_views.CloudViews` are embedded as ``data:`` URIs,
so the page stays one self-contained file; ``base_dir`` is the folder their paths in
``report["cloud"]`` are relative to (the output folder). Without it, or without the files, the
page names the files instead of showing them.
"""

from __future__ import annotations

import base64
import struct
from pathlib import Path
from typing import Any

from kinreg.report.text import DASH, _count, _esc, _fmt, _get, _tag


def _png_size(data: bytes) -> tuple[int, int] | None:
    if data[:8] != b"\x89PNG\r\n\x1a\n" or len(data) < 24:
        return None
    return struct.unpack(">II", data[16:24])


def _image(path: Any, alt: str, base_dir: Path | None) -> str:
    """An ``<img>`` with the PNG inline, or a note naming the file when it cannot be read."""
    if not isinstance(path, str) or not path:
        return ""
    data = b""
    if base_dir is not None:
        try:
            data = (Path(base_dir) / path).read_bytes()
        except OSError:
            data = b""
    size = _png_size(data)
    if size is None:
        return _tag("p", _esc(f"Image {path}: in the output folder (not embedded)."), class_="sub")
    uri = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    return f'<img class="cloud" src="{uri}" alt="{_esc(alt)}" width="{size[0]}" height="{size[1]}">'


def _pair(before: str, after: str, caption: str) -> str:
    return _tag("figure", _tag("div", before + after, class_="pair") + _tag("figcaption", _esc(caption)))


def thickness_figure(report: dict[str, Any]) -> tuple[str, str, str]:
    """The key-figures row of the plane thickness: label, ratio, medians."""
    th = _get(report, "cloud", "thickness", default={})
    ratio = th.get("median_ratio_after_before")
    return ("plane thickness after/before", f"median {_fmt(ratio, 2)}",
            f"{_fmt(th.get('median_before_mm'), 1)} \u2192 {_fmt(th.get('median_after_mm'), 1, 'mm')}")


def _histogram_svg(deviations: dict[str, Any]) -> str:
    """Before (grey) and after (blue) distance histograms as one inline SVG, shares per bin."""
    edges = deviations.get("edges_mm") or [None, None]
    series = {w: (deviations.get(w) or {}).get("histogram") or [] for w in ("before", "after")}
    if not all(isinstance(e, int | float) for e in edges) or not any(series.values()):
        return ""
    width, height, left, bottom = 560, 200, 40, 24
    shares = {w: [v / max(sum(h), 1) for v in h] for w, h in series.items() if h}
    top = max(max(s) for s in shares.values()) or 1.0
    lines = []
    for w, colour in (("before", "#999"), ("after", "#1f6fb4")):
        if w not in shares:
            continue
        n = len(shares[w])
        points = " ".join(f"{left + (k + 0.5) * (width - left - 10) / n:.1f},"
                          f"{height - bottom - v / top * (height - bottom - 20):.1f}" for k, v in enumerate(shares[w]))
        lines.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{points}"/>')
    noise = deviations.get("noise_mm")
    lo, hi = float(edges[0]), float(edges[1])

    def x(mm: float) -> float:
        return left + (mm - lo) / (hi - lo) * (width - left - 10)

    ticks = "".join(f'<line class="grid" x1="{x(v):.1f}" x2="{x(v):.1f}" y1="20" y2="{height - bottom}"/>'
                    f'<text x="{x(v):.1f}" y="{height - 6}" text-anchor="middle" font-size="11">{v:g}</text>'
                    for v in (lo, lo / 2, 0.0, hi / 2, hi))
    band = ""
    if isinstance(noise, int | float) and noise > 0:
        band = (f'<rect x="{x(-2 * noise):.1f}" y="20" width="{x(2 * noise) - x(-2 * noise):.1f}" '
                f'height="{height - bottom - 20}" fill="#1f6fb4" opacity="0.08"/>')
    legend = ('<text x="48" y="14" font-size="11">grey: before, blue: after; shaded: \u00b12 \u00d7 noise; '
              'distance [mm]</text>')
    return (f'<svg class="plot" viewBox="0 0 {width} {height}" role="img" aria-label="Histogram of the signed '
            f'distances to the static planes before and after">{band}{ticks}{"".join(lines)}{legend}</svg>')


def static_deviations(cloud: dict[str, Any]) -> str:
    """The kinematic-vs-static card: figures before and after, and the histogram."""
    dev = cloud.get("static_deviations")
    if not isinstance(dev, dict):
        return ""
    noise = dev.get("noise_mm")

    def row(label: str, key: str, digits: int, unit: str, scale: float = 1.0) -> str:
        cells = []
        for w in ("before", "after"):
            v = (dev.get(w) or {}).get(key)
            cells.append(_tag("td", _esc(_fmt(v * scale if isinstance(v, int | float) else None, digits, unit)),
                              class_="num"))
        return _tag("tr", _tag("td", _esc(label)) + "".join(cells))

    head = _tag("tr", "<th></th>" + _tag("th", "before", class_="num") + _tag("th", "after", class_="num"))
    body = (row("points compared", "n", 0, "") + row("mean", "mean_mm", 2, "mm") + row("RMS", "rms_mm", 2, "mm")
            + row(f"within 2 \u00d7 noise ({_fmt(noise, 1, 'mm')})", "share_within_2_noise", 1, "%", 100.0)
            + row("within 3 \u00d7 noise", "share_within_3_noise", 1, "%", 100.0))
    note = _tag("p", f"Signed distance of the kinematic points to the static cloud's local planes "
                f"({_count(dev.get('n_core_points'))} planar cubes of {_fmt(dev.get('cell_m'), 2, 'm')}, along the "
                f"static normal; every {dev.get('stride', 1)}th point; farther than "
                f"{_fmt(dev.get('max_distance_mm'), 0, 'mm')} not counted). Noise: the corrected cloud's median "
                "plane thickness.", class_="sub")
    return _tag("div", "<h3>Kinematic vs static</h3>" + _tag("table", head + body) + _histogram_svg(dev) + note,
                class_="card")


def cloud_section(report: dict[str, Any], base_dir: Path | None) -> str:
    """The page section of ``report["cloud"]``; empty when the run has none."""
    cloud = _get(report, "cloud", default=None)
    if not isinstance(cloud, dict):
        return ""
    times = cloud.get("time_range_s") or [None, None]
    duration = (times[1] - times[0]) if all(isinstance(t, int | float) for t in times[:2]) else None
    parts = [_tag("h2", "The cloud: sections before and after, plane thickness")]
    legend = ("Points coloured by time, from dark blue (start) through green to yellow (end, "
              f"{_fmt(duration, 0, 's')}): a wall that drifted between two passes shows twice, in two colours. "
              "Scale bar in metres; N: +y of the cloud's frame (grid north in a projected CRS).")
    for k, section in enumerate(s for s in cloud.get("sections") or [] if isinstance(s, dict)):
        z, band = _fmt(section.get("z_m"), 2, "m"), _fmt(section.get("band_m"), 2, "m")
        images = section.get("images") or {}
        before = _image(images.get("before"), f"Horizontal section {k + 1} at z = {z} (band {band}) before the "
                        "drift correction, points coloured by time", base_dir)
        after = _image(images.get("after"), f"Horizontal section {k + 1} at z = {z} (band {band}) after the "
                       "drift correction, points coloured by time", base_dir)
        caption = (f"Section {k + 1}: z = {z} \u00b1 {_fmt((section.get('band_m') or 0) / 2, 2, 'm')} "
                   f"({cloud.get('heights', DASH)} height), before (left, or above on a narrow screen) and after "
                   "the correction; "
                   f"{_count(section.get('n_points_before'))} / {_count(section.get('n_points_after'))} points, "
                   f"pixel {_fmt((section.get('pixel_m') or 0) * 100, 1, 'cm')}. " + legend)
        parts.append(_pair(before, after, caption))
        insets = [i for i in section.get("insets") or [] if isinstance(i, dict)]
        figures = []
        for n, inset in enumerate(insets, 1):
            where = f"x = {_fmt(inset.get('x_m'), 1, 'm')}, y = {_fmt(inset.get('y_m'), 1, 'm')}"
            pictures = inset.get("images") or {}
            figures.append(_pair(
                _image(pictures.get("before"), f"Inset {n} of section {k + 1} at {where}, before the correction",
                       base_dir),
                _image(pictures.get("after"), f"Inset {n} of section {k + 1} at {where}, after the correction",
                       base_dir),
                f"Inset {n} (red box {n}): {_fmt(inset.get('size_m'), 0, 'm')} square at {where}; mean horizontal "
                f"correction of its points {_fmt(inset.get('correction_mm'), 1, 'mm')}. Before left, after right."))
        if figures:
            parts.append(_tag("div", "".join(figures), class_="insets"))
    vertical = cloud.get("vertical_section")
    if isinstance(vertical, dict):
        images = vertical.get("images") or {}
        start, end = vertical.get("start_xy") or [None, None], vertical.get("end_xy") or [None, None]
        where = (f"from ({_fmt(start[0], 1)}, {_fmt(start[1], 1)}) to ({_fmt(end[0], 1)}, {_fmt(end[1], 1, 'm')}), "
                 f"azimuth {_fmt(vertical.get('azimuth_deg'), 0)}\u00b0")
        alt = "Vertical section {}, {} the correction, coloured by time"
        parts.append(_pair(
            _image(images.get("before"), alt.format(where, "before"), base_dir),
            _image(images.get("after"), alt.format(where, "after"), base_dir),
            f"Vertical section along the longest straight stretch of the trajectory, {where}, "
            f"{_fmt(vertical.get('length_m'), 1, 'm')} long, band {_fmt(vertical.get('band_m'), 2, 'm')}; "
            "horizontal axis: distance along the line, vertical: height (the scale bar holds for both). "
            "Before left (or above), after right (or below)."))
    cards = static_deviations(cloud)
    th = cloud.get("thickness")
    if isinstance(th, dict):
        rows = [
            ("median ratio after/before (cells planar in both)", _fmt(th.get("median_ratio_after_before"), 3)),
            ("median thickness before / after", f"{_fmt(th.get('median_before_mm'), 2)} / "
                                                f"{_fmt(th.get('median_after_mm'), 2, 'mm')}"),
            ("share of cells thinner after", _fmt(100 * th["share_thinner_after"], 0, "%")
             if isinstance(th.get("share_thinner_after"), int | float) else DASH),
            ("planar cells before / after / both", f"{_count(th.get('n_planar_before'))} / "
                                                   f"{_count(th.get('n_planar_after'))} / "
                                                   f"{_count(th.get('n_planar_both'))}"),
            ("cell", _fmt(th.get("cell_m"), 2, "m")),
        ]
        body = "".join(_tag("tr", _tag("td", _esc(a)) + _tag("td", _esc(b), class_="num")) for a, b in rows)
        parts.append(_tag("div", _tag("div", "<h3>Plane thickness</h3>" + _tag("table", body)
                          + _tag("p", "Per cube of the grid: the root of the smallest eigenvalue of its points' "
                                 "covariance where they form a plane. It needs no ground truth: a wall seen twice "
                                 "with drift between is thick, a corrected one as thin as the scanner's noise.",
                                 class_="sub"), class_="card") + cards, class_="cards"))
        cards = ""
        images = th.get("images") or {}
        if images:
            vmax = _fmt(th.get("map_max_mm"), 0, "mm")
            parts.append(_pair(
                _image(images.get("before"), "Map of the plane thickness per grid column before the correction",
                       base_dir),
                _image(images.get("after"), "Map of the plane thickness per grid column after the correction",
                       base_dir),
                f"Plane thickness per column of {_fmt(th.get('cell_m'), 1, 'm')} cells (the median over its planar "
                f"cells), before left (or above), after right (or below); light yellow 0 to dark red {vmax} and "
                "more; grey: no planar "
                "cell."))
    per_point = cloud.get("per_point")
    if isinstance(per_point, dict) and per_point.get("images"):
        images = per_point["images"]
        parts.append(_pair(
            _image(images.get("sigma_3d"), "Map of the median 3D position sigma of the points per grid column",
                   base_dir),
            _image(images.get("correction"), "Map of the median correction length of the points per grid column",
                   base_dir),
            f"Accuracy per point, as in corrected.laz's extra bytes sigma_3d_mm and correction_mm: the median "
            f"per column of {_fmt(per_point.get('cell_m'), 1, 'm')} of each point's 3D position sigma (from the "
            f"adjusted stations, interpolated in time; light yellow 0 to dark red "
            f"{_fmt(per_point.get('sigma_3d_map_max_mm'), 1, 'mm')}) left (or above), and of the length of its "
            f"correction (0 to {_fmt(per_point.get('correction_map_max_mm'), 1, 'mm')}) right (or below); "
            "grey: no points."))
    if cards:
        parts.append(cards)
    return "\n".join(parts)
