"""The per-point correction on a time grid equals the correction evaluated at every point."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_trajectory

from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.types import Trajectory


def _exact(c: DriftCorrection, xyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Today's formula at every point: R(t) (x - p(t)) + p(t) + delta(t) from the spline."""
    rotvec, delta, pivot = c.at(t)
    R = Pose(rotvec_to_quat(rotvec), np.zeros_like(delta)).rotation_matrix
    return np.einsum("nij,nj->ni", R, xyz - pivot) + pivot + delta


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (500_000.0, 5_400_000.0, 300.0)])
def test_grid_correction_is_within_a_hundredth_of_a_millimetre_of_the_exact_one(offset) -> None:
    rng = np.random.default_rng(1)
    traj: Trajectory = make_trajectory(60.0, offset=offset)
    ts = np.linspace(traj.t_start_s + 2.0, traj.t_end_s - 2.0, 12)  # points before and after the stations too
    initial = traj.pose_at(ts)
    adjusted = initial.compose(Pose(rotvec_to_quat(rng.normal(0, 0.005, (12, 3))), rng.normal(0, 0.05, (12, 3))))
    correction = DriftCorrection.from_stations(ts, initial, adjusted, traj)
    t = np.sort(rng.uniform(traj.t_start_s, traj.t_end_s, 200_000))
    xyz = traj.pose_at(t).t_xyz + rng.normal(0, 15.0, (len(t), 3))
    fast = correction.apply_to_points(xyz, t)
    exact = _exact(correction, xyz, t)
    assert np.abs(fast - exact).max() < 1e-5  # metres: 0.01 mm
    assert np.abs(fast - xyz).max() > 0.01  # and the correction is not nothing


def test_identity_correction_leaves_points_exactly_as_they_are() -> None:
    traj = make_trajectory(20.0)
    ts = np.linspace(traj.t_start_s + 1, traj.t_end_s - 1, 5)
    poses = traj.pose_at(ts)
    correction = DriftCorrection.from_stations(ts, poses, poses, traj)
    xyz = traj.poses.t_xyz + 3.0
    assert np.array_equal(correction.apply_to_points(xyz, traj.stamps_s), xyz)
    assert correction.apply_to_points(np.zeros((0, 3)), np.zeros(0)).shape == (0, 3)
