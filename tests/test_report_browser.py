"""The report with its cloud images in headless Chromium: images decoded, nothing clipped at 1280 px
or on a phone, printed on A4 (marker ``browser``; skips without /usr/bin/chromium)."""

from __future__ import annotations

import html
import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_report_cloud import drifted_pass, views_for
from test_report_html import png_pixel_bytes, synthetic_report

from kinreg.report.html import render_html

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars"]

# Runs after load in a copy of the page (the report itself has no script): what a reader would see.
PROBE = """<script>
window.addEventListener('load', () => {
  const width = document.documentElement.clientWidth;
  const clipped = [];
  for (const el of document.querySelectorAll('.card, figure, .verdict, h1, h2, .cards td, .cards th, img')) {
    const box = el.getBoundingClientRect();
    if (box.width > 0 && (box.right > width + 0.5 || box.left < -0.5)) clipped.push(el.tagName + '.' + el.className);
  }
  const overflowing = [...document.querySelectorAll('.card')].filter(c => c.scrollWidth > c.clientWidth + 1)
    .map(c => (c.querySelector('h3') || {}).textContent);
  const images = [...document.images].map(i => ({w: i.naturalWidth, h: i.naturalHeight, done: i.complete,
    alt: i.alt, shown: i.getBoundingClientRect().width}));
  const pre = document.createElement('pre');
  pre.id = 'probe';
  pre.textContent = JSON.stringify({width, scrollWidth: document.documentElement.scrollWidth, clipped,
    overflowing, images});
  window.parent.document.body.appendChild(pre);  // the host page when the report is in a phone-wide frame
});
</script>"""


def chromium(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    profile = tmp_path / f"profile-{len(list(tmp_path.glob('profile-*')))}"
    return subprocess.run([str(CHROMIUM), *FLAGS, f"--user-data-dir={profile}", *args], check=True, timeout=90,
                          capture_output=True, text=True)


@pytest.fixture(scope="module")
def report_page(tmp_path_factory) -> tuple[Path, str]:
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is absent")
    out = tmp_path_factory.mktemp("run")
    before, after, times = drifted_pass(np.random.default_rng(2), 0.05)
    views = views_for(before, after, times + 1000.0)
    views.add(before, after, times + 1000.0)
    report = {**synthetic_report(), **views.finish(out)}
    report["crs"] = {"name": "ETRS89 / UTM zone 32N (a long name that must wrap on a phone)", "epsg": 25832}
    page = render_html(report, base_dir=out)
    (out / "report.html").write_text(page, encoding="utf-8")
    return out, page


def probe(tmp_path: Path, page: str, width: int) -> dict:
    """What :data:`PROBE` sees of ``page`` in a viewport ``width`` px wide. Headless Chromium's
    window is at least 500 px wide, so narrower viewports are an iframe of that width."""
    probed = page.replace("</body>", PROBE + "</body>")
    if width < 500:
        probed = (f'<!doctype html><html><body style="margin:0"><iframe style="width:{width}px;height:900px;'
                  f'border:0" srcdoc="{html.escape(probed, quote=True)}"></iframe></body></html>')
    target = tmp_path / f"probe-{width}.html"
    target.write_text(probed, encoding="utf-8")
    dom = chromium(tmp_path, "--dump-dom", "--virtual-time-budget=5000", f"--window-size={max(width, 500)},900",
                   target.as_uri()).stdout
    found = re.search(r'<pre id="probe">(.*?)</pre>', dom, re.S)
    assert found, dom[-500:]
    seen = json.loads(html.unescape(found.group(1)))
    assert seen["width"] == width  # the viewport the test meant
    return seen


@pytest.mark.browser
@pytest.mark.parametrize("width", [1280, 390])
def test_images_decode_and_nothing_is_clipped(report_page, tmp_path, width):
    _, page = report_page
    seen = probe(tmp_path, page, width)
    images = seen["images"]
    assert len(images) == 10  # section before/after, 3 insets before/after, thickness before/after
    for image in images:
        assert image["done"] and image["w"] > 0 and image["h"] > 0
        assert len(image["alt"]) > 20
        assert 0 < image["shown"] <= width
    assert seen["scrollWidth"] <= seen["width"], "the page scrolls sideways"
    assert seen["clipped"] == []
    assert seen["overflowing"] == [], "a card needs scrolling to show its values"


@pytest.mark.browser
def test_screenshot_shows_the_report(report_page, tmp_path):
    out, _ = report_page
    png = tmp_path / "report.png"
    chromium(tmp_path, f"--screenshot={png}", "--window-size=1280,4000", "--virtual-time-budget=5000",
             (out / "report.html").as_uri())
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pixels = png_pixel_bytes(data)
    assert len(pixels) > 1280 * 4000 * 3
    assert len(set(pixels[::7])) > 100  # not blank


@pytest.mark.browser
def test_prints_on_a4(report_page, tmp_path):
    out, _ = report_page
    pdf = tmp_path / "report.pdf"
    chromium(tmp_path, f"--print-to-pdf={pdf}", "--no-pdf-header-footer", "--virtual-time-budget=5000",
             (out / "report.html").as_uri())
    data = pdf.read_bytes()
    boxes = {tuple(round(float(v)) for v in m) for m in
             re.findall(rb"/MediaBox\s*\[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", data)}
    assert boxes == {(595, 842)}  # A4 in points, every page
    assert data.count(b"/Type /Page\n") + data.count(b"/Type /Page ") + data.count(b"/Type/Page\n") >= 2 or \
        len(re.findall(rb"/Type\s*/Page[^s]", data)) >= 2
