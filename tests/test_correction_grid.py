"""The per-point correction on a time grid equals the correction evaluated at every point."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_trajectory, random_correction

from kinreg.estimate.correction import DriftCorrection, _interval_runs
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
    # points before and after the stations too
    correction, _, _ = random_correction(traj, 12, rng, 0.005, 0.05, margin_s=2.0)
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


@pytest.mark.parametrize("coupling", [0.0, 1.0])
def test_a_coupled_attitude_error_turns_points_about_the_sensor_where_it_was(coupling) -> None:
    """GNSS/INS-like: the positions are right and the attitude is off by a heading error that grows
    along the run, so a point seen at time t is off by that error turned about the sensor at t,
    sway and turns included. With the coupling 1 the correction turns it back about the
    trajectory's own position; the stations' spline as pivot (coupling 0) is what a SLAM-like drift
    needs, and here misses by the heading error times the sway (5 mrad x 0.3 m = 1.5 mm)."""
    t = np.arange(0.0, 60.0, 0.01)
    xyz = np.column_stack([0.5 * t, 0.3 * np.sin(2 * np.pi * t / 5.0), 0 * t])  # sway of 0.3 m at 0.2 Hz
    truth = Trajectory(t, Pose(np.tile([1.0, 0, 0, 0], (len(t), 1)), xyz))
    heading = 5e-3 * t / t[-1]  # [rad]
    D = Pose(rotvec_to_quat(np.column_stack([0 * t, 0 * t, heading])), np.zeros((len(t), 3)))
    exported = Trajectory(t, Pose(D.compose(truth.poses).quat_wxyz, xyz))  # positions right, attitude off
    stamps = np.arange(3.0, 60.0, 6.0)
    initial, adjusted = exported.pose_at(stamps), truth.pose_at(stamps)
    correction = DriftCorrection.from_stations(stamps, initial, adjusted, exported, coupling=coupling)
    rng = np.random.default_rng(3)
    when = rng.uniform(stamps[0], stamps[-1], 2000)
    in_sensor = rng.uniform(-5.0, 5.0, (2000, 3))
    seen = exported.pose_at(when).apply(in_sensor)
    error = np.linalg.norm(correction.apply_to_points(seen, when) - truth.pose_at(when).apply(in_sensor), axis=1)
    if coupling == 1.0:
        assert error.max() < 1e-5
    else:
        assert error.max() > 5e-4
    corrected = correction.apply_to_trajectory(exported)
    position_error = np.abs(corrected.poses.t_xyz - xyz).max()
    assert (position_error < 1e-9) if coupling == 1.0 else (position_error > 5e-4)


def _grid_reference(c: DriftCorrection, xyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The grid correction as first written: the 15 node values of every point gathered into (n, 15)
    and combined per point, in one block (what the blocked, row-wise loop must reproduce bit for bit)."""
    from kinreg.estimate.correction import POINT_GRID_S

    lo, hi = float(t.min()), float(t.max())
    nodes = lo + POINT_GRID_S * np.arange(int(np.ceil((hi - lo) / POINT_GRID_S)) + 2)
    grid = np.union1d(nodes, c.stamps_s[[0, -1]]).astype(np.float64)
    rotvec, delta, pivot = c.at(grid)
    A = Pose(rotvec_to_quat(rotvec), np.zeros_like(delta)).rotation_matrix - np.eye(3)
    origin = pivot[0]
    table = np.hstack([A.reshape(-1, 9), delta, pivot - origin])
    slope = np.diff(table, axis=0) / np.diff(grid)[:, None]
    k = np.clip(np.searchsorted(grid, t, side="right") - 1, 0, len(grid) - 2)
    v = table[k] + (t - grid[k])[:, None] * slope[k]
    d = xyz - (v[:, 12:15] + origin)
    out = np.empty_like(xyz)
    for i in range(3):
        out[:, i] = v[:, 3 * i] * d[:, 0] + v[:, 3 * i + 1] * d[:, 1] + v[:, 3 * i + 2] * d[:, 2]
    return out + xyz + v[:, 9:12]


@pytest.mark.parametrize(("layout", "order"), [("C", "random"), ("F", "random"), ("F", "sorted"), ("C", "sorted")])
def test_blocked_row_wise_correction_gives_the_bits_of_the_per_point_formula(layout, order) -> None:
    """Row-wise in cache-sized blocks (and on columns of either memory order; time-sorted points
    through the runs of each grid interval), the correction computes exactly what the per-point
    formula does: corrected.laz keeps its integers."""
    rng = np.random.default_rng(5)
    traj = make_trajectory(60.0, offset=(500_000.0, 5_400_000.0, 300.0))
    correction, _, _ = random_correction(traj, 10, rng, 0.005, 0.05, margin_s=2.0)
    n = 70_000  # several blocks and a partial one
    t = rng.uniform(traj.t_start_s, traj.t_end_s, n)  # random: every block spans the run
    # times exactly on grid nodes (the interval above them), repeated times, and a gap of empty intervals
    t[:2000] = t.min() + 0.01 * np.arange(2000)
    t[2000:2500] = t[1000]
    t = t[(t < traj.t_start_s + 20.0) | (t > traj.t_start_s + 23.0)]
    if order == "sorted":
        t = np.sort(t)
    xyz = np.asarray(traj.pose_at(t).t_xyz + rng.normal(0, 15.0, (len(t), 3)), order=layout)
    fast = correction.apply_to_points(xyz, t)
    assert fast.shape == (len(t), 3)
    assert (_interval_runs(np.array([t.min(), t.max()]), t) is None) == (order == "random")
    assert np.array_equal(fast, _grid_reference(correction, np.ascontiguousarray(xyz), t))
    assert np.abs(fast - xyz).max() > 0.01
    # into a kept buffer (rows of a larger one, as corrected.laz reuses it chunk after chunk)
    buffer = np.full((3, len(t) + 100), np.nan)
    into = correction.apply_to_points(xyz, t, out=buffer[:, :len(t)])
    assert np.shares_memory(into, buffer) and np.array_equal(into, fast)
    with pytest.raises(ValueError, match="coordinate rows"):
        correction.apply_to_points(xyz, t, out=buffer[:, :len(t) - 1])
