"""The simulated scene: planar patches of a building (rooms, corridor, doors) or a box, and the walk plan through it."""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import (
    FloatArray,
)

logger = logging.getLogger(__name__)

IntArray = NDArray[np.int64]


_EZ = np.array([0.0, 0.0, 1.0])


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
