"""Which scans to link, and which of their planes are the same physical plane (METHOD.md step 6).

Candidate pairs are sequence neighbours plus scans whose centres are close (loop closures).
Planes of scan j are mapped into scan i with the approximate pairwise transform from the
trajectory and matched on normal angle, offset and overlapping extent. Ambiguities are resolved
conservatively: where a plane has candidates on two different physical planes (parallel planes
close together) and neither is clearly better, it is not matched at all; several patches of one
physical plane (a wall seen in pieces) may all match. Data snooping in the pairwise adjustment
catches what slips through.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import overload

import numpy as np
from scipy.spatial import cKDTree

from kinreg.config import MatchingConfig
from kinreg.geometry import FloatArray, Pose
from kinreg.types import Plane, PlaneMatch

# A candidate on another physical plane must be this much worse (in offset) than the best one
# before the best is trusted; otherwise the plane is left unmatched.
_AMBIGUITY_RATIO = 3.0

_Candidate = tuple[tuple[int, int], float, float, float]  # (plane a, plane b), angle, offset, overlap share


def candidate_pairs(positions_xyz: FloatArray, config: MatchingConfig) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of stations to link: sequence neighbours up to ``neighbour_depth``
    apart, plus stations whose centres are within ``radius_m`` (loop closures), of which each
    station chooses at most ``max_loop_pairs`` (:func:`_thinned_loops`). Sorted."""
    n = len(positions_xyz)
    depth = config.neighbour_depth
    pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + depth + 1))}
    if n > 1 and config.radius_m > 0:
        near = cKDTree(positions_xyz).query_pairs(config.radius_m, output_type="ndarray")
        loops = near[near[:, 1] - near[:, 0] > depth]
        if config.max_loop_pairs > 0:
            loops = _thinned_loops(positions_xyz, loops, config.max_loop_pairs)
        pairs |= {(int(a), int(b)) for a, b in loops}
    return sorted(pairs)


def _thinned_loops(positions_xyz: FloatArray, loops: np.ndarray, budget: int) -> np.ndarray:
    """The loop pairs ``loops`` (m, 2), i < j, of which each station keeps at most ``budget``
    (:func:`chosen_partners`). A pair stays where either of its stations keeps it."""
    both = np.concatenate([loops, loops[:, ::-1]])
    counts = np.bincount(both[:, 0], minlength=len(positions_xyz))
    if counts.max(initial=0) <= budget:
        return loops
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    starts = np.concatenate([[0], np.cumsum(counts)])
    kept: set[tuple[int, int]] = set()
    for i in np.flatnonzero(counts):
        chosen = chosen_partners(positions_xyz, int(i), both[starts[i]:starts[i + 1], 1], budget)
        kept.update((min(int(i), j), max(int(i), j)) for j in chosen.tolist())
    return np.array(sorted(kept), dtype=np.int64).reshape(-1, 2)


def chosen_partners(positions_xyz: FloatArray, i: int, partners: np.ndarray, budget: int) -> np.ndarray:
    """At most ``budget`` of station ``i``'s loop partners (sorted indices), spread over its
    passes: the partners are split into passes (runs of consecutive stations) and taken round by
    round, the nearest station of every pass (nearest pass first), then every pass's second
    nearest, ... A station passed 30 times keeps a link into as many passes as it can, not 40 into
    the slowest one."""
    if len(partners) <= budget:
        return partners
    dist = np.linalg.norm(positions_xyz[partners] - positions_xyz[i], axis=1)
    visit = np.concatenate([[0], np.cumsum(np.diff(partners) > 1)])
    by_pass = np.lexsort((dist, visit))  # pass by pass, nearest first
    first = np.flatnonzero(np.diff(visit[by_pass], prepend=-1))
    rank = np.arange(len(partners)) - np.repeat(first, np.diff(np.append(first, len(partners))))
    nearest_of_pass = np.minimum.reduceat(dist[by_pass], first)[visit[by_pass]]
    order = np.lexsort((dist[by_pass], nearest_of_pass, rank))[:budget]
    return np.sort(partners[by_pass[order]])


def _box_in_plane(points: FloatArray, origin: FloatArray, u: FloatArray, v: FloatArray) -> tuple[float, ...]:
    """(umin, vmin, umax, vmax) of ``points`` (k, 3) about ``origin`` along ``u`` and ``v``."""
    local = points - origin
    along_u, along_v = local @ u, local @ v
    return (float(np.minimum.reduce(along_u)), float(np.minimum.reduce(along_v)),
            float(np.maximum.reduce(along_u)), float(np.maximum.reduce(along_v)))


def _overlap_share(box_a: tuple[float, ...], box_b: tuple[float, ...]) -> float:
    """Overlapping area of two (umin, vmin, umax, vmax) boxes over the smaller box's area."""
    du = min(box_a[2], box_b[2]) - max(box_a[0], box_b[0])
    dv = min(box_a[3], box_b[3]) - max(box_a[1], box_b[1])
    if du <= 0 or dv <= 0:
        return 0.0
    area = min((box_a[2] - box_a[0]) * (box_a[3] - box_a[1]), (box_b[2] - box_b[0]) * (box_b[3] - box_b[1]))
    return float(du * dv / max(area, 1e-12))


# The normals' dot products of all pairs at once (one matrix product) may round a few ulp apart
# from the row-by-row products the grouping is defined with; within this of the threshold the row
# is computed again as defined, so that the labels are the same to the bit.
_DOT_MARGIN = 1e-9


def _coplanar_groups(normals: FloatArray, d_m: FloatArray, config: MatchingConfig) -> np.ndarray:
    """Label planes (unit normals (k, 3), offsets (k,)) so that patches of one physical plane share
    a label: plane k, unless labelled already, labels every unlabelled plane within
    ``coplanar_angle_deg`` and ``coplanar_offset_m`` of it (itself included) with ``k``."""
    cos_max = np.cos(np.radians(config.coplanar_angle_deg))
    cos = normals @ normals.T
    close = np.abs(d_m[None, :] - d_m[:, None]) <= config.coplanar_offset_m
    same = (cos >= cos_max) & close
    for row_k in np.flatnonzero((np.abs(cos - cos_max) <= _DOT_MARGIN).any(axis=1)):
        same[row_k] = (normals @ normals[row_k] >= cos_max) & close[row_k]
    labels = [-1] * len(d_m)
    for k, row in enumerate(same.tolist()):
        if labels[k] < 0:
            for j in itertools.compress(range(len(row)), row):
                if labels[j] < 0:
                    labels[j] = k
    return np.array(labels, dtype=int)


class StationPlanes(Sequence[Plane]):
    """One station's planes, with what :func:`match_planes` works on formed once for all the pairs
    the station is in: normals (k, 3), offsets (k,), centroids (k, 3) and hulls; on first use each
    plane's box (:meth:`box`) and the coplanar groups (:meth:`groups`). Indexed, iterated and
    counted as the planes."""

    def __init__(self, planes: tuple[Plane, ...]) -> None:
        self.planes = planes
        self.normals = np.array([p.normal for p in planes])
        self.d_m = np.array([p.d_m for p in planes])
        self.centroids_xyz = np.array([p.centroid_xyz for p in planes])
        self.hulls_xyz = [np.asarray(p.hull_xyz, dtype=np.float64) for p in planes]
        self._boxes: list[tuple[float, ...] | None] = [None] * len(planes)
        self._groups: dict[tuple[float, float], np.ndarray] = {}

    def box(self, k: int) -> tuple[float, ...]:
        """Plane k's box (umin, vmin, umax, vmax) in its own tangent basis about its centroid."""
        box = self._boxes[k]
        if box is None:
            plane = self.planes[k]
            box = self._boxes[k] = _box_in_plane(plane.hull_xyz, self.centroids_xyz[k], *plane.basis_uv)
        return box

    def groups(self, config: MatchingConfig) -> np.ndarray:
        """The planes' coplanar groups (:func:`_coplanar_groups`) under ``config``."""
        key = (config.coplanar_angle_deg, config.coplanar_offset_m)
        if key not in self._groups:
            self._groups[key] = _coplanar_groups(self.normals, self.d_m, config)
        return self._groups[key]

    @overload
    def __getitem__(self, index: int) -> Plane: ...
    @overload
    def __getitem__(self, index: slice) -> tuple[Plane, ...]: ...
    def __getitem__(self, index: int | slice) -> Plane | tuple[Plane, ...]:
        return self.planes[index]

    def __len__(self) -> int:
        return len(self.planes)


def match_planes(
    planes_i: tuple[Plane, ...] | StationPlanes, planes_j: tuple[Plane, ...] | StationPlanes, T_i_j: Pose,
    config: MatchingConfig,
) -> tuple[PlaneMatch, ...]:
    """Plane correspondences between two scans, given the approximate transform ``T_i_j``.

    Normals must agree within ``max_angle_deg``, the planes lie within ``max_offset_m`` of each
    other (measured at the other patch's centroid, both ways), and their extents overlap by at
    least ``min_overlap``. Returns the matches sorted by (plane_i, plane_j). A station matched in
    many pairs may come as its :class:`StationPlanes`, formed once.
    """
    si = planes_i if isinstance(planes_i, StationPlanes) else StationPlanes(planes_i)
    sj = planes_j if isinstance(planes_j, StationPlanes) else StationPlanes(planes_j)
    if not si.planes or not sj.planes:
        return ()
    n_a, d_a, c_a = si.normals, si.d_m, si.centroids_xyz
    # T_i_j's rotation formed once (Pose.apply forms it on every call), and
    # applied as they apply it: the same products, the same floats.
    R_i_j, t_i_j = T_i_j.rotation_matrix, T_i_j.t_xyz
    n_b = sj.normals @ R_i_j.T
    d_b = sj.d_m + n_b @ t_i_j
    c_b = sj.centroids_xyz @ R_i_j.T + t_i_j

    cos = np.clip(n_a @ n_b.T, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    # Offset at the other patch's centroid, both ways: robust to where the planes' origins lie.
    off_ab = np.abs(c_b @ n_a.T - d_a[None, :]).T  # plane a evaluated at centroid of b
    off_ba = np.abs(c_a @ n_b.T - d_b[None, :])  # plane b evaluated at centroid of a
    offset = 0.5 * (off_ab + off_ba)
    gate = (angle <= config.max_angle_deg) & (offset <= config.max_offset_m)

    candidates: list[_Candidate] = []
    hulls_b: dict[int, FloatArray] = {}  # each plane's hull in frame i, once per call
    gated_a, gated_b = np.nonzero(gate)
    for a, b, angle_ab, offset_ab in zip(gated_a.tolist(), gated_b.tolist(), angle[gated_a, gated_b].tolist(),
                                         offset[gated_a, gated_b].tolist(), strict=True):
        if b not in hulls_b:
            hulls_b[b] = sj.hulls_xyz[b] @ R_i_j.T + t_i_j  # T_i_j.apply
        u, v = si.planes[a].basis_uv
        share = _overlap_share(si.box(a), _box_in_plane(hulls_b[b], c_a[a], u, v))
        if share >= config.min_overlap:
            candidates.append(((a, b), angle_ab, offset_ab, share))

    # Each plane of i keeps only its candidates on one physical plane of j, then each plane of j
    # its candidates on one physical plane of i.
    kept = _one_plane_each(candidates, lambda: _coplanar_groups(n_b, d_b, config).tolist(), 0, config)
    kept = _one_plane_each(kept, lambda: si.groups(config).tolist(), 1, config)
    return tuple(PlaneMatch(si.planes[a].plane_id, sj.planes[b].plane_id, angle_deg, offset_m, share)
                 for (a, b), angle_deg, offset_m, share in sorted(kept))


def _one_plane_each(candidates: list[_Candidate], other_groups: Callable[[], list[int]], own: int,
                    config: MatchingConfig) -> list[_Candidate]:
    """The candidates ((a, b), angle, offset, share) left when every plane on side ``own`` (0: a,
    1: b) keeps those on the physical plane (coplanar group, from ``other_groups()``, of the other
    side's plane) of its best (smallest offset) candidate, and only where no candidate on another
    physical plane comes close to it (then it keeps none). In the order given. ``other_groups`` is
    called only where a plane has more than one candidate."""
    other = 1 - own
    mine: dict[int, list[_Candidate]] = {}
    for c in candidates:
        mine.setdefault(c[0][own], []).append(c)
    if len(mine) == len(candidates):  # one candidate each: nothing to choose between
        return candidates
    groups_of_other = other_groups()
    chosen: dict[int, int] = {}  # plane -> the group it keeps
    for k, cands in mine.items():
        best: dict[int, float] = {}  # the best offset on each physical plane
        for c in cands:
            g = groups_of_other[c[0][other]]
            best[g] = min(best.get(g, np.inf), c[2])
        if len(best) > 1:
            first, second = sorted(best.values())[:2]
            if not second > _AMBIGUITY_RATIO * first + config.coplanar_offset_m:
                continue
        # Two physical planes tied for the best never get here (ambiguous), so the order of
        # the candidates does not choose between them.
        chosen[k] = groups_of_other[min(cands, key=lambda c: c[2])[0][other]]
    return [c for c in candidates if chosen.get(c[0][own]) == groups_of_other[c[0][other]]]


def count_directions(normals: FloatArray, min_angle_deg: float = 20.0) -> int:
    """Number of distinct normal directions (up to sign) among unit normals (k, 3)."""
    reps: list[FloatArray] = []
    cos_min = np.cos(np.radians(min_angle_deg))
    for n in normals:
        if all(abs(float(n @ r)) < cos_min for r in reps):
            reps.append(n)
    return len(reps)
