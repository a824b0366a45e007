"""corrected.laz carries each point's 3D position sigma and correction length as documented extra
bytes, keeps the input's own extra bytes, and the report maps both."""

from __future__ import annotations

import re

import laspy
import numpy as np
import pytest
from conftest import make_trajectory
from test_report_cloud import decode_png

from kinreg.config import ReportConfig
from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.report.cloud_views import CloudViews
from kinreg.report.html import render_html
from kinreg.run.corrected_cloud import (
    CORRECTION_DESCRIPTION,
    CORRECTION_DIMENSION,
    PER_POINT_QUANTUM_MM,
    SIGMA_DESCRIPTION,
    SIGMA_DIMENSION,
    write_corrected_las,
)

SCALE = 1e-4


def growing_correction(traj, rng):
    """Six stations; the first is the datum (sigma 0, no correction), the sigmas grow away from it."""
    ts = np.linspace(traj.t_start_s + 2.0, traj.t_end_s - 2.0, 6)
    initial = traj.pose_at(ts)
    turns, shifts = rng.normal(0, 0.002, (6, 3)), rng.normal(0, 0.03, (6, 3))
    turns[0], shifts[0] = 0.0, 0.0
    adjusted = initial.compose(Pose(rotvec_to_quat(turns), shifts))
    sigma_m = np.array([0.0, 0.002, 0.004, 0.006, 0.008, 0.010])
    return DriftCorrection.from_stations(ts, initial, adjusted, traj, sigma_3d_m=sigma_m), ts, sigma_m


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    rng = np.random.default_rng(11)
    traj = make_trajectory(40.0)
    correction, ts, sigma_m = growing_correction(traj, rng)
    n = 30_000
    t = np.sort(rng.uniform(traj.t_start_s, traj.t_end_s, n))
    xyz = traj.pose_at(t).t_xyz + rng.normal(0, 5.0, (n, 3))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([SCALE] * 3), np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams("reflectance", np.int16, "reflectance [0.01 dB]",
                                                  scales=[0.01], offsets=[-10.0]),
                           laspy.ExtraBytesParams("ring", np.uint8, "laser ring")])
    tmp = tmp_path_factory.mktemp("per_point")
    source, target = tmp / "in.laz", tmp / "out.laz"
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec.gps_time = t
    rec["reflectance"] = rng.uniform(-10, 300, n)
    rec["ring"] = np.arange(n) % 16
    with laspy.open(source, mode="w", header=header, do_compress=True) as w:
        w.write_points(rec)
    views = CloudViews(ReportConfig(), xyz.min(0), xyz.max(0), float(t[0]), float(t[-1]))
    assert write_corrected_las(source, target, correction, chunk_points=7_000, observer=views) == n
    return laspy.read(source), laspy.read(target), correction, ts, sigma_m, views, tmp


def test_the_two_dimensions_carry_their_descriptions(written):
    _, out, *_ = written
    structs = {s.name.rstrip(b"\0").decode(): s for s in out.header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs}
    assert structs[SIGMA_DIMENSION].description.rstrip(b"\0").decode() == SIGMA_DESCRIPTION
    assert structs[CORRECTION_DIMENSION].description.rstrip(b"\0").decode() == CORRECTION_DESCRIPTION
    assert "[mm]" in SIGMA_DESCRIPTION and "[mm]" in CORRECTION_DESCRIPTION
    for name in (SIGMA_DIMENSION, CORRECTION_DIMENSION):
        assert out.points.array.dtype[name] == np.float32


def test_sigma_is_zero_at_the_datum_and_grows_away(written):
    src, out, _, ts, sigma_m, *_ = written
    t = np.asarray(out.gps_time)
    sigma = np.asarray(out[SIGMA_DIMENSION], dtype=np.float64)
    assert np.all(sigma >= 0.0)
    at_datum = np.abs(t - ts[0]) < 0.005
    assert at_datum.any() and sigma[at_datum].max() < 0.01  # mm: zero at the datum station's time
    assert np.all(sigma[t <= ts[0]] == sigma[at_datum].min())  # held before the first station
    assert np.all(np.diff(sigma[t >= ts[0]]) >= -1e-4)  # growing away from it (sorted times)
    for k in range(1, len(ts)):  # the stations' sigmas at their times
        near = np.abs(t - ts[k]) < 0.005
        assert sigma[near] == pytest.approx(sigma_m[k] * 1000.0, abs=0.01)


def test_correction_length_is_the_coordinate_change(written):
    src, out, *_ = written
    moved = np.column_stack([out.x - src.x, out.y - src.y, out.z - src.z])
    length_mm = np.linalg.norm(moved, axis=1) * 1000.0
    # within the LAS quantum: each coordinate rounded to the scale, before and after
    quantum_mm = np.sqrt(3) * SCALE * 1000.0 + PER_POINT_QUANTUM_MM / 2
    assert np.abs(np.asarray(out[CORRECTION_DIMENSION]) - length_mm).max() <= quantum_mm
    assert np.median(length_mm) > 1.0  # the correction moved the points


def test_the_inputs_extra_bytes_are_kept(written):
    src, out, *_ = written
    assert list(out.point_format.dimension_names)[:len(list(src.point_format.dimension_names))] == \
        list(src.point_format.dimension_names)
    for name in ("reflectance", "ring", "gps_time", "intensity"):
        assert np.array_equal(np.asarray(out[name]), np.asarray(src[name])), name
    structs = {s.name.rstrip(b"\0").decode(): s for s in out.header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs}
    assert structs["reflectance"].description.rstrip(b"\0").decode() == "reflectance [0.01 dB]"
    assert structs["reflectance"].scale[0] == 0.01 and structs["reflectance"].offset[0] == -10.0
    assert structs["ring"].description.rstrip(b"\0").decode() == "laser ring"


def test_a_corrected_cloud_processed_again_keeps_one_of_each(written, tmp_path):
    _, _, correction, *_, tmp = written
    again = tmp_path / "again.laz"
    write_corrected_las(tmp / "out.laz", again, correction)
    names = list(laspy.read(again).point_format.dimension_names)
    assert names.count(SIGMA_DIMENSION) == 1 and names.count(CORRECTION_DIMENSION) == 1


def test_the_report_maps_both(written):
    *_, views, tmp = written
    result = views.finish(tmp)
    per_point = result["cloud"]["per_point"]
    assert set(per_point["images"]) == {"sigma_3d", "correction"}
    for path in per_point["images"].values():
        image = decode_png((tmp / path).read_bytes())
        assert image.shape[0] > 50 and image.shape[1] >= 400
    assert 0.0 < per_point["sigma_3d_median_mm"] < 12.0
    assert per_point["correction_median_mm"] > 1.0
    page = render_html({"schema_version": 1, **result}, base_dir=tmp)
    assert len(re.findall(r'<img [^>]*alt="Map of the median (?:3D position sigma|correction length)', page)) == 2
    assert "sigma_3d_mm" in page
