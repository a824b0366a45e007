"""Plane detection in one scan (METHOD.md section 2, step 5).

Every scan (static or quasi-static) is searched for planar patches in its own frame:

1. **Downsample** the finite points on a voxel grid (``voxel_m``) so that the search
   sees every surface with about the same weight, whatever its range.
2. **RANSAC** on the downsampled copy, one plane per round, inliers removed after each round.
   Hypotheses are the planes of small cells (``ransac_cell_m``), each found by a small
   three-point RANSAC inside the cell and refitted by least squares, not planes through three
   points drawn from the whole scan: almost every cell of a building lies on some plane, so a
   few hundred hypotheses per round (``ransac_iterations``) find even small planes. They are
   scored on a random sample of the remaining points (``ransac_sample_points``), the best few on
   all of them, and the winner is refined by least squares (locally optimised RANSAC). A winner
   counts only if enough of its inliers lie in well-filled cells of a grid in the plane: a
   surface fills its cells, stray points that line up by chance do not. The search stops at
   ``max_planes`` planes or after a few rejected winners in a row.
   A RANSAC of planes through three points scored on every point (open3d's ``segment_plane``)
   is not used: it takes seconds per scan of twenty planes, against a budget of about 1 s.
3. **Assign** every full-resolution point to the nearest plane within ``refit_distance_m``;
   refit every plane by least squares and re-select its points around the refitted plane (a
   band around a slightly tilted plane would cut one side's noise tail). A point within the band
   of two crossing planes (the strip along a wall-floor edge) belongs to neither: it would pull
   the plane it is not on, and along a door's threshold it would bridge the opening. Nor do the
   band points of a cell of the plane (5 cm) through which the scan's points go on beyond the
   band (more than the noise tail explains, :func:`_flat_cells`): a door's jamb and soffit or a
   window's reveal is too small to be a plane of its own, and its first 3 cm would pull the wall
   into itself (by 2 mm seen from 0.2 m in front of a door, 5 mm in a door passage's window).
4. **Split** each plane's inliers into connected patches on a 2D occupancy grid in the plane
   (``patch_cell_m``, 8-connectivity; cells with fewer than ``patch_min_cell_points`` points do
   not connect): the wall in front of a door and the wall behind it are two patches. Patches
   with fewer than ``min_points`` points or a convex hull smaller than ``min_area_m2`` are
   dropped (``area_m2`` is the hull's area: it is what matching compares extents with).
5. **Refit** each patch: least squares, then once more without the points beyond three robust
   sigmas (a neighbouring surface, outliers); then the covariance and the convex hull.

The normal points towards the scan origin: ``n . (0 - centroid) > 0``, so ``d < 0``. For a
quasi-static scan the origin is the virtual scanner centre; a surface seen only from a part of
the window on its other side (walking through a door: the wall's far face, seen from the room
before the door) is turned towards the sensor that saw it once the sensor's positions are known
(:func:`facing_the_sensor`), so that the two faces of a wall keep opposite normals. Planes are
numbered by decreasing inlier count. The result depends only on the points and the configuration (the seed
included), not on timing or threads.

Covariance (:func:`plane_covariance`). With the centroid ``c``, the scatter-matrix eigenvectors
``u, v, n`` (eigenvalues ``l_u >= l_v >= l_n``) and in-plane coordinates ``s = u.(p-c)``,
``t = v.(p-c)``, the residual of point ``p`` under a perturbed plane is
``r = n.(p-c) + a s + b t - e_c``. The design columns ``[s, t, -1]`` are orthogonal, so with equal
noise ``var(a) = s0^2 / l_u``, ``var(b) = s0^2 / l_v``, ``var(e_c) = s0^2 / N``, uncorrelated,
``s0^2 = sum r^2 / (N - 3)``. kinreg uses the heteroscedasticity-consistent (sandwich) form of
the same model, because range noise along the rays is smaller across the plane for grazing
points than for frontal ones. The offset at the scan origin is ``d' = n'.c + e_c``, so
``e = (u.c) a + (v.c) b + e_c``: the tilt sigmas reach ``d`` through the lever arm of the
centroid. Range noise along the rays also biases the tilt slightly (at grazing incidence the
in-plane shift of a point correlates with its residual): of the order of
``sigma^2 sin(2 theta) / (2 var(s))``, about 2e-5-1e-4 rad for 1 cm noise on 1-2 m patches,
below the default ``min_sigma_angle_rad``. The floors ``min_sigma_angle_rad`` and
``min_sigma_d_m`` are added in quadrature (tilts, offset at the centroid): the least-squares
sigmas shrink with the point count (0.03 mm for 1e5 points) while the errors of a real
quasi-static scan are correlated (drift inside the window, incidence-dependent range bias,
uneven walls).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from kinreg.config import PlanesConfig
from kinreg.geometry import FloatArray, tangent_basis
from kinreg.types import Plane, Scan

logger = logging.getLogger(__name__)

IntArray = NDArray[np.int64]

# Hypotheses first scored on the sample; this many of the best are then scored on all points.
_TOP_HYPOTHESES = 4
# Least-squares refinement rounds of the RANSAC winner on the downsampled points.
_REFINE_ROUNDS = 3
# A cell is a plane hypothesis if its thickness (smallest eigenvalue's sigma) is below this share
# of the RANSAC threshold and its second sigma shows a surface, not a line.
_CELL_THICKNESS_SHARE = 0.5
_CELL_MIN_POINTS = 6  # at least, whatever the voxel size
# Three-point planes tried per cell.
_CELL_TRIPLETS = 12
# A cell stops proposing planes once most of its points belong to accepted planes.
_CELL_ALIVE_SHARE = 0.5
# The search ends after this many rejected RANSAC winners in a row (what is left is clutter).
_MAX_FAILED_ROUNDS = 5
# Patch refit: points beyond this many robust sigmas of the fit are dropped (3 sigma keeps
# 99.7 % of Gaussian noise and removes neighbouring surfaces and outliers).
_TRIM_SIGMAS = 3.0
# ... trimmed and refitted until nothing more is trimmed, at most this many times: a sparse line of
# points just behind a small wall (a door's jamb, 50 points 18-30 mm behind the face) turns the
# first fit towards it, and a single trim about that fit kept most of it (a patch tilted 3.9 mrad
# at a sigma of 0.69).
_TRIM_ROUNDS = 10
# A new RANSAC plane this close to an accepted one (angle, offset at its centroid) is the same
# plane found again (a slightly bent wall); its points are removed without a new plane.
_DUPLICATE_ANGLE_RAD = np.radians(2.0)
# Planes at a larger angle than this cross: points in the bands of both are ambiguous.
_CROSSING_ANGLE_RAD = np.radians(10.0)
# The shoulder of a plane's band: points between the band and this many times the band away. A
# flat surface leaves only its noise tail there; a surface that leaves the plane at an edge inside
# the band (a door's jamb or soffit, a window's reveal: too small to be planes of their own) goes
# on through it. Where a cell of the plane (``_SHOULDER_CELL_M``) holds more shoulder points than
# the noise tail explains, its band points are not the plane's: they would pull it into the wall
# by millimetres, one-sidedly (a door passage's scan, 5 mm at 0.4 m).
_SHOULDER_BANDS = 3.0
_SHOULDER_CELL_M = 0.05
# The test: more shoulder points in a cell than the expected tail plus this many of its Poisson
# sigmas, and at least _SHOULDER_MIN_POINTS.
_SHOULDER_SIGMAS = 3.0
_SHOULDER_MIN_POINTS = 4
# The first full-resolution pass collects points within (1 + this) times the band, so that the
# refitted planes (mm away from the RANSAC planes) find all of theirs in the second pass.
_REASSIGN_MARGIN = 0.5
# A cell (``ransac_cell_m``) crossed by a surface holds about (cell / voxel)^2 downsampled points.
# Cells with fewer than this share of that propose no plane, and a RANSAC plane counts only its
# inliers in cells of its own in-plane grid that are that full: a surface fills its cells, a
# slab of stray points does not, nor a strip where a plane crosses a wall (it grows with the
# cell's side, a surface with its square).
_FILLED_CELL_SHARE = 0.4
# A cell proposes a plane with this share: small surfaces (a cupboard side) fill few cells fully.
_HYPOTHESIS_CELL_SHARE = 0.25
# Largest occupancy grid (cells) of one plane's patch split; beyond it the cells are coarsened.
_MAX_GRID_CELLS = 4_000_000
# Voxel grids up to this many cells (a 30 x 30 x 8 m scan at 0.1 m: 7 M) are indexed with a dense
# lookup table (8 bytes a cell); larger ones by sorting the keys.
_DENSE_VOXELS = 16_000_000


def detect_planes(scan: Scan, config: PlanesConfig) -> tuple[Plane, ...]:
    """Planar patches of ``scan``, in its frame, normals towards the scanner.

    ``scan.points_xyz`` (N, 3) float64 metres in the scan frame (scanner at the origin);
    non-finite points are ignored. Returns at most ``config.max_planes`` patches numbered
    ``plane_id = 0..K-1`` by decreasing inlier count, ``scan_id`` copied from the scan; an empty
    tuple for an empty or tiny scan or one without planes. Deterministic for a given
    ``config.seed``.
    """
    points = np.asarray(scan.points_xyz, dtype=np.float64).reshape(-1, 3)
    # A nan or inf coordinate makes the sum non-finite (a matrix-vector product is much faster
    # than a reduction along the short axis); copy only if something must go.
    finite = np.isfinite(points @ np.ones(3))
    if not finite.all():
        points = points[finite]
    if len(points) < max(config.min_points, 3):
        return ()
    # The full-resolution work on coordinate rows (3, N): numpy broadcasts and gathers an (N, 3)
    # array row by row, several times slower than over three long rows.
    rows = np.ascontiguousarray(points.T)
    down = _voxel_downsample(rows, config.voxel_m)
    rng = np.random.default_rng(config.seed)
    models = _ransac_planes(down, config, rng)
    if not models:
        return ()

    # Two assignment passes: the second with the planes refitted on the full-resolution inliers,
    # so that the band is centred on the best plane available (a band around a slightly tilted
    # plane would cut one side's noise tail). The first pass collects a wider band, so the second
    # only needs to re-check each point against its own plane.
    band = config.refit_distance_m
    labels, shoulders = _assign_nearest(points.astype(np.float32), models, band, band * (1 + _REASSIGN_MARGIN),
                                        _SHOULDER_BANDS * band)
    fitted: list[_Fit] = []
    for k, idx in enumerate(_groups(labels, len(models))):
        if len(idx) < config.min_points:
            continue
        group = rows.take(idx, axis=1)
        n, d = models[k]
        inliers = _within(n, d, group, band)
        if np.count_nonzero(inliers) < config.min_points:
            continue
        # np.compress: a boolean index along the second axis is about five times slower.
        n, d = _refit(np.compress(inliers, group, axis=1))
        group = np.compress(_within(n, d, group, band), group, axis=1)
        flat = _flat_cells(group, rows.take(shoulders[k], axis=1), n, d, band)
        if not flat.all():
            group = np.compress(flat, group, axis=1)
            n, d = _refit(group) if group.shape[1] >= 3 else (n, d)
        if group.shape[1] < config.min_points:
            continue
        for patch in _split_patches(group, n, config):
            # A plane of one patch (the most common) needs no copy of its points.
            whole = len(patch.index) == group.shape[1]
            fit = _fit_patch(group if whole else group.take(patch.index, axis=1), patch, config)
            if fit is not None:
                fitted.append(fit)

    # Deterministic numbering: by inlier count, ties by the centroid.
    fitted.sort(key=lambda f: (-f.n_points, *np.round(f.centroid, 9)))
    fitted = fitted[: config.max_planes]
    planes = tuple(f.as_plane(scan.scan_id, i) for i, f in enumerate(fitted))
    logger.debug("scan %d: %d points, %d downsampled, %d planes, %d patches", scan.scan_id, len(points),
                 len(down), len(models), len(planes))
    return planes


# --------------------------------------------------------------------------- least squares


# Reductions over the points, one coordinate at a time: numpy reduces an (N, 3) array along its
# first axis row by row (10-20 times slower than three contiguous passes).


def _column_min(values: NDArray[Any]) -> NDArray[Any]:
    return np.array([values[:, k].min() for k in range(values.shape[1])])


def _column_max(values: NDArray[Any]) -> NDArray[Any]:
    return np.array([values[:, k].max() for k in range(values.shape[1])])


def _column_mean(values: FloatArray) -> FloatArray:
    return np.array([values[:, k].mean() for k in range(values.shape[1])])



def _scatter(X: FloatArray) -> FloatArray:
    """``X @ X.T`` of centred coordinate rows (3, N): six sums of products of contiguous rows
    (BLAS's product of a 3 x N by an N x 3 matrix is about ten times slower; numpy's sums, not
    BLAS's dot, so that the bits do not depend on the number of BLAS threads). The products go
    into one buffer, which stays in the cache (six fresh arrays cost as much again)."""
    S = np.empty((3, 3))
    product = np.empty(X.shape[1])
    for i in range(3):
        for j in range(i, 3):
            S[i, j] = S[j, i] = np.sum(np.multiply(X[i], X[j], out=product))
    return S


def _within(normal: FloatArray, d: float, rows: FloatArray, band_m: float) -> NDArray[np.bool_]:
    """``np.abs(normal @ rows - d) < band_m`` for coordinate rows (3, N), in one buffer."""
    r = normal @ rows
    r -= d
    return np.abs(r, out=r) < band_m


def _median(values: FloatArray) -> float:
    """``np.median`` of a 1D array without NaNs, from one partition (np.median's checks and copies
    cost as much again)."""
    half = len(values) // 2
    if len(values) % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return float((part[half - 1] + part[half]) / 2)


def fit_plane_lsq(points_xyz: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Least-squares plane through ``points_xyz`` (N >= 3, metres).

    Returns ``(centroid (3,), eigenvalues (3,) ascending, eigenvectors (3, 3) as columns)`` of
    the centred scatter matrix ``sum (p - c)(p - c)^T``; the normal is the first column.
    """
    c = _column_mean(points_xyz)
    X = points_xyz - c
    w, V = np.linalg.eigh(X.T @ X)
    return c, w, V


def plane_covariance(
    st_m: FloatArray,
    resid_m: FloatArray,
    centroid_xyz: FloatArray,
    basis_uv: FloatArray,
    min_sigma_angle_rad: float = 0.0,
    min_sigma_d_m: float = 0.0,
) -> FloatArray:
    """3x3 covariance of (tilt towards u [rad], tilt towards v [rad], d [m]) of a fitted plane.

    ``st_m`` (N, 2) are the inliers' coordinates along ``basis_uv`` (2, 3) about the centroid
    ``centroid_xyz`` (scan frame), ``resid_m`` (N,) their residuals; ``basis_uv`` must be the
    scatter-matrix eigenvectors (then ``sum s t = 0``). The covariance of (a, b, e_c) is the
    heteroscedasticity-consistent sandwich ``N^-1 (A^T diag(r^2) A) N^-1 * N / (N - 3)`` with
    the design ``A = [s, t, -1]`` and ``N = A^T A = diag(sum s^2, sum t^2, N)``: range noise along
    the rays makes far, grazing points less noisy across the plane than near ones, and the plain
    ``s^2 N^-1`` then misjudges the offset at the origin by up to 40 %. With equal noise it is
    ``s^2 N^-1`` (module docstring). The floors are added in quadrature to the tilt sigmas and to
    the sigma of the offset at the centroid; then the offset is carried to the scan origin.
    """
    n_pts = len(resid_m)
    w = resid_m * resid_m
    # Contiguous columns and numpy's own sums (not BLAS: same bits for any thread count).
    s, t = np.ascontiguousarray(st_m[:, 0]), np.ascontiguousarray(st_m[:, 1])
    ws, wt = w * s, w * t
    product = np.empty(n_pts)  # one buffer for the products to be summed (it stays in the cache)
    meat = np.empty((3, 3))
    meat[0, 0], meat[1, 1] = np.sum(np.multiply(ws, s, out=product)), np.sum(np.multiply(wt, t, out=product))
    meat[0, 1] = meat[1, 0] = np.sum(np.multiply(ws, t, out=product))
    meat[0, 2] = meat[2, 0] = -np.sum(ws)
    meat[1, 2] = meat[2, 1] = -np.sum(wt)
    meat[2, 2] = w.sum()
    N_inv = 1.0 / np.array([np.sum(np.multiply(s, s, out=product)), np.sum(np.multiply(t, t, out=product)),
                            float(n_pts)])
    cov_c = N_inv[:, None] * meat * N_inv[None, :] * (n_pts / max(n_pts - 3, 1))
    cov_c[0, 0] += min_sigma_angle_rad**2
    cov_c[1, 1] += min_sigma_angle_rad**2
    cov_c[2, 2] += min_sigma_d_m**2
    # d' = n'.c + e_c: a tilt a towards u moves the offset at the origin by a (u.c).
    J = np.eye(3)
    J[2, 0] = basis_uv[0] @ centroid_xyz
    J[2, 1] = basis_uv[1] @ centroid_xyz
    return J @ cov_c @ J.T


class _Fit:
    """A refitted patch before it gets its ids."""

    def __init__(self, normal: FloatArray, d: float, centroid: FloatArray, basis_uv: FloatArray,
                 cov: FloatArray, hull: FloatArray, area: float, n_points: int, rms: float) -> None:
        self.normal, self.d, self.centroid, self.basis_uv = normal, d, centroid, basis_uv
        self.cov, self.hull, self.area, self.n_points, self.rms = cov, hull, area, n_points, rms

    def as_plane(self, scan_id: int, plane_id: int) -> Plane:
        return Plane(scan_id=scan_id, plane_id=plane_id, normal=self.normal, d_m=self.d,
                     centroid_xyz=self.centroid, basis_uv=self.basis_uv, cov_uvd=self.cov,
                     hull_xyz=self.hull, area_m2=self.area, n_points=self.n_points, rms_m=self.rms)


def _fit_patch(rows: FloatArray, patch: _Patch, config: PlanesConfig) -> _Fit | None:
    """Least-squares fit, trimmed at three robust sigmas and refitted until nothing more is trimmed
    (:data:`_TRIM_ROUNDS`); covariance, hull, orientation.

    ``rows`` (3, N) are the patch's points (coordinate rows), ``patch`` its grid cells (for the
    hull).
    """
    c = rows.mean(axis=1)
    X = rows - c[:, None]
    cells = patch.cell
    _, V = np.linalg.eigh(_scatter(X))
    for _ in range(_TRIM_ROUNDS):
        r = np.abs(V[:, 0] @ X)
        keep = r <= max(_TRIM_SIGMAS * 1.4826 * _median(r), 1e-9)
        if keep.all():
            break
        X, cells = np.compress(keep, X, axis=1), cells[keep]
        if X.shape[1] < max(config.min_points, 4):
            return None
        shift = X.mean(axis=1)
        X -= shift[:, None]
        c = c + shift
        _, V = np.linalg.eigh(_scatter(X))
    n = V[:, 0]
    # Towards the scanner at the origin: n . (0 - c) > 0.
    if n @ c > 0:
        n = -n
    u = V[:, 2]
    # Fix the sign of u (eigh's is arbitrary) and make (u, v, n) right-handed.
    if u[np.argmax(np.abs(u))] < 0:
        u = -u
    basis = np.stack([u, np.cross(n, u)])
    proj = np.vstack([basis, n]) @ X  # (3, N): s, t in the plane, residual
    st, r = proj[:2].T, proj[2]
    hull_st, area = _hull_2d(proj[:2], patch.hull_candidates(cells))
    if area < config.min_area_m2:
        return None
    cov = plane_covariance(st, r, c, basis, config.min_sigma_angle_rad, config.min_sigma_d_m)
    hull_xyz = c + hull_st @ basis
    return _Fit(n, float(n @ c), c, basis, cov, hull_xyz, area, X.shape[1], float(np.sqrt(np.mean(r**2))))


def _hull_2d(st_rows: FloatArray, candidates: NDArray[np.bool_]) -> tuple[FloatArray, float]:
    """Convex hull (K, 2) and its area of 2D points (coordinate rows (2, N)); empty if degenerate.
    The vertices run counter-clockwise in (s, t), i.e. seen from the side the normal points to
    (the scanner).

    Only the ``candidates`` can be hull vertices (:meth:`_Patch.hull_candidates`); of those, Qhull
    gets the ones not strictly inside the polygon of the extreme points in eight directions
    (Akl-Toussaint): a rectangle's rim of cells leaves a few hundred points of some 20,000, the
    same hull (Qhull on 20,000 points cost most of a patch's fit).
    """
    cand_rows = np.compress(candidates, st_rows, axis=1)
    cand = np.ascontiguousarray(np.compress(_outside_extreme_polygon(cand_rows), cand_rows, axis=1).T)
    try:
        hull = ConvexHull(cand)
    except (QhullError, ValueError):
        return np.zeros((0, 2)), 0.0
    return cand[hull.vertices], float(hull.volume)


# Directions of the extreme points whose polygon screens hull candidates (counter-clockwise).
_SCREEN_DIRECTIONS = np.array([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)])
# A point counts as inside the screening polygon only this far inside each edge [m]: far above the
# rounding of the test, so that no point on the hull is screened out.
_SCREEN_MARGIN_M = 1e-9


def _outside_extreme_polygon(st_rows: FloatArray) -> NDArray[np.bool_]:
    """Which 2D points (coordinate rows (2, N)) are not strictly inside the convex polygon of
    their extreme points in ``_SCREEN_DIRECTIONS``; all of them if that polygon is degenerate.
    A point strictly inside a polygon of some of the points is no vertex of their convex hull,
    nor on its boundary, so the hull of the returned points is the hull of all."""
    n = st_rows.shape[1]
    if n < 16:
        return np.ones(n, dtype=bool)
    extreme = np.argmax(_SCREEN_DIRECTIONS.T @ st_rows, axis=1)
    # Extreme points in directions sorted by angle run counter-clockwise around the hull.
    extreme = extreme[np.concatenate([[True], extreme[1:] != extreme[:-1]])]
    if len(extreme) > 1 and extreme[0] == extreme[-1]:
        extreme = extreme[:-1]
    if len(extreme) < 3:
        return np.ones(n, dtype=bool)
    corners = st_rows[:, extreme].T  # (K, 2)
    edges = np.roll(corners, -1, axis=0) - corners
    length = np.hypot(edges[:, 0], edges[:, 1])
    if not np.all(length > 0):
        return np.ones(n, dtype=bool)
    # Inward unit normals of the counter-clockwise edges; inside: normal . (p - corner) > margin.
    inward = np.stack([-edges[:, 1], edges[:, 0]], axis=1) / length[:, None]
    depth = inward @ st_rows - np.einsum("kj,kj->k", inward, corners)[:, None]  # (K, N)
    return ~np.all(depth > _SCREEN_MARGIN_M, axis=0)


# --------------------------------------------------------------------------- downsampling, RANSAC


def _voxel_downsample(rows: FloatArray, voxel_m: float) -> FloatArray:
    """Centroids (M, 3) of the occupied voxels of the points ``rows`` (3, N), sorted
    lexicographically.

    The grid starts at the points' lower bound minus half a voxel, and each centroid is the sum
    of its points in their order over their count (as open3d's ``voxel_down_sample`` forms them),
    so that the same points give the same centroids to the bit.
    """
    lower = rows.min(axis=1) - voxel_m * 0.5
    # Non-negative: truncation is the floor. Subtraction and division are monotonic, so the
    # largest index is that of the largest coordinate (no pass over the indices).
    dims = ((rows.max(axis=1) - lower) / voxel_m).astype(np.int64) + 1
    scaled = rows - lower[:, None]
    scaled /= voxel_m
    q = _truncated_rows(scaled, int(dims.max()))
    del scaled
    key = q[0] * dims[1]  # int64 (dims is)
    key += q[1]
    key *= dims[2]
    key += q[2]
    n_cells = int(np.prod(dims))
    if n_cells <= _DENSE_VOXELS:  # a mask over the box instead of a sort
        seen = np.zeros(n_cells, dtype=bool)  # a byte a cell, not a count of eight
        seen[key] = True
        occupied = np.flatnonzero(seen)
        lookup = np.empty(n_cells, dtype=np.int64)
        lookup[occupied] = np.arange(len(occupied))
        voxel = lookup[key]
        n_voxels = len(occupied)
    else:
        _, voxel = np.unique(key, return_inverse=True)
        voxel = voxel.reshape(-1)
        n_voxels = int(voxel.max()) + 1 if len(voxel) else 0
    count = np.bincount(voxel, minlength=n_voxels).astype(np.float64)
    down = np.empty((n_voxels, 3))
    for k in range(3):
        down[:, k] = np.bincount(voxel, weights=rows[k], minlength=n_voxels) / count
    # Lexicographic order; without ties in x it is the order of x, which a plain sort finds
    # several times faster than lexsort's three stable passes.
    order = np.argsort(down[:, 0])
    x = down[order, 0]
    if not np.all(x[1:] > x[:-1]):
        order = np.lexsort(down.T[::-1])
    return down[order]


def _truncated_rows(values: FloatArray, bound: int) -> NDArray[np.signedinteger[Any]]:
    """``values.astype(np.int64)`` of non-negative values below ``bound``: through int32 where
    they fit (a SIMD conversion, about four times faster than numpy's to int64; the same
    truncation); int64 arithmetic on them needs an int64 operand."""
    if bound < 2**31 - 1:
        return values.astype(np.int32)
    return values.astype(np.int64)


def _cell_planes(points: FloatArray, cell_m: float, distance_m: float, min_points: float,
                 rng: np.random.Generator) -> tuple[IntArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Group ``points`` into cubic cells; a robust plane in every cell.

    Each cell tries ``_CELL_TRIPLETS`` planes through three of its points (a small RANSAC, all
    cells at once), keeps the one with the most points within ``distance_m`` and refits it by
    least squares on those: clutter and stray points in a cell do not tilt its plane.
    Returns the cell of every point (M,), the cells' normals (C, 3) and offsets (C,), and which
    cells are planar enough to propose a plane (``min_points`` inliers or more).
    """
    q = np.floor(points / cell_m).astype(np.int64)
    q -= _column_min(q)
    dims = _column_max(q) + 1
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    _, cell, count = np.unique(key, return_inverse=True, return_counts=True)
    cell = cell.reshape(-1)
    n_cells = len(count)
    order = np.argsort(cell, kind="stable")
    start = np.searchsorted(cell[order], np.arange(n_cells))
    # Triplets: three random members of each cell (repeats give degenerate planes, scored 0).
    pick = (rng.random((n_cells, _CELL_TRIPLETS, 3)) * count[:, None, None]).astype(np.int64)
    tri = points[order[start[:, None, None] + pick]]  # (C, T, 3 points, 3)
    nrm = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    length = np.linalg.norm(nrm, axis=2)
    ok = length > 1e-9
    nrm = nrm / np.where(ok, length, 1.0)[:, :, None]
    off = np.einsum("ctj,ctj->ct", nrm, tri[:, :, 0])
    resid = np.abs(np.einsum("ij,itj->it", points, nrm[cell]) - off[cell])  # (M, T)
    within = (resid < distance_m) & ok[cell]
    # Inliers per cell and triplet: one count over (cell, triplet) pairs (exact integers).
    votes = np.bincount((cell[:, None] * _CELL_TRIPLETS + np.arange(_CELL_TRIPLETS))[within],
                        minlength=n_cells * _CELL_TRIPLETS).reshape(n_cells, _CELL_TRIPLETS)
    best = np.argmax(votes, axis=1)
    w = within[np.arange(len(points)), best[cell]].astype(np.float64)
    # Least squares on the best triplet's inliers, all cells at once.
    cnt = np.bincount(cell, w, n_cells)
    safe = np.maximum(cnt, 1.0)
    mean = np.stack([np.bincount(cell, w * points[:, i], n_cells) for i in range(3)], axis=1) / safe[:, None]
    X = points - mean[cell]
    C = np.empty((n_cells, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            C[:, i, j] = C[:, j, i] = np.bincount(cell, w * X[:, i] * X[:, j], n_cells) / safe
    ev, V = np.linalg.eigh(C)
    normals = V[:, :, 0]
    offsets = np.einsum("ij,ij->i", normals, mean)
    thin = np.sqrt(np.maximum(ev[:, 0], 0.0)) < _CELL_THICKNESS_SHARE * distance_m
    wide = np.sqrt(np.maximum(ev[:, 1], 0.0)) > 0.15 * cell_m
    planar = thin & wide & (cnt >= min_points)
    return cell, normals, offsets, planar


def _ransac_planes(down: FloatArray, config: PlanesConfig,
                   rng: np.random.Generator) -> list[tuple[FloatArray, float]]:
    """Planes ``(normal (3,), d)`` found one by one in the downsampled points, largest first."""
    thr = config.distance_m
    # A valid patch has min_points points or covers min_area_m2; its downsampled copy has at least
    # about the smaller of min_points and area / voxel^2 points. Half of that stops the search.
    min_votes = max(10, int(0.5 * min(config.min_points, config.min_area_m2 / config.voxel_m**2)))
    if len(down) < min_votes:
        return []
    full = (config.ransac_cell_m / config.voxel_m) ** 2
    filled = max(_CELL_MIN_POINTS, _FILLED_CELL_SHARE * full)
    cell, hyp_n, hyp_d, valid = _cell_planes(down, config.ransac_cell_m, thr,
                                             max(_CELL_MIN_POINTS, _HYPOTHESIS_CELL_SHARE * full), rng)
    cell_total = np.bincount(cell, minlength=len(hyp_d))
    alive = np.ones(len(down), dtype=bool)
    models: list[tuple[FloatArray, float]] = []
    failed = 0
    for _ in range(3 * config.max_planes):
        if len(models) >= config.max_planes or failed >= _MAX_FAILED_ROUNDS:
            break
        cand = np.flatnonzero(valid)
        alive_idx = np.flatnonzero(alive)
        if len(cand) == 0 or len(alive_idx) < min_votes:
            break
        hyp = rng.choice(cand, size=min(config.ransac_iterations, len(cand)), replace=False)
        sample = alive_idx
        if len(alive_idx) > config.ransac_sample_points:
            sample = rng.choice(alive_idx, size=config.ransac_sample_points, replace=False)
        votes = _votes(down[sample] @ hyp_n[hyp].T, hyp_d[hyp], thr)
        top = hyp[np.argsort(-votes, kind="stable")[:_TOP_HYPOTHESES]]
        rest = down[alive_idx]
        full_votes = _votes(rest @ hyp_n[top].T, hyp_d[top], thr)
        best = int(top[np.argmax(full_votes)])
        n, d = hyp_n[best], float(hyp_d[best])
        inl = np.abs(rest @ n - d) < thr
        for _ in range(_REFINE_ROUNDS):
            if inl.sum() < 3:
                break
            c, _, V = fit_plane_lsq(rest[inl])
            n, d = V[:, 0], float(V[:, 0] @ c)
            inl = np.abs(rest @ n - d) < thr
        n_inl = int(inl.sum())
        support = _dense_support(rest[inl], n, config.ransac_cell_m, filled) if n_inl >= min_votes else 0
        logger.debug("RANSAC round: %d candidate cells, %d inliers, %d in filled cells (need %d)",
                     len(cand), n_inl, support, min_votes)
        if support < min_votes:
            # Too small, or stray points that happen to line up (clutter, outliers): not a
            # surface. The cells on this plane propose no more; the points stay for the planes
            # they may belong to.
            valid[best] = False
            valid &= ~_same_plane(hyp_n, hyp_d, n, d, thr)
            failed += 1
            continue
        failed = 0
        c = _column_mean(rest[inl])
        duplicate = any(abs(float(m @ n)) > np.cos(_DUPLICATE_ANGLE_RAD) and abs(float(m @ c) - dm) < thr
                        for m, dm in models)
        if not duplicate:
            models.append((n, d))
        alive[alive_idx[inl]] = False
        valid[best] = False
        remaining = np.bincount(cell[alive], minlength=len(hyp_d))
        valid &= remaining >= _CELL_ALIVE_SHARE * cell_total
    return models


def _votes(dots: FloatArray, offsets: FloatArray, distance_m: float) -> IntArray:
    """Per column of ``dots`` (points x planes, the points' products with the planes' normals):
    how many points lie within ``distance_m`` of the plane (``offsets`` (K,)); in place."""
    dots -= offsets
    return np.count_nonzero(np.abs(dots, out=dots) < distance_m, axis=0)


def _same_plane(normals: FloatArray, offsets: FloatArray, n: FloatArray, d: float,
                distance_m: float) -> NDArray[np.bool_]:
    """Which planes (K, 3), (K,) (either normal sign) coincide with (n, d)."""
    cos = normals @ n
    return (np.abs(cos) > np.cos(_DUPLICATE_ANGLE_RAD)) & (np.abs(np.sign(cos) * offsets - d) < distance_m)


def _dense_support(points: FloatArray, normal: FloatArray, cell_m: float, filled: float) -> int:
    """How many of a plane's (downsampled) inliers lie in cells of a grid in the plane that hold
    at least ``filled`` of them (see ``_FILLED_CELL_SHARE``)."""
    st = points @ tangent_basis(normal).T
    ij = np.floor(st / cell_m).astype(np.int64)
    ij -= _column_min(ij)
    _, counts = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1], return_counts=True)
    return int(counts[counts >= filled].sum())



# --------------------------------------------------------------------------- full resolution


def _assign_nearest(points32: NDArray[np.float32], models: list[tuple[FloatArray, float]],
                    band_m: float, collect_m: float, shoulder_m: float) -> tuple[IntArray, list[IntArray]]:
    """Index of the nearest plane within ``collect_m`` of every point, ``len(models)`` for none.

    A point within ``band_m`` of two planes that cross (the strip along a wall-floor edge) is
    ambiguous and belongs to neither: it would pull the fit of the plane it is not on, and it
    would bridge a door opening (the floor's edge runs through it) so that the patch split could
    not see the gap. Near-parallel planes (a poster on a wall) just take the nearest.
    float32 is enough to choose the plane (micrometres at 30 m); the fits use float64. The float32
    products go over every point in one call: OpenBLAS gives a row other bits in an array of
    another length, so a pass over nearby points only would move points across the band's edge.
    Also returns, per model, the indices of its points between ``band_m`` and ``shoulder_m`` away
    (its shoulder, :func:`_flat_cells`).
    """
    none = len(models)
    label = np.full(len(points32), none, dtype=np.int64)
    best = np.full(len(points32), np.inf, dtype=np.float32)
    ambiguous = np.zeros(len(points32), dtype=bool)
    shoulders: list[IntArray] = []
    if not models:
        return label, shoulders
    normals = np.array([n for n, _ in models])
    crossing = np.abs(normals @ normals.T) < np.cos(_CROSSING_ANGLE_RAD)
    crossing = np.concatenate([crossing, np.zeros((none, 1), dtype=bool)], axis=1)  # column: no plane
    r = np.empty(len(points32), dtype=np.float32)  # one buffer for every plane's distances
    for k, (n, d) in enumerate(models):
        np.matmul(points32, n.astype(np.float32), out=r)
        r -= np.float32(d)
        np.abs(r, out=r)
        near = np.flatnonzero(r < max(collect_m, shoulder_m))
        r_near = r[near]
        shoulders.append(near[r_near >= band_m])
        inside = r_near < collect_m
        idx, rk = near[inside], r_near[inside]
        best_k = best[idx]
        if k:  # the first plane crosses none before it
            both = (rk < band_m) & (best_k < band_m) & crossing[k, label[idx]]
            ambiguous[idx[both]] = True
        closer = rk < best_k
        idx = idx[closer]
        best[idx] = rk[closer]
        label[idx] = k
    label[ambiguous] = none
    return label, shoulders


def _groups(labels: IntArray, n_groups: int) -> list[IntArray]:
    """Point indices of each label ``0..n_groups-1`` (one sort instead of a pass per label)."""
    # int16 labels make numpy's stable sort a linear-time radix sort.
    small = labels.astype(np.int16)
    order = np.argsort(small, kind="stable")
    bounds = np.searchsorted(small[order], np.arange(n_groups + 1))
    return [order[bounds[k] : bounds[k + 1]] for k in range(n_groups)]


def _refit(rows: FloatArray) -> tuple[FloatArray, float]:
    """Least-squares plane ``(normal, d)`` of the points ``rows`` (3, N; at least three)."""
    c = rows.mean(axis=1)
    _, V = np.linalg.eigh(_scatter(rows - c[:, None]))
    return V[:, 0], float(V[:, 0] @ c)


def _flat_cells(group: FloatArray, shoulder: FloatArray, normal: FloatArray, d: float,
                band_m: float) -> NDArray[np.bool_]:
    """Which of a plane's band points ``group`` (3, N) lie where the surface is the plane: not in a
    cell of the plane (``_SHOULDER_CELL_M``) through which the scan's points go on beyond the band
    (``shoulder`` (3, M): points of the plane's shoulder, re-tested against the refitted plane
    ``normal``, ``d``). A flat surface leaves only its noise tail in the shoulder: with the band's
    RMS as the noise sigma, the expected tail count of a cell is its band count times the tail's
    share of a Gaussian (a jamb's share in the band inflates that sigma a little: the test errs
    towards keeping points)."""
    keep = np.ones(group.shape[1], dtype=bool)
    if shoulder.shape[1] == 0 or group.shape[1] == 0:
        return keep
    r_s = np.abs(normal @ shoulder - d)
    shoulder = np.compress((r_s >= band_m) & (r_s < _SHOULDER_BANDS * band_m), shoulder, axis=1)
    if shoulder.shape[1] < _SHOULDER_MIN_POINTS:
        return keep
    r = normal @ group - d
    sigma = max(float(np.sqrt(np.dot(r, r) / len(r))), 1e-6)  # the band's RMS: enough for a tail
    # Share of a Gaussian's points in the shoulder against its share inside the band.
    inside, outside = (math.erf(band_m / (sigma * math.sqrt(2.0))),
                       math.erf(_SHOULDER_BANDS * band_m / (sigma * math.sqrt(2.0))))
    tail = (outside - inside) / max(inside, 1e-12)
    flat, shape = _plane_cells(tangent_basis(normal) @ np.hstack([group, shoulder]), _SHOULDER_CELL_M)
    flat_g, flat_s = flat[: group.shape[1]], flat[group.shape[1]:]
    n_s = np.bincount(flat_s, minlength=shape[0] * shape[1])
    candidate = n_s >= _SHOULDER_MIN_POINTS
    if not candidate.any():
        return keep
    n_g = np.bincount(flat_g, minlength=shape[0] * shape[1])
    expected = n_g * tail
    rough = candidate & (n_s > expected + _SHOULDER_SIGMAS * np.sqrt(expected))
    if rough.any():
        keep = ~rough[flat_g]
    return keep


def _plane_cells(st: FloatArray, cell_m: float) -> tuple[NDArray[np.signedinteger[Any]], tuple[int, int]]:
    """Cells (flat, row-major) of in-plane coordinates ``st`` (2, N; shifted to their minimum in
    place) on a dense grid of ``cell_m``, and the grid's shape."""
    st -= st.min(axis=1)[:, None]
    extent = st.max(axis=1)
    # A stray far point must not blow up the dense grid: coarsen it instead (very large planes).
    while np.prod(extent / cell_m + 1) > _MAX_GRID_CELLS:
        cell_m *= 2.0
    # Non-negative: truncation is the floor.
    ij = _truncated_rows(st / cell_m, int(extent.max() / cell_m) + 1)
    shape = (int(ij[0].max()) + 1, int(ij[1].max()) + 1)
    return ij[0] * shape[1] + ij[1], shape


class _Patch:
    """A connected patch of one plane's points: their indices and grid cells (flat, row-major)."""

    def __init__(self, index: IntArray, cell: IntArray, grid_shape: tuple[int, int]) -> None:
        self.index, self.cell, self.grid_shape = index, cell, grid_shape

    def hull_candidates(self, cell: IntArray) -> NDArray[np.bool_]:
        """Which points (given by their cells) can be vertices of the convex hull.

        A point whose cell has all of its 5 x 5 neighbourhood occupied is not: in any direction
        a neighbour two cells away holds a point farther out. Exact, and it leaves Qhull only
        the rim of a large patch.
        """
        occupied = np.bincount(cell, minlength=self.grid_shape[0] * self.grid_shape[1]) > 0
        interior = ndimage.binary_erosion(occupied.reshape(self.grid_shape), np.ones((5, 5), dtype=bool),
                                          border_value=0)
        return ~interior.reshape(-1)[cell]


def _split_patches(rows: FloatArray, normal: FloatArray, config: PlanesConfig) -> list[_Patch]:
    """The connected patches of one plane's points ``rows`` (3, N) (occupancy grid in the plane,
    8-connected).

    Cells with fewer than ``patch_min_cell_points`` points neither join nor connect patches.
    Patches with fewer than ``min_points`` points are left out; ordered by size, largest first.
    """
    st = tangent_basis(normal) @ rows  # (2, N); any in-plane basis will do for the grid
    flat, shape = _plane_cells(st, config.patch_cell_m)
    occupancy = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape)
    grid, n_labels = ndimage.label(occupancy >= config.patch_min_cell_points, structure=np.ones((3, 3)))
    # Points per patch from the cells' counts (a pass over the cells, not the points).
    sizes = np.bincount(grid.reshape(-1), weights=occupancy.reshape(-1), minlength=n_labels + 1).astype(np.int64)
    sizes[0] = 0
    patches: list[_Patch] = []
    point_label = None
    for lab in np.argsort(-sizes, kind="stable"):
        if sizes[lab] < config.min_points:
            break
        if sizes[lab] == rows.shape[1]:  # every point in one patch (the most common)
            patches.append(_Patch(np.arange(rows.shape[1]), flat, shape))
            break
        if point_label is None:
            point_label = grid.reshape(-1)[flat]
        idx = np.flatnonzero(point_label == lab)
        patches.append(_Patch(idx, flat[idx], shape))
    return patches


def facing_the_sensor(planes: tuple[Plane, ...], band_m: float) -> tuple[Plane, ...]:
    """The planes with each normal towards the sensor that saw it (METHOD.md section 4): where a
    plane's mean sensor position (``sensor_xyz``, the mean of the sensor's positions at its points'
    times) lies more than ``band_m`` behind it, the plane is turned round. Detection orients a
    plane towards the scan origin, the sensor at the window's centre time; a window that passes
    through a door sees the wall's face on the side it came from, the origin is beyond the wall,
    and the two faces of the wall (its thickness apart) would be one direction and match each
    other. Every point is seen from the plane's visible side, so their mean sensor position is on
    it too; within the band of the plane, the origin keeps the decision.

    Turning a plane round keeps it right-handed: ``n' = -n``, ``v' = -v``, ``d' = -d``; a
    perturbation (a, b, e) of the plane is (-a, b, -e) of the turned one, and the time and sensor
    slopes along v change sign."""
    out = []
    flip = np.diag([-1.0, 1.0, -1.0])
    for p in planes:
        if p.sensor_xyz is None or not float(p.normal @ p.sensor_xyz) - p.d_m < -band_m:
            out.append(p)
            continue
        slope_u, slope_v = p.t_slope_s_per_m
        out.append(replace(
            p, normal=-p.normal, d_m=-p.d_m, basis_uv=np.array([p.basis_uv[0], -p.basis_uv[1]]),
            cov_uvd=flip @ p.cov_uvd @ flip, t_slope_s_per_m=(slope_u, -slope_v),
            sensor_slope=None if p.sensor_slope is None else p.sensor_slope * np.array([1.0, -1.0])))
    return tuple(out)
