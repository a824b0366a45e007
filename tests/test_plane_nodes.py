"""The physical planes as nodes of the block (issue #14): each scan's planes counted once."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from planefixtures import ROOM, pose, scan_planes

from kinreg.config import BlockConfig
from kinreg.estimate.block import adjust_block
from kinreg.estimate.drift import plane_motion_jacobian
from kinreg.estimate.plane_nodes import PlaneNodes, plane_clusters, plane_node_observations
from kinreg.geometry import Pose
from kinreg.types import LinkStatus, ObservationKind, PlaneMatch

CONFIG = BlockConfig(data_snooping=False, variance_components=False)


def _room_nodes(n_scans: int) -> PlaneNodes:
    return PlaneNodes(tuple(tuple((k, pid) for k in range(n_scans)) for pid in range(len(ROOM))))


def _frame_covariance(planes) -> np.ndarray:
    """How well a scan's planes fix its frame (6x6): ``(sum J^T C^-1 J)^-1``."""
    H = sum(plane_motion_jacobian(p).T @ np.linalg.inv(p.cov_uvd) @ plane_motion_jacobian(p) for p in planes)
    return np.linalg.inv(H)


def _adjust(poses: Pose, planes, nodes: PlaneNodes):
    extra, observations = plane_node_observations(poses, planes, nodes, len(poses))
    both = Pose(np.concatenate([poses.quat_wxyz, extra.quat_wxyz]), np.concatenate([poses.t_xyz, extra.t_xyz]))
    fixed = np.zeros(len(both), dtype=bool)
    fixed[0] = True
    return adjust_block(both, observations, fixed, CONFIG)


def test_a_scan_among_many_that_see_the_same_planes_is_fixed_by_its_planes_and_the_datum_s_once():
    """Five scans at one place see the same room; the first is the datum. Each other scan's pose
    relative to it is as good as the two scans' planes make it, ``2 F`` (``F``: what one scan's
    planes fix), however many other scans see the room too. Links between every pair would count
    each scan's planes once per link and report less."""
    poses = Pose.stack([Pose.identity()] * 5)
    planes = [scan_planes(Pose.identity(), k, None) for k in range(5)]
    result = _adjust(poses, planes, _room_nodes(5))
    F = _frame_covariance(planes[0])
    for k in range(1, 5):
        np.testing.assert_allclose(result.cov_xi[k], 2.0 * F, rtol=1e-4, atol=1e-14)
    assert result.redundancy > 0


def test_the_reported_covariance_holds_over_noisy_planes():
    """Three scans at different poses, their planes noisy by their own covariances: the squared
    Mahalanobis error of the third scan's pose averages 6 (chi-square, six degrees of freedom)."""
    rng = np.random.default_rng(7)
    truth = Pose.stack([pose([0, 0, 0], [0, 0, 0]), pose([0.01, -0.02, 0.3], [1.5, 0.4, 0.1]),
                        pose([-0.02, 0.01, -0.4], [-1.0, 1.2, -0.1])])
    start = Pose.stack([truth[0], truth[1].compose(pose([0.002, 0, -0.003], [0.02, -0.01, 0.03])),
                        truth[2].compose(pose([-0.001, 0.003, 0.002], [-0.03, 0.02, 0.01]))])
    squares = []
    for _ in range(60):
        planes = [scan_planes(truth[k], k, rng) for k in range(3)]
        result = _adjust(start, planes, _room_nodes(3))
        error = truth[2].inverse().compose(result.poses[2]).log()
        squares.append(float(error @ np.linalg.solve(result.cov_xi[2], error)))
        assert not result.failure
        kinds = {t.kind for t in result.tests}
        assert kinds == {ObservationKind.PLANE, ObservationKind.PLANE_OFFSET, ObservationKind.STATION}
    assert 4.5 < np.mean(squares) < 7.5


def test_the_links_matches_join_into_physical_planes():
    def link(i, j, pairs, status=LinkStatus.OK):
        return SimpleNamespace(scan_i=i, scan_j=j, status=status, rank=6,
                               matches=tuple(PlaneMatch(a, b, 0.0, 0.0, 1.0) for a, b in pairs))

    links = [link(0, 1, [(0, 0), (1, 1)]), link(1, 2, [(0, 3)]), link(2, 3, [(5, 5)], LinkStatus.REJECTED)]
    nodes = plane_clusters(links)
    assert nodes.clusters == (((0, 0), (1, 0), (2, 3)), ((0, 1), (1, 1)))


def test_the_report_draws_a_scan_plane_s_residuals_with_its_own_degrees_of_freedom():
    from kinreg.report.plots import _residual_dofs

    assert _residual_dofs({}, "plane") == {2: 1.0}
    assert _residual_dofs({}, "plane offset") == {1: 1.0}
    assert _residual_dofs({}, "trajectory") == {6: 1.0}


def test_scan_planes_whose_model_is_mostly_the_floor_form_kinds_of_their_own():
    """A scan plane's tilts (or offset) whose covariance is more than half the floor go to the
    ``(floor)`` kinds, each with its own variance component: large planes and planes set by their
    points' noise are not off from their models by the same factor."""
    poses = Pose.stack([Pose.identity(), pose([0.01, 0.02, 0.0], [0.3, -0.2, 0.0])])
    planes = [scan_planes(poses[k].inverse(), k, None, sigma_tilt=2e-4, sigma_d=5e-4) for k in range(2)]
    nodes = _room_nodes(2)

    def kinds(floors):
        _, observations = plane_node_observations(poses, planes, PlaneNodes(nodes.clusters, floors), 2)
        return [o.kind for o in observations if o.kind is not ObservationKind.STATION]

    n = 2 * len(ROOM)
    assert kinds((0.0, 0.0)) == [ObservationKind.PLANE, ObservationKind.PLANE_OFFSET] * n
    # floors of the planes' own size: more than half of each variance; the floor and the ceiling
    # (ROOM's planes 4 and 5; plane 7 is inclined 37 deg) in kinds of their own
    level = [abs(normal[2]) > 0.9 for normal, *_ in ROOM]
    assert level == [False] * 4 + [True] * 2 + [False] * 2
    assert kinds((2e-4, 5e-4)) == [kind for lv in level for kind in (
        [ObservationKind.PLANE_FLOOR_LEVEL, ObservationKind.PLANE_OFFSET_FLOOR_LEVEL] if lv
        else [ObservationKind.PLANE_FLOOR, ObservationKind.PLANE_OFFSET_FLOOR]) * 2]
    # a tenth of it in the tilts only
    assert kinds((2e-5, 5e-4)) == [kind for lv in level for kind in (
        [ObservationKind.PLANE, ObservationKind.PLANE_OFFSET_FLOOR_LEVEL] if lv
        else [ObservationKind.PLANE, ObservationKind.PLANE_OFFSET_FLOOR]) * 2]
