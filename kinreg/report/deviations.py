"""Kinematic vs static: signed distances of the kinematic points to the static cloud's local planes.

M3C2-like, simplified: the static cloud (``--static``, its registered scans in the object frame)
is cut into cubes of ``cell_m``; every cube whose points form a plane is a core point with a
normal (oriented towards the static station nearest to it, METHOD.md section 4). A kinematic point
in a planar cube gets the signed distance ``n . (p - c)`` along the static normal (``c``: the
cube's centroid); points farther than ``max_distance_m`` are not counted (another surface). The
distances are gathered before and after the correction while ``corrected.laz`` is written, as a
histogram of 0.5 mm bins, and summarised as mean, RMS, and the share within 2 and 3 times the
kinematic noise (the median plane thickness of the corrected cloud, :mod:`kinreg.report.thickness`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import FloatArray
from kinreg.report.thickness import _BITS, PLANAR_RATIO, CellMoments

BIN_MM = 0.5


class StaticPlanes:
    """The planar cubes of a static cloud: sorted keys, unit normals (k, 3), centroids (k, 3)."""

    def __init__(self, origin: FloatArray, cell_m: float, keys: NDArray[np.int64], normals: FloatArray,
                 centroids: FloatArray) -> None:
        self.origin, self.cell_m = origin, cell_m
        self.keys, self.normals, self.centroids = keys, normals, centroids

    @classmethod
    def from_scans(cls, scans: Iterable[tuple[FloatArray, FloatArray]], origin: FloatArray, cell_m: float = 0.5,
                   min_points: int = 30) -> StaticPlanes:
        """From ``(points_obj (n, 3), station_xyz (3,))`` per static scan (object frame)."""
        moments = CellMoments(origin, cell_m)
        stations = []
        for points, station in scans:
            moments.add(points)
            stations.append(np.asarray(station, dtype=np.float64))
        sums = moments.sums
        n = np.maximum(sums[:, 0], 1.0)
        mean = sums[:, 1:4] / n[:, None]
        second = np.empty((len(n), 3, 3))
        for (a, b), k in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(4, 10), strict=True):
            second[:, a, b] = second[:, b, a] = sums[:, k] / n - mean[:, a] * mean[:, b]
        values, vectors = np.linalg.eigh(second) if len(n) else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
        planar = (sums[:, 0] >= min_points) & (values[:, 0] <= PLANAR_RATIO * values[:, 1]) & (values[:, 1] > 0)
        if planar.any():  # clean planes only: a cube that also holds the foot of a wall is thicker
            thickness = np.sqrt(np.clip(values[:, 0], 0.0, None))
            planar &= thickness <= 2.0 * np.median(thickness[planar])
        normals = vectors[planar, :, 0]
        indices = moments.cell_indices()[planar]
        centroids = indices * cell_m + mean[planar]
        if stations and len(normals):
            where = np.array(stations)
            nearest = np.argmin(np.linalg.norm(centroids[:, None, :] - where[None, :, :], axis=2), axis=1)
            flip = np.einsum("ij,ij->i", where[nearest] - centroids, normals) < 0
            normals[flip] *= -1.0
        return cls(moments.origin, cell_m, moments.keys[planar], normals, centroids)

    def distances(self, xyz: FloatArray, max_distance_m: float) -> FloatArray:
        """Signed distances [m] of the points in planar cubes within ``max_distance_m`` (others dropped)."""
        if len(self.keys) == 0 or len(xyz) == 0:
            return np.zeros(0)
        ijk = np.floor((xyz - self.origin) / self.cell_m).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < 1 << _BITS), axis=1)
        key = (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]
        at = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        ok &= self.keys[at] == key
        at, points = at[ok], xyz[ok]
        d = np.einsum("ij,ij->i", points - self.centroids[at], self.normals[at])
        return d[np.abs(d) <= max_distance_m]


class Deviations:
    """Histograms of the signed distances before and after (see the module)."""

    def __init__(self, planes: StaticPlanes, max_distance_m: float = 0.05, stride: int = 4) -> None:
        self.planes, self.max_distance_m, self.stride = planes, max_distance_m, stride
        n_bins = round(2 * max_distance_m * 1000 / BIN_MM)
        self.edges_mm = np.linspace(-max_distance_m * 1000, max_distance_m * 1000, n_bins + 1)
        self.hist = {"before": np.zeros(n_bins, dtype=np.int64), "after": np.zeros(n_bins, dtype=np.int64)}
        self.sums = {"before": np.zeros(3), "after": np.zeros(3)}  # n, sum d, sum d^2 [mm]

    def add(self, which: str, xyz: FloatArray) -> None:
        d_mm = self.planes.distances(xyz[:: self.stride], self.max_distance_m) * 1000.0
        self.hist[which] += np.histogram(d_mm, self.edges_mm)[0]
        self.sums[which] += (len(d_mm), d_mm.sum(), (d_mm**2).sum())

    def figures(self, noise_mm: float) -> dict[str, Any]:
        """Mean, RMS, share within 2 and 3 times ``noise_mm``, and the histograms, before and after."""
        centres = 0.5 * (self.edges_mm[1:] + self.edges_mm[:-1])
        out: dict[str, Any] = {"n_core_points": len(self.planes.keys), "cell_m": self.planes.cell_m,
                               "max_distance_mm": self.max_distance_m * 1000.0, "stride": self.stride,
                               "noise_mm": noise_mm, "bin_mm": BIN_MM, "edges_mm": [float(self.edges_mm[0]),
                                                                                    float(self.edges_mm[-1])]}
        for which in ("before", "after"):
            n, s, s2 = self.sums[which]
            hist = self.hist[which]
            within = {f"share_within_{k}_noise": float(hist[np.abs(centres) <= k * noise_mm].sum() / n) if n else None
                      for k in (2, 3)}
            out[which] = {"n": int(n), "mean_mm": s / n if n else None,
                          "rms_mm": float(np.sqrt(s2 / n)) if n else None, **within, "histogram": hist.tolist()}
        return out


def static_planes_from_e57(path: str | Path, origin: FloatArray, cell_m: float = 0.5) -> StaticPlanes:
    """:class:`StaticPlanes` of the registered static scans of an E57 file (poses required)."""
    from kinreg.io.e57 import iter_e57_scans

    def scans() -> Iterable[tuple[FloatArray, FloatArray]]:
        for scan in iter_e57_scans(path, require_pose=True):
            yield scan.T_obj_scan.apply(scan.points_xyz), scan.T_obj_scan.t_xyz

    return StaticPlanes.from_scans(scans(), origin, cell_m)
