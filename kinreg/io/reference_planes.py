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
    [[link]]
    station = "qs_00012"
    plane = "p3"
    reference = "south_wall"

A plane is ``n . x = d`` with ``|n| = 1`` in metres. An axis plane with ``normal_sign = -1`` at
``offset_m = c`` has ``n = -e_axis`` and ``d = -c`` (the same geometric plane, opposite face).
Every problem raises :class:`~kinreg.errors.ConfigError` with the file path and one line.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomllib

from kinreg.errors import ConfigError
from kinreg.geometry import FloatArray

logger = logging.getLogger(__name__)

_AXES = {"x": 0, "y": 1, "z": 2}
# Normals shorter than this are treated as zero (cannot be normalised meaningfully).
_MIN_NORMAL_NORM = 1e-9


@dataclass(frozen=True, eq=False)
class ReferencePlane:
    """One reference plane ``normal . x = d_m`` in the object frame (unit normal, metres)."""

    name: str
    normal: FloatArray
    d_m: float

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
    plane offsets and the "wobble" of the normals, metres. ``source`` is the file it came from.
    """

    accuracy_m: float
    planes: tuple[ReferencePlane, ...]
    links: tuple[ReferenceLink, ...] = ()
    source: str | None = field(default=None, compare=False)

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


def read_reference_planes(path: str | Path) -> ReferencePlanes:
    """Read a reference-plane TOML file (format in the module docstring).

    Raises :class:`ConfigError` (with ``path``) for a missing file, a TOML syntax error, missing or
    wrongly typed keys, an unknown axis, a zero normal, a non-positive accuracy, duplicate names
    or a link to an unknown plane.
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
    return reference_planes_from_mapping(doc, source)


def reference_planes_from_mapping(doc: Mapping[str, Any], source: str | None = None) -> ReferencePlanes:
    """Build :class:`ReferencePlanes` from an already parsed TOML document (e.g. a config section)."""
    known = {"plane_construction_accuracy_m", "plane", "link"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise ConfigError(f"unknown top-level key(s) {', '.join(unknown)} (expected "
                          "plane_construction_accuracy_m, [[plane]], [[link]])", source)
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
    logger.debug("read %d reference planes and %d links from %s", len(planes), len(links), source)
    return ReferencePlanes(accuracy_m=accuracy, planes=tuple(planes), links=links, source=source)


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
    allowed = {"name"} | axis_keys | general_keys
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
        return ReferencePlane(name=name, normal=normal, d_m=float(sign) * offset)
    if has_general:
        for key in ("normal", "d_m"):
            if key not in entry:
                raise ConfigError(f"{where}: missing key '{key}'", source)
        raw = entry["normal"]
        if not isinstance(raw, list) or len(raw) != 3:
            raise ConfigError(f"{where}: normal must be a list of 3 numbers, got {raw!r}", source)
        n = np.array([_number(v, f"{where}: normal", source) for v in raw])
        norm = float(np.linalg.norm(n))
        if norm < _MIN_NORMAL_NORM:
            raise ConfigError(f"{where}: normal is zero", source)
        d = _number(entry["d_m"], f"{where}: d_m", source)
        if abs(norm - 1.0) > 1e-3:
            # d_m is a distance in metres along the *unit* normal; a long normal is only a direction.
            logger.warning("%s: normal has length %.6g; normalised, d_m kept as the distance %.6g m",
                           where, norm, d)
        return ReferencePlane(name=name, normal=n / norm, d_m=d)
    raise ConfigError(f"{where}: missing keys: give axis/offset_m/normal_sign or normal/d_m", source)


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
