"""Kinematic vs static: signed distances to the static cloud's local planes, before and after."""

from __future__ import annotations

import numpy as np
import pytest
from test_report_cloud import UTM, room

from kinreg.report.deviations import Deviations, StaticPlanes


@pytest.mark.parametrize("origin", [np.zeros(3), UTM])
def test_distances_along_the_static_normals(origin):
    rng = np.random.default_rng(4)
    static = room(200_000, rng, noise_m=0.001, origin=origin)
    station = origin + [5.0, 3.0, 1.5]  # inside the room: normals point inwards
    planes = StaticPlanes.from_scans([(static, station)], origin - 1.0)
    assert len(planes.keys) > 300
    kinematic = room(100_000, rng, noise_m=0.004, origin=origin)
    deviations = Deviations(planes, stride=1)
    deviations.add("after", kinematic)
    # Before: the kinematic cloud pushed 10 mm outwards (towards +x, +y, +z in every direction would not be
    # one sign; a shift of +10 mm in x moves the wall x = 10 away from the station, the wall x = 0 towards it).
    deviations.add("before", kinematic + [0.010, 0.0, 0.0])
    figures = deviations.figures(noise_mm=4.0)
    after, before = figures["after"], figures["before"]
    assert after["n"] > 50_000
    assert abs(after["mean_mm"]) < 0.3
    assert after["rms_mm"] == pytest.approx(np.hypot(4.0, 1.0), rel=0.15)
    assert after["share_within_2_noise"] == pytest.approx(0.95, abs=0.03)
    assert after["share_within_3_noise"] == pytest.approx(0.997, abs=0.01)
    # A third of the points are on the walls x = 0 or x = 10: 10 mm off, with opposite signs.
    assert before["rms_mm"] > after["rms_mm"] + 1.5
    assert before["share_within_2_noise"] < after["share_within_2_noise"] - 0.1
    hist = np.array(before["histogram"])
    assert sum(hist) == before["n"]


def test_cloud_views_report_the_deviations_and_the_page_shows_them(tmp_path):
    from test_report_cloud import drifted_pass

    from kinreg.config import ReportConfig
    from kinreg.report.cloud_views import CloudViews
    from kinreg.report.html import render_html

    rng = np.random.default_rng(8)
    static = room(150_000, rng, noise_m=0.001)
    planes = StaticPlanes.from_scans([(static, np.array([5.0, 3.0, 1.5]))], np.full(3, -2.0))
    before, after, times = drifted_pass(rng, 0.02)
    views = CloudViews(ReportConfig(), np.minimum(before.min(0), after.min(0)), before.max(0), 0.0, 150.0,
                       static_planes=planes)
    views.add(before, after, times)
    result = views.finish(tmp_path)
    deviations = result["cloud"]["static_deviations"]
    # Noise: the corrected cloud's median plane thickness (3 mm); half the points were 20 mm off before.
    assert deviations["noise_mm"] == pytest.approx(3.0, rel=0.25)
    assert deviations["after"]["rms_mm"] < 4.0 < 8.0 < deviations["before"]["rms_mm"]
    page = render_html(result, base_dir=tmp_path)
    assert "Kinematic vs static" in page
    assert 'aria-label="Histogram of the signed distances' in page
    assert page.count("<polyline") == 2  # before and after
