"""The real hall's export (benchmarks/real_hall.py) on the public dataset, where a copy is at hand:
``KINREG_REAL_HALL`` names the dataset's folder or a git mirror of its repository (skipped without)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

DATA = Path(os.environ.get("KINREG_REAL_HALL", "/work/.mirror/hku-mars+BALM/repo"))


@pytest.fixture(scope="module")
def hall():
    if not DATA.exists():
        pytest.skip(f"the real hall is absent ({DATA}; set KINREG_REAL_HALL)")
    import real_hall

    return real_hall, real_hall.read_hall(DATA)


def test_the_hall_is_read_whole(hall):
    real_hall, h = hall
    assert len(h.stamps_s) == 177 and np.all(np.diff(h.stamps_s) > 0.4)
    assert sum(len(p) for p in h.points_body) > 13_000_000
    assert np.allclose(np.linalg.det(h.T_world_body[:, :3, :3]), 1.0, atol=1e-4)


def test_an_export_without_drift_is_the_cloud_on_the_dataset_s_poses(hall, tmp_path):
    real_hall, h = hall
    # a few keyframes are enough to check the frames and times
    few = real_hall.Hall(h.stamps_s[:9], h.T_world_body[:9], h.points_body[:9], h.intensity[:9])
    ref = real_hall.reference_trajectory(few)
    times = np.concatenate(real_hall.point_times(few))
    p_world = real_hall.world_points(few)
    assert np.all((times > few.stamps_s[0] - 0.1 - 1e-9) & (times <= few.stamps_s[-1]))
    drifted = real_hall.export(few, ref, times, p_world, np.concatenate(few.intensity), "slam", 0.0, 0.0, 1, tmp_path)
    assert np.allclose(drifted.poses.t_xyz, ref.poses.t_xyz, atol=1e-9)
    import laspy

    las = laspy.read(tmp_path / "cloud.laz")
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    order = np.argsort(times, kind="stable")
    assert np.max(np.abs(xyz - p_world[order])) < 1e-4  # the LAS quantum
