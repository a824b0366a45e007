"""The simulated instruments: a rotating multi-beam LiDAR head cast against the scene; static tripod scans."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import (
    FloatArray,
    Pose,
)
from kinreg.simulation.scene import Scene
from kinreg.simulation.walk import _rot_x, _rot_y, _rot_z
from kinreg.types import Scan, ScanKind

if TYPE_CHECKING:
    from kinreg.simulation.realism import RealWorld

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorConfig:
    """A handheld rotating LiDAR: a spinning-mirror profiler (or multi-beam) on a rotating head.

    Each beam sweeps a full circle in the head's x-z plane ``line_rate_hz`` times a second (one
    scan line per turn); the head turns about the platform's z axis at ``head_rate_hz``, so half a
    head turn covers the whole sphere. Directions inside ``blind_cone_deg`` around
    ``blind_axis_p`` (the operator behind and below the unit) return nothing.
    ``pulse_rate_hz`` is the emitted pulse rate; the recorded point rate is lower by the blind
    cone (and by misses, none inside a closed building).
    """

    pulse_rate_hz: float = 10_000.0
    line_rate_hz: float = 100.0
    n_beams: int = 1
    beam_spread_deg: float = 30.0  # total spread of the beams' elevations (n_beams > 1)
    head_rate_hz: float = 0.5
    blind_cone_deg: float = 50.0  # half-angle
    blind_axis_p: tuple[float, float, float] = (-1.0, 0.0, -0.6)
    range_sigma_m: float = 0.01
    angle_sigma_deg: float = 0.01
    max_range_m: float = 30.0
    min_range_m: float = 0.5
    intensity_noise: float = 0.03  # relative
    head_tilt_deg: float = 0.0  # the head's spin axis tilted forward from the platform's z axis


@dataclass(frozen=True)
class StaticConfig:
    """Static tripod scans (TLS) at known poses: a spherical grid, millimetre noise."""

    n_scans: int = 3
    angle_step_deg: float = 1.0
    elevation_min_deg: float = -60.0
    tripod_height_m: float = 1.5
    range_sigma_m: float = 0.002
    max_range_m: float = 60.0
    min_range_m: float = 0.3


def _interpolate_fast(stamps_s: FloatArray, poses: Pose,
                      query_s: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation matrices (N, 3, 3) and translations (N, 3) at ``query_s``.

    The same formula as :func:`kinreg.geometry.interpolate_poses` (linear position, SLERP
    rotation, clamped at the ends) with the per-segment angle computed once per segment instead
    of once per point; results agree to rounding (tested).
    """
    s = stamps_s
    i = np.clip(np.searchsorted(s, query_s, side="right") - 1, 0, len(s) - 2)
    u = np.clip((query_s - s[i]) / (s[i + 1] - s[i]), 0.0, 1.0)
    t = poses.t_xyz[i] + u[:, None] * (poses.t_xyz[i + 1] - poses.t_xyz[i])
    q0 = poses.quat_wxyz[:-1]
    q1 = poses.quat_wxyz[1:]
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    theta = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-9
    safe = np.where(near, 1.0, sin_theta)
    th, sf, nr = theta[i], safe[i], near[i]
    w0 = np.where(nr, 1.0 - u, np.sin((1.0 - u) * th) / sf)
    w1 = np.where(nr, u, np.sin(u * th) / sf)
    q = w0[:, None] * q0[i] + w1[:, None] * q1[i]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Pose(q, t).rotation_matrix, t


def _head_directions(theta: FloatArray, elev: FloatArray, psi: FloatArray) -> FloatArray:
    """Unit beam directions (N, 3) in the platform frame.

    Mirror angle ``theta`` sweeps the head's x-z plane, ``elev`` tilts the beam out of it, the
    head is turned by ``psi`` about the platform's z axis.
    """
    ce = np.cos(elev)
    hx = ce * np.cos(theta)
    hy = np.sin(elev)
    c, s = np.cos(psi), np.sin(psi)
    out = np.empty((len(theta), 3))
    out[:, 0] = c * hx - s * hy
    out[:, 1] = s * hx + c * hy
    out[:, 2] = ce * np.sin(theta)
    return out


def _intensity(refl: FloatArray, cos_inc: FloatArray, range_m: FloatArray, noise: float,
               rng: np.random.Generator) -> NDArray[np.uint16]:
    """Plausible 16-bit intensity: reflectivity, incidence (Lambert-like), range fall-off, noise."""
    val = refl * (0.25 + 0.75 * np.clip(cos_inc, 0.0, 1.0)) * np.exp(-range_m / 40.0)
    val *= 1.0 + noise * rng.standard_normal(len(val))
    return np.clip(np.round(val * 60000.0), 0, 65535).astype(np.uint16)


def static_scan_positions(scene: Scene, n: int, height_m: float) -> FloatArray:
    """Tripod positions (n, 3) in building coordinates: corridor middle, then rooms' walk loops."""
    plan = scene.walk_plan
    if plan is None:
        raise ValueError("the scene has no walk plan")
    (cx0, cy0), (cx1, cy1) = plan.corridor_xy_min, plan.corridor_xy_max
    out = [(0.5 * (cx0 + cx1) + 0.37, 0.5 * (cy0 + cy1) + 0.21, height_m)]
    m = plan.keep_out_m
    rooms = sorted(plan.rooms, key=lambda r: r.door_xy[0])
    order = [0, len(rooms) - 1, *range(1, len(rooms) - 1)]
    for i in order:
        r = rooms[i]
        (x0, y0), (x1, y1) = r.xy_min, r.xy_max
        y_far = y1 - m if r.door_inward_xy[1] > 0 else y0 + m
        out.append((x0 + m + 0.3 * (x1 - x0 - 2 * m), y_far, height_m))
    return np.array(out[:n], dtype=np.float64)


def make_static_scans(scene: Scene, config: StaticConfig, rng: np.random.Generator,
                      origin_xyz: FloatArray | None = None, world: RealWorld | None = None) -> tuple[Scan, ...]:
    """Static tripod scans: points (scan frame) on a spherical grid, poses ``T_obj_scan``.

    The scanner stands level (a few hundredths of a degree of residual tilt) with a random
    heading. ``origin_xyz`` is added to the poses' translations. With ``world`` the rays see its
    wavy surfaces and its furniture (not its walkers: the building is empty for a static scan).
    """
    origin = np.zeros(3) if origin_xyz is None else np.asarray(origin_xyz, dtype=np.float64)
    step = math.radians(config.angle_step_deg)
    az = np.arange(0.0, 2 * np.pi, step)
    el = np.arange(math.radians(config.elevation_min_deg), np.pi / 2 + 1e-9, step)
    A, E = np.meshgrid(az, el, indexing="ij")
    A, E = A.ravel(), E.ravel()
    d_scan = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=1)
    scans = []
    for i, pos in enumerate(static_scan_positions(scene, config.n_scans, config.tripod_height_m)):
        tilt = np.radians(0.03) * rng.standard_normal(2)
        heading = np.array(rng.uniform(-np.pi, np.pi))
        R = _rot_z(heading) @ _rot_y(np.array(tilt[0])) @ _rot_x(np.array(tilt[1]))
        T_local = Pose.from_rotation_translation(R, pos)
        if world is None:
            r, pid = scene.raycast(np.broadcast_to(pos, d_scan.shape), d_scan @ R.T, config.max_range_m,
                                   config.min_range_m)
            hit = pid >= 0
        else:
            r, pid, normals_all = world.raycast(np.ascontiguousarray(np.broadcast_to(pos, d_scan.shape)),
                                                d_scan @ R.T, None, config.max_range_m, config.min_range_m)
            hit = np.isfinite(r)
        r_meas = r[hit] + config.range_sigma_m * rng.standard_normal(int(hit.sum()))
        pts = r_meas[:, None] * d_scan[hit]
        if world is None:
            refl = np.array([p.reflectivity for p in scene.patches])[pid[hit]]
            normals = np.array([p.normal for p in scene.patches])[pid[hit]]
        else:
            refl = np.where(pid[hit] >= 0, np.array([p.reflectivity for p in scene.patches])[pid[hit]], 0.5)
            normals = normals_all[hit]
        inten = _intensity(refl, -np.einsum("ij,ij->i", normals, d_scan[hit] @ R.T), r[hit], 0.02, rng)
        T_obj_scan = Pose(T_local.quat_wxyz, T_local.t_xyz + origin)
        scans.append(Scan(i, f"static_{i:02d}", ScanKind.STATIC, T_obj_scan, pts,
                          intensity=inten.astype(np.float32)))
    return tuple(scans)
