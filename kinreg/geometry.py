"""Rigid-body geometry: quaternions, poses, SE(3) exp/log and interpolation, all vectorised.

Conventions (METHOD.md section 4):

- A pose ``T_a_b = (R, t)`` maps frame-b coordinates into frame a: ``x_a = R x_b + t``.
- Quaternions are Hamilton, unit norm, scalar first: ``quat_wxyz = (w, x, y, z)``.
- A twist ``xi = (rho, phi)`` has the translational part first (metres) and the rotation vector
  second (radians); ``Pose.exp(xi)`` is the matrix exponential of its hat matrix.

Every function accepts arrays with arbitrary leading dimensions (``(..., 4)`` quaternions,
``(..., 3)`` vectors) and broadcasts over them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

# Below this rotation angle the series expansions replace the closed forms (avoids 0/0).
_SMALL_ANGLE_RAD = 1e-7


def _as_float(a: ArrayLike) -> FloatArray:
    return np.asarray(a, dtype=np.float64)


# --------------------------------------------------------------------------- quaternions


def quat_normalize(quat_wxyz: ArrayLike) -> FloatArray:
    """Unit quaternion(s) of the same direction.

    >>> quat_normalize([2.0, 0.0, 0.0, 0.0])
    array([1., 0., 0., 0.])
    """
    q = _as_float(quat_wxyz)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_conjugate(quat_wxyz: ArrayLike) -> FloatArray:
    """Conjugate (the inverse for unit quaternions)."""
    q = _as_float(quat_wxyz).copy()
    q[..., 1:] *= -1.0
    return q


def quat_multiply(q1_wxyz: ArrayLike, q2_wxyz: ArrayLike) -> FloatArray:
    """Hamilton product ``q1 * q2`` (rotation q2 first, then q1)."""
    q1 = _as_float(q1_wxyz)
    q2 = _as_float(q2_wxyz)
    # Indexed, not np.moveaxis: the same views, without its cost on the one quaternion of a pair's solve.
    w1, x1, y1, z1 = q1[..., 0], q1[..., 1], q1[..., 2], q1[..., 3]
    w2, x2, y2, z2 = q2[..., 0], q2[..., 1], q2[..., 2], q2[..., 3]
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_to_matrix(quat_wxyz: ArrayLike) -> FloatArray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)``.

    >>> np.round(quat_to_matrix([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]) @ [1.0, 0, 0], 12)
    array([0., 1., 0.])
    """
    q = _as_float(quat_wxyz)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    # Written into one array (not stacked from nine): half the temporaries on many quaternions.
    R = np.empty((*w.shape, 3, 3))
    R[..., 0, 0] = 1 - 2 * (yy + zz)
    R[..., 0, 1] = 2 * (xy - wz)
    R[..., 0, 2] = 2 * (xz + wy)
    R[..., 1, 0] = 2 * (xy + wz)
    R[..., 1, 1] = 1 - 2 * (xx + zz)
    R[..., 1, 2] = 2 * (yz - wx)
    R[..., 2, 0] = 2 * (xz - wy)
    R[..., 2, 1] = 2 * (yz + wx)
    R[..., 2, 2] = 1 - 2 * (xx + yy)
    return R


def matrix_to_quat(R: ArrayLike) -> FloatArray:
    """Unit quaternions ``(..., 4)`` with ``w >= 0`` of rotation matrices ``(..., 3, 3)``.

    Uses the largest of the four candidate divisors (Shepperd), so it is stable for any angle.
    """
    M = _as_float(R)
    m00, m11, m22 = M[..., 0, 0], M[..., 1, 1], M[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate solutions, each well conditioned where its leading component is large.
    cand = np.stack(
        [
            np.stack([1 + trace, M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0],
                      M[..., 1, 0] - M[..., 0, 1]], axis=-1),
            np.stack([M[..., 2, 1] - M[..., 1, 2], 1 + m00 - m11 - m22, M[..., 0, 1] + M[..., 1, 0],
                      M[..., 0, 2] + M[..., 2, 0]], axis=-1),
            np.stack([M[..., 0, 2] - M[..., 2, 0], M[..., 0, 1] + M[..., 1, 0], 1 - m00 + m11 - m22,
                      M[..., 1, 2] + M[..., 2, 1]], axis=-1),
            np.stack([M[..., 1, 0] - M[..., 0, 1], M[..., 0, 2] + M[..., 2, 0],
                      M[..., 1, 2] + M[..., 2, 1], 1 - m00 - m11 + m22], axis=-1),
        ],
        axis=-2,
    )  # fmt: skip
    lead = np.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    best = np.argmax(lead, axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = quat_normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_rotvec(quat_wxyz: ArrayLike) -> FloatArray:
    """Rotation vectors ``(..., 3)`` (axis times angle in radians, angle in [0, pi])."""
    q = _as_float(quat_wxyz)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    # angle / s -> 2 / w for small angles
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(s > _SMALL_ANGLE_RAD, angle / np.where(s > 0, s, 1.0), 2.0 / q[..., 0])
    return v * factor[..., None]


def rotvec_to_quat(rotvec: ArrayLike) -> FloatArray:
    """Unit quaternions ``(..., 4)`` of rotation vectors ``(..., 3)``."""
    r = _as_float(rotvec)
    angle = np.linalg.norm(r, axis=-1)
    half = 0.5 * angle
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(angle > _SMALL_ANGLE_RAD, np.sin(half) / np.where(angle > 0, angle, 1.0),
                     0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half)[..., None], r * k[..., None]], axis=-1)


def quat_slerp(q0_wxyz: ArrayLike, q1_wxyz: ArrayLike, u: ArrayLike) -> FloatArray:
    """Spherical linear interpolation at fraction ``u`` (0 gives q0, 1 gives q1), shortest arc."""
    q0 = _as_float(q0_wxyz)
    q1 = _as_float(q1_wxyz)
    u = _as_float(u)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-9
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    w1 = np.where(near, u, np.sin(u * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


def make_quat_continuous(quat_wxyz: ArrayLike) -> FloatArray:
    """Flip signs along the first axis so consecutive quaternions have a non-negative dot product.

    q and -q are the same rotation; a sign flip between two rows would make naive interpolation
    or differencing go the long way round.
    """
    q = _as_float(quat_wxyz).copy()
    if len(q) < 2:
        return q
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.concatenate([[0], np.cumsum(dots < 0)]) % 2
    q[flips == 1] *= -1.0
    return q


def skew(v: ArrayLike) -> FloatArray:
    """Skew-symmetric matrices ``(..., 3, 3)`` with ``skew(a) @ b == cross(a, b)``."""
    v = _as_float(v)
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    K = np.zeros((*v.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w, y
    K[..., 1, 0], K[..., 1, 2] = w, -x
    K[..., 2, 0], K[..., 2, 1] = -y, x
    return K


def _so3_left_jacobian(phi: FloatArray) -> FloatArray:
    angle = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = angle < 1e-5
    a = np.where(small, 1.0, angle)
    c1 = np.where(small, 0.5 - angle**2 / 24.0, (1.0 - np.cos(a)) / a**2)
    c2 = np.where(small, 1.0 / 6.0 - angle**2 / 120.0, (a - np.sin(a)) / a**3)
    return np.eye(3) + c1 * K + c2 * (K @ K)


def _so3_left_jacobian_inv(phi: FloatArray) -> FloatArray:
    angle = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = angle < 1e-5
    a = np.where(small, 1.0, angle)
    c2 = np.where(small, 1.0 / 12.0 + angle**2 / 720.0,
                  (1.0 / a**2) - (1.0 + np.cos(a)) / (2.0 * a * np.sin(a)))
    return np.eye(3) - 0.5 * K + c2 * (K @ K)


def relative_poses(quat_a: ArrayLike, t_a: ArrayLike, R_a: ArrayLike, quat_b: ArrayLike,
                   t_b: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """``T_a^-1 T_b`` of poses given as arrays, ``R_a`` the rotation matrices of ``quat_a`` (at hand
    from elsewhere, so not formed again): ``(quat_wxyz, t_xyz)``, rounded exactly as
    ``Pose(quat_a, t_a).inverse().compose(Pose(quat_b, t_b))`` rounds them.

    >>> q, t = relative_poses([1.0, 0, 0, 0], [1.0, 2.0, 3.0], np.eye(3), [1.0, 0, 0, 0], [2.0, 2.0, 2.0])
    >>> t
    array([ 1.,  0., -1.])
    """
    q = quat_normalize(quat_multiply(quat_conjugate(quat_a), quat_b))
    # R(q)^T is R(conj q) to the bit; einsum on a contiguous copy rounds as Pose.inverse and compose do
    R_inv = np.ascontiguousarray(np.swapaxes(_as_float(R_a), -1, -2))
    t = np.einsum("...ij,...j->...i", R_inv, _as_float(t_b)) - np.einsum("...ij,...j->...i", R_inv, _as_float(t_a))
    return q, t


# --------------------------------------------------------------------------- poses


@dataclass(frozen=True, eq=False)
class Pose:
    """One pose or an array of poses ``T_a_b``: ``x_a = R(quat_wxyz) x_b + t_xyz``.

    ``quat_wxyz`` has shape ``(..., 4)`` (unit, scalar first), ``t_xyz`` shape ``(..., 3)`` in
    metres; the leading shapes must agree. Indexing and ``len`` work over the leading axis.
    """

    quat_wxyz: FloatArray
    t_xyz: FloatArray

    def __post_init__(self) -> None:
        q = _as_float(self.quat_wxyz)
        t = _as_float(self.t_xyz)
        if q.shape[-1:] != (4,) or t.shape[-1:] != (3,) or q.shape[:-1] != t.shape[:-1]:
            raise ValueError(f"Pose needs quat (...,4) and t (...,3) of one leading shape, "
                             f"got {q.shape} and {t.shape}")
        object.__setattr__(self, "quat_wxyz", q)
        object.__setattr__(self, "t_xyz", t)

    # constructors
    def cache_key_parts(self) -> tuple[FloatArray, FloatArray]:
        """What identifies the pose in a cache key (:mod:`kinreg.run.stage_cache`)."""
        return self.quat_wxyz, self.t_xyz

    @classmethod
    def identity(cls, n: int | None = None) -> Pose:
        """The identity pose, or ``n`` of them."""
        shape = () if n is None else (n,)
        q = np.zeros((*shape, 4))
        q[..., 0] = 1.0
        return cls(q, np.zeros((*shape, 3)))

    @classmethod
    def from_matrix(cls, T: ArrayLike) -> Pose:
        """From homogeneous matrices ``(..., 4, 4)``."""
        M = _as_float(T)
        return cls(matrix_to_quat(M[..., :3, :3]), M[..., :3, 3].copy())

    @classmethod
    def from_rotation_translation(cls, R: ArrayLike, t_xyz: ArrayLike) -> Pose:
        """From rotation matrices ``(..., 3, 3)`` and translations ``(..., 3)``."""
        return cls(matrix_to_quat(R), _as_float(t_xyz))

    @classmethod
    def exp(cls, xi: ArrayLike) -> Pose:
        """SE(3) exponential of twists ``xi = (rho, phi)``, shape ``(..., 6)``."""
        xi = _as_float(xi)
        rho, phi = xi[..., :3], xi[..., 3:]
        t = np.einsum("...ij,...j->...i", _so3_left_jacobian(phi), rho)
        return cls(rotvec_to_quat(phi), t)

    @classmethod
    def stack(cls, poses: list[Pose]) -> Pose:
        """Concatenate single poses into an array of poses."""
        return cls(np.stack([p.quat_wxyz for p in poses]), np.stack([p.t_xyz for p in poses]))

    # converters
    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.t_xyz.shape[:-1])

    @property
    def rotation_matrix(self) -> FloatArray:
        """Rotation matrices ``(..., 3, 3)``."""
        return quat_to_matrix(self.quat_wxyz)

    def as_matrix(self) -> FloatArray:
        """Homogeneous matrices ``(..., 4, 4)``."""
        T = np.zeros((*self.shape, 4, 4))
        T[..., :3, :3] = self.rotation_matrix
        T[..., :3, 3] = self.t_xyz
        T[..., 3, 3] = 1.0
        return T

    def log(self) -> FloatArray:
        """SE(3) logarithm: twists ``(..., 6)`` with ``Pose.exp(p.log()) == p``."""
        phi = quat_to_rotvec(self.quat_wxyz)
        rho = np.einsum("...ij,...j->...i", _so3_left_jacobian_inv(phi), self.t_xyz)
        return np.concatenate([rho, phi], axis=-1)

    # algebra
    def inverse(self) -> Pose:
        """``T_b_a`` from ``T_a_b``."""
        q_inv = quat_conjugate(self.quat_wxyz)
        return Pose(q_inv, -np.einsum("...ij,...j->...i", quat_to_matrix(q_inv), self.t_xyz))

    def compose(self, other: Pose) -> Pose:
        """``T_a_c = T_a_b.compose(T_b_c)``; broadcasts over leading shapes."""
        q = quat_normalize(quat_multiply(self.quat_wxyz, other.quat_wxyz))
        t = np.einsum("...ij,...j->...i", self.rotation_matrix, other.t_xyz) + self.t_xyz
        return Pose(q, t)

    def apply(self, points_xyz: ArrayLike) -> FloatArray:
        """Map points from frame b into frame a.

        A single pose maps any ``(..., 3)`` array; an array of poses of shape ``S`` maps points of
        shape ``(*S, 3)`` pose by pose.
        """
        p = _as_float(points_xyz)
        R = self.rotation_matrix
        if self.shape == ():
            return p @ R.T + self.t_xyz
        return np.einsum("...ij,...j->...i", R, p) + self.t_xyz

    def apply_inverse(self, points_xyz: ArrayLike) -> FloatArray:
        """Map points from frame a into frame b: ``R^T (x_a - t)`` (no inverse pose is formed).

        Subtracting ``t`` first keeps the full float64 precision of large (UTM) coordinates.
        """
        p = _as_float(points_xyz)
        R = self.rotation_matrix
        if self.shape == ():
            return (p - self.t_xyz) @ R
        return np.einsum("...ji,...j->...i", R, p - self.t_xyz)

    def __len__(self) -> int:
        if self.shape == ():
            raise TypeError("a single Pose has no length")
        return self.shape[0]

    def __getitem__(self, index: Any) -> Pose:
        if self.shape == ():
            raise TypeError("a single Pose cannot be indexed")
        return Pose(self.quat_wxyz[index], self.t_xyz[index])

    def __repr__(self) -> str:
        if self.shape == ():
            return f"Pose(quat_wxyz={np.round(self.quat_wxyz, 9)}, t_xyz={np.round(self.t_xyz, 6)})"
        return f"Pose(shape={self.shape})"


def rotation_angle_rad(pose: Pose) -> FloatArray:
    """Rotation angle(s) of a pose in radians, in [0, pi]."""
    return np.linalg.norm(quat_to_rotvec(pose.quat_wxyz), axis=-1)


def interpolate_poses(stamps_s: ArrayLike, poses: Pose, query_s: ArrayLike) -> Pose:
    """Poses at times ``query_s``: linear in position, SLERP in rotation.

    ``stamps_s`` must be strictly increasing and cover ``query_s`` (the caller checks the range;
    values outside are extrapolated from the end segment's nearest pose, i.e. clamped).
    """
    i, u = _segments(stamps_s, query_s)
    t = poses.t_xyz[i] + u[..., None] * (poses.t_xyz[i + 1] - poses.t_xyz[i])
    quat = quat_slerp(poses.quat_wxyz[i], poses.quat_wxyz[i + 1], u)
    return Pose(quat, t)


def interpolate_positions(stamps_s: ArrayLike, xyz: ArrayLike, query_s: ArrayLike) -> FloatArray:
    """The position part of :func:`interpolate_poses` alone (no SLERP): same segments, same
    rounding, clamped outside the range."""
    i, u = _segments(stamps_s, query_s)
    p = _as_float(xyz)
    return p[i] + u[..., None] * (p[i + 1] - p[i])


def _segments(stamps_s: ArrayLike, query_s: ArrayLike) -> tuple[np.ndarray, FloatArray]:
    """Segment index and fraction (clamped to [0, 1]) of each query time."""
    s = _as_float(stamps_s)
    q = _as_float(query_s)
    i = np.clip(np.searchsorted(s, q, side="right") - 1, 0, len(s) - 2)
    return i, np.clip((q - s[i]) / (s[i + 1] - s[i]), 0.0, 1.0)


def tangent_basis(normal: ArrayLike) -> FloatArray:
    """Two unit vectors ``(2, 3)`` orthogonal to a unit ``normal`` and to each other
    (right-handed: ``u x v = n``), chosen deterministically.

    >>> tangent_basis([0.0, 0.0, 1.0])
    array([[ 0.,  1.,  0.],
           [-1.,  0.,  0.]])
    """
    n = _as_float(normal)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)])


def pose_sigmas(position_m: float, rotation_rad: float) -> FloatArray:
    """Standard deviations ``(6,)`` of a pose in twist order: three positions [m], three rotations [rad].

    >>> pose_sigmas(0.002, 0.001)
    array([0.002, 0.002, 0.002, 0.001, 0.001, 0.001])
    """
    return np.array([position_m] * 3 + [rotation_rad] * 3, dtype=np.float64)
