"""match_planes with each station's arrays formed once (StationPlanes) gives the same matches, in
the same order, with the same floats, as the plane-by-plane matching it replaced (kept here as the
reference, as it was before the per-station arrays)."""

from __future__ import annotations

import numpy as np
import pytest
from planefixtures import ROOM, pose, scan_planes

from kinreg.config import MatchingConfig
from kinreg.estimate import matching
from kinreg.estimate.matching import StationPlanes, match_planes
from kinreg.geometry import Pose, rotvec_to_quat, tangent_basis
from kinreg.types import Plane, PlaneMatch

# ---------------------------------------------------------------- the reference: the former matching


def _reference_box(points, origin, u, v):
    local = points - origin
    along_u, along_v = local @ u, local @ v
    return np.array([along_u.min(), along_v.min(), along_u.max(), along_v.max()])


def _reference_groups(normals, d_m, config):
    labels = -np.ones(len(d_m), dtype=int)
    cos_max = np.cos(np.radians(config.coplanar_angle_deg))
    for k in range(len(d_m)):
        if labels[k] >= 0:
            continue
        same = (normals @ normals[k] >= cos_max) & (np.abs(d_m - d_m[k]) <= config.coplanar_offset_m)
        labels[same & (labels < 0)] = k
    return labels


def _reference_match(planes_i, planes_j, T_i_j, config) -> tuple[tuple[PlaneMatch, ...], int]:
    """The matches, and how many candidates passed the gates and the overlap (before the
    ambiguity step)."""
    if not planes_i or not planes_j:
        return (), 0
    n_a = np.array([p.normal for p in planes_i])
    d_a = np.array([p.d_m for p in planes_i])
    c_a = np.array([p.centroid_xyz for p in planes_i])
    # planes of frame j in frame i: from n_j . x_j = d_j and x_i = R x_j + t, (R n_j) . x_i = d_j + (R n_j) . t
    n_b = np.array([p.normal for p in planes_j]) @ T_i_j.rotation_matrix.T
    d_b = np.array([p.d_m for p in planes_j]) + n_b @ T_i_j.t_xyz
    c_b = T_i_j.apply(np.array([p.centroid_xyz for p in planes_j]))
    cos = np.clip(n_a @ n_b.T, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    off_ab = np.abs(c_b @ n_a.T - d_a[None, :]).T
    off_ba = np.abs(c_a @ n_b.T - d_b[None, :])
    offset = 0.5 * (off_ab + off_ba)
    gate = (angle <= config.max_angle_deg) & (offset <= config.max_offset_m)
    group_b = _reference_groups(n_b, d_b, config)
    group_a = _reference_groups(n_a, d_a, config)
    candidates = {}
    boxes_a, hulls_b = {}, {}
    for a, b in zip(*np.nonzero(gate), strict=True):
        u, v = planes_i[a].basis_uv[0], planes_i[a].basis_uv[1]
        if a not in boxes_a:
            boxes_a[a] = _reference_box(planes_i[a].hull_xyz, c_a[a], u, v)
        if b not in hulls_b:
            hulls_b[b] = T_i_j.apply(planes_j[b].hull_xyz)
        share = matching._overlap_share(boxes_a[a], _reference_box(hulls_b[b], c_a[a], u, v))
        if share >= config.min_overlap:
            candidates[(int(a), int(b))] = (float(angle[a, b]), float(offset[a, b]), share)

    def unambiguous(groups_of_other, pairs, other_index):
        best = {}
        for pair in pairs:
            g = int(groups_of_other[pair[other_index]])
            best[g] = min(best.get(g, np.inf), candidates[pair][1])
        if len(best) < 2:
            return True
        first, second = sorted(best.values())[:2]
        return second > matching._AMBIGUITY_RATIO * first + config.coplanar_offset_m

    def best_group(groups_of_other, pairs, other_index):
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
    matches = tuple(PlaneMatch(planes_i[a].plane_id, planes_j[b].plane_id, *candidates[(a, b)])
                    for a, b in sorted(keep))
    return matches, len(candidates)


# ---------------------------------------------------------------- plane sets


def _plane(scan_id, plane_id, normal, centroid, hull_uv, rng) -> Plane:
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    c = np.asarray(centroid, float)
    basis = tangent_basis(n)
    hull = c + hull_uv @ basis
    return Plane(scan_id, plane_id, n, float(n @ c), c, basis, np.diag([1e-8, 1e-8, 1e-6]), hull,
                 float(np.ptp(hull_uv[:, 0]) * np.ptp(hull_uv[:, 1])), 1000, 0.005)


def _polygon(rng, size_m) -> np.ndarray:
    """A convex-ish polygon (k, 2) about the origin, 3 to 40 corners."""
    k = int(rng.integers(3, 41))
    angles = np.sort(rng.uniform(0, 2 * np.pi, k))
    radii = size_m * rng.uniform(0.5, 1.0, k)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)]) * rng.uniform(0.3, 1.0, 2)


def random_pair(rng) -> tuple[tuple[Plane, ...], tuple[Plane, ...], Pose]:
    """Two scans of one random scene: physical planes, some seen in several patches, some with a
    parallel neighbour a few cm away (ambiguous), seen from two frames with noise, in shuffled
    order, with planes only one scan sees; and the approximate transform between the frames."""
    scene = []  # (normal, point on the plane, patch size)
    for _ in range(int(rng.integers(2, 12))):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        point = rng.uniform(-8, 8, 3)
        scene.append((n, point, rng.uniform(0.3, 4.0)))
        if rng.random() < 0.4:  # a parallel plane close by
            scene.append((n, point + n * rng.uniform(0.005, 0.12), rng.uniform(0.3, 4.0)))
    T_i_j = Pose(rotvec_to_quat(rng.normal(0, 0.3, 3)), rng.normal(0, 2.0, 3))
    T_j_i = T_i_j.inverse()

    def seen(scan_id, T_scan_obj):
        planes = []
        for n, point, size in scene:
            for _ in range(int(rng.integers(0, 4))):  # 0 to 3 patches of this plane
                basis = tangent_basis(n)
                centre = point + rng.uniform(-1, 1, 2) * size @ basis
                tilt = n + rng.normal(0, np.radians(0.3), 3)
                R = T_scan_obj.rotation_matrix
                normal = R @ (tilt / np.linalg.norm(tilt))
                centroid = T_scan_obj.apply(centre) + normal * rng.normal(0, 0.01)
                planes.append((normal, centroid, _polygon(rng, size)))
        for _ in range(int(rng.integers(0, 4))):  # planes the other scan does not see
            planes.append((rng.normal(size=3), rng.uniform(-8, 8, 3), _polygon(rng, rng.uniform(0.3, 3))))
        order = rng.permutation(len(planes))
        return tuple(_plane(scan_id, k, *planes[o], rng) for k, o in enumerate(order))

    planes_i = seen(0, Pose.identity())
    planes_j = seen(1, T_j_i)
    T_prior = T_i_j.compose(Pose(rotvec_to_quat(rng.normal(0, 0.005, 3)), rng.normal(0, 0.02, 3)))
    return planes_i, planes_j, T_prior


def _key(matches) -> list[tuple]:
    """Everything of the matches, floats to the bit."""
    return [(m.plane_i, m.plane_j, float(m.angle_deg).hex(), float(m.offset_m).hex(), float(m.overlap).hex())
            for m in matches]


CONFIGS = [
    MatchingConfig(),
    MatchingConfig(max_angle_deg=3.0, max_offset_m=0.15, min_overlap=0.05, coplanar_angle_deg=1.5,
                   coplanar_offset_m=0.04),
    MatchingConfig(max_angle_deg=1.0, max_offset_m=0.05, min_overlap=0.3, coplanar_angle_deg=0.5,
                   coplanar_offset_m=0.01),
]


@pytest.mark.parametrize("config", CONFIGS)
def test_matching_equals_the_former_on_random_scenes(config):
    rng = np.random.default_rng(18)
    n_candidates = n_matches = 0
    for _ in range(150):
        planes_i, planes_j, T_prior = random_pair(rng)
        expected, candidates = _reference_match(planes_i, planes_j, T_prior, config)
        assert _key(match_planes(planes_i, planes_j, T_prior, config)) == _key(expected)
        assert _key(match_planes(StationPlanes(planes_i), StationPlanes(planes_j), T_prior, config)) == _key(expected)
        n_candidates += candidates
        n_matches += len(expected)
    # the scenes exercise both the matching and the ambiguity step (candidates taken out)
    assert n_matches > 100 and n_candidates > n_matches


def test_matching_equals_the_former_with_stations_reused_over_many_pairs():
    """One StationPlanes per station used in all its pairs (as a link task does), on room scans
    with noise, one wall split into two patches and an empty station."""
    rng = np.random.default_rng(7)
    room = [*ROOM, ((1, 0, 0), 0.0, (0, 6.5, 1.5), (1.0, 1.5)), ((0, 1, 0), -0.03, (3, 0, 1.5), (1.0, 1.0))]
    poses = [pose(rng.normal(0, [0.05, 0.05, 0.3]), [4.0 + k, 3.0, 1.4] + rng.normal(0, 0.3, 3)) for k in range(6)]
    planes = [scan_planes(T, k, rng, room=room) for k, T in enumerate(poses)] + [()]
    stations = [StationPlanes(p) for p in planes]
    config = MatchingConfig()
    n_matches = 0
    for i in range(len(planes)):
        for j in range(len(planes)):
            if i == j:
                continue
            T_prior = (poses[i].inverse().compose(poses[j]) if j < len(poses) and i < len(poses)
                       else Pose.identity())
            T_prior = T_prior.compose(Pose.exp(rng.normal(0, [0.02, 0.02, 0.02, 0.003, 0.003, 0.003])))
            expected, _ = _reference_match(planes[i], planes[j], T_prior, config)
            assert _key(match_planes(stations[i], stations[j], T_prior, config)) == _key(expected)
            n_matches += len(expected)
    assert n_matches > 0


@pytest.mark.parametrize("margin", [-1.0, 2.0])
def test_coplanar_groups_are_the_former_with_and_without_the_rows_done_again(monkeypatch, margin):
    """Never (-1) or always (2) computing the rows again gives the same labels: the matrix product
    agrees with the row products away from the threshold."""
    monkeypatch.setattr(matching, "_DOT_MARGIN", margin)
    rng = np.random.default_rng(3)
    config = MatchingConfig(coplanar_angle_deg=2.0, coplanar_offset_m=0.05)
    for _ in range(300):
        k = int(rng.integers(1, 30))
        base = rng.normal(size=(int(rng.integers(1, 6)), 3))
        normals = base[rng.integers(0, len(base), k)] + rng.normal(0, np.radians(1.5), (k, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        d_m = rng.choice([-3.0, -1.0, 0.5], k) + rng.normal(0, 0.04, k)
        expected = _reference_groups(normals, d_m, config).tolist()
        assert matching._coplanar_groups(normals, d_m, config).tolist() == expected


def test_station_planes_read_as_the_planes():
    planes = scan_planes(pose([0, 0, 0.1], [1.0, 2.0, 1.0]), 0, np.random.default_rng(1))
    station = StationPlanes(planes)
    assert len(station) == len(planes) and station[2] is planes[2] and tuple(station) == planes
    assert station[1:3] == planes[1:3]
