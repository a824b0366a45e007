"""corrected.laz written with decoding and encoding overlapped equals the correction applied to
every point at once."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from conftest import make_trajectory, random_correction

from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose
from kinreg.run.corrected_cloud import with_per_point_dimensions, write_corrected_las


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_chunked_overlapped_writer_gives_every_point_its_correction(tmp_path, suffix) -> None:
    rng = np.random.default_rng(3)
    traj = make_trajectory(40.0)
    correction, _, _ = random_correction(traj, 8, rng, 0.003, 0.03, margin_s=1.0)
    n = 25_000
    t = rng.uniform(traj.t_start_s, traj.t_end_s, n)  # not time-sorted
    xyz = traj.pose_at(t).t_xyz + rng.normal(0, 5.0, (n, 3))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([1e-4, 1e-4, 1e-4]), np.array([0.0, 0.0, 0.0])
    source = tmp_path / f"in{suffix}"
    with laspy.open(source, mode="w", header=header, do_compress=suffix == ".laz") as w:
        rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
        rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec.gps_time = t
        rec.intensity = np.arange(n) % 65536
        w.write_points(rec)
    stored = laspy.read(source)
    xyz_stored = np.column_stack([stored.x, stored.y, stored.z])

    target = tmp_path / f"out{suffix}"
    observer = CopyingObserver()
    assert write_corrected_las(source, target, correction, chunk_points=3_000, observer=observer) == n  # 9 chunks
    out = laspy.read(target)
    expected = correction.apply_to_points(xyz_stored, np.asarray(stored.gps_time))
    # the scale's rounding, and the grid of the correction placed per chunk (within a micrometre)
    assert np.abs(np.column_stack([out.x, out.y, out.z]) - expected).max() <= 0.5e-4 + 1e-6
    assert np.array_equal(out.gps_time, stored.gps_time)  # same order
    assert np.array_equal(out.intensity, stored.intensity)
    # the observer (the report's views) saw every chunk once, in order, before and after
    assert [len(c) for c in observer.stamps] == [3_000] * 8 + [1_000]
    assert np.array_equal(np.concatenate(observer.stamps), stored.gps_time)
    assert np.array_equal(np.concatenate(observer.before), xyz_stored)
    assert np.abs(np.concatenate(observer.after) - expected).max() <= 1e-6


class CopyingObserver:
    """Keeps a copy of every chunk it is given."""

    def __init__(self) -> None:
        self.before: list[np.ndarray] = []
        self.after: list[np.ndarray] = []
        self.stamps: list[np.ndarray] = []

    def add(self, xyz_before: np.ndarray, xyz_after: np.ndarray, stamps_s: np.ndarray,
            sigma_mm: np.ndarray | None = None, correction_mm: np.ndarray | None = None) -> None:
        self.before.append(np.array(xyz_before))
        self.after.append(np.array(xyz_after))
        self.stamps.append(np.array(stamps_s))


def test_chunk_integers_are_those_of_laspy_scaled_setters(tmp_path) -> None:
    """The raw-integer path of a chunk (coordinates from X * scale + offset, back by rounding) gives
    exactly the integers of laspy's scaled views (``points.x = ...``) with the same correction, and
    the same overflow error."""
    from kinreg.errors import CloudError
    from kinreg.run.corrected_cloud import _corrected, with_per_point_dimensions

    rng = np.random.default_rng(4)
    traj = make_trajectory(30.0, offset=(500_000.0, 5_400_000.0, 300.0))
    correction, ts, initial = random_correction(traj, 6, rng, 0.003, 0.03, margin_s=1.0)
    n = 150_000  # more than one block of the rounding
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([1e-4, 1e-4, 1e-3]), np.array([500_000.0, 5_400_000.0, 300.0])
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    t = rng.uniform(traj.t_start_s, traj.t_end_s, n)
    xyz = traj.pose_at(t).t_xyz + rng.normal(0, 5.0, (n, 3))
    rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec.gps_time = t
    expected = laspy.ScaleAwarePointRecord(rec.array.copy(), rec.point_format, rec.scales, rec.offsets)
    fixed = correction.apply_to_points(np.column_stack([expected.x, expected.y, expected.z]), t)
    expected.x, expected.y, expected.z = fixed[:, 0], fixed[:, 1], fixed[:, 2]

    before = rec.array["X"].copy()
    header = with_per_point_dimensions(header)
    got, extremes, _ = _corrected(rec, correction, header, tmp_path / "in.laz", None, 0.0, None)
    for dim, (lo, hi) in zip("XYZ", extremes, strict=True):
        assert np.array_equal(got.array[dim], expected.array[dim])
        assert (lo, hi) == (got.array[dim].min(), got.array[dim].max())
    assert np.abs(got.array["X"] - before).max() > 10  # the correction moved the points (> 1 mm)

    far = DriftCorrection.from_stations(ts, initial, initial.compose(Pose(initial.quat_wxyz * 0 + [1, 0, 0, 0],
                                                                         np.full((6, 3), 1e6))), traj)
    with pytest.raises(CloudError, match="does not fit"):
        _corrected(laspy.ScaleAwarePointRecord(rec.array.copy(), rec.point_format, rec.scales, rec.offsets),
                   far, header, tmp_path / "in.laz", None, 0.0, None)


@pytest.mark.parametrize("point_format", [6, 1])
def test_header_statistics_are_laspys(tmp_path, point_format) -> None:
    """The header of corrected.laz (bounds, point count, points by return), gathered from the
    correction instead of laspy's ``LasHeader.grow``, is byte for byte the one laspy writes for the
    same points; also with several return numbers (4 bits in format 6, 3 in format 1) and points
    without a finite time left out."""
    rng = np.random.default_rng(5)
    traj = make_trajectory(30.0)
    correction, _, _ = random_correction(traj, 6, rng, 0.003, 0.03, margin_s=1.0)
    n = 20_000
    t = rng.uniform(traj.t_start_s, traj.t_end_s, n)
    t[::997] = np.nan
    xyz = traj.pose_at(np.nan_to_num(t, nan=traj.t_start_s)).t_xyz + rng.normal(0, 5.0, (n, 3))
    header = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    header.scales, header.offsets = np.array([1e-4, 1e-4, 1e-3]), np.array([10.0, -20.0, 0.0])
    source = tmp_path / "in.laz"
    with laspy.open(source, mode="w", header=header, do_compress=True) as w:
        rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
        rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec.gps_time = t
        top = 15 if point_format >= 6 else 7
        rec.return_number = rng.integers(0, top + 1, n)
        rec.number_of_returns = np.full(n, top, dtype=np.uint8)
        w.write_points(rec)

    target = tmp_path / "out.laz"
    assert write_corrected_las(source, target, correction, chunk_points=3_000) == n - len(t[::997])
    written = laspy.read(target)
    again = tmp_path / "again.laz"  # the same points through laspy's own writer
    with laspy.open(source) as r, laspy.open(again, mode="w", header=with_per_point_dimensions(r.header),
                                             do_compress=True) as w:
        for a in range(0, len(written.points), 3_000):
            w.write_points(written.points[a:a + 3_000])
    with open(target, "rb") as f, open(again, "rb") as g:
        size = written.header.offset_to_point_data
        assert f.read(size) == g.read(size)
    assert written.header.number_of_points_by_return[1:5].min() > 0  # LAS 1.2 stores 5
