"""The HTML report: a self-contained, well-formed page from any report dict, missing keys included."""

from __future__ import annotations

import copy
import doctest
import math
import re
import struct
import subprocess
import zlib
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

import kinreg.report.html
from kinreg.report.html import render_html

VOID = {"meta", "br", "hr", "img", "input", "link", "col", "area", "base", "wbr", "source"}
SVG_LEAVES = {"rect", "line", "polyline", "circle", "stop", "path"}  # may be self-closed in SVG
CHROMIUM = Path("/usr/bin/chromium")


def synthetic_report() -> dict:
    """A small run: five quasi-static stations and one static one, a station named ``<b>``,
    NaN/None values, a rejected link and a rejected block observation; no ``timings_s``."""
    n = 5
    rows = []
    for k in range(n):
        rows.append({
            "station": "<b>" if k == 2 else f"qs_{k:05d}", "t": 1000.0 + 6 * k + 3, "t_start": 1000.0 + 6 * k,
            "t_end": 1006.0 + 6 * k, "x": 2.0 * k, "y": math.sin(k), "z": 1.3,
            "qw": 1.0, "qx": 0.0, "qy": 0.0, "qz": 0.0,
            "sx_mm": 0.5 * k, "sy_mm": 0.4 * k, "sz_mm": 0.2 * k, "s3d_mm": 0.7 * k,
            "n_points": 50000, "n_planes": 8, "n_links": 3, "srx_mdeg": 5.0, "sry_mdeg": 5.0, "srz_mdeg": 6.0,
            "kind": "quasi_static", "fixed": k == 0,
        })  # fmt: skip
    rows[3]["sz_mm"] = float("nan")
    rows[4]["s3d_mm"] = None
    rows.append({"station": "static_1", "t": None, "t_start": None, "t_end": None, "x": 4.0, "y": 3.0,
                 "z": 1.5, "sx_mm": 1.0, "sy_mm": 1.0, "sz_mm": 1.0, "s3d_mm": 1.7, "kind": "static",
                 "fixed": False})
    t = [0.1 * k for k in range(300)]
    return {
        "schema_version": 1,
        "kinreg_version": "0.1.0",
        "inputs": {"trajectory": "run/<traj>.txt", "cloud": "run/cloud.laz", "n_points": 2025310,
                   "n_trajectory_rows": 3000, "duration_s": 30.0, "path_length_m": 12.5},
        "config_toml": '[block]\nalpha = 0.001\nname = "<&>"\n',
        "slicing": {"n_scans": n, "n_points_in_scans": 250000, "n_points_outside_trajectory": 0,
                    "skipped_windows": []},
        "adjustment": {
            "datum": "first_station", "sigma0": 0.8737, "redundancy": 40.0, "alpha": 0.001,
            "global_test_passed": False, "variance_factor_applied": float("nan"),
            "variance_components": {"planes": 1.0, "trajectory": None}, "iterations": 4,
            "n_observations": 12,
            "rejected_observations": [{"kind": "planes", "i": 1, "j": 3}],
            "normalised_residuals": {"planes": [0.2, 0.9, 1.4, None, 0.7, 3.1],
                                     "trajectory": [-0.5, 0.3, 1.1, -1.8]},
        },
        "stations": {
            "n": n + 1, "n_fixed": 1,
            "position_sigma_mm": {"rms": 2.345, "mean": 2.0, "max": 2.8},
            "orientation_sigma_mdeg": {"rms": 5.5, "mean": 5.4, "max": None},
            "correction_mm": {"rms": 9.0, "mean": 8.0, "max": 21.0},
            "rows": rows,
        },
        "before_after": {"type": "rigid", "rotation_mdeg": 12.0, "translation_mm": [1.0, 2.0, 3.0],
                         "gaps_mm": {"rms": 7.1, "mean": 6.789, "max": 24.76},
                         "gap_per_station_mm": [10.0, 9.1, float("nan"), 4.0, 2.0]},
        "links": {"n_candidate_pairs": 10, "n_links": 5,
                  "by_status": {"ok": 3, "prior_only": 1, "rejected": 1},
                  "rank_histogram": {"0": 1, "5": 2, "6": 2},
                  "pairs": [[0, 1, "ok"], [1, 2, "ok"], [1, 3, "ok"], [2, 4, "prior_only"],
                            [0, 4, "rejected"], [3, 99, "ok"], ["bad"]]},
        "trajectory_plot": {"t": t, "x_before": [0.27 * s for s in t],
                            "y_before": [math.sin(s / 5) for s in t],
                            "x_after": [0.27 * s + 1e-4 * s for s in t],
                            "y_after": [math.sin(s / 5) if s != 5.0 else None for s in t]},
    }


class StrictParser(HTMLParser):
    """Collects text and the first nesting error (HTMLParser itself never complains)."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        if tag not in VOID and tag not in SVG_LEAVES:
            self.errors.append(f"self-closed <{tag}/>")

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def png_pixel_bytes(data: bytes) -> bytes:
    """The decompressed image data of a PNG (filter bytes included): enough to tell blank from not."""
    idat, pos = b"", 8
    while pos < len(data):
        (length,), kind = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        if kind == b"IDAT":
            idat += data[pos + 8:pos + 8 + length]
        pos += 12 + length
    return zlib.decompress(idat)


def parse(page: str) -> StrictParser:
    parser = StrictParser()
    parser.feed(page)
    parser.close()
    return parser


@pytest.fixture(scope="module")
def page() -> str:
    return render_html(synthetic_report())


def test_page_is_well_formed(page):
    parser = parse(page)
    assert parser.errors == []
    assert parser.stack == []
    assert page.startswith("<!doctype html>")


def test_page_has_the_plots(page):
    # plan, link graph, sigma along time, correction, one histogram per observation kind
    assert page.count("<svg") >= 6
    assert page.count("<polyline") >= 5
    assert "cbar-plan" in page  # the colour bar of the plan view


def test_page_is_self_contained(page):
    assert "http://" not in page
    assert "https://" not in page
    assert "<script" not in page
    assert "<link" not in page
    assert not re.search(r"\bsrc=", page)
    assert "url(" not in page.replace("url(#", "")  # only references into the page itself


def test_text_is_escaped(page):
    assert "<b>" not in page
    assert "&lt;b&gt;" in page
    assert "&lt;traj&gt;" in page
    assert 'name = &quot;&lt;&amp;&gt;&quot;' in page


def test_key_figures_appear(page):
    text = " ".join(parse(page).text)
    assert "0.874" in text  # sigma0
    assert "FAILED" in text
    assert "mean 6.8\u2009mm" in text  # gaps before/after
    assert "max 24.8\u2009mm" in text
    assert "RMS 2.3\u2009mm" in text  # position sigma
    assert "2\u202f025\u202f310" in text  # points
    assert "Rejected observations (1)" in text


def test_nan_and_none_become_dashes(page):
    text = " ".join(parse(page).text)
    assert "max \u2013" in text  # orientation sigma max is None
    assert "nan" not in text.lower().replace("nance", "")  # no 'nan' printed (variance is fine)


@pytest.mark.parametrize("drop", ["trajectory_plot", "stations", "links", "adjustment", "before_after",
                                  "inputs"])
def test_missing_sections_do_not_crash(drop):
    report = synthetic_report()
    del report[drop]
    parser = parse(render_html(report))
    assert parser.errors == []


def test_empty_and_odd_reports_do_not_crash():
    odd = ({}, {"stations": {"rows": "not a list"}}, {"adjustment": {"normalised_residuals": {"x": 3}}},
           {"links": {"pairs": [[0, 1]]}, "stations": {"rows": [{"x": 1.0, "y": 1.0}, {}]}})
    for report in odd:
        parser = parse(render_html(report))
        assert parser.errors == []


def test_numpy_values_from_build_report():
    # The pipeline passes build_report's dict (numpy scalars and arrays, NaN) straight in.
    report = synthetic_report()
    report["adjustment"]["sigma0"] = np.float64(0.8737)
    report["adjustment"]["global_test_passed"] = np.bool_(True)
    report["adjustment"]["normalised_residuals"]["planes"] = np.array([0.1, np.nan, 0.5])
    report["stations"]["n"] = np.int64(6)
    report["before_after"]["gap_per_station_mm"] = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    page = render_html(report)
    assert "0.874" in page
    assert "global test passed" in page


def test_large_coordinates_get_an_axis_offset():
    report = copy.deepcopy(synthetic_report())
    for row in report["stations"]["rows"]:
        row["x"] += 500000.0
        row["y"] += 5300000.0
    plot = report["trajectory_plot"]
    plot["x_before"] = [x + 500000.0 for x in plot["x_before"]]
    plot["x_after"] = [x + 500000.0 for x in plot["x_after"]]
    plot["y_before"] = [y + 5300000.0 for y in plot["y_before"]]
    plot["y_after"] = [None if y is None else y + 5300000.0 for y in plot["y_after"]]
    page = render_html(report)
    assert "x \u2212 500000 [m]" in page
    assert "y \u2212 5300000 [m]" in page


def test_doctests():
    assert doctest.testmod(kinreg.report.html).failed == 0


@pytest.mark.browser
def test_renders_in_headless_chromium(page, tmp_path):
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is absent")
    html_file, png = tmp_path / "report.html", tmp_path / "report.png"
    html_file.write_text(page, encoding="utf-8")
    subprocess.run(
        [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={png}", "--window-size=1280,2000",
         html_file.as_uri()],
        check=True, timeout=60, capture_output=True,
    )
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pixels = png_pixel_bytes(data)
    assert len(pixels) > 1280 * 1000 * 3  # the full window
    # Non-blank: a blank page is one colour; text, plots and a colour bar bring hundreds.
    assert len(set(pixels[::7])) > 100
