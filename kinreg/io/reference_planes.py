"""Reading reference planes known in the object frame (METHOD.md section 5, TOML).

The file describes building planes for the virtual reference station (METHOD.md section 2, item 9)
and the reference planes of a calibration field (section 3). Both stages share this parser, so it
keeps everything the file says, including ``[[link]]`` entries it does not interpret itself::

    plane_construction_accuracy_m = 0.05
    [[plane]]
    name = "south_wall"
    axis = "y"          # orthogonal to this axis, at offset_m along it
    offset_m = 0.0
    normal_sign = 1     # +1: normal along +axis, -1: along -axis
    [[plane]]
    name = "slanted_roof"
    normal = [0.0, 0.5, 0.866]   # a general plane n . x = d: normal is a direction
    d_m = 2.5                    # (normalised on reading), d_m the distance along the unit normal
    [[plane]]                    # a finite plate of a calibration field: give its extent
    name = "RP1"
    normal = [0.0, -0.7071, 0.7071]
    d_m = 1.5
    extent = { center_m = [0.0, 3.0, -0.8], size_m = [0.35, 0.35], axis_u = [1.0, 0.0, 0.0] }
    # or: extent = { polygon_m = [[x, y, z], [x, y, z], [x, y, z], ...] }  (corners, in order)
    [[link]]
    station = "qs_00012"
    plane = "p3"
    reference = "south_wall"
    [initial_transform]          # optional: the trajectory's frame is not the planes' frame
    rotation_deg = [0.0, 0.0, 90.0]
    translation_m = [512300.0, 5402100.0, 312.0]

A plane is ``n . x = d`` with ``|n| = 1`` in metres. An axis plane with ``normal_sign = -1`` at
``offset_m = c`` has ``n = -e_axis`` and ``d = -c`` (the same geometric plane, opposite face).

``extent`` (optional, any plane) says where on its infinite plane the physical plate lies: a
rectangle ``center_m`` + ``size_m`` (side, or ``[u, v]`` sides) with ``axis_u`` the direction of
the u side (optional: default the horizontal direction in the plane, or x for a horizontal
plane), or a polygon ``polygon_m`` of at least three corners in order. Centre and corners are
projected onto the plane; a centre or corner farther than :data:`EXTENT_OFF_PLANE_M` from the
plane is an error (the extent belongs to another plane). Files without extents read as before.

``[initial_transform]`` is the rough pose ``T_ref_traj`` of the trajectory's (SLAM) frame in the
planes' frame, ``x_ref = R x_traj + t``, for data whose frame is arbitrary. Either

- ``rotation_deg = [rx, ry, rz]``: rotations about the *fixed* axes x, then y, then z, in degrees,
  ``R = Rz(rz) Ry(ry) Rx(rx)`` (roll, pitch, yaw; scipy ``from_euler("xyz", ...)``, lower case;
  a heading alone is ``[0, 0, heading]``, counter-clockwise seen from +z), and/or
  ``translation_m = [tx, ty, tz]`` (a missing one is zero), or
- ``matrix = [[r, r, r, tx], [r, r, r, ty], [r, r, r, tz], [0, 0, 0, 1]]``: the 4x4 homogeneous
  matrix by rows; its rotation part must be orthonormal within ``MATRIX_TOLERANCE`` with
  determinant +1, its last row exactly ``0 0 0 1``.

It only has to be good enough for the association gates (``[reference]`` in the configuration);
the adjustment finds the exact datum.

Every problem raises :class:`~kinreg.errors.ConfigError` with the file path and one line.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tomllib

from kinreg.errors import ConfigError
from kinreg.geometry import FloatArray, Pose

# The file's content as the estimation takes it; importable from here as well (redundant aliases:
# re-exported).
from kinreg.survey import PlaneExtent as PlaneExtent
from kinreg.survey import ReferenceLink as ReferenceLink
from kinreg.survey import ReferencePlane as ReferencePlane
from kinreg.survey import ReferencePlanes as ReferencePlanes

logger = logging.getLogger(__name__)

_AXES = {"x": 0, "y": 1, "z": 2}
# Normals shorter than this are treated as zero (cannot be normalised meaningfully).
_MIN_NORMAL_NORM = 1e-9
# Largest |R^T R - I| element accepted for the rotation of an [initial_transform] matrix: loose
# enough for matrices printed with 6 decimals, tight enough to catch scale and shear.
MATRIX_TOLERANCE = 1e-5
# Largest distance of an extent's centre or corner from its plane: a drawing's coordinates of a
# plate lie on its plane within millimetres; 5 cm off means the extent belongs elsewhere.
EXTENT_OFF_PLANE_M = 0.05


def rectangle_extent(normal: FloatArray, d_m: float, center_m: FloatArray, size_uv_m: FloatArray,
                     axis_u: FloatArray | None = None) -> PlaneExtent:
    """Rectangular :class:`PlaneExtent` on the plane ``normal . x = d_m``: centre (projected),
    sides ``size_uv_m`` (2,) along ``axis_u`` (projected into the plane; default horizontal)."""
    n = np.asarray(normal, dtype=np.float64)
    c = np.asarray(center_m, dtype=np.float64)
    c = c - (c @ n - d_m) * n
    u = _in_plane_axis(n, axis_u)
    su, sv = 0.5 * np.asarray(size_uv_m, dtype=np.float64)
    poly = np.array([[-su, -sv], [su, -sv], [su, sv], [-su, sv]])
    return PlaneExtent(c, u, np.cross(n, u), poly)


def _in_plane_axis(n: FloatArray, axis_u: FloatArray | None) -> FloatArray:
    if axis_u is None:
        a = np.cross(np.array([0.0, 0.0, 1.0]), n)  # horizontal in the plane
        axis_u = a if np.linalg.norm(a) > 1e-6 else np.array([1.0, 0.0, 0.0])
    u = np.asarray(axis_u, dtype=np.float64)
    u = u - (u @ n) * n
    norm = float(np.linalg.norm(u))
    if norm < 1e-6:
        raise ValueError("axis_u is (nearly) along the normal")
    return u / norm


def read_reference_planes(path: str | Path) -> ReferencePlanes:
    """Read a reference-plane TOML file (format in the module docstring).

    Raises :class:`ConfigError` (with ``path``) for a missing file, a TOML syntax error, missing or
    wrongly typed keys, an unknown axis, a zero normal, a non-positive accuracy, duplicate names,
    a link to an unknown plane, or an ``[initial_transform]`` that is not a rigid transform.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("reference-plane file not found", p) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read reference-plane file: {e}", p) from None
    return parse_reference_planes(text, source=str(p))


def parse_reference_planes(text: str, source: str | None = None) -> ReferencePlanes:
    """Parse the TOML text of a reference-plane file; ``source`` names it in errors."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"TOML syntax error: {e}", source) from None
    except RecursionError:
        raise ConfigError("TOML syntax error: arrays or tables nested too deep", source) from None
    return reference_planes_from_mapping(doc, source)


def reference_planes_from_mapping(doc: Mapping[str, Any], source: str | None = None) -> ReferencePlanes:
    """Build :class:`ReferencePlanes` from an already parsed TOML document (e.g. a config section)."""
    known = {"plane_construction_accuracy_m", "plane", "link", "initial_transform"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise ConfigError(f"unknown top-level key(s) {', '.join(unknown)} (expected "
                          "plane_construction_accuracy_m, [[plane]], [[link]], [initial_transform])", source)
    if "plane_construction_accuracy_m" not in doc:
        raise ConfigError("missing key 'plane_construction_accuracy_m'", source)
    accuracy = _number(doc["plane_construction_accuracy_m"], "plane_construction_accuracy_m", source)
    if not accuracy > 0.0:
        raise ConfigError(f"plane_construction_accuracy_m must be > 0, got {accuracy}", source)

    raw_planes = doc.get("plane")
    if raw_planes is None:
        raise ConfigError("no [[plane]] entries", source)
    if not isinstance(raw_planes, list):
        raise ConfigError("'plane' must be an array of tables ([[plane]])", source)
    planes: list[ReferencePlane] = []
    seen: set[str] = set()
    for i, entry in enumerate(raw_planes):
        plane = _parse_plane(entry, i, source)
        if plane.name in seen:
            raise ConfigError(f"duplicate plane name '{plane.name}'", source)
        seen.add(plane.name)
        planes.append(plane)

    raw_links = doc.get("link", [])
    if not isinstance(raw_links, list):
        raise ConfigError("'link' must be an array of tables ([[link]])", source)
    links = tuple(_parse_link(entry, i, seen, source) for i, entry in enumerate(raw_links))
    T_ref_traj = _parse_initial_transform(doc["initial_transform"], source) if "initial_transform" in doc else None
    logger.debug("read %d reference planes and %d links from %s", len(planes), len(links), source)
    return ReferencePlanes(accuracy_m=accuracy, planes=tuple(planes), links=links, source=source,
                           T_ref_traj=T_ref_traj)


def _number(value: Any, what: str, source: str | None) -> float:
    # bool is an int subclass in Python; `true` is never a valid number here.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{what} must be a number, got {value!r}", source)
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{what} must be finite, got {value!r}", source)
    return v


def _parse_plane(entry: Any, i: int, source: str | None) -> ReferencePlane:
    where = f"plane #{i + 1}"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a table", source)
    name = entry.get("name")
    if name is None:
        raise ConfigError(f"{where}: missing key 'name'", source)
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"{where}: 'name' must be a non-empty string, got {name!r}", source)
    where = f"plane '{name}'"
    axis_keys = {"axis", "offset_m", "normal_sign"}
    general_keys = {"normal", "d_m"}
    allowed = {"name", "extent"} | axis_keys | general_keys
    unknown = sorted(set(entry) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}", source)
    has_axis = bool(axis_keys & set(entry))
    has_general = bool(general_keys & set(entry))
    if has_axis and has_general:
        raise ConfigError(f"{where}: give either axis/offset_m/normal_sign or normal/d_m, not both",
                          source)
    if has_axis:
        for key in ("axis", "offset_m", "normal_sign"):
            if key not in entry:
                raise ConfigError(f"{where}: missing key '{key}'", source)
        axis = entry["axis"]
        if not isinstance(axis, str) or axis.lower() not in _AXES:
            raise ConfigError(f"{where}: unknown axis {axis!r} (expected x, y or z)", source)
        offset = _number(entry["offset_m"], f"{where}: offset_m", source)
        sign = entry["normal_sign"]
        if isinstance(sign, bool) or sign not in (1, -1):
            raise ConfigError(f"{where}: normal_sign must be +1 or -1, got {sign!r}", source)
        normal = np.zeros(3)
        normal[_AXES[axis.lower()]] = float(sign)
        return _with_extent(ReferencePlane(name=name, normal=normal, d_m=float(sign) * offset),
                            entry, where, source)
    if has_general:
        for key in ("normal", "d_m"):
            if key not in entry:
                raise ConfigError(f"{where}: missing key '{key}'", source)
        raw = entry["normal"]
        if not isinstance(raw, list) or len(raw) != 3:
            raise ConfigError(f"{where}: normal must be a list of 3 numbers, got {raw!r}", source)
        n = np.array([_number(v, f"{where}: normal", source) for v in raw])
        # Scaled by the largest component first: the squares of [1e308, 1e308, 0] overflow.
        largest = float(np.abs(n).max())
        norm = largest * float(np.linalg.norm(n / largest)) if largest > 0.0 else 0.0
        if norm < _MIN_NORMAL_NORM:
            raise ConfigError(f"{where}: normal is zero", source)
        n = n / largest
        d = _number(entry["d_m"], f"{where}: d_m", source)
        if abs(norm - 1.0) > 1e-3:
            # d_m is a distance in metres along the *unit* normal; a long normal is only a direction.
            logger.warning("%s: normal has length %.6g; normalised, d_m kept as the distance %.6g m",
                           where, norm, d)
        return _with_extent(ReferencePlane(name=name, normal=n / float(np.linalg.norm(n)), d_m=d), entry, where,
                            source)
    raise ConfigError(f"{where}: missing keys: give axis/offset_m/normal_sign or normal/d_m", source)


def _with_extent(plane: ReferencePlane, entry: dict[str, Any], where: str,
                 source: str | None) -> ReferencePlane:
    if "extent" not in entry:
        return plane
    ext = entry["extent"]
    where = f"{where}: extent"
    if not isinstance(ext, dict):
        raise ConfigError(f"{where} must be a table (center_m/size_m[/axis_u] or polygon_m)", source)
    rect_keys, poly_keys = {"center_m", "size_m", "axis_u"}, {"polygon_m"}
    unknown = sorted(set(ext) - rect_keys - poly_keys)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}", source)
    if bool(rect_keys & set(ext)) == bool(poly_keys & set(ext)):
        raise ConfigError(f"{where}: give either center_m and size_m (rectangle) or polygon_m", source)
    n, d = plane.normal, plane.d_m
    if "polygon_m" in ext:
        raw = ext["polygon_m"]
        if not isinstance(raw, list) or len(raw) < 3:
            raise ConfigError(f"{where}: polygon_m must be a list of at least 3 corners [x, y, z]", source)
        corners = np.array([_vector3(c, f"{where}: polygon_m corner", source) for c in raw])
        _check_on_plane(corners, n, d, where, source)
        origin = corners.mean(axis=0)
        origin = origin - (origin @ n - d) * n
        u = _in_plane_axis(n, None)
        extent = PlaneExtent(origin, u, np.cross(n, u), np.stack(
            [(corners - origin) @ u, (corners - origin) @ np.cross(n, u)], axis=-1))
    else:
        for key in ("center_m", "size_m"):
            if key not in ext:
                raise ConfigError(f"{where}: missing key '{key}'", source)
        center = _vector3(ext["center_m"], f"{where}: center_m", source)
        _check_on_plane(center[None, :], n, d, where, source)
        size = ext["size_m"]
        sizes = (np.array([_number(v, f"{where}: size_m", source) for v in size])
                 if isinstance(size, list) and len(size) == 2
                 else np.full(2, _number(size, f"{where}: size_m", source)) if not isinstance(size, list)
                 else None)
        if sizes is None or not np.all(sizes > 0):
            raise ConfigError(f"{where}: size_m must be a positive side or [u, v] sides, got {size!r}", source)
        axis_u = _vector3(ext["axis_u"], f"{where}: axis_u", source) if "axis_u" in ext else None
        try:
            extent = rectangle_extent(n, d, center, sizes, axis_u)
        except ValueError:
            raise ConfigError(f"{where}: axis_u is (nearly) along the plane's normal", source) from None
    if not extent.area_m2 > 1e-8:
        raise ConfigError(f"{where}: the polygon has no area (corners on a line?)", source)
    return ReferencePlane(plane.name, plane.normal, plane.d_m, extent)


def _check_on_plane(points: FloatArray, n: FloatArray, d: float, where: str, source: str | None) -> None:
    off = float(np.max(np.abs(points @ n - d)))
    if off > EXTENT_OFF_PLANE_M:
        raise ConfigError(f"{where} lies {off:.3f} m off the plane (more than {EXTENT_OFF_PLANE_M} m): "
                          "centre/corners must be on the plane", source)


def _parse_link(entry: Any, i: int, names: set[str], source: str | None) -> ReferenceLink:
    where = f"link #{i + 1}"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a table", source)
    values: dict[str, str] = {}
    for key in ("station", "plane", "reference"):
        if key not in entry:
            raise ConfigError(f"{where}: missing key '{key}'", source)
        v = entry[key]
        # Station and plane ids may be written as integers in hand-made files.
        if isinstance(v, bool) or not isinstance(v, (str, int)):
            raise ConfigError(f"{where}: '{key}' must be a string, got {v!r}", source)
        values[key] = str(v)
    unknown = sorted(set(entry) - {"station", "plane", "reference"})
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}", source)
    if values["reference"] not in names:
        raise ConfigError(f"{where}: unknown reference plane '{values['reference']}'", source)
    return ReferenceLink(**values)


def rotation_from_degrees(rotation_deg: FloatArray) -> FloatArray:
    """``R = Rz(rz) Ry(ry) Rx(rx)`` for ``rotation_deg = [rx, ry, rz]``: rotations about the fixed
    axes x, then y, then z (the ``[initial_transform]`` convention).

    >>> np.round(rotation_from_degrees(np.array([0.0, 0.0, 90.0])) @ [1.0, 0.0, 0.0], 12)
    array([0., 1., 0.])
    """
    rx, ry, rz = np.radians(np.asarray(rotation_deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def _vector3(value: Any, what: str, source: str | None) -> FloatArray:
    if not isinstance(value, list) or len(value) != 3:
        raise ConfigError(f"{what} must be a list of 3 numbers, got {value!r}", source)
    return np.array([_number(v, what, source) for v in value])


def _parse_initial_transform(entry: Any, source: str | None) -> Pose:
    where = "[initial_transform]"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a table", source)
    unknown = sorted(set(entry) - {"rotation_deg", "translation_m", "matrix"})
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)} (expected rotation_deg and "
                          "translation_m, or matrix)", source)
    if "matrix" in entry:
        if {"rotation_deg", "translation_m"} & set(entry):
            raise ConfigError(f"{where}: give either matrix or rotation_deg/translation_m, not both", source)
        return _rigid_matrix(entry["matrix"], where, source)
    if not entry:
        raise ConfigError(f"{where}: give rotation_deg and translation_m, or matrix", source)
    R = np.eye(3)
    if "rotation_deg" in entry:
        R = rotation_from_degrees(_vector3(entry["rotation_deg"], f"{where}: rotation_deg", source))
    t = np.zeros(3)
    if "translation_m" in entry:
        t = _vector3(entry["translation_m"], f"{where}: translation_m", source)
    return Pose.from_rotation_translation(R, t)


def _rigid_matrix(raw: Any, where: str, source: str | None) -> Pose:
    shape_error = f"{where}: matrix must be 4 rows of 4 numbers, got {raw!r}"
    if not isinstance(raw, list) or len(raw) != 4:
        raise ConfigError(shape_error, source)
    if not all(isinstance(row, list) and len(row) == 4 for row in raw):
        raise ConfigError(shape_error, source)
    M = np.array([[_number(v, f"{where}: matrix", source) for v in row] for row in raw])
    if not np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0]):
        raise ConfigError(f"{where}: the matrix's last row must be 0 0 0 1, got {M[3].tolist()}", source)
    R = M[:3, :3]
    # Bounded entries first, so that R^T R cannot overflow for absurd input.
    error = float(np.abs(R.T @ R - np.eye(3)).max()) if np.abs(R).max() <= 1.0 + MATRIX_TOLERANCE else np.inf
    if not error <= MATRIX_TOLERANCE:
        raise ConfigError(f"{where}: the matrix's rotation part is not orthonormal (largest |R^T R - I| element "
                          f"{error:.3g}, tolerance {MATRIX_TOLERANCE:g}); scale and shear are not allowed", source)
    if np.linalg.det(R) < 0.0:
        raise ConfigError(f"{where}: the matrix's rotation part has determinant -1 (a reflection, e.g. a "
                          "left-handed frame), not a rotation", source)
    # The nearest rotation (the polar factor), so that the tolerance does not leak into the poses.
    U, _, Vt = np.linalg.svd(R)
    return Pose.from_rotation_translation(U @ Vt, M[:3, 3])
