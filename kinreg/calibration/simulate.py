"""Simulated calibration data with ground truth: a profile scanner on a moving platform.

The platform moves with constant velocity and constant angular rate about a fixed axis, so that
linear interpolation of position and SLERP of rotation between tracker epochs reproduce the true
pose exactly: every difference between estimate and truth comes from the simulated noise.

* The scanner runs in profile mode (``phi = 90 deg``, zenith angle round the full circle at
  ``zenith_step_deg``), ``profile_rate_hz`` profiles per second; the points of a profile are
  spread in time over the revolution.
* The tracker measures the platform pose at the start of every profile (and once more after the
  last one), with independent errors per epoch: ``t + dt``, ``Exp(dtheta) R`` (the estimator's
  error model).
* Scanner noise is added to range, horizontal direction and zenith angle.
* Optionally the reference planes handed to the estimator are perturbed by the plane sigmas.
* Optionally (:class:`RoomConfig`) the field stands in a room: floor, four walls, ceiling, and
  each plate sits on a larger backing board a few centimetres behind it, held by a post to the
  floor or the ceiling. Rays that miss the plates hit these surfaces, so the cloud holds the
  points a real scan of a calibration field holds; they carry plane index -1.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from kinreg.calibration.arrangement import (
    DEFAULT_BLIND_NADIR_HALF_ANGLE_DEG,
    PlanePatch,
    cast_rays,
    polar_to_xyz,
    profile_directions,
    table2_arrangement,
)
from kinreg.calibration.model import ScannerSigmas, SystemCalibration, TrackerSigmas
from kinreg.geometry import FloatArray, Pose, quat_multiply, rotvec_to_quat
from kinreg.survey import ReferencePlane, ReferencePlanes
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)


def default_truth() -> SystemCalibration:
    """A plausible T-probe mounting: 0.25 m above the scanner, a few degrees of boresight."""
    return SystemCalibration(np.array([0.012, -0.031, 0.254]), np.radians([1.2, -0.8, 2.5]))


def default_field() -> tuple[PlanePatch, ...]:
    """Table 2 arrangement at y1 = 3 m, z1 = 2.5 m, alpha1 = 45, beta1 = 45, gamma1 = 45 deg,
    0.5 m planes, placed with the scanner's start position at the object-frame origin."""
    a = math.radians(45.0)
    return table2_arrangement(3.0, 2.5, a, a, a, size_m=0.5)


@dataclass(frozen=True)
class RoomConfig:
    """The surroundings of the calibration field (object frame, scanner start at the origin).

    A box room: floor at ``floor_z_m``, ceiling at ``ceiling_z_m``, walls at ``y = +-wall_y_m``
    and ``x = +-wall_x_m``. Every plate has a mount: a backing board ``board_scale`` times its
    size, ``board_offset_m`` behind it (parallel: the hardest surface to tell from the plate),
    and a vertical post ``post_width_m`` wide down to the floor (plates below
    ``post_split_z_m``) or up to the ceiling, standing behind the board by the board's half
    size (so that it passes behind the plates stacked below or above). A mount that would cut
    through another plate is an error: such a world cannot be built.
    """

    floor_z_m: float = -1.6
    ceiling_z_m: float = 3.3
    wall_y_m: float = 4.0
    wall_x_m: float = 5.0
    board_scale: float = 1.25
    board_offset_m: float = 0.03
    post_width_m: float = 0.06
    post_split_z_m: float = 1.0


def room_surfaces(plates: Sequence[PlanePatch], room: RoomConfig) -> tuple[PlanePatch, ...]:
    """The room's surfaces (:class:`RoomConfig`) round ``plates``, each facing the origin.

    Raises ``ValueError`` if a board or post would cut through a plate.
    """
    ex, ey, ez = np.eye(3)
    lx, ly = 2.0 * room.wall_x_m, 2.0 * room.wall_y_m
    lz = room.ceiling_z_m - room.floor_z_m
    zc = 0.5 * (room.ceiling_z_m + room.floor_z_m)

    def box_face(name: str, center: tuple[float, float, float], u: FloatArray, v: FloatArray,
                 size: tuple[float, float]) -> PlanePatch:
        c = np.asarray(center, dtype=np.float64)
        n = np.cross(u, v)
        if n @ c > 0:  # face the origin
            n, v = -n, -v
        return PlanePatch(name, c, u.copy(), v.copy(), n, 0.5 * np.asarray(size, dtype=np.float64))

    out = [box_face("floor", (0.0, 0.0, room.floor_z_m), ex, ey, (lx, ly)),
           box_face("ceiling", (0.0, 0.0, room.ceiling_z_m), ex, ey, (lx, ly)),
           box_face("wall_+y", (0.0, room.wall_y_m, zc), ex, ez, (lx, lz)),
           box_face("wall_-y", (0.0, -room.wall_y_m, zc), ex, ez, (lx, lz)),
           box_face("wall_+x", (room.wall_x_m, 0.0, zc), ey, ez, (ly, lz)),
           box_face("wall_-x", (-room.wall_x_m, 0.0, zc), ey, ez, (ly, lz))]
    mounts = []
    for p in plates:
        board_half = room.board_scale * p.half_size_m
        board_c = p.center_m - room.board_offset_m * p.normal
        mounts.append(PlanePatch(f"{p.name}_board", board_c, p.axis_u, p.axis_v, p.normal, board_half))
        corners = [board_c + su * board_half[0] * p.axis_u + sv * board_half[1] * p.axis_v
                   for su in (-1, 1) for sv in (-1, 1)]
        zs = [float(c[2]) for c in corners]
        if p.center_m[2] < room.post_split_z_m:
            z_a, z_b = room.floor_z_m, min(zs)
        else:
            z_a, z_b = max(zs), room.ceiling_z_m
        if z_b - z_a <= 0.0:
            continue
        behind = board_c - (room.board_offset_m + float(np.max(board_half))) * p.normal
        horiz = np.array([behind[0], behind[1], 0.0])
        n = -horiz / np.linalg.norm(horiz) if np.linalg.norm(horiz) > 1e-9 else -ey
        c = np.array([behind[0], behind[1], 0.5 * (z_a + z_b)])
        u = np.cross(ez, n)
        mounts.append(PlanePatch(f"{p.name}_post", c, u, np.cross(n, u), n,
                                 np.array([0.5 * room.post_width_m, 0.5 * (z_b - z_a)])))
    for m in mounts:
        for p in plates:
            if rectangles_cross(m, p):
                raise ValueError(f"the mount {m.name} cuts through plate {p.name}: change the RoomConfig")
    return tuple(out + mounts)


def rectangles_cross(a: PlanePatch, b: PlanePatch) -> bool:
    """Whether two rectangular patches intersect (share a segment); parallel ones never do.

    >>> from kinreg.calibration.arrangement import PlanePatch
    >>> h = PlanePatch.from_angles("h", (0, 0, 0), (0, 0, 0), 1.0, facing=None)
    >>> rectangles_cross(h, PlanePatch.from_angles("v", (0, 0, 0.2), (math.pi / 2, 0, 0), 1.0))
    True
    >>> rectangles_cross(h, PlanePatch.from_angles("v", (0, 0, 0.6), (math.pi / 2, 0, 0), 1.0))
    False
    """
    direction = np.cross(a.normal, b.normal)
    if np.linalg.norm(direction) < 1e-12:
        return False
    # A point on both planes: least-norm solution of the two plane equations.
    A = np.stack([a.normal, b.normal])
    p0 = np.linalg.lstsq(A, np.array([a.d_m, b.d_m]), rcond=None)[0]
    lo, hi = -np.inf, np.inf
    for r in (a, b):
        for axis, half in ((r.axis_u, r.half_size_m[0]), (r.axis_v, r.half_size_m[1])):
            k = float(direction @ axis)
            off = float((p0 - r.center_m) @ axis)
            if abs(k) < 1e-12:
                if abs(off) > half:
                    return False
                continue
            s1, s2 = sorted(((-half - off) / k, (half - off) / k))
            lo, hi = max(lo, s1), min(hi, s2)
    return bool(lo <= hi)


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate. Platform motion: start pose chosen so that the scanner starts at the
    object-frame origin with its axes along the object axes, then ``velocity_m_s`` (object
    frame) and ``angular_rate_rad_s`` (rotation vector rate, object frame)."""

    truth: SystemCalibration = field(default_factory=default_truth)
    planes: tuple[PlanePatch, ...] = field(default_factory=default_field)
    scanner: ScannerSigmas = field(default_factory=ScannerSigmas)
    tracker: TrackerSigmas = field(default_factory=TrackerSigmas)
    n_profiles: int = 40
    profile_rate_hz: float = 50.0
    zenith_step_deg: float = 0.2
    blind_nadir_half_angle_deg: float = DEFAULT_BLIND_NADIR_HALF_ANGLE_DEG
    velocity_m_s: tuple[float, float, float] = (0.2, 0.0, 0.0)
    angular_rate_rad_s: tuple[float, float, float] = (0.0, 0.0, math.radians(10.0))
    plane_sigma_d_m: float = 0.0
    plane_sigma_normal_rad: float = 0.0
    t0_s: float = 1000.0
    room: RoomConfig | None = None  # the surroundings; None: only the plates are in the cloud


@dataclass(frozen=True, eq=False)
class SimulatedCalibration:
    """Simulated inputs of :func:`~kinreg.calibration.model.estimate_calibration` and the truth.

    ``points_s`` ``(N, 3)`` noisy scanner points, ``stamps_s`` ``(N,)``, ``plane_index`` ``(N,)``
    (the true plate of each point, -1 for room surfaces and mounts),
    ``trajectory`` the noisy tracker poses ``T_l_b``, ``trajectory_true`` the noise-free ones,
    ``planes`` the reference planes as given to the estimator (perturbed if plane sigmas are set),
    ``planes_true`` the true ones.
    """

    points_s: FloatArray
    stamps_s: FloatArray
    plane_index: np.ndarray
    trajectory: Trajectory
    trajectory_true: Trajectory
    planes: ReferencePlanes
    planes_true: ReferencePlanes
    truth: SystemCalibration


def simulate_calibration(config: SimulationConfig | None = None, seed: int | None = 0
                         ) -> SimulatedCalibration:
    """Simulate one calibration run (module docstring); ``seed`` makes it reproducible."""
    cfg = config or SimulationConfig()
    rng = np.random.default_rng(seed)
    T_b_s = cfg.truth.as_pose()
    # Start pose: scanner at the origin, aligned with the object axes -> T_l_b0 = T_b_s^-1.
    start = T_b_s.inverse()
    v = np.asarray(cfg.velocity_m_s, dtype=np.float64)
    wrate = np.asarray(cfg.angular_rate_rad_s, dtype=np.float64)

    def true_pose(t_rel: FloatArray) -> Pose:
        q = quat_multiply(rotvec_to_quat(t_rel[:, None] * wrate), start.quat_wxyz)
        return Pose(q, start.t_xyz + t_rel[:, None] * v)

    theta, dirs_s = profile_directions(math.radians(cfg.zenith_step_deg),
                                       math.radians(cfg.blind_nadir_half_angle_deg))
    frac = (theta + math.pi) / (2.0 * math.pi)  # position of each ray in the revolution
    period = 1.0 / cfg.profile_rate_hz
    t_rel = (np.arange(cfg.n_profiles)[:, None] * period + frac[None, :] * period).ravel().astype(np.float64)
    dirs = np.tile(dirs_s, (cfg.n_profiles, 1))
    th = np.tile(theta, cfg.n_profiles)
    T_l_b = true_pose(t_rel)
    T_l_s = T_l_b.compose(T_b_s)
    surfaces = tuple(cfg.planes) + (room_surfaces(cfg.planes, cfg.room) if cfg.room is not None else ())
    rng_m, index = cast_rays(surfaces, T_l_s.t_xyz, np.einsum("nij,nj->ni", T_l_s.rotation_matrix, dirs))
    hit = index >= 0
    index = np.where(index < len(cfg.planes), index, -1)
    n_hit = int(hit.sum())
    d = rng_m[hit] + rng.normal(0.0, cfg.scanner.sigma_d_m, n_hit)
    ph = math.pi / 2 + rng.normal(0.0, cfg.scanner.sigma_phi_rad, n_hit)
    tt = th[hit] + rng.normal(0.0, cfg.scanner.sigma_theta_rad, n_hit)
    points = polar_to_xyz(d, ph, tt)

    # Tracker epochs: one per profile start, plus one closing the last profile.
    t_ep = (np.arange(cfg.n_profiles + 1) * period).astype(np.float64)
    true_ep = true_pose(t_ep)
    n_ep = len(t_ep)
    dtheta = rng.normal(0.0, cfg.tracker.sigma_rot_rad, (n_ep, 3))
    dt = rng.normal(0.0, cfg.tracker.sigma_t_m, (n_ep, 3))
    meas = Pose(quat_multiply(rotvec_to_quat(dtheta), true_ep.quat_wxyz), true_ep.t_xyz + dt)
    stamps_ep = (cfg.t0_s + t_ep).astype(np.float64)

    planes_true = ReferencePlanes(accuracy_m=max(cfg.plane_sigma_d_m, 1e-6),
                                  planes=tuple(p.as_reference_plane() for p in cfg.planes))
    planes_obs = planes_true
    if cfg.plane_sigma_d_m > 0 or cfg.plane_sigma_normal_rad > 0:
        planes_obs = _perturb_planes(planes_true, cfg.plane_sigma_d_m, cfg.plane_sigma_normal_rad, rng)
    logger.debug("simulated %d points on %d planes, %d tracker epochs", n_hit, len(cfg.planes), n_ep)
    return SimulatedCalibration(
        points_s=points, stamps_s=cfg.t0_s + t_rel[hit], plane_index=index[hit],
        trajectory=Trajectory(stamps_ep, meas, source="simulated"),
        trajectory_true=Trajectory(stamps_ep, true_ep, source="simulated (true)"),
        planes=planes_obs, planes_true=planes_true, truth=cfg.truth)


def _perturb_planes(planes: ReferencePlanes, sigma_d_m: float, sigma_normal_rad: float,
                    rng: np.random.Generator) -> ReferencePlanes:
    from kinreg.calibration.model import _tangent_bases

    normals = planes.normals
    tang = _tangent_bases(normals)
    out: list[ReferencePlane] = []
    for p, n, tb in zip(planes.planes, normals, tang, strict=True):
        tilt = rng.normal(0.0, sigma_normal_rad, 2)
        nn = n + tilt @ tb
        out.append(ReferencePlane(p.name, nn / np.linalg.norm(nn), p.d_m + rng.normal(0.0, sigma_d_m),
                                  p.extent))
    return ReferencePlanes(accuracy_m=planes.accuracy_m, planes=tuple(out), links=planes.links)


def static_single_profile(patches: Sequence[PlanePatch], truth: SystemCalibration,
                          zenith_step_deg: float,
                          blind_nadir_half_angle_deg: float = DEFAULT_BLIND_NADIR_HALF_ANGLE_DEG
                          ) -> SimulatedCalibration:
    """Noise-free data of one profile from a standing platform with a single tracker epoch.

    The scanner sits at the origin with identity orientation, the plane patches are given in its
    frame (the planning set-up): used to check the planning covariance against the estimator.
    """
    cfg = SimulationConfig(truth=truth, planes=tuple(patches), n_profiles=1,
                           zenith_step_deg=zenith_step_deg,
                           blind_nadir_half_angle_deg=blind_nadir_half_angle_deg,
                           velocity_m_s=(0.0, 0.0, 0.0), angular_rate_rad_s=(0.0, 0.0, 0.0),
                           scanner=ScannerSigmas(0.0, 0.0, 0.0), tracker=TrackerSigmas(0.0, 0.0))
    sim = simulate_calibration(cfg, seed=0)
    # A single epoch at the profile start; all points of the profile share it.
    traj = Trajectory(sim.trajectory.stamps_s[:1].copy(), sim.trajectory_true.poses[:1])
    stamps = np.full(len(sim.stamps_s), traj.stamps_s[0])
    return SimulatedCalibration(sim.points_s, stamps, sim.plane_index, traj, traj, sim.planes,
                                sim.planes_true, truth)


def room_scenario(seed: int, n_profiles: int = 40, zenith_step_deg: float = 0.2,
                  start_lever_m: float = 0.02, start_angle_deg: float = 0.5,
                  room: RoomConfig | None = None) -> tuple[SimulationConfig, SystemCalibration]:
    """A seeded calibration run in a room and its starting values (the issue-19 scenario).

    Table 2 field (y1 = 3 m, z1 = 2.5 m, 45 deg) of 0.35 m plates in :class:`RoomConfig`; the
    truth varies with the seed: lever arm about 0.2 m (each axis +-5 cm), boresight angles
    uniform in +-1.4 deg; the platform moves at 0.15 m/s in a random horizontal direction and
    turns about a random axis at 6-10 deg/s (vertical component dominant). The starting values are
    ``start_lever_m`` off in a random direction and ``start_angle_deg`` off in each angle with a
    random sign. Returns the simulation config and the starting values.
    """
    rng = np.random.default_rng([19, seed])
    a = math.radians(45.0)
    plates = table2_arrangement(3.0, 2.5, a, a, a, size_m=0.35)
    lever = np.array([0.0, 0.0, 0.2]) + rng.uniform(-0.05, 0.05, 3)
    angles = np.radians(rng.uniform(-1.4, 1.4, 3))
    truth = SystemCalibration(lever, angles)
    heading = rng.uniform(0.0, 2.0 * math.pi)
    velocity = 0.15 * np.array([math.cos(heading), math.sin(heading), 0.0])
    axis = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.choice([-1.0, 1.0])])
    rate = math.radians(rng.uniform(6.0, 10.0)) * axis / np.linalg.norm(axis)
    cfg = SimulationConfig(truth=truth, planes=plates, n_profiles=n_profiles,
                           zenith_step_deg=zenith_step_deg,
                           velocity_m_s=(float(velocity[0]), float(velocity[1]), 0.0),
                           angular_rate_rad_s=(float(rate[0]), float(rate[1]), float(rate[2])),
                           room=room if room is not None else RoomConfig())
    direction = rng.normal(size=3)
    start = SystemCalibration(lever + start_lever_m * direction / np.linalg.norm(direction),
                              angles + np.radians(start_angle_deg) * rng.choice([-1.0, 1.0], 3))
    return cfg, start
