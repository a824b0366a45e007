"""The drift inside a window (issue #14): a plane's time slope, the plane's change under a motion
(:func:`plane_motion_jacobian`), the window gain of a scan, the time offsets and slopes measured
from its points, and the block with a scan frame and a sensor pose per quasi-static station."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from planefixtures import plane_in_scan

from kinreg.config import BlockConfig
from kinreg.estimate.block import adjust_block
from kinreg.estimate.drift import DriftRates, plane_motion_jacobian, plane_time_offsets
from kinreg.estimate.frames import adjust_with_frames, sensor_nodes, window_gain
from kinreg.geometry import Pose, skew
from kinreg.types import ObservationKind, RelativeObservation, ScanKind, Station

RNG = np.random.default_rng(4)


def _plane(normal, d, centre, slope=(0.0, 0.0), tau=0.0):
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    centre = np.asarray(centre, float) + (d - n @ np.asarray(centre, float)) * n  # on the plane
    p = plane_in_scan(n, d, centre, (2.0, 1.5), Pose.identity(), 0, 0, 1e-4, 3e-4, None)
    return replace(p, t_offset_s=tau, t_slope_s_per_m=slope)


def _moved(p, displacement):
    """The plane's (tilt u, tilt v, offset at the origin) after its points move by
    ``displacement(x)``, from three points on it (exact for a small motion)."""
    u, v = 1e-3 * p.basis_uv  # the tilt at the centroid: a plane fit's, for a patch about it
    pts = np.array([p.centroid_xyz, p.centroid_xyz + u, p.centroid_xyz + v])
    moved = pts + np.array([displacement(x) for x in pts])
    n = np.cross(moved[1] - moved[0], moved[2] - moved[0])
    n /= np.linalg.norm(n) * np.sign(n @ p.normal)
    dn = n - p.normal
    return np.array([dn @ p.basis_uv[0], dn @ p.basis_uv[1], n @ moved[0] - p.d_m])


@pytest.mark.parametrize("slope", [(0.0, 0.0), (1.5, -0.7)])
def test_the_plane_change_under_a_motion_matches_moving_its_points(slope):
    """A wall seen from 1 s before to 1 s after the centre as the unit walks past it: a drift
    velocity moves each of its points by its own time; the Jacobian gives the tilt and offset
    that moving the points gives."""
    p = _plane((0.3, 1.0, 0.1), 4.0, (2.0, -4.0, 1.0), slope=slope, tau=0.8)
    twist = np.array([2e-4, -1e-4, 3e-4, 2e-5, -4e-5, 6e-5])  # a drift velocity (m/s, rad/s)
    g = np.asarray(slope)

    def displacement(x):
        tau = 0.8 + g @ (p.basis_uv @ (x - p.centroid_xyz))
        return tau * (twist[:3] + np.cross(twist[3:], x))

    expected = _moved(p, displacement)
    got = plane_motion_jacobian(p, 0.8, g) @ twist
    np.testing.assert_allclose(got, expected, rtol=5e-3, atol=1e-8)  # first order: the motion is small
    # a slope tilts the plane: without it the same velocity tilts it by the rotation only
    if any(slope):
        assert abs(got[0] - (plane_motion_jacobian(p, 0.8) @ twist)[0]) > 1e-5


def test_a_scan_seen_at_one_time_offset_moves_by_the_velocity_times_it():
    """Every plane seen 2 s after the centre, no slope: the frame its planes fix moves by the
    drift velocity times 2 s (the window gain is 2 I where the planes fix every direction)."""
    normals = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 0, 1)]
    planes = [_plane(n, 3.0 + k, (1.0 + k, 2.0 - k, 0.5 * k), tau=2.0) for k, n in enumerate(normals)]
    np.testing.assert_allclose(window_gain(planes), 2.0 * np.eye(6), atol=1e-3)


def test_time_offset_and_slope_of_a_swept_plane():
    """Points of a floor seen while walking along x at 0.5 m/s: their time rises by 2 s per metre
    along x; the slope along the plane's basis is that, projected."""
    x = RNG.uniform(-2, 2, 4000)
    y = RNG.uniform(-1, 1, 4000)
    pts = np.column_stack([x, y, -1.5 + RNG.normal(0, 0.002, 4000)])
    stamps = 100.0 + 0.3 + 2.0 * x + RNG.normal(0, 0.05, 4000)
    floor = plane_in_scan((0, 0, 1), -1.5, (0, 0, -1.5), (2.0, 1.0), Pose.identity(), 0, 0, 1e-4, 3e-4, None)
    offsets, slopes, _, _ = plane_time_offsets(pts, stamps, 100.0, [floor], 0.03)
    assert offsets[0] == pytest.approx(0.3, abs=0.02)
    along_x = np.array([1.0, 0.0, 0.0])
    in_plane = 2.0 * along_x - 2.0 * (along_x @ floor.normal) * floor.normal
    np.testing.assert_allclose(slopes[0] @ floor.basis_uv, in_plane, atol=0.02)


def _stations(n):
    poses = Pose(np.tile([1.0, 0, 0, 0], (n, 1)), np.column_stack([2.0 * np.arange(n), np.zeros(n), np.zeros(n)]))
    return [Station(k, f"s{k}", ScanKind.QUASI_STATIC, 6.0 * k, 6.0 * k - 3, 6.0 * k + 3, poses[k], 1000, 1.5)
            for k in range(n)], poses


def test_the_frame_model_returns_the_sensor_poses_and_names_stations():
    """Four stations, plane links between scan frames and trajectory links between sensor poses:
    the result has one pose per station (the sensor pose), tests name stations (a frame tie its
    station twice), and with stiff frame ties it is the plain block's solution."""
    stations, truth = _stations(4)
    rates = DriftRates(np.full(3, 1e-4), np.full(3, 1e-5), 1e-4, 1e-5)
    initial = Pose.exp(RNG.normal(0, [1e-3] * 3 + [1e-4] * 3, (4, 6))).compose(truth)
    initial = Pose(initial.quat_wxyz, initial.t_xyz)
    obs = []
    for i, j, kind, s in [(0, 1, ObservationKind.PLANES, 3e-4), (1, 2, ObservationKind.PLANES, 3e-4),
                          (0, 2, ObservationKind.PLANES, 5e-4), (2, 3, ObservationKind.PLANES, 3e-4),
                          (0, 1, ObservationKind.TRAJECTORY, 1e-3), (1, 2, ObservationKind.TRAJECTORY, 1e-3),
                          (2, 3, ObservationKind.TRAJECTORY, 1e-3)]:
        Z = truth[i].inverse().compose(truth[j]).compose(Pose.exp(RNG.normal(0, [s] * 3 + [s / 10] * 3)))
        obs.append(RelativeObservation(kind, i, j, Z, np.diag(1.0 / np.array([s] * 3 + [s / 10] * 3) ** 2), 6))
    fixed = np.array([True, False, False, False])
    assert sensor_nodes(stations) == {0: 4, 1: 5, 2: 6, 3: 7}
    gain = np.zeros((4, 6, 6))  # no drift inside the windows: the ties hold hard
    framed = adjust_with_frames(stations, initial, obs, fixed, rates, BlockConfig(), gain=gain)
    plain = adjust_block(initial, obs, fixed, BlockConfig())
    assert len(framed.poses) == 4 and framed.cov_xi.shape == (4, 6, 6)
    np.testing.assert_allclose(framed.poses.t_xyz, plain.poses.t_xyz, atol=2e-5)
    frames = [t for t in framed.tests if t.kind is ObservationKind.FRAME]
    assert sorted((t.i, t.j) for t in frames) == [(k, k) for k in range(4)]
    assert all(0 <= t.i < 4 and 0 <= t.j < 4 for t in framed.tests)
    # a loose tie (a window that drifts) lets the plane links and the trajectory disagree there:
    # the sensor poses then get larger sigmas than with the scan frames held to them
    loose = np.broadcast_to(np.eye(6) * 3.0, (4, 6, 6)).copy()
    wide = adjust_with_frames(stations, initial, obs, fixed, rates, BlockConfig(variance_components=False), gain=loose)
    assert np.all(np.diagonal(wide.cov_xi[1:], axis1=1, axis2=2) >= np.diagonal(framed.cov_xi[1:], axis1=1, axis2=2)
                  * 0.999)
    assert wide.cov_xi[3, 1, 1] > 1.5 * framed.cov_xi[3, 1, 1]


def test_skew_is_the_cross_product():  # the Jacobians above rely on it
    a, b = RNG.normal(size=3), RNG.normal(size=3)
    np.testing.assert_allclose(skew(a) @ b, np.cross(a, b))
