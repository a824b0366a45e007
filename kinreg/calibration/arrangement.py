"""Finite reference-plane patches, the seed's Table 2 arrangement, profile ray casting, polar errors.

Frames: a :class:`PlanePatch` lives in whatever frame its caller uses; the planning works in the
scanner frame s of the nominal set-up (seed 000, Table 2: "positions of the RP with respect to the
laser scanner"), the simulator in the object frame l.

Scanner polar convention (used for the stochastic model everywhere in this package)::

    x = d sin(theta) cos(phi),  y = d sin(theta) sin(phi),  z = d cos(theta)

``theta`` is the zenith angle (mirror angle), ``phi`` the horizontal direction of the head. In
profile mode the head stands still at ``phi = 90 deg``, so the profile is the scanner's y-z plane
(x_s = 0) and ``theta`` runs round the full circle (signed, -180..180 deg; negative values are the
-y half). An error in ``phi`` tilts the profile plane (moves points along x_s), an error in
``theta`` moves them along the profile.

Table 2 orientation convention (the seed gives angles but no formula; decided here): a patch with
all angles zero is horizontal (normal along z), and the angles rotate it by
``R = Rz(gamma) @ Ry(beta) @ Rx(alpha)`` (alpha first). This reproduces the seed's descriptions:
#5 (all zero) is a ceiling plane, #2/#10 (alpha = 90) are side walls perpendicular to the
profile, gamma turns #1/#11 about the vertical, beta tilts the ceiling plane #6 about y, and the
bounds alpha1 >= 20 deg, beta1, gamma1 <= 70 deg limit the angle of incidence to 70 deg for a
scanner at the origin. Normals are flipped to face the scanner (METHOD.md section 4).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
from numpy.typing import ArrayLike

from kinreg.errors import ConfigError
from kinreg.geometry import FloatArray
from kinreg.survey import PlaneExtent, ReferencePlane

logger = logging.getLogger(__name__)

DEFAULT_PLANE_SIZE_M = 0.3
# Z+F IMAGER 5016: vertical field of view 320 deg, i.e. a 40 deg blind cone round the nadir.
DEFAULT_BLIND_NADIR_HALF_ANGLE_DEG = 20.0


def rot_x(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def patch_rotation(alpha_rad: float, beta_rad: float, gamma_rad: float) -> FloatArray:
    """``Rz(gamma) @ Ry(beta) @ Rx(alpha)``: columns are the patch's u axis, v axis and normal."""
    return rot_z(gamma_rad) @ rot_y(beta_rad) @ rot_x(alpha_rad)


@dataclass(frozen=True, eq=False)
class PlanePatch:
    """A rectangular plane patch: centre ``center_m`` (3,), unit ``normal`` (3,), in-plane unit
    axes ``axis_u``/``axis_v`` (3,) and half extents ``half_size_m`` (2,) along them, metres."""

    name: str
    center_m: FloatArray
    axis_u: FloatArray
    axis_v: FloatArray
    normal: FloatArray
    half_size_m: FloatArray

    @classmethod
    def from_angles(cls, name: str, center_m: ArrayLike, angles_rad: ArrayLike,
                    size_m: ArrayLike = DEFAULT_PLANE_SIZE_M,
                    facing: ArrayLike | None = (0.0, 0.0, 0.0)) -> PlanePatch:
        """Patch from the Table 2 angles ``(alpha, beta, gamma)`` (module docstring).

        ``size_m`` is the side length (or ``(u, v)`` lengths); with ``facing`` the normal is
        flipped to point towards that point.
        """
        c = np.asarray(center_m, dtype=np.float64).reshape(3)
        a, b, g = (float(v) for v in np.asarray(angles_rad, dtype=np.float64).reshape(3))
        R = patch_rotation(a, b, g)
        sizes = np.broadcast_to(np.asarray(size_m, dtype=np.float64), (2,)).copy()
        u, v, n = R[:, 0].copy(), R[:, 1].copy(), R[:, 2].copy()
        if facing is not None and float(n @ (np.asarray(facing, dtype=np.float64) - c)) < 0.0:
            n, v = -n, -v  # keep (u, v, n) right-handed
        return cls(name, c, u, v, n, 0.5 * sizes)

    @property
    def d_m(self) -> float:
        """Plane offset ``d`` in ``normal . x = d``."""
        return float(self.normal @ self.center_m)

    def as_reference_plane(self) -> ReferencePlane:
        """The patch's plane with the patch as its extent."""
        hu, hv = self.half_size_m
        poly = np.array([[-hu, -hv], [hu, -hv], [hu, hv], [-hu, hv]])
        extent = PlaneExtent(self.center_m.copy(), self.axis_u.copy(), self.axis_v.copy(), poly)
        return ReferencePlane(self.name, self.normal.copy(), self.d_m, extent)

TABLE2_NAMES = ("RP1", "RP2", "RP4", "RP5", "RP6", "RP8", "RP10", "RP11")


def table2_arrangement(y1_m: float, z1_m: float, alpha1_rad: float, beta1_rad: float,
                       gamma1_rad: float, size_m: float = DEFAULT_PLANE_SIZE_M) -> tuple[PlanePatch, ...]:
    """The eight reference planes of seed 000, Table 2, in the scanner frame (scanner at origin).

    ==== ===== ===== ===== ======= ===== =======
    #    x     y     z     alpha   beta  gamma
    ==== ===== ===== ===== ======= ===== =======
    1    0     y1    -0.8  90      0     -gamma1
    2    0     y1    -0.4  90      0     0
    4    0     y1    0     -alpha1 0     0
    5    0     0.4   z1    0       0     0
    6    0     0     z1    0       beta1 0
    8    0     -y1   0     alpha1  0     0
    10   0     -y1   -0.4  90      0     0
    11   0     -y1   -0.8  90      0     gamma1
    ==== ===== ===== ===== ======= ===== =======
    """
    r90 = math.pi / 2
    rows = (
        ((0.0, y1_m, -0.8), (r90, 0.0, -gamma1_rad)),
        ((0.0, y1_m, -0.4), (r90, 0.0, 0.0)),
        ((0.0, y1_m, 0.0), (-alpha1_rad, 0.0, 0.0)),
        ((0.0, 0.4, z1_m), (0.0, 0.0, 0.0)),
        ((0.0, 0.0, z1_m), (0.0, beta1_rad, 0.0)),
        ((0.0, -y1_m, 0.0), (alpha1_rad, 0.0, 0.0)),
        ((0.0, -y1_m, -0.4), (r90, 0.0, 0.0)),
        ((0.0, -y1_m, -0.8), (r90, 0.0, gamma1_rad)),
    )
    return tuple(PlanePatch.from_angles(name, c, a, size_m)
                 for name, (c, a) in zip(TABLE2_NAMES, rows, strict=True))


# --------------------------------------------------------------------------- ray casting


def profile_directions(zenith_step_rad: float, blind_nadir_half_angle_rad: float = 0.0
                       ) -> tuple[FloatArray, FloatArray]:
    """Signed zenith angles ``(M,)`` of one full profile and their unit directions ``(M, 3)``.

    Directions are in the scanner frame at ``phi = 90 deg``: ``(0, sin theta, cos theta)``; rays
    within ``blind_nadir_half_angle_rad`` of the nadir are left out.
    """
    n = round(2.0 * math.pi / zenith_step_rad)
    theta = -math.pi + (np.arange(n) + 0.5) * (2.0 * math.pi / n)
    keep = np.abs(theta) < math.pi - blind_nadir_half_angle_rad
    theta = theta[keep]
    dirs = np.stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)], axis=-1)
    return theta, dirs


def cast_rays(patches: Sequence[PlanePatch], origins: FloatArray, dirs: FloatArray,
              min_range_m: float = 0.0) -> tuple[FloatArray, np.ndarray]:
    """Nearest hit of each ray on the patches.

    ``origins`` ``(M, 3)`` (or ``(3,)``) and unit ``dirs`` ``(M, 3)`` in the patches' frame.
    Returns ranges ``(M,)`` in metres (``inf`` for no hit) and patch indices ``(M,)`` (-1 for no
    hit). Hits closer than ``min_range_m`` are ignored.
    """
    dirs = np.asarray(dirs, dtype=np.float64)
    origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), dirs.shape)
    best = np.full(len(dirs), np.inf)
    index = np.full(len(dirs), -1, dtype=np.int64)
    for k, p in enumerate(patches):
        denom = dirs @ p.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            rng = ((p.center_m - origins) @ p.normal) / denom
        hit = origins + rng[:, None] * dirs - p.center_m
        inside = ((np.abs(denom) > 1e-12) & (rng > min_range_m)
                  & (np.abs(hit @ p.axis_u) <= p.half_size_m[0])
                  & (np.abs(hit @ p.axis_v) <= p.half_size_m[1]) & (rng < best))
        best = np.where(inside, rng, best)
        index = np.where(inside, k, index)
    return best, index


# --------------------------------------------------------------------------- polar observations


def polar_to_xyz(range_m: ArrayLike, phi_rad: ArrayLike, theta_rad: ArrayLike) -> FloatArray:
    """Scanner-frame points ``(..., 3)`` from range, horizontal direction and zenith angle."""
    d = np.asarray(range_m, dtype=np.float64)
    ph = np.asarray(phi_rad, dtype=np.float64)
    th = np.asarray(theta_rad, dtype=np.float64)
    return np.stack([d * np.sin(th) * np.cos(ph), d * np.sin(th) * np.sin(ph), d * np.cos(th)], axis=-1)


def polar_jacobian_columns(points_s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Columns ``dP/dd``, ``dP/dphi``, ``dP/dtheta`` (each ``(N, 3)``) at scanner points ``(N, 3)``.

    Written in Cartesian terms so that the sign convention of ``theta`` does not matter:
    ``dP/dd = P/d``, ``dP/dphi = (-y, x, 0)``, ``dP/dtheta = (x z/rho, y z/rho, -rho)`` with
    ``rho = sqrt(x^2 + y^2)``. At the zenith (``rho = 0``) the profile direction (y) is used.
    """
    P = np.asarray(points_s, dtype=np.float64)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    d = np.linalg.norm(P, axis=1)
    rho = np.hypot(x, y)
    at_pole = rho < 1e-12
    rho_safe = np.where(at_pole, 1.0, rho)
    j_d = P / np.where(d > 0, d, 1.0)[:, None]
    j_phi = np.stack([-y, x, np.zeros_like(x)], axis=1)
    j_theta = np.stack([np.where(at_pole, 0.0, x * z / rho_safe),
                        np.where(at_pole, np.abs(z), y * z / rho_safe),
                        -rho], axis=1)
    return j_d, j_phi, j_theta


def projected_variance(points_s: FloatArray, directions_s: FloatArray, sigma_d_m: float,
                       sigma_phi_rad: float, sigma_theta_rad: float) -> FloatArray:
    """``n^T Sigma_P n`` ``(N,)`` in m^2 for scanner points ``(N, 3)`` and unit vectors ``(N, 3)``.

    The variance of a point's distance to a plane with normal ``n`` (scanner frame) caused by the
    polar measurement errors; the full 3x3 covariance is never formed.
    """
    j_d, j_phi, j_theta = polar_jacobian_columns(points_s)
    nd = np.einsum("ij,ij->i", j_d, directions_s)
    nphi = np.einsum("ij,ij->i", j_phi, directions_s)
    nth = np.einsum("ij,ij->i", j_theta, directions_s)
    return (sigma_d_m * nd) ** 2 + (sigma_phi_rad * nphi) ** 2 + (sigma_theta_rad * nth) ** 2


# --------------------------------------------------------------------------- arrangement files


def read_arrangement(path: str | Path, default_size_m: float = DEFAULT_PLANE_SIZE_M
                     ) -> tuple[PlanePatch, ...]:
    """Read a general plane arrangement (scanner frame of the nominal set-up) from TOML::

        [[plane]]
        name = "wall_left"
        center_m = [0.0, 3.0, -0.4]
        angles_deg = [90.0, 0.0, 30.0]    # alpha, beta, gamma as in Table 2 (module docstring)
        size_m = 0.3                       # optional: side, or [u, v]; default ``default_size_m``

    Raises :class:`ConfigError` naming the file for any problem.
    """
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("arrangement file not found", p) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read arrangement file: {e}", p) from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"TOML syntax error: {e}", p) from None
    entries = doc.get("plane")
    if not isinstance(entries, list) or not entries:
        raise ConfigError("no [[plane]] entries", p)
    patches = []
    names: set[str] = set()
    for i, entry in enumerate(entries):
        patches.append(_arrangement_plane(entry, i, default_size_m, p))
        if patches[-1].name in names:
            raise ConfigError(f"duplicate plane name '{patches[-1].name}'", p)
        names.add(patches[-1].name)
    return tuple(patches)


def _vector(value: Any, n: int, what: str, path: Path) -> FloatArray:
    if (not isinstance(value, list) or len(value) != n
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value)):
        raise ConfigError(f"{what} must be a list of {n} numbers, got {value!r}", path)
    return np.array(value, dtype=np.float64)


def _arrangement_plane(e: Any, i: int, default_size_m: float, path: Path) -> PlanePatch:
    if not isinstance(e, dict):
        raise ConfigError(f"plane #{i + 1} must be a table", path)
    name = str(e.get("name", f"plane{i + 1}"))
    for key in ("center_m", "angles_deg"):
        if key not in e:
            raise ConfigError(f"plane '{name}': missing key '{key}'", path)
    unknown = sorted(set(e) - {"name", "center_m", "angles_deg", "size_m"})
    if unknown:
        raise ConfigError(f"plane '{name}': unknown key(s) {', '.join(unknown)}", path)
    center = _vector(e["center_m"], 3, f"plane '{name}': center_m", path)
    angles = np.deg2rad(_vector(e["angles_deg"], 3, f"plane '{name}': angles_deg", path))
    size = e.get("size_m", default_size_m)
    sizes = (_vector(size, 2, f"plane '{name}': size_m", path) if isinstance(size, list)
             else np.array([size, size], dtype=np.float64) if isinstance(size, (int, float))
             and not isinstance(size, bool) else None)
    if sizes is None or not np.all(sizes > 0):
        raise ConfigError(f"plane '{name}': size_m must be > 0, got {size!r}", path)
    return PlanePatch.from_angles(name, center, angles, sizes)
