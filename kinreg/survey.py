"""What is known in the object frame before a run: reference planes (a building's, a calibration
field's) and surveyed control points, as the estimation uses them.

The readers of their files are :mod:`kinreg.io.reference_planes` and :mod:`kinreg.io.control`;
the types live here, below both ``io`` and ``estimate``, so that the estimation never imports a
reader.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kinreg.geometry import FloatArray, Pose


@dataclass(frozen=True, eq=False)
class PlaneExtent:
    """Where a reference plane's physical plate lies: a polygon in the plane.

    ``origin_m`` (3,) a point on the plane, ``axis_u``/``axis_v`` (3,) orthonormal in-plane axes,
    ``polygon_uv`` (M, 2) the corners in those axes (metres, M >= 3, in order).
    """

    origin_m: FloatArray
    axis_u: FloatArray
    axis_v: FloatArray
    polygon_uv: FloatArray

    @property
    def area_m2(self) -> float:
        x, y = self.polygon_uv[:, 0], self.polygon_uv[:, 1]
        return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))

    def to_uv(self, points_xyz: FloatArray) -> FloatArray:
        """In-plane coordinates ``(N, 2)`` of object-frame points ``(N, 3)`` (projected)."""
        d = np.asarray(points_xyz, dtype=np.float64) - self.origin_m
        return np.stack([d @ self.axis_u, d @ self.axis_v], axis=-1)

    def contains(self, points_xyz: FloatArray, margin_m: float = 0.0) -> np.ndarray:
        """Which points ``(N, 3)`` project into the polygon grown by ``margin_m`` (>= 0).

        >>> e = PlaneExtent(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
        ...                 np.array([[-1.0, -1], [1, -1], [1, 1], [-1, 1]]))
        >>> e.contains(np.array([[0.5, 0.5, 3.0], [1.05, 0.0, 0.0]]), margin_m=0.1).tolist()
        [True, True]
        """
        uv = self.to_uv(points_xyz)
        return _inside_polygon(uv, self.polygon_uv, margin_m)


def _inside_polygon(uv: FloatArray, poly: FloatArray, margin_m: float) -> np.ndarray:
    # Crossing number, then (for a margin) the distance to every edge.
    x, y = uv[:, 0], uv[:, 1]
    inside = np.zeros(len(uv), dtype=bool)
    a, b = poly, np.roll(poly, -1, axis=0)
    for (xa, ya), (xb, yb) in zip(a, b, strict=True):
        crosses = (ya > y) != (yb > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = xa + (y - ya) * (xb - xa) / (yb - ya)
        inside ^= crosses & (x < x_cross)
    if margin_m > 0.0:
        for pa, pb in zip(a, b, strict=True):
            e = pb - pa
            s = np.clip(((uv - pa) @ e) / float(e @ e), 0.0, 1.0)
            inside |= np.linalg.norm(uv - (pa + s[:, None] * e), axis=1) <= margin_m
    return inside


@dataclass(frozen=True, eq=False)
class ReferencePlane:
    """One reference plane ``normal . x = d_m`` in the object frame (unit normal, metres)."""

    name: str
    normal: FloatArray
    d_m: float
    extent: PlaneExtent | None = None  # the plate's polygon; None: the plane is unbounded

    def distance_m(self, points_xyz: FloatArray) -> FloatArray:
        """Signed distances ``(N,)`` of object-frame points ``(N, 3)`` to the plane, metres."""
        return np.asarray(points_xyz, dtype=np.float64) @ self.normal - self.d_m


@dataclass(frozen=True)
class ReferenceLink:
    """A user-given link of a detected plane (``plane``) in a station to a reference plane.

    Kept as data for the reference stage; this module only checks that ``reference`` names a
    plane of the file.
    """

    station: str
    plane: str
    reference: str


@dataclass(frozen=True, eq=False)
class ReferencePlanes:
    """The content of a reference-plane file.

    ``accuracy_m`` is ``plane_construction_accuracy_m`` (> 0): the standard deviation of the
    plane offsets and the "wobble" of the normals, metres. ``T_ref_traj`` is the
    ``[initial_transform]`` (trajectory frame into the planes' frame), ``None`` when the file has
    none (the trajectory is then roughly in the planes' frame already). ``source`` is the file it
    came from.
    """

    accuracy_m: float
    planes: tuple[ReferencePlane, ...]
    links: tuple[ReferenceLink, ...] = ()
    source: str | None = field(default=None, compare=False)
    T_ref_traj: Pose | None = None

    def __len__(self) -> int:
        return len(self.planes)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.planes)

    @property
    def normals(self) -> FloatArray:
        """Unit normals ``(k, 3)``."""
        return np.array([p.normal for p in self.planes], dtype=np.float64).reshape(-1, 3)

    @property
    def d_m(self) -> FloatArray:
        """Offsets ``(k,)`` in metres."""
        return np.array([p.d_m for p in self.planes], dtype=np.float64)

    def index(self, name: str) -> int:
        """Position of the plane called ``name``; ``KeyError`` if absent."""
        for i, p in enumerate(self.planes):
            if p.name == name:
                return i
        raise KeyError(name)


@dataclass(frozen=True, eq=False)
class ControlPoint:
    """One surveyed point: its name, object-frame coordinates [m], standard deviation per axis
    [m], and the interval [s] the unit stood on it (``nan``: to be found in the trajectory); or,
    for a target in a static scan, the scan (``station``, as the file names it) and the target's
    scan-frame coordinates ``scan_xyz`` (3,) [m]. ``line`` is the row's line (for messages)."""

    name: str
    xyz: FloatArray
    sigma_m: float
    t_start_s: float = math.nan
    t_end_s: float = math.nan
    station: str = ""
    scan_xyz: FloatArray | None = None
    line: int = 0

    @property
    def has_times(self) -> bool:
        return math.isfinite(self.t_start_s)

    @property
    def is_target(self) -> bool:
        """A target in a static scan (not a stand-still of the unit)."""
        return self.scan_xyz is not None


@dataclass(frozen=True, eq=False)
class ControlPoints:
    """The points of one file, in file order; ``source`` is the file (for messages)."""

    points: tuple[ControlPoint, ...]
    source: str

    def __len__(self) -> int:
        return len(self.points)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.points)

    @property
    def targets(self) -> tuple[ControlPoint, ...]:
        """The targets in static scans (rows with a ``station``)."""
        return tuple(p for p in self.points if p.is_target)
