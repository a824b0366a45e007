"""The small frozen types that cross stage boundaries. Defined here and nowhere else."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from kinreg.errors import TrajectoryError
from kinreg.geometry import FloatArray, Pose, interpolate_poses, quat_to_matrix, rotvec_to_quat


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Time-ordered platform poses ``T_obj_platform`` (strictly increasing float64 seconds).

    ``extra`` holds user columns of the source file (shape ``(N, k)``, names in
    ``extra_names``) so that writers can reproduce them; readers may leave it empty.
    """

    stamps_s: FloatArray
    poses: Pose
    source: str | None = None
    extra: FloatArray | None = None
    extra_names: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.stamps_s)

    @property
    def t_start_s(self) -> float:
        return float(self.stamps_s[0])

    @property
    def t_end_s(self) -> float:
        return float(self.stamps_s[-1])

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    def path_length_m(self) -> float:
        """Length of the polyline through the positions."""
        return float(np.linalg.norm(np.diff(self.poses.t_xyz, axis=0), axis=1).sum())

    def covers(self, query_s: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which query times lie inside the trajectory's time range."""
        q = np.asarray(query_s, dtype=np.float64)
        return (q >= self.stamps_s[0]) & (q <= self.stamps_s[-1])

    def pose_at(self, query_s: float | NDArray[np.float64]) -> Pose:
        """Interpolated poses (linear position, SLERP rotation) at ``query_s``.

        Raises :class:`TrajectoryError` if any time lies outside the trajectory's range.
        """
        q = np.asarray(query_s, dtype=np.float64)
        inside = self.covers(q)
        if not np.all(inside):
            bad = float(np.atleast_1d(q)[~np.atleast_1d(inside)][0])
            raise TrajectoryError(
                f"time {bad:.6f} s is outside the trajectory's range "
                f"[{self.t_start_s:.6f}, {self.t_end_s:.6f}] s",
                self.source,
            )
        return interpolate_poses(self.stamps_s, self.poses, q)

    def nearest_index(self, query_s: float) -> int:
        """Index of the trajectory row nearest in time to ``query_s``."""
        i = int(np.searchsorted(self.stamps_s, query_s))
        if i <= 0:
            return 0
        if i >= len(self.stamps_s):
            return len(self.stamps_s) - 1
        return i if self.stamps_s[i] - query_s < query_s - self.stamps_s[i - 1] else i - 1


@dataclass(frozen=True, eq=False)
class CloudChunk:
    """A block of points in the object frame: float64 coordinates, float64 times.

    ``first_index`` is the position of the chunk's first point in the file, so that point order
    can be reproduced. ``intensity`` is optional (``None`` where the file has none).
    """

    xyz: FloatArray
    stamps_s: FloatArray | None
    intensity: NDArray[np.float32] | None = None
    first_index: int = 0

    def __len__(self) -> int:
        return len(self.xyz)


class ScanKind(enum.Enum):
    QUASI_STATIC = "quasi_static"
    STATIC = "static"


@dataclass(frozen=True)
class ScanWindow:
    """A time window of the trajectory that becomes one quasi-static scan.

    ``T_obj_scan`` is the trajectory pose nearest the middle of the window (the virtual scanner
    centre), ``t_s`` its time. Points with ``t_start_s <= t < t_end_s`` belong to the window
    (the last window also takes ``t == t_end_s``).
    """

    scan_id: int
    t_start_s: float
    t_end_s: float
    t_s: float
    T_obj_scan: Pose = field(compare=False)

    @property
    def name(self) -> str:
        return f"qs_{self.scan_id:05d}"


@dataclass(frozen=True, eq=False)
class Scan:
    """A scan with its points in its own frame and its pose ``T_obj_scan``.

    Quasi-static scans carry times (``t_s`` is the centre time, the window bounds in
    ``t_start_s``/``t_end_s``); static scans have ``nan`` times and may lack ``stamps_s``.
    """

    scan_id: int
    name: str
    kind: ScanKind
    T_obj_scan: Pose
    points_xyz: FloatArray
    stamps_s: FloatArray | None = None
    intensity: NDArray[np.float32] | None = None
    t_s: float = float("nan")
    t_start_s: float = float("nan")
    t_end_s: float = float("nan")

    def __len__(self) -> int:
        return len(self.points_xyz)

    def points_in_object_frame(self) -> FloatArray:
        """The points mapped into the object frame with ``T_obj_scan``."""
        return self.T_obj_scan.apply(self.points_xyz)


@dataclass(frozen=True, eq=False)
class Plane:
    """A planar patch detected in one scan, in that scan's frame: ``normal . x = d_m``.

    ``normal`` is unit and points towards the scanner that saw it: the scan origin, so ``d_m < 0``
    for a plane not through it, unless the sensor saw the plane from its other side in part of the
    window (:func:`kinreg.estimate.planes.facing_the_sensor`). The normal has two degrees of freedom: its
    uncertainty is expressed as small rotations along the two tangent directions ``basis_uv``
    (rows, unit, orthogonal to the normal and each other), and ``cov_uvd`` is the 3x3 covariance
    of (rotation towards u [rad], rotation towards v [rad], d [m]), i.e. a perturbed plane is
    ``n' = normalize(n + a u + b v)``, ``d' = d + e``.

    ``centroid_xyz`` is the mean of the inliers, ``hull_xyz`` (K, 3) the convex hull of the
    inliers in the plane (scan frame), ``area_m2`` its area, ``rms_m`` the RMS of the
    orthogonal residuals of the ``n_points`` full-resolution inliers. ``t_offset_s`` is when the
    plane was seen, relative to the scan's centre time: drift inside the window moves the plane by
    the drift over that time (see :func:`kinreg.estimate.drift.with_window_deformation`), and,
    with ``t_slope_s_per_m``, tilts it.
    """

    scan_id: int
    plane_id: int
    normal: FloatArray
    d_m: float
    centroid_xyz: FloatArray
    basis_uv: FloatArray
    cov_uvd: FloatArray
    hull_xyz: FloatArray
    area_m2: float
    n_points: int
    rms_m: float
    t_offset_s: float = 0.0  # mean time of the inliers minus the scan's centre time (0: static scan)
    # how the inliers' time changes across the plane [s/m], along basis_uv: a plane swept over
    # while walking is seen early at one end and late at the other, so a drift velocity tilts it
    t_slope_s_per_m: tuple[float, float] = (0.0, 0.0)
    # Where the sensor was while it saw the plane (scan frame [m]): the mean over the inliers of its
    # position at each one's time, and how that changes across the plane along basis_uv ((3, 2),
    # [m/m]); None where unknown (a static scan, a scan without a trajectory). Where the attitude
    # error turns each point about the sensor (GNSS/INS-like drift), the plane moves about these,
    # not about where the sensor was at the plane's mean time: a walk that slows down inside the
    # window puts the two 0.3 m apart (3 mm at 10 mrad).
    sensor_xyz: FloatArray | None = None
    sensor_slope: FloatArray | None = None

    def cov_nd(self) -> FloatArray:
        """The (rank-3) 4x4 covariance of (nx, ny, nz, d)."""
        J = np.zeros((4, 3))
        J[:3, 0] = self.basis_uv[0]
        J[:3, 1] = self.basis_uv[1]
        J[3, 2] = 1.0
        return J @ self.cov_uvd @ J.T


@dataclass(frozen=True)
class PlaneMatch:
    """Plane ``plane_i`` of scan i and plane ``plane_j`` of scan j are the same physical plane.

    ``angle_deg`` and ``offset_m`` are the differences after mapping plane j into scan i with the
    approximate pairwise transform; ``overlap`` the share of the smaller extent that overlaps.
    """

    plane_i: int
    plane_j: int
    angle_deg: float
    offset_m: float
    overlap: float


class LinkStatus(enum.Enum):
    OK = "ok"
    PRIOR_ONLY = "prior_only"  # no usable plane pair: the link carries no plane information
    REJECTED = "rejected"  # too many wrong matches: the global test failed when snooping hit its cap


@dataclass(frozen=True, eq=False)
class Link:
    """The pairwise adjustment of scans i and j (METHOD.md section 2, step 6).

    ``T_i_j`` maps scan-j coordinates into scan i (planes and trajectory prior combined);
    ``cov_xi`` is the 6x6 covariance of the right-perturbation twist ``xi = (rho, phi)`` with
    ``T = T_i_j.compose(Pose.exp(xi))``. The plane-only information, for a block adjustment that
    adds the trajectory once by itself: ``info_planes`` (6x6, rank ``rank``, possibly deficient)
    about the relative pose ``T_i_j_planes`` in the same twist convention.

    ``axis_sigma_planes`` are the plane-only standard deviations (tx, ty, tz [m], rx, ry, rz [rad])
    in scan i's axes, ``inf`` where the planes do not determine that axis; ``n_directions`` the
    number of distinct plane normal directions (3 fixes the translation). ``sigma0`` is the
    a-posteriori standard deviation of unit weight with ``redundancy`` degrees of freedom;
    ``global_test_passed`` its chi-square test. ``rejected`` lists matches removed by data
    snooping; ``max_normalised_residual`` is the largest remaining one.
    """

    scan_i: int
    scan_j: int
    status: LinkStatus
    T_i_j: Pose
    cov_xi: FloatArray
    T_i_j_prior: Pose
    T_i_j_planes: Pose
    info_planes: FloatArray
    rank: int
    axis_sigma_planes: FloatArray
    n_directions: int
    sigma0: float
    redundancy: int
    global_test_passed: bool
    matches: tuple[PlaneMatch, ...]
    rejected: tuple[PlaneMatch, ...]
    max_normalised_residual: float
    dt_s: float


class ObservationKind(enum.Enum):
    PLANES = "planes"  # plane-only information of a pairwise link
    TRAJECTORY = "trajectory"  # the trajectory's relative pose between consecutive stations
    STATION = "station"  # a direct observation of one station's pose (static scans with sigmas)
    DRIFT = "drift"  # how the trajectory's drift velocity changes from one link to the next
    POINT = "point"  # a surveyed point on the pose interpolated between two stations (control points)
    FRAME = "frame"  # a quasi-static scan's frame against its sensor pose (the window bias, kinreg.estimate.frames)
    PLANE = "plane"  # one scan plane's tilts against the physical plane it belongs to (kinreg.estimate.plane_nodes)
    PLANE_OFFSET = "plane offset"  # ... and its offset, given its tilts
    PLANE_FLOOR = "plane (floor)"  # a scan plane's tilts whose model is mostly the floor (a large plane)
    PLANE_OFFSET_FLOOR = "plane offset (floor)"  # ... its offset, likewise
    PLANE_FLOOR_LEVEL = "plane (floor, level)"  # ... of a level plane: floor, ceiling (no heading drift in them)
    PLANE_OFFSET_FLOOR_LEVEL = "plane offset (floor, level)"  # ... its offset, likewise


# The kinds a scan plane observes its physical plane with (kinreg.estimate.plane_nodes), and their
# ranks: its tilts 2, its offset given the tilts 1.
SCAN_PLANE_RANK = {ObservationKind.PLANE: 2, ObservationKind.PLANE_OFFSET: 1, ObservationKind.PLANE_FLOOR: 2,
                   ObservationKind.PLANE_OFFSET_FLOOR: 1, ObservationKind.PLANE_FLOOR_LEVEL: 2,
                   ObservationKind.PLANE_OFFSET_FLOOR_LEVEL: 1}


@dataclass(frozen=True, eq=False)
class RelativeObservation:
    """One observation of the block adjustment: the relative pose ``T_i_j`` of stations i and j
    (or, for ``STATION``, the pose ``T_obj_i`` itself; ``j`` is then -1) with its 6x6 information
    matrix in the right-perturbation twist convention (``T = Z.compose(Pose.exp(e))``), possibly
    rank deficient.

    The trajectory's drift velocity (METHOD.md section 2): where the block has a drift velocity
    ``v`` for the trajectory link that starts at station i (6 values in object axes, the
    translation part at the station: the rate of the trajectory's error), a ``TRAJECTORY``
    observation over ``dt_s`` seconds predicts ``T_i^-1 T_j = Z exp(dt_s S_j v)`` (``S_j`` turns
    object axes into station j's). A ``DRIFT`` observation ties the velocity of the link from j
    to that of the link from i, ``v_j - decay v_i ~ N(0, info^-1)`` (``decay`` per axis) (first-order Gauss-Markov), or
    with ``j = -1`` observes ``v_i ~ N(0, info^-1)`` (its stationary spread); ``Z`` is unused.

    A ``POINT`` observation (a control point) observes the object-frame position ``Z.t_xyz`` of a
    point that lies at ``levers_m[0]`` in station i's frame and ``levers_m[1]`` in station j's,
    on the pose interpolated between them: ``(1 - share) T_i l_0 + share T_j l_1`` (``j = -1``:
    station i alone); its information is on the object-frame residual (the first three rows of
    the twist order), rank 3."""

    kind: ObservationKind
    i: int
    j: int
    Z: Pose
    info: FloatArray
    rank: int
    dt_s: float = 0.0
    decay: float | FloatArray = 0.0  # per axis where an array (6,)
    # A trajectory link whose attitude error is coupled (GNSS/INS-like, kinreg.estimate.drift):
    # its translation is (1 - coupling) Z.t + coupling R_i^T step_obj, with R_i the adjusted
    # attitude of station i and step_obj the trajectory's object-frame step.
    coupling: float = 0.0
    step_obj: FloatArray | None = None
    levers_m: FloatArray | None = None  # POINT: (2, 3) the point in station i's and j's frames
    share: float = 0.0  # POINT: the weight of station j in the interpolated pose


@dataclass(frozen=True)
class ObservationTest:
    """How an observation fits after the block adjustment."""

    index: int  # position in the observation list
    kind: ObservationKind
    i: int
    j: int
    statistic: float  # e^T Q_ee^-1 e over its determined directions, chi-square with `dof`
    dof: int
    redundancy: float  # its share of the total redundancy (0: uncontrolled, dof: fully controlled)
    normalised: float  # sqrt(statistic / dof)
    rejected: bool
    vtpv: float = float("nan")  # its weighted squared residual e^T P e (for variance components)
    # the least redundancy of any one direction it determines (0: that direction rests on it alone,
    # so rejecting it would leave the network undetermined there)
    min_redundancy: float = float("nan")
    # covariance (6x6, twist of its relative pose in station i's frame) of the adjusted relative
    # pose it observes: how well the network itself determines what this observation measures
    cov_adjusted: FloatArray | None = field(default=None, repr=False, compare=False)
    # its residual (6,) after the adjustment: for a pose observation the translation [m] and the
    # rotation vector [rad] between what it observes and what the network says
    residual: FloatArray | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True, eq=False)
class BlockResult:
    """The adjusted network.

    ``poses`` are the adjusted ``T_obj_scan`` of every station, ``cov_xi`` (n, 6, 6) the
    covariance of each station's right-perturbation twist (rho in the station frame, then
    phi), ``cov_position`` (n, 3, 3) that of its position in the object frame, both already
    multiplied by ``variance_factor`` (1, or the estimated sigma0^2 where the global test
    showed the a-priori model too optimistic). Fixed stations have zero covariance.

    ``failure`` says why the adjustment is not a result (no convergence, a non-finite value, a
    negative redundancy); empty when it is one. A failed adjustment never passes its global test.
    """

    poses: Pose
    poses_initial: Pose
    fixed: NDArray[np.bool_]
    cov_xi: FloatArray
    cov_position: FloatArray
    sigma0: float
    redundancy: float
    global_test_passed: bool
    variance_factor: float
    iterations: int
    tests: tuple[ObservationTest, ...]
    variance_components: dict[str, float]
    failure: str = ""

    @property
    def failed(self) -> bool:
        return bool(self.failure)

    @property
    def sigma_position_m(self) -> FloatArray:
        """Standard deviations (n, 3) of the station positions along the object axes."""
        return np.sqrt(np.maximum(np.diagonal(self.cov_position, axis1=1, axis2=2), 0.0))


@dataclass(frozen=True, eq=False)
class Station:
    """A node of the network: a scan's id, kind, time (nan for static) and initial pose, and the
    run (0-based index of the trajectory + cloud) a quasi-static station was sliced from."""

    scan_id: int
    name: str
    kind: ScanKind
    t_s: float
    t_start_s: float
    t_end_s: float
    T_obj_scan: Pose
    n_points: int
    tau_s: float = float("nan")  # effective time offset of the scan's planes from t_s (window bias)
    run: int = 0


@dataclass(frozen=True)
class SkippedWindow:
    """A window that had too few points to become a scan."""

    t_start_s: float
    t_end_s: float
    n_points: int


@dataclass(frozen=True)
class SlicingSummary:
    """What slicing did, for reports."""

    n_points_read: int
    n_points_in_scans: int
    n_points_outside_trajectory: int
    n_points_in_skipped_windows: int
    n_scans: int
    skipped: tuple[SkippedWindow, ...]

    @property
    def share_outside(self) -> float:
        return self.n_points_outside_trajectory / self.n_points_read if self.n_points_read else 0.0


@dataclass(frozen=True)
class Tie:
    """Detected plane ``plane_id`` of station ``station`` is on reference plane ``reference``."""

    station: int
    plane_id: int
    reference: int
    explicit: bool = False


@dataclass(frozen=True, eq=False)
class TrajectoryJump:
    """One jump: between samples ``index - 1`` and ``index`` the trajectory stepped by ``step``.

    ``index`` is the first sample that carries the step, ``t_s`` its time (the end of the jump
    interval), ``t_before_s`` the time of the sample before. The step is a rigid transformation of
    the object frame, ``T_traj = step . T_continuous`` from ``index`` on, parametrised as a
    rotation ``rotvec_rad`` (object frame, radians) about ``pivot_xyz`` (the position of sample
    ``index - 1``) followed by ``translation_m`` (object frame, metres): ``translation_m`` is how
    far the scanner itself was displaced, whatever the distance to the frame's origin (and UTM
    offsets do not enter the parameters). Both are estimated, never zeroed: a component within the
    noise is the noise of the estimate.

    ``translation_sigmas`` / ``rotation_sigmas`` are the excesses in robust noise sigmas,
    ``significance`` the largest factor by which an excess passed both its thresholds (floor and
    ``k_sigma``; >= 1 for every reported jump). ``sigma_translation_m`` / ``sigma_rotation_rad``
    are the noise scales (per axis, the largest of x, y, z) the step was judged against: the
    robust scale of the excesses of pass 1 around the jump. Use them as the per-axis standard
    deviation of the step (about right with white noise; conservative on smooth motion, where the
    fit of pass 2 is more precise).
    """

    index: int
    t_s: float
    t_before_s: float
    translation_m: FloatArray
    rotvec_rad: FloatArray
    pivot_xyz: FloatArray
    translation_sigmas: float
    rotation_sigmas: float
    significance: float
    sigma_translation_m: float
    sigma_rotation_rad: float

    @property
    def step(self) -> Pose:
        """The step ``S`` (``T_traj = S . T_continuous`` from ``index`` on) as a pose of the object
        frame: ``x -> R (x - pivot) + pivot + translation``."""
        q = rotvec_to_quat(self.rotvec_rad)
        R = quat_to_matrix(q)
        return Pose(q, self.pivot_xyz + self.translation_m - R @ self.pivot_xyz)

    @property
    def step_m(self) -> float:
        """Length of the translation of the scanner (metres)."""
        return float(np.linalg.norm(self.translation_m))

    @property
    def step_deg(self) -> float:
        """Rotation angle of the step (degrees)."""
        return math.degrees(float(np.linalg.norm(self.rotvec_rad)))
