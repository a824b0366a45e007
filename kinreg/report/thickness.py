"""Plane thickness per cell: how crisp the cloud is, without ground truth.

The cloud is cut into cubes of ``cell_m`` on an absolute grid (multiples of ``cell_m`` in the
cloud's frame). Each cell keeps the first and second moments of its points; at the end a cell is
*planar* when its points spread in two directions and are thin in the third (smallest eigenvalue
of the covariance at most 1/16 of the middle one, at least ``min_points`` points), and its
*thickness* is the square root of the smallest eigenvalue. A wall seen twice with a drift between
the two passes is thicker than the same wall corrected; the median ratio after/before over the
cells planar in both clouds is the key figure (below 1: the correction made the cloud crisper).
Memory: 80 bytes per occupied cell.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import FloatArray

_BITS = 21  # per axis in the cell key: 2^21 cells (2,097 km at 1 m) from the grid's origin
PLANAR_RATIO = 1.0 / 16.0  # smallest / middle eigenvalue: thickness at most a quarter of the spread
MIN_SPREAD_M = 0.1  # the middle eigenvalue's root: a patch, not a line of points
DENSE_CELLS = 250_000  # cells of the bounding box up to which the sums are one dense array (20 MB)
_BLOCK_POINTS = 1 << 15  # points per block of the dense sums


class CellMoments:
    """Sums of 1, x, y, z, xx, xy, xz, yy, yz, zz per occupied cell, coordinates relative to the
    cell's corner (so that UTM-sized coordinates keep their precision).

    With ``extent`` (the size of the box from ``origin`` that holds every point) and at most
    :data:`DENSE_CELLS` cells in it, the sums live in one dense array (a bincount per chunk, no
    sorting); otherwise they are kept for the occupied cells only, merged chunk by chunk.
    """

    def __init__(self, origin: FloatArray, cell_m: float, extent: FloatArray | None = None) -> None:
        self.origin = np.floor(np.asarray(origin, dtype=np.float64) / cell_m) * cell_m  # on the absolute grid
        self.cell_m = cell_m
        self._keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, 10), dtype=np.float64)
        self._dims: tuple[int, int, int] | None = None
        self._dense: FloatArray | None = None
        if extent is not None:
            top = np.asarray(origin, dtype=np.float64) + np.asarray(extent, dtype=np.float64)
            dims = np.ceil((top - self.origin) / cell_m).astype(np.int64) + 1
            if np.prod(dims) <= DENSE_CELLS:
                self._dims = (int(dims[0]), int(dims[1]), int(dims[2]))
                self._dense = np.zeros((10, int(np.prod(dims))), dtype=np.float64)

    def add(self, xyz: FloatArray) -> None:
        """Add the points ``xyz`` (n, 3)."""
        if self._dense is None:
            self._add(xyz)
            return
        # In blocks whose temporaries stay in the cache: fresh arrays of a whole chunk cost more
        # than the arithmetic (the kernel maps and zeroes every page of every new large array).
        for a in range(0, len(xyz), _BLOCK_POINTS):
            self._add(xyz[a:a + _BLOCK_POINTS])

    def _add(self, xyz: FloatArray) -> None:
        # One coordinate at a time on contiguous columns (numpy's (n, 3) arithmetic and its
        # reductions along the first axis are several times slower), the cell indices as floats
        # (whole numbers, exact) converted to integers once, in the cell key.
        rel = [xyz[:, k] - self.origin[k] for k in range(3)]
        ijk = [np.floor(c / self.cell_m) for c in rel]
        limit = self._dims if self._dims is not None else (1 << _BITS,) * 3
        if len(rel[0]) and any(q.min() < 0 or q.max() >= top for q, top in zip(ijk, limit, strict=True)):
            ok = np.ones(len(rel[0]), dtype=bool)  # rare: test per point
            for q, top in zip(ijk, limit, strict=True):
                ok &= (q >= 0) & (q < top)
            rel, ijk = [c[ok] for c in rel], [q[ok] for q in ijk]
        if len(rel[0]) == 0:
            return
        x, y, z = (c - q * self.cell_m for c, q in zip(rel, ijk, strict=True))
        weights = (None, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z)
        if self._dense is not None and self._dims is not None:
            flat_f = ijk[0] * self._dims[1]
            flat_f += ijk[1]
            flat_f *= self._dims[2]
            flat_f += ijk[2]
            flat = flat_f.astype(np.int64)  # below DENSE_CELLS: exact in float64
            n = self._dense.shape[1]
            for row, w in zip(self._dense, weights, strict=True):
                row += np.bincount(flat, weights=w, minlength=n)
            return
        i, j, k = (q.astype(np.int64) for q in ijk)
        key = (i << (2 * _BITS)) | (j << _BITS) | k
        cells, inverse = np.unique(key, return_inverse=True)
        m = len(cells)
        sums = np.column_stack([np.bincount(inverse, weights=w, minlength=m).astype(np.float64) for w in weights])
        self._merge(cells, sums)

    def _merge(self, cells: NDArray[np.int64], sums: FloatArray) -> None:
        if len(self._keys) == 0:
            self._keys, self._sums = cells, sums
            return
        keys = np.union1d(self._keys, cells)
        merged = np.zeros((len(keys), 10))
        merged[np.searchsorted(keys, self._keys)] += self._sums
        merged[np.searchsorted(keys, cells)] += sums
        self._keys, self._sums = keys, merged

    @property
    def keys(self) -> NDArray[np.int64]:
        """Packed keys of the occupied cells (sorted), relative to ``origin``."""
        self._to_sparse()
        return self._keys

    @property
    def sums(self) -> FloatArray:
        """(k, 10) moments of the occupied cells, in the order of :attr:`keys`."""
        self._to_sparse()
        return self._sums

    def _to_sparse(self) -> None:
        if self._dense is None or self._dims is None:
            return
        occupied = np.flatnonzero(self._dense[0] > 0)
        i, rest = np.divmod(occupied, self._dims[1] * self._dims[2])
        j, k = np.divmod(rest, self._dims[2])
        self._merge((i << (2 * _BITS)) | (j << _BITS) | k, self._dense[:, occupied].T.copy())
        self._dense[:] = 0.0

    def cell_indices(self) -> NDArray[np.int64]:
        """(k, 3) absolute integer cell indices (floor(x / cell_m), ...) of the occupied cells."""
        mask = (1 << _BITS) - 1
        rel = np.column_stack([self.keys >> (2 * _BITS), (self.keys >> _BITS) & mask, self.keys & mask])
        return rel + np.round(self.origin / self.cell_m).astype(np.int64)

    def thickness(self, min_points: int) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Per occupied cell: the thickness [m] (root of the smallest covariance eigenvalue) and
        whether the cell is planar."""
        n = self.sums[:, 0]
        safe = np.maximum(n, 1.0)
        mean = self.sums[:, 1:4] / safe[:, None]
        xx, xy, xz, yy, yz, zz = (self.sums[:, k] / safe for k in range(4, 10))
        cov = np.empty((len(n), 3, 3))
        mx, my, mz = mean[:, 0], mean[:, 1], mean[:, 2]
        cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2] = xx - mx * mx, xy - mx * my, xz - mx * mz
        cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2] = yy - my * my, yz - my * mz, zz - mz * mz
        cov[:, 1, 0], cov[:, 2, 0], cov[:, 2, 1] = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
        eig = np.clip(np.linalg.eigvalsh(cov), 0.0, None) if len(n) else np.zeros((0, 3))
        planar = (n >= min_points) & (eig[:, 1] >= MIN_SPREAD_M**2) & (eig[:, 0] <= PLANAR_RATIO * eig[:, 1])
        return np.sqrt(eig[:, 0]), planar


@dataclasses.dataclass(frozen=True)
class ThicknessResult:
    """Planar cells of both clouds and the figures of :func:`compare`."""

    cells_before: NDArray[np.int64]  # (k, 3) absolute cell indices of planar cells
    thickness_before_m: FloatArray
    cells_after: NDArray[np.int64]
    thickness_after_m: FloatArray
    ratio: FloatArray  # after / before, over the cells planar in both
    figures: dict[str, Any]


def compare(before: CellMoments, after: CellMoments, min_points: int) -> ThicknessResult:
    """Thickness of the planar cells before and after, and the median ratio after/before over the
    cells planar in both (the key figure; NaN without such cells)."""
    t_before, planar_before = before.thickness(min_points)
    t_after, planar_after = after.thickness(min_points)
    cells_b, cells_a = before.cell_indices()[planar_before], after.cell_indices()[planar_after]
    tb, ta = t_before[planar_before], t_after[planar_after]
    common, ib, ia = np.intersect1d(before.keys[planar_before] + _shift(before, after), after.keys[planar_after],
                                    return_indices=True)
    ratio = ta[ia] / np.maximum(tb[ib], 1e-9)

    def median_mm(v: FloatArray) -> float:
        return float(np.median(v) * 1000.0) if len(v) else float("nan")

    figures = {
        "cell_m": before.cell_m,
        "min_points": min_points,
        "n_cells_before": len(before.keys),
        "n_cells_after": len(after.keys),
        "n_planar_before": int(planar_before.sum()),
        "n_planar_after": int(planar_after.sum()),
        "n_planar_both": len(common),
        "median_before_mm": median_mm(tb[ib]),
        "median_after_mm": median_mm(ta[ia]),
        "median_ratio_after_before": float(np.median(ratio)) if len(ratio) else float("nan"),
        "share_thinner_after": float(np.mean(ratio < 1.0)) if len(ratio) else float("nan"),
    }
    return ThicknessResult(cells_b, tb, cells_a, ta, ratio, figures)


def _shift(before: CellMoments, after: CellMoments) -> int:
    """Key offset between two grids with different origins (0 when they share one)."""
    d = np.round((before.origin - after.origin) / before.cell_m).astype(np.int64)
    return int((d[0] << (2 * _BITS)) + (d[1] << _BITS) + d[2])


def column_map(cells: NDArray[np.int64], thickness_m: FloatArray, i0: int, j1: int, width: int,
               height: int) -> FloatArray:
    """(height, width) map of the median thickness [m] of the planar cells in each vertical column
    (NaN where none; the median, not the largest: a cube that holds one face of a wall and a little
    of the other is thick before and after, and would mark every wall); column (i, j) goes to row
    ``j1 - j``, column ``i - i0`` (north up)."""
    out = np.full((height, width), np.nan)
    if len(cells) == 0:
        return out
    col, row = cells[:, 0] - i0, j1 - cells[:, 1]
    ok = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    flat = row[ok] * width + col[ok]
    values = thickness_m[ok]
    order = np.lexsort((values, flat))
    flat, values = flat[order], values[order]
    starts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]])
    ends = np.r_[starts[1:], len(flat)]
    out.reshape(-1)[flat[starts]] = [np.median(values[a:b]) for a, b in zip(starts, ends, strict=True)]
    return out
