"""Ground-truth simulator: a planar building, a handheld rotating LiDAR, a walk, SLAM drift, static scans.

Every later stage is tested against this module, so everything is parametrised (scene, sensor,
walk, drift, noise, seed) and deterministic given the configuration.

Frames and conventions (METHOD.md section 4):

- object frame ``obj``: the building's frame, metres; ``z`` up, the floor at ``z = 0``.
- platform frame ``p``: the handheld unit, ``x`` forward, ``y`` left, ``z`` up; the exported
  trajectories are ``T_obj_p``. The sensor origin is the platform origin, so the "sensor-frame"
  points of the simulator are platform-frame points (the head rotation is internal to the
  instrument, as in a GeoSLAM ZEB whose head angle is measured by an encoder).
- A patch's normal points into the free space (towards any scanner that can see it), so the
  two faces of a 0.2 m wall have opposite normals.

The georeferencing is done exactly as SLAM software does it: the 100 Hz trajectory rows are
interpolated (linear position, SLERP rotation, :func:`kinreg.geometry.interpolate_poses`) at every
point time. The rays are cast from the interpolated TRUE trajectory; the exported cloud is mapped
with the interpolated DRIFTED trajectory ``T_slam(t) = D(t) * T_true(t)``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import json
import logging
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import (
    FloatArray,
    Pose,
    make_quat_continuous,
    matrix_to_quat,
    quat_to_rotvec,
    rotvec_to_quat,
)
from kinreg.io.atomic import atomic_path
from kinreg.io.trajectory import write_trajectory_geoslam as _write_geoslam
from kinreg.types import Scan, ScanKind, Trajectory

logger = logging.getLogger(__name__)

# Version of the files written by :func:`write_run` (run_meta.json, truth_scene.json,
# static_truth.json). Bump when a field changes meaning or is removed.
SIMULATION_SCHEMA_VERSION = 1

IntArray = NDArray[np.int64]

_EZ = np.array([0.0, 0.0, 1.0])


# =========================================================================== scene


@dataclass(frozen=True, eq=False)
class Patch:
    """A planar convex polygon of the scene, object frame, metres.

    ``normal`` (3,) is unit and points into the free space; ``n . x = d`` on the patch.
    ``vertices`` (k, 3) are ordered around the polygon. ``plane_id`` groups coplanar patches
    (a wall interrupted by doors is one plane, several patches). ``role`` is one of
    ``outer_wall``, ``interior_wall``, ``floor``, ``ceiling``, ``door_reveal``, ``object``,
    ``ramp``. ``reflectivity`` in [0, 1] drives the simulated intensity.
    """

    patch_id: int
    name: str
    plane_name: str
    role: str
    normal: FloatArray
    d: float
    vertices: FloatArray
    reflectivity: float = 0.6
    plane_id: int = -1


@dataclass(frozen=True, eq=False)
class ScenePlane:
    """An infinite plane ``n . x = d`` of the scene and the patches that lie on it."""

    plane_id: int
    name: str
    role: str
    normal: FloatArray
    d: float
    patch_ids: tuple[int, ...]


@dataclass(frozen=True)
class Room:
    """A room of the walk plan: axis-aligned footprint, door in the wall towards the corridor.

    ``xy_min``/``xy_max`` bound the free floor (wall faces), ``door_xy`` is the door's centre on
    the wall's mid-plane, ``door_inward_xy`` the unit direction from the corridor into the room.
    """

    name: str
    xy_min: tuple[float, float]
    xy_max: tuple[float, float]
    door_xy: tuple[float, float]
    door_inward_xy: tuple[float, float]


@dataclass(frozen=True)
class WalkPlan:
    """Where a walker can go: a corridor along x and rooms with a door on the corridor side.

    ``keep_out_m`` is the band along each room's walls that holds the furniture; the walk stays
    farther from the walls than that.
    """

    corridor_xy_min: tuple[float, float]
    corridor_xy_max: tuple[float, float]
    rooms: tuple[Room, ...]
    keep_out_m: float = 1.25


@dataclass(frozen=True, eq=False)
class Scene:
    """A building as planar convex patches (object frame, metres) plus a walk plan.

    Use :meth:`raycast` to intersect rays with it and :meth:`planes` for the plane list.
    """

    name: str
    patches: tuple[Patch, ...]
    walk_plan: WalkPlan | None = None

    @property
    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """Axis-aligned bounds ``(min (3,), max (3,))`` of all patch vertices."""
        v = np.concatenate([p.vertices for p in self.patches])
        return v.min(axis=0), v.max(axis=0)

    def planes(self) -> list[ScenePlane]:
        """The distinct planes, ordered by ``plane_id``."""
        groups: dict[int, list[Patch]] = {}
        for p in self.patches:
            groups.setdefault(p.plane_id, []).append(p)
        return [
            ScenePlane(pid, ps[0].plane_name, ps[0].role, ps[0].normal, ps[0].d,
                       tuple(p.patch_id for p in ps))
            for pid, ps in sorted(groups.items())
        ]

    def plane_of_patch(self) -> IntArray:
        """``plane_id`` of every patch, indexed by ``patch_id`` (shape ``(n_patches,)``)."""
        return np.array([p.plane_id for p in self.patches], dtype=np.int64)

    # ------------------------------------------------------------------ ray casting

    @cached_property
    def _tables(self) -> dict[str, Any]:
        """Per-patch arrays for :meth:`raycast`: plane, 2D frame, bounding box, polygon edges."""
        n = np.array([p.normal for p in self.patches])
        d = np.array([p.d for p in self.patches])
        origin = np.array([p.vertices[0] for p in self.patches])
        e_u = np.empty_like(n)
        e_v = np.empty_like(n)
        box = np.empty((len(self.patches), 4))
        edges: dict[int, FloatArray] = {}
        for i, p in enumerate(self.patches):
            u = p.vertices[1] - p.vertices[0]
            u /= np.linalg.norm(u)
            v = np.cross(p.normal, u)
            e_u[i], e_v[i] = u, v
            uv = (p.vertices - origin[i]) @ np.stack([u, v]).T
            box[i] = [*uv.min(axis=0), *uv.max(axis=0)]
            # A polygon that fills its bounding rectangle needs no edge test.
            area = 0.5 * abs(np.sum(uv[:, 0] * np.roll(uv[:, 1], -1) - np.roll(uv[:, 0], -1) * uv[:, 1]))
            rect_area = (box[i, 2] - box[i, 0]) * (box[i, 3] - box[i, 1])
            if area < rect_area * (1 - 1e-9):
                signed = np.sum(uv[:, 0] * np.roll(uv[:, 1], -1) - np.roll(uv[:, 0], -1) * uv[:, 1])
                if signed < 0:
                    uv = uv[::-1]
                nxt = np.roll(uv, -1, axis=0)
                # inside iff (b - a) x (p - a) >= 0 for every edge a->b (counter-clockwise order):
                # -(b_v - a_v) * p_u + (b_u - a_u) * p_v >= c.
                a_u = -(nxt[:, 1] - uv[:, 1])
                a_v = nxt[:, 0] - uv[:, 0]
                c = a_u * uv[:, 0] + a_v * uv[:, 1]
                edges[i] = np.stack([a_u, a_v, c], axis=1)
        return {"n": n, "d": d, "origin": origin, "e_u": e_u, "e_v": e_v, "box": box, "edges": edges}

    def raycast(
        self,
        origins: FloatArray,
        directions: FloatArray,
        max_range_m: float = 30.0,
        min_range_m: float = 0.0,
        chunk_rays: int = 2048,
    ) -> tuple[FloatArray, IntArray]:
        """Nearest hit of each ray with the scene's patches.

        ``origins`` (N, 3) and ``directions`` (N, 3) in the object frame; directions must be unit
        vectors. Only the front side of a patch is hit (the side its normal points to), which is
        correct for a scene whose faces bound solids. Returns ``range_m`` (N,) float64 (``inf``
        where nothing is hit within ``(min_range_m, max_range_m]``) and ``patch_id`` (N,) int64
        (-1 where nothing is hit).
        """
        O = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        D = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        rng_out = np.full(len(O), np.inf)
        id_out = np.full(len(O), -1, dtype=np.int64)
        for s in range(0, len(O), chunk_rays):
            r, i = self._raycast_chunk(O[s : s + chunk_rays], D[s : s + chunk_rays], max_range_m, min_range_m)
            rng_out[s : s + chunk_rays] = r
            id_out[s : s + chunk_rays] = i
        return rng_out, id_out

    def _raycast_chunk(
        self, O: FloatArray, D: FloatArray, max_range_m: float, min_range_m: float
    ) -> tuple[FloatArray, IntArray]:
        tab = self._tables
        centre = 0.5 * (O.min(axis=0) + O.max(axis=0))
        # Cull patches whose front side faces away from every origin of the chunk: a ray can only
        # hit a face from the front. The extreme of n . o over the origins' box is at a corner.
        half = 0.5 * (O.max(axis=0) - O.min(axis=0))
        front_max = tab["n"] @ centre + np.abs(tab["n"]) @ half - tab["d"]
        cand = np.nonzero(front_max > 0.0)[0]
        if len(cand) == 0:
            return np.full(len(O), np.inf), np.full(len(O), -1, dtype=np.int64)
        # float32 relative to the chunk centre for the search (micrometre decisions near edges do
        # not matter); the final range is recomputed in float64 for the chosen patch.
        n = tab["n"][cand]
        Orel = (O - centre).astype(np.float32)
        Df = D.astype(np.float32)
        d_rel = (tab["d"][cand] - n @ centre).astype(np.float32)
        o_rel = tab["origin"][cand] - centre
        eu = tab["e_u"][cand]
        ev = tab["e_v"][cand]
        nf = n.T.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return self._raycast_candidates(O, D, Orel, Df, nf, d_rel, o_rel, eu, ev, cand, max_range_m,
                                            min_range_m)

    def _raycast_candidates(self, O: FloatArray, D: FloatArray, Orel: NDArray[np.float32],
                            Df: NDArray[np.float32], nf: NDArray[np.float32], d_rel: NDArray[np.float32],
                            o_rel: FloatArray, eu: FloatArray, ev: FloatArray, cand: IntArray,
                            max_range_m: float, min_range_m: float) -> tuple[FloatArray, IntArray]:
        tab = self._tables
        denom = Df @ nf  # (n, P): n . dir, negative for a front-side hit
        dist = d_rel - Orel @ nf  # (n, P): d - n . o, negative where the origin is in front
        t = dist / denom
        ok = denom < 0
        ok &= dist < 0
        ok &= t <= np.float32(max_range_m)
        ok &= t > np.float32(min_range_m)
        cu = np.einsum("ij,ij->i", o_rel, eu).astype(np.float32)
        cv = np.einsum("ij,ij->i", o_rel, ev).astype(np.float32)
        u = Orel @ eu.T.astype(np.float32)
        u -= cu
        u += t * (Df @ eu.T.astype(np.float32))
        v = Orel @ ev.T.astype(np.float32)
        v -= cv
        v += t * (Df @ ev.T.astype(np.float32))
        box = tab["box"][cand].astype(np.float32)
        ok &= u >= box[:, 0]
        ok &= u <= box[:, 2]
        ok &= v >= box[:, 1]
        ok &= v <= box[:, 3]
        for k, pid in enumerate(cand):
            e = tab["edges"].get(int(pid))
            if e is None:
                continue
            rows = np.nonzero(ok[:, k])[0]
            if len(rows) == 0:
                continue
            inside = np.all(u[rows, k, None] * e[:, 0] + v[rows, k, None] * e[:, 1] >= e[:, 2] - 1e-6, axis=1)
            ok[rows[~inside], k] = False
        t = np.where(ok, t, np.float32(np.inf))
        best = np.argmin(t, axis=1)
        hit = np.isfinite(t[np.arange(len(O)), best])
        pid = np.where(hit, cand[best], -1)
        # Exact float64 range on the chosen patch.
        nb = tab["n"][pid[hit]]
        r = np.full(len(O), np.inf)
        r[hit] = (tab["d"][pid[hit]] - np.einsum("ij,ij->i", nb, O[hit])) / np.einsum("ij,ij->i", nb, D[hit])
        return r, pid.astype(np.int64)


# --------------------------------------------------------------------------- building


class BuildingLayout(enum.Enum):
    """Floor plans :func:`make_building` can generate."""

    #: a corridor along the south wall, one row of rooms north of it
    CORRIDOR_ROW = "corridor_row"
    #: a corridor through the middle, rooms on both sides
    CENTRAL_CORRIDOR = "central_corridor"


@dataclass(frozen=True)
class BuildingConfig:
    """Parameters of :func:`make_building`.

    ``size_m`` is the free interior (x, y, height) between the outer walls' inner faces; the
    object frame has its origin at the inner south-west floor corner.
    """

    size_m: tuple[float, float, float] = (24.0, 12.0, 3.0)
    n_rooms: int = 3
    layout: BuildingLayout = BuildingLayout.CORRIDOR_ROW
    seed: int = 0
    wall_thickness_m: float = 0.2
    corridor_width_m: float = 2.4
    door_width_m: float = 0.9
    door_height_m: float = 2.1
    boxes_per_room: int = 2
    n_ramps: int = 2
    connecting_door_probability: float = 0.5


class _SceneBuilder:
    """Collects patches; plane ids are assigned at the end by grouping coplanar patches."""

    def __init__(self) -> None:
        self.patches: list[Patch] = []

    def add(self, name: str, plane_name: str, role: str, vertices: Sequence[Sequence[float]] | FloatArray,
            normal_hint: Sequence[float] | FloatArray, reflectivity: float) -> None:
        v = np.asarray(vertices, dtype=np.float64)
        n = np.cross(v[1] - v[0], v[2] - v[0])
        n /= np.linalg.norm(n)
        if n @ np.asarray(normal_hint) < 0:
            n = -n
        n = np.where(np.abs(n) < 1e-15, 0.0, n)  # no -0.0 in the files
        d = float(n @ v.mean(axis=0))
        if np.max(np.abs(v @ n - d)) > 1e-9:
            raise ValueError(f"patch {name} is not planar")
        self.patches.append(Patch(len(self.patches), name, plane_name, role, n, d, v, reflectivity))

    def axis_rect(self, name: str, plane_name: str, role: str, axis: int, coord: float, sign: int,
                  lo: Sequence[float], hi: Sequence[float], reflectivity: float) -> None:
        """Rectangle on the plane ``x[axis] = coord``, normal ``sign * e_axis``; ``lo``/``hi`` are
        the bounds along the other two axes in cyclic order (axis+1, axis+2)."""
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        corners = []
        for c1, c2 in ((lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])):
            p = [0.0, 0.0, 0.0]
            p[axis], p[a1], p[a2] = coord, c1, c2
            corners.append(p)
        hint = [0.0, 0.0, 0.0]
        hint[axis] = float(sign)
        self.add(name, plane_name, role, corners, hint, reflectivity)

    def box(self, name: str, centre_xy: Sequence[float], size: Sequence[float], yaw_rad: float,
            reflectivity: float, z0: float = 0.0, top: bool = True) -> None:
        """A box standing on the floor (no bottom face), rotated by ``yaw_rad`` about z."""
        sx, sy, h = size
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        ex = np.array([c, s, 0.0]) * sx / 2
        ey = np.array([-s, c, 0.0]) * sy / 2
        ctr = np.array([centre_xy[0], centre_xy[1], z0])
        zt = np.array([0.0, 0.0, h])
        for k, (a, b) in enumerate(((ex, ey), (ey, -ex), (-ex, -ey), (-ey, ex))):
            # side face through ctr + a, spanned by b (horizontal) and z; outward normal along a
            p0 = ctr + a - b
            p1 = ctr + a + b
            self.add(f"{name}_side{k}", f"{name}_side{k}", "object", [p0, p1, p1 + zt, p0 + zt], a,
                     reflectivity)
        if top:
            corners = [ctr + zt + sa * ex + sb * ey for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            self.add(f"{name}_top", f"{name}_top", "object", corners, _EZ, reflectivity)

    def wedge(self, name: str, x_range: Sequence[float], y_range: Sequence[float], height: float,
              rise_axis: int, rise_sign: int, reflectivity: float) -> None:
        """A ramp (solid wedge) on the floor rising along ``rise_sign * e_rise_axis`` to ``height``.

        Faces: the slanted top, two triangular sides, the vertical back at the high end.
        """
        lo = np.array([x_range[0], y_range[0]])
        hi = np.array([x_range[1], y_range[1]])
        other = 1 - rise_axis
        low_c = lo[rise_axis] if rise_sign > 0 else hi[rise_axis]
        high_c = hi[rise_axis] if rise_sign > 0 else lo[rise_axis]

        def pt(r: float, o: float, z: float) -> list[float]:
            p = [0.0, 0.0, z]
            p[rise_axis], p[other] = r, o
            return p

        o0, o1 = lo[other], hi[other]
        run = abs(high_c - low_c)
        slope_hint = [0.0, 0.0, run]
        slope_hint[rise_axis] = -rise_sign * height
        self.add(f"{name}_slope", f"{name}_slope", "ramp",
                 [pt(low_c, o0, 0), pt(low_c, o1, 0), pt(high_c, o1, height), pt(high_c, o0, height)],
                 slope_hint, reflectivity)
        for k, (oc, sgn) in enumerate(((o0, -1.0), (o1, 1.0))):
            hint = [0.0, 0.0, 0.0]
            hint[other] = sgn
            self.add(f"{name}_side{k}", f"{name}_side{k}", "ramp",
                     [pt(low_c, oc, 0), pt(high_c, oc, 0), pt(high_c, oc, height)], hint, reflectivity)
        hint = [0.0, 0.0, 0.0]
        hint[rise_axis] = float(rise_sign)
        self.add(f"{name}_back", f"{name}_back", "ramp",
                 [pt(high_c, o0, 0), pt(high_c, o1, 0), pt(high_c, o1, height), pt(high_c, o0, height)],
                 hint, reflectivity)

    def build(self, name: str, walk_plan: WalkPlan | None) -> Scene:
        # Coplanar patches (same normal and offset) share one plane id, in order of appearance.
        keys: dict[tuple[float, ...], int] = {}
        out = []
        for p in self.patches:
            key = (*np.round(p.normal, 9), round(p.d, 6))
            pid = keys.setdefault(key, len(keys))
            out.append(dataclasses.replace(p, plane_id=pid))
        return Scene(name, tuple(out), walk_plan)


@dataclass(frozen=True)
class _Region:
    name: str
    x0: float
    y0: float
    x1: float
    y1: float


@dataclass(frozen=True)
class _Door:
    axis: int  # axis the wall is orthogonal to (0: wall at constant x, 1: constant y)
    c_lo: float  # wall faces' coordinates along ``axis``
    c_hi: float
    a: float  # opening along the other horizontal axis
    b: float


def make_building(config: BuildingConfig | None = None) -> Scene:
    """A small planar building: corridor, rooms, doors, furniture, ramps and a pillar.

    Walls have two faces (``wall_thickness_m`` apart, opposite normals); walls with doors are
    split into several patches on one plane; door reveals (jambs, soffit, threshold) close the
    openings. Boxes stand with random yaw along the back walls (normals in many horizontal
    directions); ramps (slanted planes) stand along side walls; the largest room has a pillar.
    Everything the walker must avoid lies within ``WalkPlan.keep_out_m`` of the room walls
    (except the pillar, in the room's centre). Deterministic given ``config``.
    """
    cfg = config or BuildingConfig()
    rng = np.random.default_rng([cfg.seed, 7001])
    Lx, Ly, H = cfg.size_m
    t = cfg.wall_thickness_m
    cw = cfg.corridor_width_m
    keep_out = 1.25
    if cfg.n_rooms < 1:
        raise ValueError("n_rooms must be >= 1")

    # Rows of rooms: (y0, y1, door side): door side +1 means the corridor is north of the row.
    if cfg.layout is BuildingLayout.CORRIDOR_ROW:
        corridor = _Region("corridor", 0.0, 0.0, Lx, cw)
        rows = [(cw + t, Ly, -1, cfg.n_rooms)]
    else:
        y_s = (Ly - cw - 2 * t) / 2
        corridor = _Region("corridor", 0.0, y_s + t, Lx, y_s + t + cw)
        n_south = (cfg.n_rooms + 1) // 2
        rows = [(0.0, y_s, +1, n_south), (y_s + 2 * t + cw, Ly, -1, cfg.n_rooms - n_south)]

    regions = [corridor]
    doors: list[_Door] = []
    rooms: list[Room] = []
    for row_i, (y0, y1, door_side, n) in enumerate(rows):
        if n == 0:
            continue
        if y1 - y0 < 2 * keep_out + 0.5:
            raise ValueError(f"rooms too shallow ({y1 - y0:.2f} m) for the building size")
        w = 1.0 + rng.uniform(-0.2, 0.2, n)
        splits = np.concatenate([[0.0], np.cumsum(w) / w.sum() * Lx])
        splits[-1] = Lx  # exactly, so that the last room's east side is recognised as outer wall
        for i in range(n):
            x0 = splits[i] + (t / 2 if i > 0 else 0.0)
            x1 = splits[i + 1] - (t / 2 if i < n - 1 else 0.0)
            if x1 - x0 < 2 * keep_out + 1.0:
                raise ValueError(f"rooms too narrow ({x1 - x0:.2f} m) for the building size")
            name = f"room{len(rooms)}"
            regions.append(_Region(name, x0, y0, x1, y1))
            # door towards the corridor, far enough from the side walls for a straight entry
            xd = rng.uniform(x0 + keep_out + 0.1, x1 - keep_out - 0.1)
            wall_lo, wall_hi = (y1, y1 + t) if door_side > 0 else (y0 - t, y0)
            doors.append(_Door(1, wall_lo, wall_hi, xd - cfg.door_width_m / 2, xd + cfg.door_width_m / 2))
            rooms.append(Room(name, (x0, y0), (x1, y1), (float(xd), (wall_lo + wall_hi) / 2),
                              (0.0, float(-door_side))))
            if i < n - 1 and rng.uniform() < cfg.connecting_door_probability:
                yd = rng.uniform(y0 + 0.8, y1 - 0.8 - cfg.door_width_m)
                xw = splits[i + 1]
                doors.append(_Door(0, xw - t / 2, xw + t / 2, yd, yd + cfg.door_width_m))
        del row_i

    b = _SceneBuilder()
    walls_refl = 0.7
    for reg in regions:
        b.axis_rect(f"{reg.name}_floor", "floor", "floor", 2, 0.0, +1, (reg.x0, reg.y0), (reg.x1, reg.y1),
                    0.35)
        b.axis_rect(f"{reg.name}_ceiling", "ceiling", "ceiling", 2, H, -1, (reg.x0, reg.y0), (reg.x1, reg.y1),
                    0.85)
        # four sides: (axis, coordinate, inward sign, span along the other axis, side name)
        sides = ((0, reg.x0, +1, (reg.y0, reg.y1), "w"), (0, reg.x1, -1, (reg.y0, reg.y1), "e"),
                 (1, reg.y0, +1, (reg.x0, reg.x1), "s"), (1, reg.y1, -1, (reg.x0, reg.x1), "n"))
        for axis, coord, sign, span, side in sides:
            outer = coord in (0.0, Lx) if axis == 0 else coord in (0.0, Ly)
            outer_names = {(0, 0.0): "outer_west", (0, Lx): "outer_east", (1, 0.0): "outer_south",
                           (1, Ly): "outer_north"}
            plane_name = outer_names[(axis, coord)] if outer else (
                f"wall_{'xy'[axis]}{coord:+.2f}_n{'+' if sign > 0 else '-'}{'xy'[axis]}")
            role = "outer_wall" if outer else "interior_wall"
            openings = sorted((dr.a, dr.b) for dr in doors
                              if dr.axis == axis and min(abs(coord - dr.c_lo), abs(coord - dr.c_hi)) < 1e-9
                              and span[0] < dr.a and dr.b < span[1])
            _wall_face(b, f"{reg.name}_{side}", plane_name, role, axis, coord, sign, span, openings,
                       H, cfg.door_height_m, walls_refl)
    for k, dr in enumerate(doors):
        _door_reveal(b, f"door{k}", dr, cfg.door_height_m, walls_refl)

    # furniture, ramps, pillar: only inside the keep-out band of the rooms (the pillar excepted)
    room_regions = regions[1:]
    ramp_rooms = set(rng.choice(len(room_regions), size=min(cfg.n_ramps, len(room_regions)), replace=False))
    for ri, (reg, room) in enumerate(zip(room_regions, rooms, strict=True)):
        back_y = reg.y1 if room.door_inward_xy[1] > 0 else reg.y0
        back_sign = -1.0 if room.door_inward_xy[1] > 0 else 1.0  # direction from the back wall inwards
        slots = np.linspace(reg.x0 + 1.0, reg.x1 - 1.0, cfg.boxes_per_room + 1)
        for k in range(cfg.boxes_per_room):
            sx, sy = rng.uniform(0.4, 0.8), rng.uniform(0.35, 0.6)
            h = rng.uniform(0.6, 2.0)
            yaw = rng.uniform(-0.5, 0.5)
            half_y = sx / 2 * abs(math.sin(yaw)) + sy / 2 * abs(math.cos(yaw))
            half_x = sx / 2 * abs(math.cos(yaw)) + sy / 2 * abs(math.sin(yaw))
            x_lo = slots[k] + half_x + 0.05
            xc = rng.uniform(x_lo, max(x_lo, slots[k + 1] - half_x - 0.05))
            yc = back_y + back_sign * (half_y + 0.05)
            b.box(f"{reg.name}_box{k}", (xc, yc), (sx, sy, h), yaw, float(rng.uniform(0.15, 0.9)))
        if ri in ramp_rooms:
            x_side = reg.x0 + 0.1 if rng.uniform() < 0.5 else reg.x1 - 0.9
            ym = 0.5 * (reg.y0 + reg.y1)
            length = min(2.0, reg.y1 - reg.y0 - 2 * keep_out)
            b.wedge(f"{reg.name}_ramp", (x_side, x_side + 0.8), (ym - length / 2, ym + length / 2),
                    float(rng.uniform(0.3, 0.8)), 1, int(rng.choice([-1, 1])), 0.5)
    largest = int(np.argmax([(r.x1 - r.x0) * (r.y1 - r.y0) for r in room_regions]))
    reg = room_regions[largest]
    b.box(f"{reg.name}_pillar", (0.5 * (reg.x0 + reg.x1), 0.5 * (reg.y0 + reg.y1)), (0.4, 0.4, H),
          float(rng.uniform(0.2, 0.6)), 0.6, top=False)

    plan = WalkPlan((corridor.x0, corridor.y0), (corridor.x1, corridor.y1), tuple(rooms), keep_out)
    return b.build(f"{cfg.layout.value}_{Lx:g}x{Ly:g}x{H:g}_seed{cfg.seed}", plan)


def _wall_face(b: _SceneBuilder, name: str, plane_name: str, role: str, axis: int, coord: float, sign: int,
               span: tuple[float, float], openings: list[tuple[float, float]], H: float, door_h: float,
               refl: float) -> None:
    """One face of a wall: full-height segments between the openings and a lintel over each."""
    cuts = [span[0]]
    for a, bb in openings:
        cuts += [a, bb]
    cuts.append(span[1])
    for k in range(0, len(cuts), 2):
        _wall_rect(b, f"{name}_seg{k // 2}", plane_name, role, axis, coord, sign, (cuts[k], cuts[k + 1]),
                   (0.0, H), refl)
    for k, (a, bb) in enumerate(openings):
        _wall_rect(b, f"{name}_lintel{k}", plane_name, role, axis, coord, sign, (a, bb), (door_h, H), refl)


def _wall_rect(b: _SceneBuilder, name: str, plane_name: str, role: str, axis: int, coord: float, sign: int,
               span: tuple[float, float], z: tuple[float, float], refl: float) -> None:
    # axis_rect's cyclic order: axis 0 -> (y, z); axis 1 -> (z, x)
    if axis == 0:
        b.axis_rect(name, plane_name, role, 0, coord, sign, (span[0], z[0]), (span[1], z[1]), refl)
    else:
        b.axis_rect(name, plane_name, role, 1, coord, sign, (z[0], span[0]), (z[1], span[1]), refl)


def _door_reveal(b: _SceneBuilder, name: str, dr: _Door, door_h: float, refl: float) -> None:
    """Jambs, soffit and threshold of a door, so that no ray leaks through the wall's thickness."""
    other = 1 - dr.axis
    for k, (c, sgn) in enumerate(((dr.a, +1), (dr.b, -1))):
        if other == 0:
            b.axis_rect(f"{name}_jamb{k}", f"{name}_jamb{k}", "door_reveal", 0, c, sgn, (dr.c_lo, 0.0),
                        (dr.c_hi, door_h), refl)
        else:
            b.axis_rect(f"{name}_jamb{k}", f"{name}_jamb{k}", "door_reveal", 1, c, sgn, (0.0, dr.c_lo),
                        (door_h, dr.c_hi), refl)
    lo = [0.0, 0.0]
    hi = [0.0, 0.0]
    lo[dr.axis], hi[dr.axis] = dr.c_lo, dr.c_hi
    lo[other], hi[other] = dr.a, dr.b
    b.axis_rect(f"{name}_soffit", f"{name}_soffit", "door_reveal", 2, door_h, -1, lo, hi, refl)
    b.axis_rect(f"{name}_threshold", "floor", "floor", 2, 0.0, +1, lo, hi, 0.35)


def make_box_scene(size_m: Sequence[float] = (4.0, 3.0, 2.5)) -> Scene:
    """A closed empty box ``[0, sx] x [0, sy] x [0, sz]`` with inward normals (for tests)."""
    sx, sy, sz = size_m
    b = _SceneBuilder()
    b.axis_rect("x0", "x0", "outer_wall", 0, 0.0, +1, (0, 0), (sy, sz), 0.7)
    b.axis_rect("x1", "x1", "outer_wall", 0, sx, -1, (0, 0), (sy, sz), 0.7)
    b.axis_rect("y0", "y0", "outer_wall", 1, 0.0, +1, (0, 0), (sz, sx), 0.7)
    b.axis_rect("y1", "y1", "outer_wall", 1, sy, -1, (0, 0), (sz, sx), 0.7)
    b.axis_rect("floor", "floor", "floor", 2, 0.0, +1, (0, 0), (sx, sy), 0.35)
    b.axis_rect("ceiling", "ceiling", "ceiling", 2, sz, -1, (0, 0), (sx, sy), 0.85)
    return b.build(f"box_{sx:g}x{sy:g}x{sz:g}", None)


# =========================================================================== configuration


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


@dataclass(frozen=True)
class DriftConfig:
    """SLAM drift ``D(t)``: an integrated random walk of the drift rate (sigma grows ~ t^1.5).

    The realisation is scaled so that at 300 s after the start the position drift has magnitude
    ``drift_pos_m_at_300s`` and the rotation ``drift_rot_deg_at_300s`` exactly (whatever the
    run's duration). The rotation acts about the start position (where SLAM initialises), the
    tilt components (roll, pitch: gravity-aided in real units) weighted by ``tilt_weight``
    relative to yaw.
    """

    drift_pos_m_at_300s: float = 0.04
    drift_rot_deg_at_300s: float = 0.25
    tilt_weight: float = 0.4


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


@dataclass(frozen=True)
class SimulationConfig:
    """Everything :func:`simulate_run` needs. Deterministic given the configuration.

    ``origin_xyz`` is added to every object-frame output (a UTM-like offset, e.g.
    ``(500000.0, 5400000.0, 0.0)``); the simulation itself runs in building coordinates.
    """

    seed: int = 1
    duration_s: float = 240.0
    t0_s: float = 1623220971.0
    building: BuildingConfig = field(default_factory=BuildingConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    walk: WalkConfig = field(default_factory=WalkConfig)
    drift: DriftConfig = field(default_factory=DriftConfig)
    static: StaticConfig = field(default_factory=StaticConfig)
    origin_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    block_s: float = 10.0  # the cloud is generated in blocks of this much scanning time


def config_as_dict(config: SimulationConfig) -> dict[str, Any]:
    """The configuration as plain JSON-able values (enums by value)."""

    def conv(x: Any) -> Any:
        if isinstance(x, enum.Enum):
            return x.value
        if isinstance(x, dict):
            return {k: conv(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [conv(v) for v in x]
        return x

    return conv(dataclasses.asdict(config))


def config_from_dict(data: dict[str, Any]) -> SimulationConfig:
    """The inverse of :func:`config_as_dict` (e.g. from ``run_meta.json``): rebuilds the run."""
    sections = {"building": BuildingConfig, "sensor": SensorConfig, "walk": WalkConfig, "drift": DriftConfig,
                "static": StaticConfig}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key in sections:
            sub = dict(value)
            if key == "building" and "layout" in sub:
                sub["layout"] = BuildingLayout(sub["layout"])
            kwargs[key] = sections[key](**{k: tuple(v) if isinstance(v, list) else v for k, v in sub.items()})
        else:
            kwargs[key] = tuple(value) if isinstance(value, list) else value
    return SimulationConfig(**kwargs)


def _rng(seed: int, stream: int) -> np.random.Generator:
    # One independent stream per purpose, so that changing e.g. the noise leaves the walk alone.
    return np.random.default_rng([seed, stream])


# =========================================================================== trajectories


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


def make_walk(scene: Scene, config: WalkConfig, duration_s: float, t0_s: float,
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


def make_drift(stamps_s: FloatArray, pivot_xyz: FloatArray, config: DriftConfig,
               rng: np.random.Generator) -> Pose:
    """Drift poses ``D(t)`` (object frame) at ``stamps_s`` (equally spaced, shape (M,)).

    Each of the six components (translation xyz, rotation vector xyz) is an integrated random
    walk of its rate, so it is smooth (C1) and its sigma grows like t^1.5; the rotation acts about
    ``pivot_xyz``: ``x -> R_d (x - pivot) + pivot + tau``. ``D(stamps_s[0])`` is the identity.
    """
    dt = float(stamps_s[1] - stamps_s[0])
    t_rel = stamps_s - stamps_s[0]
    n_gen = math.ceil(max(float(t_rel[-1]), 300.0) / dt) + 2
    w = rng.standard_normal((n_gen, 6))
    w[0] = 0.0
    rate = np.cumsum(w, axis=0) * math.sqrt(dt)
    x = np.concatenate([np.zeros((1, 6)), np.cumsum(rate[:-1], axis=0) * dt])
    x[:, 3:5] *= config.tilt_weight
    t_gen = np.arange(n_gen) * dt
    at300 = np.array([np.interp(300.0, t_gen, x[:, i]) for i in range(6)])
    n_pos, n_rot = np.linalg.norm(at300[:3]), np.linalg.norm(at300[3:])
    x[:, :3] *= config.drift_pos_m_at_300s / n_pos if n_pos > 0 else 0.0
    x[:, 3:] *= math.radians(config.drift_rot_deg_at_300s) / n_rot if n_rot > 0 else 0.0
    xs = np.stack([np.interp(t_rel, t_gen, x[:, i]) for i in range(6)], axis=1)
    q = rotvec_to_quat(xs[:, 3:])
    R = Pose(q, np.zeros((len(q), 3))).rotation_matrix
    piv = np.asarray(pivot_xyz, dtype=np.float64)
    t = piv - np.einsum("nij,j->ni", R, piv) + xs[:, :3]
    return Pose(q, t)


def apply_drift(truth: Trajectory, drift: Pose) -> Trajectory:
    """The exported trajectory ``T_slam = D * T_true`` row by row."""
    poses = drift.compose(truth.poses)
    return Trajectory(truth.stamps_s.copy(), Pose(make_quat_continuous(poses.quat_wxyz), poses.t_xyz),
                      source="simulated SLAM (drifted)")


def _offset_trajectory(traj: Trajectory, origin: FloatArray) -> Trajectory:
    return Trajectory(traj.stamps_s, Pose(traj.poses.quat_wxyz, traj.poses.t_xyz + origin), traj.source)


# =========================================================================== the run


@dataclass(frozen=True, eq=False)
class CloudBlock:
    """One block of simulated points, in acquisition order.

    ``stamps_s`` (N,) float64 point times; ``xyz_sensor`` (N, 3) measured points in the platform
    frame (range noise included); ``xyz_obj`` (N, 3) exported object-frame points (mapped with the
    interpolated DRIFTED trajectory, ``origin_xyz`` included); ``intensity`` (N,) uint16;
    ``patch_id`` (N,) the scene patch each ray hit; ``range_m`` (N,) measured ranges.
    """

    stamps_s: FloatArray
    xyz_sensor: FloatArray
    xyz_obj: FloatArray
    intensity: NDArray[np.uint16]
    patch_id: IntArray
    range_m: FloatArray
    first_index: int = 0

    def __len__(self) -> int:
        return len(self.stamps_s)


@dataclass(frozen=True, eq=False)
class SimulatedRun:
    """A simulated acquisition with its ground truth. Object-frame values include ``origin_xyz``.

    ``truth`` and ``slam`` are the true and the exported (drifted) 100 Hz trajectories
    ``T_obj_p``; ``drift`` (one pose per row) satisfies ``slam = drift * truth``. ``scene`` is in
    building coordinates (add ``origin_xyz``, or use :meth:`scene_planes_obj`). The cloud is
    generated on demand, block by block, by :meth:`iter_cloud_blocks`.
    """

    config: SimulationConfig
    scene: Scene
    truth: Trajectory
    slam: Trajectory
    drift: Pose
    static_scans: tuple[Scan, ...]

    @property
    def origin(self) -> FloatArray:
        return np.asarray(self.config.origin_xyz, dtype=np.float64)

    def n_blocks(self) -> int:
        return max(1, math.ceil(self.config.duration_s / self.config.block_s - 1e-9))

    def iter_cloud_blocks(self) -> Iterator[CloudBlock]:
        """The cloud in time blocks of ``config.block_s``; deterministic, independent of callers."""
        first = 0
        for b in range(self.n_blocks()):
            blk = self.cloud_block(b, first_index=first)
            first += len(blk)
            yield blk

    def cloud_block(self, index: int, first_index: int = 0) -> CloudBlock:
        """Block ``index`` of the cloud (its pulses ``[index, index + 1) * block_s``)."""
        return _simulate_block(self, index, first_index)

    def scene_planes_obj(self) -> list[ScenePlane]:
        """The scene's planes in the output object frame (``origin_xyz`` applied)."""
        o = self.origin
        return [dataclasses.replace(p, d=float(p.d + p.normal @ o)) for p in self.scene.planes()]

    def drift_at_end(self) -> tuple[float, float]:
        """(position difference slam - truth in metres, drift rotation angle in degrees) at the end."""
        dp = float(np.linalg.norm(self.slam.poses.t_xyz[-1] - self.truth.poses.t_xyz[-1]))
        da = float(np.degrees(np.linalg.norm(quat_to_rotvec(self.drift.quat_wxyz[-1]))))
        return dp, da


def simulate_run(config: SimulationConfig | None = None) -> SimulatedRun:
    """Build the scene, the true walk, the drifted trajectory and the static scans.

    The point cloud is not generated here (it may be hundreds of millions of points): iterate
    :meth:`SimulatedRun.iter_cloud_blocks` or call :func:`write_run`.
    """
    cfg = config or SimulationConfig()
    if cfg.duration_s <= 2 * cfg.walk.pause_s + 4.0:
        raise ValueError(f"duration_s must exceed 2 * pause_s + 4 s, got {cfg.duration_s}")
    scene = make_building(cfg.building)
    truth_local = make_walk(scene, cfg.walk, cfg.duration_s, cfg.t0_s, _rng(cfg.seed, 1))
    drift = make_drift(truth_local.stamps_s, truth_local.poses.t_xyz[0], cfg.drift, _rng(cfg.seed, 2))
    slam_local = apply_drift(truth_local, drift)
    origin = np.asarray(cfg.origin_xyz, dtype=np.float64)
    # The drift in the output frame: D' = O D O^-1 (same rotation, pivot moved with the origin).
    drift_out = Pose(drift.quat_wxyz, drift.t_xyz + origin - np.einsum("nij,j->ni", drift.rotation_matrix,
                                                                          origin))
    static = make_static_scans(scene, cfg.static, _rng(cfg.seed, 4), origin)
    return SimulatedRun(cfg, scene, _offset_trajectory(truth_local, origin),
                        _offset_trajectory(slam_local, origin), drift_out, static)


def _simulate_block(run: SimulatedRun, index: int, first_index: int) -> CloudBlock:
    cfg = run.config
    sen = cfg.sensor
    rng = _rng(cfg.seed, 1000 + index)
    pr = sen.pulse_rate_hz
    k0 = round(index * cfg.block_s * pr)
    k1 = min(round((index + 1) * cfg.block_s * pr), math.floor(cfg.duration_s * pr))
    k = np.arange(k0, max(k0, k1), dtype=np.int64)
    # float64 seconds: t0 + k / rate is exact to ~0.2 microseconds at GPS-like magnitudes
    stamps = cfg.t0_s + k / pr
    beam = k % sen.n_beams
    theta = 2 * np.pi * np.mod(k * (sen.line_rate_hz / pr), 1.0)
    psi = 2 * np.pi * np.mod(k * (sen.head_rate_hz / pr), 1.0)
    if sen.n_beams > 1:
        elev = np.radians(np.linspace(-sen.beam_spread_deg / 2, sen.beam_spread_deg / 2, sen.n_beams))[beam]
    else:
        elev = np.zeros(len(k))
    d_nom = _head_directions(theta, elev, psi)
    blind_axis = np.asarray(sen.blind_axis_p, dtype=np.float64)
    blind_axis /= np.linalg.norm(blind_axis)
    seen = d_nom @ blind_axis < math.cos(math.radians(sen.blind_cone_deg))
    stamps, theta, elev, psi, d_nom = stamps[seen], theta[seen], elev[seen], psi[seen], d_nom[seen]
    n = len(stamps)
    # The laser goes where the encoders do not quite say: cast along the perturbed direction,
    # report along the nominal one.
    sa = math.radians(sen.angle_sigma_deg)
    d_true = _head_directions(theta + sa * rng.standard_normal(n), elev + sa * rng.standard_normal(n), psi)
    # Ray casting in building coordinates from the interpolated TRUE trajectory.
    origin = run.origin
    truth = run.truth
    R_true, o_true = _interpolate_fast(truth.stamps_s, truth.poses, stamps)
    dirs_obj = np.einsum("nij,nj->ni", R_true, d_true)
    r_true, pid = run.scene.raycast(o_true - origin, dirs_obj, sen.max_range_m, sen.min_range_m)
    hit = pid >= 0
    stamps, d_nom, dirs_obj, r_true, pid = stamps[hit], d_nom[hit], dirs_obj[hit], r_true[hit], pid[hit]
    n = len(stamps)
    r_meas = r_true + sen.range_sigma_m * rng.standard_normal(n)
    xyz_sensor = r_meas[:, None] * d_nom
    # Exported cloud: the interpolated DRIFTED trajectory, exactly as SLAM software georeferences.
    R_slam, t_slam = _interpolate_fast(run.slam.stamps_s, run.slam.poses, stamps)
    xyz_obj = np.einsum("nij,nj->ni", R_slam, xyz_sensor) + t_slam
    normals = np.array([p.normal for p in run.scene.patches])[pid]
    refl = np.array([p.reflectivity for p in run.scene.patches])[pid]
    intensity = _intensity(refl, -np.einsum("ij,ij->i", normals, dirs_obj), r_true, sen.intensity_noise, rng)
    return CloudBlock(stamps, xyz_sensor, xyz_obj, intensity, pid, r_meas, first_index)


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


# =========================================================================== static scans


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
                      origin_xyz: FloatArray | None = None) -> tuple[Scan, ...]:
    """Static tripod scans: points (scan frame) on a spherical grid, poses ``T_obj_scan``.

    The scanner stands level (a few hundredths of a degree of residual tilt) with a random
    heading. ``origin_xyz`` is added to the poses' translations.
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
        r, pid = scene.raycast(np.broadcast_to(pos, d_scan.shape), d_scan @ R.T, config.max_range_m,
                               config.min_range_m)
        hit = pid >= 0
        r_meas = r[hit] + config.range_sigma_m * rng.standard_normal(int(hit.sum()))
        pts = r_meas[:, None] * d_scan[hit]
        refl = np.array([p.reflectivity for p in scene.patches])[pid[hit]]
        normals = np.array([p.normal for p in scene.patches])[pid[hit]]
        inten = _intensity(refl, -np.einsum("ij,ij->i", normals, d_scan[hit] @ R.T), r[hit], 0.02, rng)
        T_obj_scan = Pose(T_local.quat_wxyz, T_local.t_xyz + origin)
        scans.append(Scan(i, f"static_{i:02d}", ScanKind.STATIC, T_obj_scan, pts,
                          intensity=inten.astype(np.float32)))
    return tuple(scans)


# =========================================================================== writers


def write_trajectory_geoslam(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """GeoSLAM text (kinreg's writer), replacing an existing file."""
    _write_geoslam(path, trajectory, overwrite=True)


def _las_header(run: SimulatedRun) -> Any:
    import laspy

    lo, hi = run.scene.bounds
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    # offsets near the data centre keep the 0.1 mm integers small even with UTM coordinates
    header.offsets = np.round(0.5 * (lo + hi) + run.origin)
    header.system_identifier = "kinreg simulation"
    header.generating_software = "kinreg.simulation"
    # a fixed date (the run's day) so that equal configurations give equal bytes
    header.creation_date = _dt.datetime.fromtimestamp(run.config.t0_s, tz=_dt.timezone.utc).date()
    return header


def write_cloud_laz(path: str | os.PathLike[str], run: SimulatedRun,
                    blocks: Iterator[CloudBlock] | None = None) -> int:
    """Stream the run's cloud into a LAS 1.4 / point format 6 file (LAZ when ``path`` ends .laz).

    Coordinates at 0.1 mm resolution, float64 ``gps_time``, uint16 intensity. Generates and
    writes block by block (memory bounded by one block). Returns the number of points.
    """
    import laspy

    header = _las_header(run)
    n_total = 0
    compress = str(path).lower().endswith(".laz")
    with atomic_path(path, overwrite=True) as tmp, \
            laspy.open(tmp, mode="w", header=header, do_compress=compress) as writer:
        for blk in blocks if blocks is not None else run.iter_cloud_blocks():
            if len(blk) == 0:
                continue
            rec = laspy.ScaleAwarePointRecord.zeros(len(blk), header=writer.header)
            rec.x, rec.y, rec.z = blk.xyz_obj[:, 0], blk.xyz_obj[:, 1], blk.xyz_obj[:, 2]
            rec.gps_time = blk.stamps_s
            rec.intensity = blk.intensity
            rec.return_number = np.ones(len(blk), dtype=np.uint8)
            rec.number_of_returns = np.ones(len(blk), dtype=np.uint8)
            writer.write_points(rec)
            n_total += len(blk)
    return n_total


def write_static_e57(path: str | os.PathLike[str], scans: Sequence[Scan]) -> None:
    """Static scans as one E57 file: one ``data3D`` per scan, points in the scan frame (float32),
    the pose ``T_obj_scan`` in the entry's pose (quaternion w, x, y, z; float64 translation)."""
    import pye57

    with atomic_path(path, overwrite=True) as tmp:
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            for s in scans:
                data = {
                    "cartesianX": s.points_xyz[:, 0].copy(),
                    "cartesianY": s.points_xyz[:, 1].copy(),
                    "cartesianZ": s.points_xyz[:, 2].copy(),
                }
                if s.intensity is not None:
                    data["intensity"] = np.asarray(s.intensity, dtype=np.float64)
                e57.write_scan_raw(data, name=s.name, rotation=s.T_obj_scan.quat_wxyz.copy(),
                                   translation=s.T_obj_scan.t_xyz.copy())
        finally:
            e57.close()


def reference_planes_toml(run: SimulatedRun, plane_construction_accuracy_m: float = 0.05) -> str:
    """Reference planes (METHOD.md section 5): outer west and south walls and the ceiling.

    Normals point into the building (towards the scanner); offsets include ``origin_xyz``.
    """
    o = run.origin
    H = max(float(p.vertices[:, 2].max()) for p in run.scene.patches if p.role == "ceiling")
    rows = [("west_wall", "x", 0.0 + o[0], 1), ("south_wall", "y", 0.0 + o[1], 1),
            ("ceiling", "z", H + o[2], -1)]
    lines = [
        "# Reference planes of the simulated building (virtual reference station), METHOD.md section 5.",
        "# Generated by kinreg.simulation; normal_sign makes the normal point into the building.",
        f"plane_construction_accuracy_m = {plane_construction_accuracy_m}",
    ]
    for name, axis, off, sign in rows:
        lines += ["", "[[plane]]", f'name = "{name}"', f'axis = "{axis}"', f"offset_m = {off:.6f}",
                  f"normal_sign = {sign}"]
    return "\n".join(lines) + "\n"


def scene_as_dict(run: SimulatedRun) -> dict[str, Any]:
    """truth_scene.json content: planes and patches in the output object frame."""
    o = run.origin
    ref_names = {"outer_west": "west_wall", "outer_south": "south_wall", "ceiling": "ceiling"}
    planes = []
    for p in run.scene_planes_obj():
        planes.append({
            "id": p.plane_id, "name": p.name, "role": p.role,
            "normal": [round(float(x), 12) for x in p.normal], "d": round(p.d, 9),
            "reference_plane": ref_names.get(p.name),
            "patch_ids": list(p.patch_ids),
        })
    patches = [{
        "id": p.patch_id, "name": p.name, "plane_id": p.plane_id, "role": p.role,
        "reflectivity": p.reflectivity,
        "vertices": np.round(p.vertices + o, 9).tolist(),
    } for p in run.scene.patches]
    lo, hi = run.scene.bounds
    return {
        "schema_version": SIMULATION_SCHEMA_VERSION,
        "name": run.scene.name,
        "frame": "object frame of the run files (origin_xyz included); "
                 "plane n . x = d, normal into free space",
        "origin_xyz": list(map(float, o)),
        "bounds_min": (lo + o).tolist(), "bounds_max": (hi + o).tolist(),
        "planes": planes, "patches": patches,
    }


@dataclass(frozen=True)
class RunFiles:
    """What :func:`write_run` wrote: paths and counts."""

    out_dir: Path
    files: dict[str, Path]
    n_points: int
    n_static_points: tuple[int, ...]


def write_run(run: SimulatedRun, out_dir: str | os.PathLike[str], progress: Any = None) -> RunFiles:
    """Write every file of a simulated run into ``out_dir`` (created if missing).

    ``run_trajectory.txt`` (drifted, GeoSLAM), ``run_cloud.laz``, ``truth_trajectory.txt``,
    ``truth_scene.json``, ``static.e57``, ``static_truth.json``, ``reference.toml``,
    ``run_meta.json``. Each file is written under a temporary name and renamed. ``progress``
    is a :class:`kinreg.progress.Progress` (advanced per cloud block) or ``None``.
    """
    from kinreg.progress import NullProgress

    prog = progress if progress is not None else NullProgress()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {name: out / name for name in (
        "run_trajectory.txt", "run_cloud.laz", "truth_trajectory.txt", "truth_scene.json", "static.e57",
        "static_truth.json", "reference.toml", "run_meta.json")}
    write_trajectory_geoslam(files["run_trajectory.txt"], run.slam)
    write_trajectory_geoslam(files["truth_trajectory.txt"], run.truth)
    _write_text(files["truth_scene.json"], json.dumps(scene_as_dict(run), indent=1) + "\n")
    _write_text(files["reference.toml"], reference_planes_toml(run))
    write_static_e57(files["static.e57"], run.static_scans)
    _write_text(files["static_truth.json"], json.dumps({
        "schema_version": SIMULATION_SCHEMA_VERSION,
        "file": "static.e57",
        "note": "T_obj_scan maps scan-frame points into the object frame: x_obj = R(q) x_scan + t",
        "range_sigma_m": run.config.static.range_sigma_m,
        "scans": [{"index": s.scan_id, "name": s.name, "quat_wxyz": s.T_obj_scan.quat_wxyz.tolist(),
                   "t_xyz": s.T_obj_scan.t_xyz.tolist(), "n_points": len(s)} for s in run.static_scans],
    }, indent=1) + "\n")

    prog.start("simulate cloud", total=run.n_blocks(), unit="blocks")
    n_points = 0
    t_min, t_max = math.inf, -math.inf

    def blocks() -> Iterator[CloudBlock]:
        nonlocal n_points, t_min, t_max
        for blk in run.iter_cloud_blocks():
            n_points += len(blk)
            if len(blk):
                t_min, t_max = min(t_min, float(blk.stamps_s[0])), max(t_max, float(blk.stamps_s[-1]))
            yield blk
            prog.advance(1)

    write_cloud_laz(files["run_cloud.laz"], run, blocks())
    prog.finish()

    dp, da = run.drift_at_end()
    drift_pos = np.linalg.norm(run.slam.poses.t_xyz - run.truth.poses.t_xyz, axis=1)
    drift_rot = np.degrees(np.linalg.norm(quat_to_rotvec(run.drift.quat_wxyz), axis=1))
    meta = {
        "schema_version": SIMULATION_SCHEMA_VERSION,
        "generator": "kinreg.simulation",
        "config": config_as_dict(run.config),
        "scene": {"name": run.scene.name, "n_patches": len(run.scene.patches),
                  "n_planes": len(run.scene.planes())},
        "counts": {"trajectory_rows": len(run.truth), "cloud_points": n_points,
                   "static_points": [len(s) for s in run.static_scans]},
        "time_range_s": [run.truth.t_start_s, run.truth.t_end_s],
        "cloud_time_range_s": [t_min, t_max] if n_points else None,
        "path_length_m": run.truth.path_length_m(),
        "drift_at_end": {"position_mm": dp * 1e3, "rotation_deg": da},
        "drift_max": {"position_mm": float(drift_pos.max() * 1e3), "rotation_deg": float(drift_rot.max())},
        "files": {k: v.name for k, v in files.items()},
    }
    _write_text(files["run_meta.json"], json.dumps(meta, indent=1) + "\n")
    return RunFiles(out, files, n_points, tuple(len(s) for s in run.static_scans))


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path, overwrite=True) as tmp:
        tmp.write_text(text, encoding="utf-8")
