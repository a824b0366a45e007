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

import numpy as np
from scipy.spatial import cKDTree

from kinreg.config import MatchingConfig
from kinreg.geometry import FloatArray, Pose
from kinreg.types import Plane, PlaneMatch

# A candidate on another physical plane must be this much worse (in offset) than the best one
# before the best is trusted; otherwise the plane is left unmatched.
_AMBIGUITY_RATIO = 3.0


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


def transform_planes(normals: FloatArray, d_m: FloatArray, T_i_j: Pose) -> tuple[FloatArray, FloatArray]:
    """Planes (normals (k, 3), offsets (k,)) of frame j expressed in frame i.

    From ``n_j . x_j = d_j`` and ``x_i = R x_j + t``: ``(R n_j) . x_i = d_j + (R n_j) . t``.
    """
    n_i = normals @ T_i_j.rotation_matrix.T
    return n_i, d_m + n_i @ T_i_j.t_xyz


def _plane_frame(plane: Plane) -> tuple[FloatArray, FloatArray]:
    return plane.basis_uv[0], plane.basis_uv[1]


def _box_in_plane(points: FloatArray, origin: FloatArray, u: FloatArray, v: FloatArray) -> FloatArray:
    local = points - origin
    along_u, along_v = local @ u, local @ v
    return np.array([along_u.min(), along_v.min(), along_u.max(), along_v.max()])


def _overlap_share(box_a: FloatArray, box_b: FloatArray) -> float:
    """Overlapping area of two (umin, vmin, umax, vmax) boxes over the smaller box's area."""
    du = min(box_a[2], box_b[2]) - max(box_a[0], box_b[0])
    dv = min(box_a[3], box_b[3]) - max(box_a[1], box_b[1])
    if du <= 0 or dv <= 0:
        return 0.0
    area = min((box_a[2] - box_a[0]) * (box_a[3] - box_a[1]), (box_b[2] - box_b[0]) * (box_b[3] - box_b[1]))
    return float(du * dv / max(area, 1e-12))


def _coplanar_groups(normals: FloatArray, d_m: FloatArray, config: MatchingConfig) -> np.ndarray:
    """Label planes so that patches of one physical plane share a label."""
    labels = -np.ones(len(d_m), dtype=int)
    cos_max = np.cos(np.radians(config.coplanar_angle_deg))
    for k in range(len(d_m)):
        if labels[k] >= 0:
            continue
        same = (normals @ normals[k] >= cos_max) & (np.abs(d_m - d_m[k]) <= config.coplanar_offset_m)
        labels[same & (labels < 0)] = k
    return labels


def match_planes(
    planes_i: tuple[Plane, ...], planes_j: tuple[Plane, ...], T_i_j: Pose, config: MatchingConfig
) -> tuple[PlaneMatch, ...]:
    """Plane correspondences between two scans, given the approximate transform ``T_i_j``.

    Normals must agree within ``max_angle_deg``, the planes lie within ``max_offset_m`` of each
    other (measured at the other patch's centroid, both ways), and their extents overlap by at
    least ``min_overlap``. Returns the matches sorted by (plane_i, plane_j).
    """
    if not planes_i or not planes_j:
        return ()
    n_a = np.array([p.normal for p in planes_i])
    d_a = np.array([p.d_m for p in planes_i])
    c_a = np.array([p.centroid_xyz for p in planes_i])
    n_b, d_b = transform_planes(np.array([p.normal for p in planes_j]), np.array([p.d_m for p in planes_j]), T_i_j)
    c_b = T_i_j.apply(np.array([p.centroid_xyz for p in planes_j]))

    cos = np.clip(n_a @ n_b.T, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    # Offset at the other patch's centroid, both ways: robust to where the planes' origins lie.
    off_ab = np.abs(c_b @ n_a.T - d_a[None, :]).T  # plane a evaluated at centroid of b
    off_ba = np.abs(c_a @ n_b.T - d_b[None, :])  # plane b evaluated at centroid of a
    offset = 0.5 * (off_ab + off_ba)
    gate = (angle <= config.max_angle_deg) & (offset <= config.max_offset_m)

    group_b = _coplanar_groups(n_b, d_b, config)
    group_a = _coplanar_groups(n_a, d_a, config)
    candidates: dict[tuple[int, int], tuple[float, float, float]] = {}
    boxes_a: dict[int, FloatArray] = {}  # each plane's own box and hull in frame i, once per call
    hulls_b: dict[int, FloatArray] = {}
    for a, b in zip(*np.nonzero(gate), strict=True):
        u, v = _plane_frame(planes_i[a])
        if a not in boxes_a:
            boxes_a[a] = _box_in_plane(planes_i[a].hull_xyz, c_a[a], u, v)
        if b not in hulls_b:
            hulls_b[b] = T_i_j.apply(planes_j[b].hull_xyz)
        box_a = boxes_a[a]
        box_b = _box_in_plane(hulls_b[b], c_a[a], u, v)
        share = _overlap_share(box_a, box_b)
        if share >= config.min_overlap:
            candidates[(int(a), int(b))] = (float(angle[a, b]), float(offset[a, b]), share)

    def unambiguous(groups_of_other: np.ndarray, pairs: list[tuple[int, int]], other_index: int) -> bool:
        best: dict[int, float] = {}
        for pair in pairs:
            g = int(groups_of_other[pair[other_index]])
            best[g] = min(best.get(g, np.inf), candidates[pair][1])
        if len(best) < 2:
            return True
        first, second = sorted(best.values())[:2]
        return second > _AMBIGUITY_RATIO * first + config.coplanar_offset_m

    def best_group(groups_of_other: np.ndarray, pairs: list[tuple[int, int]], other_index: int) -> int:
        return int(groups_of_other[min(pairs, key=lambda p: candidates[p][1])[other_index]])

    keep = set(candidates)
    for a in range(len(planes_i)):
        pairs = [p for p in candidates if p[0] == a]
        if not pairs:
            continue
        if not unambiguous(group_b, pairs, 1):
            keep -= set(pairs)
            continue
        g = best_group(group_b, pairs, 1)
        keep -= {p for p in pairs if group_b[p[1]] != g}
    for b in range(len(planes_j)):
        pairs = [p for p in keep if p[1] == b]
        if not pairs:
            continue
        if not unambiguous(group_a, pairs, 0):
            keep -= set(pairs)
            continue
        g = best_group(group_a, pairs, 0)
        keep -= {p for p in pairs if group_a[p[0]] != g}
    return tuple(
        PlaneMatch(planes_i[a].plane_id, planes_j[b].plane_id, *candidates[(a, b)]) for a, b in sorted(keep)
    )


def count_directions(normals: FloatArray, min_angle_deg: float = 20.0) -> int:
    """Number of distinct normal directions (up to sign) among unit normals (k, 3)."""
    reps: list[FloatArray] = []
    cos_min = np.cos(np.radians(min_angle_deg))
    for n in normals:
        if all(abs(float(n @ r)) < cos_min for r in reps):
            reps.append(n)
    return len(reps)


def coarse_translation(
    planes_i: tuple[Plane, ...], planes_j: tuple[Plane, ...], T_i_j: Pose, config: MatchingConfig
) -> FloatArray | None:
    """A translation (3,) in scan i's frame that brings the planes of scan j onto those of scan i,
    when the approximate transform is off by more than the matching gates (a jump in the
    trajectory). Voting: every pair of planes with agreeing normals says ``n . tau = d_a - d_b``;
    triples of such pairs with normals in three directions give candidates, and the candidate
    most pairs agree with (within ``coplanar_offset_m``, at least ``min_matches + 1`` of them, in
    three directions) wins if it is within ``max_jump_m``. Rotation errors are not searched.
    Returns ``None`` when no such translation stands out.
    """
    if len(planes_i) < 3 or len(planes_j) < 3:
        return None
    n_a = np.array([p.normal for p in planes_i])
    d_a = np.array([p.d_m for p in planes_i])
    n_b, d_b = transform_planes(np.array([p.normal for p in planes_j]), np.array([p.d_m for p in planes_j]), T_i_j)
    ia, ib = np.nonzero(n_a @ n_b.T >= np.cos(np.radians(config.max_angle_deg)))
    if len(ia) < 3:
        return None
    normals = n_a[ia]
    delta = d_a[ia] - d_b[ib]
    keep = np.abs(delta) <= config.max_jump_m
    normals, delta = normals[keep], delta[keep]
    if len(delta) < 3:
        return None
    rng = np.random.default_rng(0)  # deterministic: the same pair always gives the same answer
    n = len(delta)
    triples = (np.array(list(itertools.combinations(range(n), 3))) if n <= 24
               else rng.integers(0, n, size=(2000, 3)))
    best, best_count = None, 0
    for tri in triples:
        M = normals[tri]
        if abs(np.linalg.det(M)) < 0.3:
            continue
        tau = np.linalg.solve(M, delta[tri])
        if np.linalg.norm(tau) > config.max_jump_m:
            continue
        inliers = np.abs(normals @ tau - delta) <= config.coplanar_offset_m
        count = int(inliers.sum())
        if count > best_count and count_directions(normals[inliers]) >= 3:
            best, best_count = tau, count
    if best is None or best_count < config.min_matches + 1:
        return None
    inliers = np.abs(normals @ best - delta) <= config.coplanar_offset_m
    return np.linalg.lstsq(normals[inliers], delta[inliers], rcond=None)[0]
