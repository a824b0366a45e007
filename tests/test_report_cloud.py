"""The report's views of the cloud: sections before/after by time, plane thickness, CRS names, PNGs."""

from __future__ import annotations

import json
import re
import struct
import zlib

import numpy as np
import pytest

from kinreg.config import ReportConfig, load_config
from kinreg.errors import ConfigError
from kinreg.io.las import LasCrs
from kinreg.report.cloud_views import CloudViews
from kinreg.report.crs import describe_crs
from kinreg.report.html import render_html
from kinreg.report.raster import encode_png, font_scale, nice_length
from kinreg.report.sections import Grid, choose_heights
from kinreg.report.thickness import CellMoments, compare

UTM = np.array([500_000.0, 5_400_000.0, 300.0])
OFF = np.array([0.37, 0.41, 0.23])  # keeps the room's faces off the 1 m grid lines of the cells


def decode_png(data: bytes) -> np.ndarray:
    """RGB pixels of an 8-bit, filter-0 PNG as written by :func:`encode_png` (independent decoder)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, size = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        assert zlib.crc32(kind + body) & 0xFFFFFFFF == struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0]
        if kind == b"IHDR":
            size = struct.unpack(">II", body[:8])
            assert body[8:10] == b"\x08\x02"  # 8 bit RGB
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert size is not None
    w, h = size
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + 3 * w)
    assert np.all(raw[:, 0] == 0)
    return raw[:, 1:].reshape(h, w, 3)


def room(n: int, rng: np.random.Generator, noise_m: float = 0.003, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Points of a 10 m x 6 m x 3 m box room: floor, ceiling and four walls, with range noise."""
    faces = rng.integers(0, 6, n)
    u, v = rng.random(n), rng.random(n)
    xyz = np.column_stack([10 * u, 6 * v, 3 * rng.random(n)])
    xyz[faces == 0, 2], xyz[faces == 1, 2] = 0.0, 3.0
    xyz[faces == 2, 0], xyz[faces == 3, 0] = 0.0, 10.0
    xyz[faces == 4, 1], xyz[faces == 5, 1] = 0.0, 6.0
    normal_axis = np.array([2, 2, 0, 0, 1, 1])[faces]
    xyz[np.arange(n), normal_axis] += rng.normal(0.0, noise_m, n)
    return xyz + OFF + np.asarray(origin)


def drifted_pass(rng: np.random.Generator, shift_m: float, origin=(0.0, 0.0, 0.0)):
    """Two passes through the room, 100 s apart: the second one drifted by ``shift_m`` in x and y
    and by half of it in z (before), both where they belong (after). Returns before, after, times."""
    first, second = room(60_000, rng, origin=origin), room(60_000, rng, origin=origin)
    after = np.vstack([first, second])
    before = np.vstack([first, second + [shift_m, shift_m, shift_m / 2]])
    times = np.r_[np.linspace(0, 50, len(first)), np.linspace(100, 150, len(second))]
    return before, after, times


def views_for(before, after, times, **config) -> CloudViews:
    lo, hi = np.minimum(before.min(0), after.min(0)), np.maximum(before.max(0), after.max(0))
    return CloudViews(ReportConfig(**config), lo, hi, float(times.min()), float(times.max()))


@pytest.fixture(scope="module")
def drifted(tmp_path_factory):
    rng = np.random.default_rng(3)
    before, after, times = drifted_pass(rng, 0.06)
    views = views_for(before, after, times, section_heights_m=(1.5,))
    for k in range(0, len(times), 25_000):  # in chunks, as corrected.laz is written
        views.add(before[k:k + 25_000], after[k:k + 25_000], times[k:k + 25_000])
    out = tmp_path_factory.mktemp("out")
    return views, views.finish(out), out


def test_png_round_trip():
    image = np.random.default_rng(0).integers(0, 256, (17, 31, 3), dtype=np.uint8)
    assert np.array_equal(decode_png(encode_png(image)), image)


def test_doubled_wall_before_single_after(drifted):
    views, result, out = drifted
    section = result["cloud"]["sections"][0]
    assert section["z_m"] == 1.5  # configured
    before = decode_png((out / section["images"]["before"]).read_bytes())
    after = decode_png((out / section["images"]["after"]).read_bytes())
    assert before.shape == after.shape
    # Rows through the middle of the room (y = 1.5 to 4.5 m) crossing the wall x = 10 m.
    grid = views.grid
    top = 12 * font_scale(np.empty((grid.height, grid.width, 0)))  # the title strip
    rows = slice(top + int((grid.y1 - 4.5 - OFF[1]) / grid.pixel_m), top + int((grid.y1 - 1.5 - OFF[1]) / grid.pixel_m))
    wall = int((10.0 + OFF[0] - grid.x0) / grid.pixel_m)
    cols = slice(wall - 10, wall + 10)

    def lines(image):
        window = image[rows, cols].astype(int)
        hits = (~np.all(window >= 235, axis=2)).sum(axis=0)
        return np.flatnonzero(hits >= 10), window

    lines_before, window_before = lines(before)
    lines_after, _ = lines(after)
    # Before: two lines 6 cm (3 pixels) apart; after: one (noise 3 mm, pixels 2 cm).
    assert lines_before.max() - lines_before.min() >= 3
    assert lines_after.max() - lines_after.min() <= 1
    # ... in two colours: early (dark) where the wall is, late (bright) where the drift put it.
    brightness = window_before.sum(axis=2)
    first, last = brightness[:, lines_before.min()], brightness[:, lines_before.max()]
    assert np.median(first[first < 700]) < np.median(last[last < 700]) - 100


def test_thickness_ratio_shows_the_correction(drifted):
    _, result, _ = drifted
    th = result["cloud"]["thickness"]
    assert th["n_planar_both"] >= 50
    # Before: two sheets 6 cm apart where both passes saw a wall (about 30 mm thick); after: the
    # 3 mm noise. Cells of floor and ceiling move only sideways and stay thin.
    assert th["median_after_mm"] == pytest.approx(3.0, rel=0.25)
    assert th["median_ratio_after_before"] < 0.5
    assert (th["images"]["before"], th["images"]["after"]) == ("figures/thickness_before.png",
                                                               "figures/thickness_after.png")


def test_summary_is_kept_for_a_resumed_run(drifted):
    _, result, out = drifted
    kept = json.loads((out / "figures" / "cloud.json").read_text())
    assert kept["cloud"]["thickness"]["n_planar_both"] == result["cloud"]["thickness"]["n_planar_both"]
    idle = CloudViews(ReportConfig(), np.zeros(3), np.ones(3), 0.0, 1.0)  # nothing added: cloud not rewritten
    assert idle.finish(out)["cloud"]["sections"] == json.loads(json.dumps(result["cloud"]["sections"]))


def test_chunking_and_dense_or_sparse_cells_do_not_change_the_figures():
    rng = np.random.default_rng(5)
    before, after, times = drifted_pass(rng, 0.04, origin=UTM)
    figures = []
    for chunk, extent in ((len(times), True), (7_001, True), (10_000, False)):
        b, a = CellMoments(UTM - 1.0, 1.0, (before.max(0) - UTM + 2) if extent else None), CellMoments(UTM - 1.0, 1.0)
        for k in range(0, len(times), chunk):
            b.add(before[k:k + chunk])
            a.add(after[k:k + chunk])
        figures.append(compare(b, a, 50).figures)
    for other in figures[1:]:
        assert other["n_planar_both"] == figures[0]["n_planar_both"]
        assert other["median_ratio_after_before"] == pytest.approx(figures[0]["median_ratio_after_before"], rel=1e-9)
    # UTM-sized coordinates lose nothing: the noise comes back.
    assert figures[0]["median_after_mm"] == pytest.approx(3.0, rel=0.25)


def test_heights_are_chosen_above_the_floor_and_avoid_a_table():
    rng = np.random.default_rng(1)
    z = room(200_000, rng)[:, 2] + 100.0
    (h,) = choose_heights(z, 0.1)
    floor = 100.0 + OFF[2]
    assert floor + 1.0 <= h <= floor + 1.5
    table = np.full(20_000, floor + 1.2) + rng.normal(0, 0.003, 20_000)
    (h,) = choose_heights(np.r_[z, table], 0.1)
    assert floor + 1.0 <= h <= floor + 1.5 and abs(h - floor - 1.2) > 0.05


def test_grid_is_capped():
    grid = Grid.covering(np.array([0.0, 0.0]), np.array([5_000.0, 300.0]), 0.02, 2000)
    assert grid.width <= 2000 and grid.height <= 2000
    assert grid.pixel_m == pytest.approx(5_001.0 / 2000)
    small = Grid.covering(np.array([0.0, 0.0]), np.array([10.0, 5.0]), 0.02, 2000)
    assert small.pixel_m == 0.02 and small.width == 550


def test_nice_lengths():
    assert [nice_length(v) for v in (0.9, 1.0, 3.0, 19.0, 999.0)] == [0.5, 1.0, 2.0, 10.0, 500.0]


def test_crs_from_wkt_and_geotiff_keys():
    wkt = ('PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_System_1989",'
           'SPHEROID["GRS 1980",6378137,298.257222101],AUTHORITY["EPSG","6258"]],AUTHORITY["EPSG","4258"]],'
           'PROJECTION["Transverse_Mercator"],UNIT["metre",1,AUTHORITY["EPSG","9001"]],AUTHORITY["EPSG","25832"]]')
    entry = describe_crs(LasCrs(wkt=wkt))
    assert entry["epsg"] == 25832
    assert "UTM zone 32N" in entry["name"]
    keys = describe_crs(LasCrs(geo_keys={1024: 1, 3072: 32633, 4096: 5703}))
    assert (keys["epsg"], keys["vertical_epsg"]) == (32633, 5703)
    assert describe_crs(LasCrs(geo_keys={3072: 32767}))["epsg"] is None  # user-defined
    assert describe_crs(LasCrs()) == {}


def test_report_config_section():
    config = load_config(overrides={"report.section_heights_m": [1.2, 2], "report.section_band_m": 0.05})
    assert config.report.section_heights_m == (1.2, 2.0)
    with pytest.raises(ConfigError, match="section_heights_m"):
        load_config(overrides={"report.section_heights_m": ["high"]})
    with pytest.raises(ConfigError, match="section_band_m"):
        load_config(overrides={"report.section_band_m": 0.0})


def test_html_embeds_the_images_with_alt_text(drifted):
    _, result, out = drifted
    page = render_html({"schema_version": 1, **result}, base_dir=out)
    images = re.findall(r"<img [^>]*>", page)
    assert len(images) == 10  # section before/after, 3 insets before/after, thickness before/after
    for tag in images:
        assert re.search(r'alt="[^"]{20,}"', tag)
        uri = re.search(r'src="data:image/png;base64,([^"]+)"', tag)
        assert uri is not None
        import base64

        pixels = decode_png(base64.b64decode(uri.group(1)))
        width = int(re.search(r'width="(\d+)"', tag).group(1))
        assert pixels.shape[1] == width
    assert "plane thickness after/before" in page
    # Without the folder the page names the files and stays valid.
    assert "figures/section_1_before.png" in render_html(result)
    assert "<img" not in render_html(result)


def test_drawing_is_clipped_to_the_image():
    from kinreg.report.raster import fill_rect

    image = np.zeros((10, 10, 3), dtype=np.uint8)
    fill_rect(image, -8, -8, -5, -5, (255, 255, 255))  # wholly outside: nothing
    fill_rect(image, 8, 8, 20, 20, (255, 255, 255))  # partly outside: the part inside
    assert image.sum() == 4 * 3 * 255


def test_insets_where_the_correction_is_largest(drifted):
    _, result, out = drifted
    insets = result["cloud"]["sections"][0]["insets"]
    assert len(insets) == 3
    # Half the points moved by 6 cm x sqrt(2) horizontally, half not at all: about 42 mm on average.
    assert all(20.0 < i["correction_mm"] < 90.0 for i in insets)
    assert [i["correction_mm"] for i in insets] == sorted((i["correction_mm"] for i in insets), reverse=True)
    for a in range(3):
        for b in range(a):
            assert np.hypot(insets[a]["x_m"] - insets[b]["x_m"], insets[a]["y_m"] - insets[b]["y_m"]) >= 4.0
        image = decode_png((out / insets[a]["images"]["before"]).read_bytes())
        assert 500 <= max(image.shape[:2]) <= 800


def test_longest_straight_stretch_and_the_vertical_section(tmp_path):
    from kinreg.report.sections import VerticalPlane, longest_straight_stretch

    # An L: 8 m east along y = 3, then 4 m north; 0.5 m/s, with 2 cm of sway.
    t = np.arange(0.0, 24.0, 0.01)
    xy = np.where(t[:, None] < 16, np.column_stack([1 + 0.5 * t, np.full_like(t, 3.0)]),
                  np.column_stack([np.full_like(t, 9.0), 3 + 0.5 * (t - 16)]))
    xy = xy + 0.02 * np.sin(t)[:, None]
    start, end = longest_straight_stretch(t, xy)
    assert np.hypot(*(end - start)) == pytest.approx(8.0, abs=0.7)
    assert abs(start[1] - 3.0) < 0.1 and abs(end[1] - 3.0) < 0.5
    plane = VerticalPlane(np.array([1.0, 3.0]), np.array([9.0, 3.0]), 0.1)
    assert plane.azimuth_deg == pytest.approx(90.0)
    projected, inside = plane.project(np.array([[5.0, 3.04, 1.0], [5.0, 3.2, 1.0], [0.0, 3.0, 2.0]]))
    assert inside.tolist() == [True, False, True]
    assert projected.tolist() == [[4.0, 1.0], [-1.0, 2.0]]
    # Through the drifted room: the section across the walls x = 0 and x = 10 shows them doubled before.
    before, after, times = drifted_pass(np.random.default_rng(6), 0.06)
    views = CloudViews(ReportConfig(), np.minimum(before.min(0), after.min(0)), np.maximum(before.max(0),
                       after.max(0)), 0.0, 150.0, vertical=VerticalPlane(np.array([-0.5, 3.4]),
                                                                         np.array([11.0, 3.4]), 0.1))
    views.add(before, after, times)
    vertical = views.finish(tmp_path)["cloud"]["vertical_section"]
    assert vertical["n_points_before"] > 1000
    rasters = {w: views.vertical_rasters[w].count.reshape(views.vertical_grid.height, -1) for w in ("before", "after")}
    grid = views.vertical_grid
    wall = int((10.0 + OFF[0] + 0.5 - grid.x0) / grid.pixel_m)  # distance along the line to the wall x = 10
    columns = {w: np.flatnonzero(r[:, wall - 8:wall + 8].sum(axis=0) >= 5) for w, r in rasters.items()}
    assert np.ptp(columns["before"]) >= 3 and np.ptp(columns["after"]) <= 1
    assert decode_png((tmp_path / vertical["images"]["before"]).read_bytes()).shape[1] == views.vertical_grid.width


def test_every_capital_letter_and_digit_has_a_glyph():
    import string

    from kinreg.report.raster import _GLYPHS

    assert set(string.ascii_uppercase + string.digits) <= set(_GLYPHS)
    assert all(g.shape == (7, 5) for g in _GLYPHS.values())


def test_column_map_takes_the_median_per_column():
    from kinreg.report.thickness import column_map

    cells = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2], [1, 1, 0], [5, 5, 0]])
    thickness = np.array([0.001, 0.009, 0.002, 0.004, 0.5])
    grid = column_map(cells, thickness, 0, 1, 2, 2)  # i in 0..1, j in 0..1: the cell at (5, 5) is off the map
    assert grid[1, 0] == pytest.approx(0.002)  # j = 0 is the bottom row
    assert grid[0, 1] == pytest.approx(0.004)
    assert np.isnan(grid[0, 0]) and np.isnan(grid[1, 1])


def test_a_tiny_cloud_still_gets_its_images(tmp_path):
    rng = np.random.default_rng(9)
    xyz = rng.random((500, 3)) * [0.3, 0.2, 2.0]  # 30 cm x 20 cm: a raster of a few dozen pixels
    views = CloudViews(ReportConfig(section_heights_m=(1.0,)), xyz.min(0), xyz.max(0), 0.0, 1.0)
    views.add(xyz, xyz, np.linspace(0, 1, 500))
    result = views.finish(tmp_path)
    image = decode_png((tmp_path / result["cloud"]["sections"][0]["images"]["before"]).read_bytes())
    assert image.shape[1] == views.grid.width
    assert "seconds" not in result["cloud"]  # only in figures/cloud.json: report.json is the same on --resume
    assert set(json.loads((tmp_path / "figures" / "cloud.json").read_text())["seconds"]) == {"gather", "figures"}


def test_views_off_write_nothing(tmp_path):
    views = CloudViews(ReportConfig(cloud_views=False), np.zeros(3), np.ones(3), 0.0, 1.0)
    views.add(np.zeros((10, 3)), np.zeros((10, 3)), np.zeros(10))
    assert views.finish(tmp_path) == {"crs": {}}
    assert not (tmp_path / "figures").exists()


def test_crs_named_by_pyproj_where_present(monkeypatch):
    """The pyproj branch, with a stand-in module (pyproj is an optional extra, absent in CI)."""
    import sys
    import types

    class CRSError(Exception):
        pass

    class FakeCRS:
        def __init__(self, name: str, epsg: int | None) -> None:
            self.name, self._epsg = name, epsg

        def to_epsg(self):
            return self._epsg

        @staticmethod
        def from_wkt(wkt: str):
            if "broken" in wkt:
                raise CRSError("bad WKT")
            return FakeCRS("resolved by PROJ", 25832)

        @staticmethod
        def from_epsg(code: int):
            return FakeCRS(f"EPSG {code} by PROJ", code)

    fake = types.ModuleType("pyproj")
    fake.CRS = FakeCRS  # type: ignore[attr-defined]
    fake.exceptions = types.SimpleNamespace(CRSError=CRSError)  # type: ignore[attr-defined]
    fake.__version__ = "9.9"  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "pyproj", fake)
    entry = describe_crs(LasCrs(wkt='PROJCS["x",AUTHORITY["EPSG","1234"]]'))
    assert (entry["name"], entry["epsg"], entry["resolved_by"]) == ("resolved by PROJ", 25832, "pyproj 9.9")
    assert describe_crs(LasCrs(geo_keys={3072: 32632}))["name"] == "EPSG 32632 by PROJ"
    broken = describe_crs(LasCrs(wkt='PROJCS["broken",AUTHORITY["EPSG","1234"]]'))
    assert (broken["name"], broken["epsg"], broken["resolved_by"]) == ("broken", 1234, "text")


def _rasters_by_masks(views: CloudViews, before: np.ndarray, after: np.ndarray, times: np.ndarray) -> dict:
    """The rasters as first written: boolean masks on the (n, 3) arrays, per block of the views."""
    from kinreg.report.cloud_views import BLOCK_POINTS
    from kinreg.report.sections import CorrectionMap, SectionRaster

    half = 0.5 * views.config.section_band_m
    out: dict = {"correction": CorrectionMap(views.grid)}
    time01 = ((times - views.t0_s) / views.duration_s).astype(np.float32)
    for a in range(0, len(times), BLOCK_POINTS):
        xb, xa, tb = before[a:a + BLOCK_POINTS], after[a:a + BLOCK_POINTS], time01[a:a + BLOCK_POINTS]
        for which, xyz in (("before", xb), ("after", xa)):
            for k, z in enumerate(views.heights or []):
                band = np.abs(xyz[:, 2] - z) <= half
                out.setdefault((z, which), SectionRaster(views.grid)).add(xyz[band, :2], tb[band])
                if k == 0 and which == "after":
                    shift = xa[band, :2] - xb[band, :2]
                    out["correction"].add(xa[band, :2], np.hypot(shift[:, 0], shift[:, 1]))
            plane = views.vertical
            u = (plane.end_xy - plane.start_xy) / plane.length_m
            x, y = xyz[:, 0] - plane.start_xy[0], xyz[:, 1] - plane.start_xy[1]
            inside = np.abs(x * u[1] - y * u[0]) <= 0.5 * plane.band_m
            along = x[inside] * u[0] + y[inside] * u[1]
            out.setdefault(("vertical", which), SectionRaster(views.vertical_grid)).add(
                np.column_stack([along, xyz[inside, 2]]), tb[inside])
    return out


@pytest.mark.parametrize("order", ["C", "F"])
def test_section_rasters_are_those_of_boolean_masks_per_point(order):
    """Gathering the band's points by index, column by column, fills the same pixels with the same
    sums (to the bit) as masking the (n, 3) arrays: the figures do not change."""
    from kinreg.report.sections import VerticalPlane

    before, after, times = drifted_pass(np.random.default_rng(8), 0.05, origin=UTM)
    before, after = np.asarray(before, order=order), np.asarray(after, order=order)
    start = UTM[:2] + [-0.5, 3.4]
    views = CloudViews(ReportConfig(section_heights_m=(1.5 + UTM[2], 0.8 + UTM[2])),
                       np.minimum(before.min(0), after.min(0)), np.maximum(before.max(0), after.max(0)), 0.0, 150.0,
                       vertical=VerticalPlane(start, start + [11.5, 0.0], 0.1))
    views.add(before, after, times)  # one chunk: two blocks of the rasters
    want = _rasters_by_masks(views, before, after, times)
    for key, raster in [*views.rasters.items(), *((("vertical", w), r) for w, r in views.vertical_rasters.items())]:
        assert raster.n_points > 1000
        assert np.array_equal(raster.count, want[key].count)
        assert np.array_equal(raster.time_sum, want[key].time_sum)
    assert np.array_equal(views.corrections.count, want["correction"].count)
    assert np.array_equal(views.corrections.shift_sum, want["correction"].shift_sum)
    assert views.corrections.count.sum() > 1000
