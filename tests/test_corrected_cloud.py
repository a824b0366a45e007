"""corrected.laz written with decoding and encoding overlapped equals the correction applied to
every point at once."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from conftest import make_trajectory

from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.run.corrected_cloud import write_corrected_las


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_chunked_overlapped_writer_gives_every_point_its_correction(tmp_path, suffix) -> None:
    rng = np.random.default_rng(3)
    traj = make_trajectory(40.0)
    ts = np.linspace(traj.t_start_s + 1.0, traj.t_end_s - 1.0, 8)
    initial = traj.pose_at(ts)
    adjusted = initial.compose(Pose(rotvec_to_quat(rng.normal(0, 0.003, (8, 3))), rng.normal(0, 0.03, (8, 3))))
    correction = DriftCorrection.from_stations(ts, initial, adjusted, traj)
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
    assert write_corrected_las(source, target, correction, chunk_points=3_000) == n  # 9 chunks
    out = laspy.read(target)
    expected = correction.apply_to_points(xyz_stored, np.asarray(stored.gps_time))
    # the scale's rounding, and the grid of the correction placed per chunk (within a micrometre)
    assert np.abs(np.column_stack([out.x, out.y, out.z]) - expected).max() <= 0.5e-4 + 1e-6
    assert np.array_equal(out.gps_time, stored.gps_time)  # same order
    assert np.array_equal(out.intensity, stored.intensity)
