import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kinreg.geometry import (
    Pose,
    interpolate_poses,
    make_quat_continuous,
    matrix_to_quat,
    quat_multiply,
    quat_slerp,
    quat_to_matrix,
    quat_to_rotvec,
    relative_poses,
    rotation_angle_rad,
    rotvec_to_quat,
)


def random_poses(n: int, seed: int = 0, scale: float = 10.0) -> Pose:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Pose(q, rng.normal(scale=scale, size=(n, 3)))


def test_quaternion_convention_is_scalar_first_hamilton():
    # 90 deg about z maps x to y
    q = [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]
    np.testing.assert_allclose(quat_to_matrix(q) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # Hamilton: i*j = k
    np.testing.assert_allclose(quat_multiply([0, 1, 0, 0], [0, 0, 1, 0]), [0, 0, 0, 1])


def test_matrix_quaternion_round_trip_all_angles():
    poses = random_poses(2000)
    R = poses.rotation_matrix
    q = matrix_to_quat(R)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    # 180 deg rotations are the hard case for the trace formula
    for axis in np.eye(3):
        R180 = quat_to_matrix(rotvec_to_quat(np.pi * axis))
        np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R180)), R180, atol=1e-12)


def test_compose_inverse_and_apply():
    a, b = random_poses(50, 1), random_poses(50, 2)
    ident = a.compose(a.inverse())
    np.testing.assert_allclose(ident.t_xyz, 0, atol=1e-12)
    np.testing.assert_allclose(np.abs(ident.quat_wxyz[:, 0]), 1, atol=1e-12)
    p = np.random.default_rng(3).normal(size=(50, 3))
    np.testing.assert_allclose(a.compose(b).apply(p), a.apply(b.apply(p)), atol=1e-10)
    np.testing.assert_allclose(a.apply_inverse(a.apply(p)), p, atol=1e-10)
    np.testing.assert_allclose(a.as_matrix() @ a.inverse().as_matrix(), np.broadcast_to(np.eye(4), (50, 4, 4)),
                               atol=1e-12)
    back = Pose.from_matrix(a.as_matrix())
    np.testing.assert_allclose(back.as_matrix(), a.as_matrix(), atol=1e-12)


def test_single_pose_maps_many_points_and_keeps_utm_precision():
    T = Pose(rotvec_to_quat([0.1, -0.2, 0.7]), [500000.123456, 5400000.654321, 312.5])
    local = np.random.default_rng(0).uniform(-30, 30, (1000, 3))
    back = T.apply_inverse(T.apply(local))
    assert np.max(np.abs(back - local)) < 1e-8  # 10 nm at UTM magnitudes


def test_exp_log_round_trip_and_small_angles():
    xi = np.random.default_rng(4).normal(size=(500, 6))
    angle = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 3.0 / angle)  # the log returns angles in [0, pi]
    np.testing.assert_allclose(Pose.exp(xi).log(), xi, atol=1e-9)
    tiny = np.array([[0.1, 0.2, 0.3, 1e-12, -2e-12, 3e-12]])
    np.testing.assert_allclose(Pose.exp(tiny).log(), tiny, atol=1e-15)
    # exp of a pure translation twist is that translation
    np.testing.assert_allclose(Pose.exp([1, 2, 3, 0, 0, 0]).t_xyz, [1, 2, 3])


def test_exp_matches_matrix_exponential():
    from scipy.linalg import expm

    xi = np.array([0.3, -0.2, 0.5, 0.4, 0.1, -0.6])
    hat = np.zeros((4, 4))
    hat[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
    hat[:3, 3] = xi[:3]
    np.testing.assert_allclose(Pose.exp(xi).as_matrix(), expm(hat), atol=1e-12)


def test_slerp_endpoints_midpoint_and_shortest_arc():
    q0 = rotvec_to_quat([0, 0, 0.0])
    q1 = rotvec_to_quat([0, 0, 1.0])
    np.testing.assert_allclose(quat_slerp(q0, q1, 0.0), q0, atol=1e-15)
    np.testing.assert_allclose(quat_slerp(q0, q1, 1.0), q1, atol=1e-15)
    np.testing.assert_allclose(quat_to_rotvec(quat_slerp(q0, q1, 0.25)), [0, 0, 0.25], atol=1e-12)
    # -q1 is the same rotation: the result must not go the long way round
    np.testing.assert_allclose(quat_to_rotvec(quat_slerp(q0, -q1, 0.5)), [0, 0, 0.5], atol=1e-12)


def test_interpolate_poses_linear_position_and_exact_at_nodes():
    stamps = np.array([0.0, 1.0, 3.0])
    poses = Pose(rotvec_to_quat([[0, 0, 0], [0, 0, 0.2], [0, 0, 0.6]]), [[0, 0, 0], [1, 0, 0], [1, 2, 0]])
    out = interpolate_poses(stamps, poses, np.array([0.0, 0.5, 1.0, 2.0, 3.0]))
    np.testing.assert_allclose(out.t_xyz, [[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 1, 0], [1, 2, 0]], atol=1e-15)
    np.testing.assert_allclose(rotation_angle_rad(out), [0, 0.1, 0.2, 0.4, 0.6], atol=1e-12)


def test_make_quat_continuous_flips_sign_jumps():
    q = rotvec_to_quat(np.column_stack([np.zeros(10), np.zeros(10), np.linspace(0, 1, 10)]))
    q[4:7] *= -1
    c = make_quat_continuous(q)
    assert np.all(np.sum(c[1:] * c[:-1], axis=1) > 0)
    np.testing.assert_allclose(quat_to_matrix(c), quat_to_matrix(q), atol=1e-15)


def test_pose_validates_shapes():
    with pytest.raises(ValueError, match="Pose needs"):
        Pose(np.zeros((3, 4)), np.zeros((2, 3)))


finite = st.floats(-1.0, 1.0, allow_nan=False)
twists = arrays(np.float64, (6,), elements=st.floats(-3.0, 3.0, allow_nan=False))


@settings(max_examples=200, deadline=None)
@given(twists, twists)
def test_property_compose_inverse_log_exp(xa, xb):
    angle = np.linalg.norm(xa[3:])
    if angle > 3.0:
        xa[3:] *= 3.0 / angle  # the log returns angles in [0, pi]
    a, b = Pose.exp(xa), Pose.exp(xb)
    ab = a.compose(b)
    np.testing.assert_allclose(ab.compose(b.inverse()).as_matrix(), a.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(Pose.exp(a.log()).as_matrix(), a.as_matrix(), atol=1e-9)
    # interpolation at the nodes returns the nodes
    both = Pose.stack([a, b])
    mid = interpolate_poses(np.array([0.0, 1.0]), both, np.array([0.0, 1.0]))
    np.testing.assert_allclose(mid.as_matrix(), both.as_matrix(), atol=1e-9)


def test_relative_poses_round_as_the_pose_algebra():
    """The block's batched T_a^-1 T_b is Pose.inverse().compose() to the last bit (at UTM-sized
    translations too): the pipeline's loops would carry a last-bit difference to its reports."""
    a, b = random_poses(500, seed=1, scale=5e6), random_poses(500, seed=2, scale=5e6)
    expected = a.inverse().compose(b)
    q, t = relative_poses(a.quat_wxyz, a.t_xyz, a.rotation_matrix, b.quat_wxyz, b.t_xyz)
    assert np.array_equal(q, expected.quat_wxyz)
    assert np.array_equal(t, expected.t_xyz)
