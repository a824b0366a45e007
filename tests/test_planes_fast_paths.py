"""The fast paths of plane detection (kinreg.estimate.planes) against the formulas they replace.

Each helper must give the same bits as the plainer numpy it stands for, so that the planes do not
move: the voxel grid's points and their order, the float-to-int truncation, the hull screened by
the extreme points' polygon, the sums of products from one buffer, the in-place band and vote
tests.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import ConvexHull

from kinreg.config import PlanesConfig
from kinreg.estimate.planes import (
    _hull_2d,
    _outside_extreme_polygon,
    _scatter,
    _split_patches,
    _truncated_rows,
    _votes,
    _voxel_downsample,
    _within,
    plane_covariance,
)
from kinreg.geometry import tangent_basis


def _voxel_downsample_reference(rows: np.ndarray, voxel_m: float) -> np.ndarray:
    """The voxel grid as written before the fast paths: int64 indices, a sorted unique key."""
    lower = rows.min(axis=1) - voxel_m * 0.5
    q = ((rows - lower[:, None]) / voxel_m).astype(np.int64)
    dims = q.max(axis=1) + 1
    key = (q[0] * dims[1] + q[1]) * dims[2] + q[2]
    _, voxel = np.unique(key, return_inverse=True)
    voxel = voxel.reshape(-1)
    n_voxels = int(voxel.max()) + 1
    count = np.bincount(voxel, minlength=n_voxels).astype(np.float64)
    down = np.empty((n_voxels, 3))
    for k in range(3):
        down[:, k] = np.bincount(voxel, weights=rows[k], minlength=n_voxels) / count
    return down[np.lexsort(down.T[::-1])]


@pytest.mark.parametrize("case", ["scan", "ties_in_x", "sparse_grid"])
def test_voxel_downsample_equals_the_plain_formula(case: str) -> None:
    rng = np.random.default_rng(11)
    if case == "scan":
        rows = rng.uniform(-15.0, 15.0, (3, 200_000)) + np.array([[3e5], [5e6], [100.0]])
    elif case == "ties_in_x":
        # Points on a lattice: many voxels share a centroid x (the lexsort fallback).
        rows = rng.integers(0, 40, (3, 50_000)).astype(np.float64) * 0.1 + 0.05
    else:
        # A grid of more than _DENSE_VOXELS cells (the sorted path), the int32 indices still.
        rows = rng.uniform(0.0, 1.0, (3, 20_000)) * np.array([[400.0], [400.0], [20.0]])
    got = _voxel_downsample(np.ascontiguousarray(rows), 0.1)
    want = _voxel_downsample_reference(rows, 0.1)
    assert got.shape == want.shape
    assert np.array_equal(got, want)


def test_truncated_rows_equal_floor_as_int64() -> None:
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.uniform(0.0, 1e6, 10_000), [0.0, 0.5, 1.0, 2.0 - 1e-12, 2**31 - 2.0]])
    assert _truncated_rows(values, 2**31 - 2).dtype == np.int32
    assert np.array_equal(_truncated_rows(values, 2**31 - 2), np.floor(values).astype(np.int64))
    big = np.array([0.0, 3.5, 2.0**40 + 0.25])
    assert _truncated_rows(big, 2**40 + 1).dtype == np.int64
    assert np.array_equal(_truncated_rows(big, 2**40 + 1), np.floor(big).astype(np.int64))


def _hull_reference(st_rows: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, float]:
    cand = np.ascontiguousarray(np.compress(candidates, st_rows, axis=1).T)
    hull = ConvexHull(cand)
    return cand[hull.vertices], float(hull.volume)


def _point_sets() -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    rect = rng.uniform((-4.0, -1.5), (4.0, 1.5), (30_000, 2))
    rect_with_hole = rect[np.hypot(rect[:, 0], rect[:, 1]) > 1.0]
    disc = rng.normal(size=(20_000, 2))
    disc = disc / np.hypot(disc[:, 0], disc[:, 1])[:, None] * np.sqrt(rng.uniform(0, 1, (20_000, 1))) * 3.0
    lattice = np.stack(np.meshgrid(np.arange(60) * 0.05, np.arange(30) * 0.05), axis=-1).reshape(-1, 2)
    tilted = rect @ np.array([[np.cos(0.3), np.sin(0.3)], [-np.sin(0.3), np.cos(0.3)]]) + (12.0, -7.0)
    triangle = rng.uniform(0, 1, (5_000, 2))
    triangle = triangle[triangle.sum(axis=1) < 1.0]
    few = rng.uniform(-1, 1, (10, 2))
    return [rect, rect_with_hole, disc, lattice, tilted, triangle, few]


@pytest.mark.parametrize("k", range(7))
def test_hull_equals_qhull_on_every_candidate(k: int) -> None:
    """The same vertices in the same order and the same area as Qhull on all candidates, with the
    candidates of a grid rim and without."""
    pts = _point_sets()[k]
    st_rows = np.ascontiguousarray(pts.T)
    rng = np.random.default_rng(k)
    for candidates in (np.ones(len(pts), dtype=bool), rng.uniform(size=len(pts)) < 0.7):
        hull, area = _hull_2d(st_rows, candidates)
        want_hull, want_area = _hull_reference(st_rows, candidates)
        assert np.array_equal(hull, want_hull)
        assert area == want_area


def test_extreme_polygon_keeps_every_hull_point() -> None:
    """No point on the hull (vertices, points on its edges) is screened out; most inner ones are."""
    for pts in _point_sets():
        keep = _outside_extreme_polygon(np.ascontiguousarray(pts.T))
        vertices = ConvexHull(pts).vertices
        assert keep[vertices].all()
        if len(pts) > 1000:
            assert keep.mean() < 0.2
    square = np.stack(np.meshgrid(np.arange(11.0), np.arange(11.0)), axis=-1).reshape(-1, 2)  # edges full of points
    keep = _outside_extreme_polygon(np.ascontiguousarray(square.T))
    on_edge = (square == 0).any(axis=1) | (square == 10).any(axis=1)
    assert keep[on_edge].all() and not keep[~on_edge].any()
    line = np.stack([np.arange(100.0), 2.0 * np.arange(100.0)])  # degenerate: everything kept
    assert _outside_extreme_polygon(line).all()


def test_scatter_within_and_votes_equal_the_plain_formulas() -> None:
    rng = np.random.default_rng(8)
    X = rng.normal(size=(3, 77_777)) * np.array([[3.0], [2.0], [0.01]])
    want = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            want[i, j] = np.sum(X[i] * X[j])
    assert np.array_equal(_scatter(X), want)

    rows = rng.uniform(-10, 10, (3, 50_000))
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    assert np.array_equal(_within(n, 1.25, rows, 0.03), np.abs(n @ rows - 1.25) < 0.03)

    pts = rng.uniform(-5, 5, (2048, 3))
    normals = rng.normal(size=(256, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    offsets = rng.uniform(-3, 3, 256)
    want_votes = (np.abs(pts @ normals.T - offsets) < 0.5).sum(axis=0)
    assert np.array_equal(_votes(pts @ normals.T, offsets, 0.5), want_votes)


def test_plane_covariance_equals_the_plain_sums() -> None:
    rng = np.random.default_rng(9)
    st = rng.uniform(-2, 2, (40_000, 2))
    st -= st.mean(axis=0)
    r = rng.normal(0, 0.005, 40_000)
    centroid = np.array([1.0, -3.0, 2.0])
    basis = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    s, t = np.ascontiguousarray(st[:, 0]), np.ascontiguousarray(st[:, 1])
    w = r * r
    meat = np.array([[np.sum(w * s * s), np.sum(w * s * t), -np.sum(w * s)],
                     [np.sum(w * s * t), np.sum(w * t * t), -np.sum(w * t)],
                     [-np.sum(w * s), -np.sum(w * t), w.sum()]])
    N_inv = 1.0 / np.array([np.sum(s * s), np.sum(t * t), float(len(r))])
    cov_c = N_inv[:, None] * meat * N_inv[None, :] * (len(r) / (len(r) - 3))
    cov_c[0, 0] += 1e-8
    cov_c[1, 1] += 1e-8
    cov_c[2, 2] += 4e-8
    J = np.eye(3)
    J[2, 0], J[2, 1] = basis[0] @ centroid, basis[1] @ centroid
    got = plane_covariance(st, r, centroid, basis, 1e-4, 2e-4)
    assert np.array_equal(got, J @ cov_c @ J.T)


def _split_reference(rows: np.ndarray, normal: np.ndarray, config: PlanesConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """The patch split as written before: floor as int64, sizes and members from every point's label."""
    st = tangent_basis(normal) @ rows
    st -= st.min(axis=1)[:, None]
    ij = np.floor(st / config.patch_cell_m).astype(np.int64)
    shape = (int(ij[0].max()) + 1, int(ij[1].max()) + 1)
    flat = ij[0] * shape[1] + ij[1]
    occupancy = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape)
    grid, n_labels = ndimage.label(occupancy >= config.patch_min_cell_points, structure=np.ones((3, 3)))
    point_label = grid.reshape(-1)[flat]
    sizes = np.bincount(point_label, minlength=n_labels + 1)
    sizes[0] = 0
    out = []
    for lab in np.argsort(-sizes, kind="stable"):
        if sizes[lab] < config.min_points:
            break
        idx = np.flatnonzero(point_label == lab)
        out.append((idx, flat[idx]))
    return out


@pytest.mark.parametrize("layout", ["one_patch", "door", "stray_points"])
def test_split_patches_equal_the_plain_formula(layout: str) -> None:
    rng = np.random.default_rng(21)
    config = PlanesConfig()
    st = rng.uniform((0.0, 0.0), (6.0, 2.5), (40_000, 2))
    if layout == "door":
        st = st[np.abs(st[:, 0] - 3.0) > 0.6]  # two patches and a sliver above nothing
    elif layout == "stray_points":
        st = np.concatenate([st, rng.uniform((-3.0, -3.0), (9.0, 5.0), (300, 2))])  # sparse cells
    normal = np.array([0.0, 0.6, 0.8])
    basis = tangent_basis(normal)
    rows = np.ascontiguousarray((st @ basis + 4.0 * normal + rng.normal(0, 0.005, (len(st), 1)) * normal).T)
    got = _split_patches(rows, normal, config)
    want = _split_reference(rows, normal, config)
    assert len(got) == len(want) >= 1
    for patch, (idx, cell) in zip(got, want, strict=True):
        assert np.array_equal(patch.index, idx)
        assert np.array_equal(patch.cell, cell)
