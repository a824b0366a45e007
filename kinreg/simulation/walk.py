"""The simulated walk: waypoints through the scene, a smooth path with step sway: the true trajectory."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from kinreg.geometry import (
    FloatArray,
    Pose,
    interpolate_poses,
    make_quat_continuous,
    matrix_to_quat,
)
from kinreg.simulation.scene import Scene, WalkPlan
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class WalkConfig:
    """The true handheld motion: a walk through every room and back to the start.

    ``speed_mps`` is the nominal walking speed; the circuit is walked at the speed that fits the
    duration (between ``min_speed_mps`` and ``max_speed_mps``), repeated if the duration allows
    several circuits at the nominal speed, cut short if it is too short for one.
    """

    rate_hz: float = 100.0
    speed_mps: float = 0.8
    min_speed_mps: float = 0.5
    max_speed_mps: float = 1.1
    pause_s: float = 3.0  # standing still at the start and the end
    height_m: float = 1.3
    corner_smoothing_m: float = 0.35
    step_rate_hz: float = 1.8
    bob_m: float = 0.015
    sway_m: float = 0.02
    pitch_deg: float = -5.0  # mean, positive nose up
    sway_deg: float = 3.0  # pitch, roll and yaw sway amplitude at the step rate
    carry_roll_deg: float = 10.0  # slow rotation about the carrying (x) axis
    carry_period_s: float = 23.0
    jitter_deg: float = 1.5  # smooth random hand jitter (1 sigma)
    # Stand-stills on control points: the walk stops this many times, spread evenly in time over
    # the walk, each for stand_still_s seconds, with smooth stops and starts of stand_still_ramp_s.
    # 0 keeps the walk exactly as without them. A hand holds the unit there: it sways about the
    # still pose by stand_still_sway_m per axis and stand_still_sway_deg per axis (1 sigma, smooth
    # noise of Gaussian correlation time stand_still_sway_corr_s), which makes about 4 cm/s median
    # speed and 1-1.5 cm extent per axis over 4 s, as measured on a handheld unit held on a point.
    stand_stills: int = 0
    stand_still_s: float = 4.0
    stand_still_ramp_s: float = 1.0
    stand_still_sway_m: float = 0.0035
    stand_still_sway_deg: float = 0.3
    stand_still_sway_corr_s: float = 0.1


def _rot_z(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape((*np.shape(a), 3, 3))


def _rot_y(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape((*np.shape(a), 3, 3))


def _rot_x(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape((*np.shape(a), 3, 3))


def _smooth_noise(rng: np.random.Generator, n: int, rate_hz: float, corr_s: float) -> FloatArray:
    """Unit-variance noise with a Gaussian correlation time of ``corr_s`` seconds, shape (n,)."""
    from scipy.ndimage import gaussian_filter1d

    sigma = max(corr_s * rate_hz, 1e-6)
    pad = int(4 * sigma) + 1
    x = gaussian_filter1d(rng.standard_normal(n + 2 * pad), sigma)[pad : pad + n]
    return x / max(float(np.std(x)), 1e-12)


def walk_waypoints(plan: WalkPlan, rng: np.random.Generator) -> FloatArray:
    """One circuit (m, 2): west end of the corridor, every room by its door, back to the start."""
    (cx0, cy0), (cx1, cy1) = plan.corridor_xy_min, plan.corridor_xy_max
    y_mid = 0.5 * (cy0 + cy1)
    m = plan.keep_out_m
    start = np.array([cx0 + 1.2, y_mid])
    pts = [start]
    for room in sorted(plan.rooms, key=lambda r: r.door_xy[0]):
        xd, yd = room.door_xy
        inward = room.door_inward_xy[1]
        (x0, y0), (x1, y1) = room.xy_min, room.xy_max
        y_near, y_far = (y0 + m, y1 - m) if inward > 0 else (y1 - m, y0 + m)
        loop = [(xd, y_near), (x0 + m, y_near), (x0 + m, y_far), (x1 - m, y_far), (x1 - m, y_near),
                (xd, y_near)]
        if rng.uniform() < 0.5:
            loop = loop[::-1]
        pts += [np.array([xd, y_mid]), np.array([xd, yd - inward * 0.6]), np.array([xd, yd + inward * 0.6])]
        pts += [np.array(p) for p in loop]
        pts += [np.array([xd, yd + inward * 0.6]), np.array([xd, yd - inward * 0.6]), np.array([xd, y_mid])]
    # back along the corridor slightly off the way out, ending next to the start
    y_back = y_mid - 0.25 * (cy1 - cy0) / 2
    pts += [np.array([cx1 - 1.5, y_mid]), np.array([cx1 - 1.5, y_back]), np.array([cx0 + 0.9, y_back]),
            np.array([cx0 + 0.9, y_mid])]
    return np.array(pts)


def _resample_polyline(pts: FloatArray, step_m: float) -> FloatArray:
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    pts = pts[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    q = np.arange(0.0, s[-1], step_m)
    return np.stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])], axis=1)


def stand_still_intervals(config: WalkConfig, duration_s: float, t0_s: float) -> FloatArray:
    """The (start, end) times (k, 2) [s] of the walk's stand-stills (:class:`WalkConfig`): spread
    evenly over the walk between the pauses at its ends; empty without stand-stills."""
    n = config.stand_stills
    if n <= 0:
        return np.zeros((0, 2))
    lo = config.pause_s + 2.0 + config.stand_still_ramp_s
    hi = duration_s - config.pause_s - 2.0 - config.stand_still_ramp_s
    slot = (hi - lo) / n
    if slot < config.stand_still_s + 2.0 * config.stand_still_ramp_s + 1.0:
        raise ValueError(f"{n} stand-stills of {config.stand_still_s} s do not fit into a {duration_s} s walk")
    mid = lo + slot * (np.arange(n) + 0.5)
    return t0_s + np.column_stack([mid - 0.5 * config.stand_still_s, mid + 0.5 * config.stand_still_s])


def _walk_time(tr: FloatArray, config: WalkConfig, duration_s: float) -> FloatArray:
    """The walk's own time at the real times ``tr`` (relative, s): it stops during the stand-stills
    and slows down to them and up from them with a raised-cosine speed over the ramps."""
    intervals = stand_still_intervals(config, duration_s, 0.0)
    rate = np.ones_like(tr)
    ramp = config.stand_still_ramp_s
    for a, b in intervals:
        into = np.clip((a - tr) / ramp, 0.0, 1.0)  # 1 before the ramp down, 0 from the stop
        out = np.clip((tr - b) / ramp, 0.0, 1.0)  # 0 until the start, 1 after the ramp up
        factor = np.where(tr < a, 0.5 - 0.5 * np.cos(np.pi * into), np.where(tr > b, 0.5 - 0.5 * np.cos(np.pi * out),
                                                                              0.0))
        rate = rate * factor
    dt = np.diff(tr, prepend=tr[0])
    return np.cumsum(0.5 * (rate + np.concatenate([[rate[0]], rate[:-1]])) * dt)


def make_walk(scene: Scene, config: WalkConfig, duration_s: float, t0_s: float,
              rng: np.random.Generator) -> Trajectory:
    """The true trajectory ``T_obj_p`` at ``config.rate_hz`` over ``duration_s`` seconds, with
    ``config.stand_stills`` stand-stills (:func:`stand_still_intervals`): the walk of the
    remaining time, its own clock stopped during them (the pose is exactly constant there)."""
    if config.stand_stills <= 0:
        return _make_moving_walk(scene, config, duration_s, t0_s, rng)
    n = round(duration_s * config.rate_hz) + 1
    tr = np.arange(n) / config.rate_hz
    tw = _walk_time(tr, config, duration_s)
    moving = _make_moving_walk(scene, config, float(np.ceil(tw[-1] * config.rate_hz) / config.rate_hz), 0.0, rng)
    poses = interpolate_poses(moving.stamps_s, moving.poses, np.minimum(tw, moving.stamps_s[-1]))
    poses = _held_by_hand(poses, tr, config, duration_s, rng)
    return Trajectory(t0_s + tr, Pose(make_quat_continuous(poses.quat_wxyz), poses.t_xyz), source="simulated truth")


def _held_by_hand(poses: Pose, tr: FloatArray, config: WalkConfig, duration_s: float,
                  rng: np.random.Generator) -> Pose:
    """``poses`` at the relative times ``tr`` with a hand's sway over the stand-stills: smooth
    noise in position (object frame) and attitude (platform frame, a right perturbation), faded
    in over the ramp before each stand-still and out over the ramp after it (drawn after the walk,
    so the walk itself does not change with it)."""
    from kinreg.geometry import rotvec_to_quat

    n = len(tr)
    envelope = np.zeros(n)
    ramp = config.stand_still_ramp_s
    for a, b in stand_still_intervals(config, duration_s, 0.0):
        rise = np.clip((tr - (a - ramp)) / ramp, 0.0, 1.0)
        fall = np.clip(((b + ramp) - tr) / ramp, 0.0, 1.0)
        envelope = np.maximum(envelope, (0.5 - 0.5 * np.cos(np.pi * rise)) * (0.5 - 0.5 * np.cos(np.pi * fall)))
    noise = np.column_stack([_smooth_noise(rng, n, config.rate_hz, config.stand_still_sway_corr_s)
                             for _ in range(6)])
    dt = config.stand_still_sway_m * noise[:, :3] * envelope[:, None]
    dphi = np.radians(config.stand_still_sway_deg) * noise[:, 3:] * envelope[:, None]
    return Pose(poses.quat_wxyz, poses.t_xyz + dt).compose(Pose(rotvec_to_quat(dphi), np.zeros((n, 3))))


def _make_moving_walk(scene: Scene, config: WalkConfig, duration_s: float, t0_s: float,
                      rng: np.random.Generator) -> Trajectory:
    """The true trajectory ``T_obj_p`` at ``config.rate_hz`` over ``duration_s`` seconds.

    The path (rounded corners) visits every room of ``scene.walk_plan`` and returns next to the
    start; the speed ramps up and down smoothly around ``pause_s`` of standing still at both
    ends. Position bobs and sways with the steps; yaw follows the path, with pitch/roll/yaw sway,
    a slow roll about the carrying axis and smooth hand jitter. Rows are exactly
    ``t0_s + k / rate_hz``.
    """
    from scipy.ndimage import gaussian_filter1d

    if scene.walk_plan is None:
        raise ValueError("the scene has no walk plan")
    cfg = config
    n = round(duration_s * cfg.rate_hz) + 1
    k = np.arange(n)
    tr = k / cfg.rate_hz  # relative time
    # path, densified and smoothed in arc length (rounded corners)
    step = 0.02
    circuit = _resample_polyline(walk_waypoints(scene.walk_plan, rng), step)
    sig = cfg.corner_smoothing_m / step
    circuit = np.stack([gaussian_filter1d(circuit[:, i], sig, mode="nearest") for i in range(2)], axis=1)
    seg = np.linalg.norm(np.diff(circuit, axis=0), axis=1)
    L = float(seg.sum())
    # speed shape: smooth start/stop ramps, +-10 % slow variation
    ramp = 2.0
    p = cfg.pause_s
    t_end = tr[-1]
    up = np.clip((tr - p) / ramp, 0.0, 1.0)
    down = np.clip((t_end - p - tr) / ramp, 0.0, 1.0)
    shape = (0.5 - 0.5 * np.cos(np.pi * up)) * (0.5 - 0.5 * np.cos(np.pi * down))
    shape *= 1.0 + 0.1 * _smooth_noise(rng, n, cfg.rate_hz, 4.0)
    s_shape = np.concatenate([[0.0], np.cumsum(0.5 * (shape[1:] + shape[:-1]))]) / cfg.rate_hz
    S = float(s_shape[-1])
    if S <= 0:
        v, laps = 0.0, 1
    else:
        laps = max(1, math.floor(S * cfg.speed_mps / L + 0.5))
        v = laps * L / S
        if v > cfg.max_speed_mps or v < cfg.min_speed_mps:
            v = cfg.speed_mps  # cut short (or, if longer, the end of the last lap is not reached)
            laps = max(1, math.ceil(S * v / L))
    path = np.concatenate([circuit] + [circuit[1:]] * (laps - 1))
    s_path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    s_t = np.minimum(s_shape * v, s_path[-1])
    xy = np.stack([np.interp(s_t, s_path, path[:, 0]), np.interp(s_t, s_path, path[:, 1])], axis=1)
    # heading from the path tangent, smoothed in time (a walker turns over ~0.3 s)
    tang = np.gradient(path, axis=0)
    heading_path = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
    heading = np.interp(s_t, s_path, heading_path)
    heading = gaussian_filter1d(heading, 0.3 * cfg.rate_hz, mode="nearest")
    # step motion scales with the walking speed
    moving = shape / max(float(shape.max()), 1e-12)
    ph = 2 * np.pi * cfg.step_rate_hz * tr
    lateral = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    xy = xy + (cfg.sway_m * moving * np.sin(0.5 * ph))[:, None] * lateral
    z = cfg.height_m + cfg.bob_m * moving * np.sin(ph) + 0.01 * _smooth_noise(rng, n, cfg.rate_hz, 2.0)
    sway = np.radians(cfg.sway_deg)
    jit = np.radians(cfg.jitter_deg)
    yaw = heading + sway * moving * np.sin(0.5 * ph + 0.3) + jit * _smooth_noise(rng, n, cfg.rate_hz, 0.8)
    pitch = (np.radians(cfg.pitch_deg) + sway * moving * np.sin(ph + 1.0)
             + jit * _smooth_noise(rng, n, cfg.rate_hz, 0.8))
    roll = (sway * moving * np.sin(0.5 * ph + 2.0) + jit * _smooth_noise(rng, n, cfg.rate_hz, 0.8)
            + np.radians(cfg.carry_roll_deg) * np.sin(2 * np.pi * tr / cfg.carry_period_s))
    R = _rot_z(yaw) @ _rot_y(-pitch) @ _rot_x(roll)
    quat = make_quat_continuous(matrix_to_quat(R))
    t_xyz = np.column_stack([xy, z])
    return Trajectory(t0_s + k / cfg.rate_hz, Pose(quat, t_xyz), source="simulated truth")
