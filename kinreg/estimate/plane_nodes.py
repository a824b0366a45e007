"""The physical planes as unknowns of the block: each scan's planes observed once.

A pairwise link carries the errors of both scans' planes. A scan linked to eight others carries
its planes' errors into eight links, and the block, which takes the links as independent, counts
them eight times: the network's turn about a station whose few planes fix its frame poorly gets a
sigma several times too small (a station of five planes is reported fixed far better than its
planes fix it).

Here the links only say which planes are the same physical plane (their matches, joined over all
links into clusters). Each cluster becomes a node of the block, a pose ``F_g`` whose z axis is the
plane's normal and whose origin lies on it. Each scan plane in it observes ``T_k^-1 F_g`` twice,
from the plane's own covariance: its two tilts (``PLANE``, rank 2) and its offset given the tilts
(``PLANE_OFFSET``, rank 1; as residuals the node's normal in the scan plane's frame and the node
plane's distance from its anchor, which the node's free directions leave as they are:
:func:`kinreg.estimate.block._scan_plane_residuals`), each kind with a variance component of its
own, which may also fall below 1 (their residuals show their whole error:
:mod:`kinreg.estimate.snooping`). A scan plane
whose model is mostly the floors (a large plane: its least-squares sigmas far below them) observes
as ``PLANE_FLOOR`` and ``PLANE_OFFSET_FLOOR`` instead, with components of their own
(:func:`floor_bound`); a level one (floor, ceiling: :func:`is_level`) as ``PLANE_FLOOR_LEVEL`` and
``PLANE_OFFSET_FLOOR_LEVEL``. The three
directions a plane leaves free (the shift in it, the turn about its normal) are held by a
``STATION`` observation of the node itself with only those directions (one metre, one radian): no
other observation sees them, so it changes nothing else, has no redundancy and is never tested.

The final adjustment only (:func:`kinreg.estimate.strategy.adjust_with_measured_drift`): the links are
still what matching, relinking and their snooping work on, and a link the block rejected joins no
planes. Scan planes are not snooped there (:mod:`kinreg.estimate.block`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kinreg.geometry import FloatArray, Pose, matrix_to_quat
from kinreg.types import SCAN_PLANE_RANK, Link, LinkStatus, ObservationKind, Plane, RelativeObservation

# The residual's order (rho, phi): where a plane's offset and tilts sit (phi_x, phi_y, rho_z).
_DETERMINED = np.array([3, 4, 2])
_FREE = np.array([0, 1, 5])
_GAUGE_SIGMA = 1.0  # [m], [rad]: the hold on a plane node's free directions


@dataclass(frozen=True, eq=False)
class PlaneNodes:
    """The physical planes of a network: per cluster its members ``(station, plane_id)``; and the
    floors the scan planes' covariances carry (tilt [rad], offset [m]:
    ``PlanesConfig.min_sigma_angle_rad``, ``min_sigma_d_m``), to tell the planes whose model is
    mostly floor from those whose model is mostly their points' noise."""

    clusters: tuple[tuple[tuple[int, int], ...], ...]
    floors: tuple[float, float] = (0.0, 0.0)

    def __len__(self) -> int:
        return len(self.clusters)


def plane_clusters(links: Sequence[Link], floors: tuple[float, float] = (0.0, 0.0)) -> PlaneNodes:
    """The scan planes joined into physical planes by the matches of the usable links (union-find
    over ``(station, plane_id)``); only planes seen by two stations or more. ``floors``: see
    :class:`PlaneNodes`."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}

    def root(key: tuple[int, int]) -> tuple[int, int]:
        parent.setdefault(key, key)
        while parent[key] != key:
            parent[key] = parent[parent[key]]
            key = parent[key]
        return key

    for link in links:
        if link.status is not LinkStatus.OK or link.rank == 0:
            continue
        for m in link.matches:
            a, b = root((link.scan_i, m.plane_i)), root((link.scan_j, m.plane_j))
            if a != b:
                parent[max(a, b)] = min(a, b)
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for key in parent:
        groups.setdefault(root(key), []).append(key)
    clusters = tuple(tuple(sorted(g)) for g in groups.values() if len({k for k, _ in g}) >= 2)
    return PlaneNodes(tuple(sorted(clusters)), floors)


def _frame(normal: FloatArray, x_hint: FloatArray) -> FloatArray:
    """Rotation (columns x, y, n) of a plane frame: z along ``normal``, x the hint projected into
    the plane."""
    x = x_hint - (x_hint @ normal) * normal
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    x = x / np.linalg.norm(x)
    return np.column_stack([x, np.cross(normal, x), normal])


def plane_information(plane: Plane, R: FloatArray, origin: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The 6x6 information of a plane frame (rotation ``R``, ``origin`` on the plane, scan axes)
    in the block's residual order, from ``cov_uvd``, in two parts that sum to it: the tilts about
    the frame's x and y axes (rank 2, their marginal information) and the offset at the origin
    given the tilts (rank 1); zero along the three free directions. The two are independent, so
    each gets a variance component of its own: a plane fit's offset and tilts are not off from
    their floors by the same factor (one component for both would leave the sigmas of one too
    large and those of the other too small)."""
    x, y = R[:, 0], R[:, 1]
    u, v = plane.basis_uv[0], plane.basis_uv[1]
    M = np.array([[x @ u, x @ v], [y @ u, y @ v]])  # (a, b) along (u, v) -> along (x, y)
    to_xy = np.eye(3)
    to_xy[:2, :2] = M
    # A normal tilted by a along x and b along y is the frame turned by -b about x and a about y;
    # the offset at the origin then moves by e - a x.o - b y.o.
    J = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [-(x @ origin), -(y @ origin), 1.0]]) @ to_xy
    cov = J @ plane.cov_uvd @ J.T
    cov = 0.5 * (cov + cov.T)
    C_tt, C_ot = cov[:2, :2], cov[2, :2]
    K = np.linalg.solve(C_tt, C_ot)  # the offset's regression on the tilts
    w = np.array([-K[0], -K[1], 1.0])
    tilts, offset = np.zeros((6, 6)), np.zeros((6, 6))
    tilts[np.ix_(_DETERMINED[:2], _DETERMINED[:2])] = np.linalg.inv(C_tt)
    offset[np.ix_(_DETERMINED, _DETERMINED)] = np.outer(w, w) / (cov[2, 2] - C_ot @ K)
    return 0.5 * (tilts + tilts.T), offset


def floor_bound(tilts: FloatArray, offset: FloatArray, floors: tuple[float, float]) -> tuple[bool, bool]:
    """Whether a scan plane's tilts, and its offset given the tilts (their information,
    :func:`plane_information`), have a model that is mostly the floors (more than half the
    variance): a large plane of many points, whose least-squares sigmas are far below them. Those
    and the planes set by their points' noise are not off from their models by the same factor
    (the floors stand for errors a window's planes share, the noise for their points' scatter), so
    each gets a variance component of its own: one for both would fit neither, and leave the
    reported sigmas too large for one group and too small for the other."""
    tilt_var = 0.5 * float(np.trace(np.linalg.inv(tilts[np.ix_(_DETERMINED[:2], _DETERMINED[:2])])))
    offset_var = 1.0 / float(offset[_DETERMINED[2], _DETERMINED[2]])  # its weight vector ends in 1
    return floors[0] ** 2 > 0.5 * tilt_var, floors[1] ** 2 > 0.5 * offset_var


# A plane whose normal is within this of the object frame's vertical (cosine: 25 deg) is level.
_LEVEL_COS = 0.9


def is_level(normal_obj: FloatArray) -> bool:
    """Whether a physical plane (its normal in the object frame, z up) is level: a floor or a
    ceiling. Its scan planes' errors are not those of the walls: the trajectory's largest drift, in
    heading, and its horizontal drift leave a level plane where it is, so the drift inside a
    window neither tilts nor shifts it, while it turns and shifts every wall. With one variance
    component for both, the walls (most of the planes) set it: the level planes then weigh too
    little, and the heights and tilts of the network they fix come out pessimistic, while the
    walls weigh too much."""
    return abs(float(normal_obj[2])) > _LEVEL_COS


def plane_node_observations(poses: Pose, planes: Sequence[Sequence[Plane]], nodes: PlaneNodes,
                            first_node: int) -> tuple[Pose, list[RelativeObservation]]:
    """The plane nodes' initial poses (object frame, from the cluster's largest plane on the
    stations' ``poses``) and their observations: one ``PLANE`` observation per scan plane (its
    station, node ``first_node + g``) and the hold on each node's free directions. Each
    observation's frame is anchored where the node's prediction puts it (the nearest point on the
    observed plane, the node's x axis turned into it), so that the free directions start at zero."""
    by_id = [{p.plane_id: p for p in ps} for ps in planes]
    quats, origins, observations = [], [], []
    gauge = np.zeros((6, 6))
    gauge[_FREE, _FREE] = 1.0 / _GAUGE_SIGMA**2
    for g, members in enumerate(nodes.clusters):
        k0, p0 = max(members, key=lambda m: by_id[m[0]][m[1]].n_points)
        plane0 = by_id[k0][p0]
        c = plane0.centroid_xyz
        R0 = _frame(plane0.normal, plane0.basis_uv[0])
        o0 = c - (plane0.normal @ c - plane0.d_m) * plane0.normal
        F = poses[k0].compose(Pose(matrix_to_quat(R0), o0))
        quats.append(F.quat_wxyz)
        origins.append(F.t_xyz)
        node = first_node + g
        level = is_level(F.rotation_matrix[:, 2])
        for k, pid in members:
            plane = by_id[k][pid]
            D = poses[k].inverse().compose(F)  # the node in scan k's frame, as predicted
            t = D.t_xyz
            # A scan on the plane's other side sees its normal the other way (towards itself): the
            # same plane, with normal and offset negated (its covariance is the same).
            side = 1.0 if plane.normal @ D.rotation_matrix[:, 2] >= 0 else -1.0
            normal, d = side * plane.normal, side * plane.d_m
            R, o = _frame(normal, D.rotation_matrix[:, 0]), t - (normal @ t - d) * normal
            Z = Pose(matrix_to_quat(R), o)
            tilts, offset = plane_information(plane, R, o)
            tilts_floor, offset_floor = floor_bound(tilts, offset, nodes.floors)
            at_floor = (ObservationKind.PLANE_FLOOR_LEVEL, ObservationKind.PLANE_OFFSET_FLOOR_LEVEL) if level else (
                ObservationKind.PLANE_FLOOR, ObservationKind.PLANE_OFFSET_FLOOR)
            for kind, info in ((at_floor[0] if tilts_floor else ObservationKind.PLANE, tilts),
                               (at_floor[1] if offset_floor else ObservationKind.PLANE_OFFSET, offset)):
                observations.append(RelativeObservation(kind, k, node, Z, info, SCAN_PLANE_RANK[kind]))
        observations.append(RelativeObservation(ObservationKind.STATION, node, -1, F, gauge.copy(), 3))
    if not quats:
        return Pose(np.zeros((0, 4)), np.zeros((0, 3))), observations
    return Pose(np.array(quats), np.array(origins)), observations
