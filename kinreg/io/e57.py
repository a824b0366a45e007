"""Reading ASTM E57 files (kinematic clouds, static scans, the quasi-static sequence); the conventions.

Reading goes through libE57Format (the ``pye57.libe57`` bindings) with a
``CompressedVectorReader`` over fixed-size buffers, so no scan is ever decoded at once.

Conventions, for reading and writing alike:

- **Poses.** A ``data3D`` entry's ``pose`` maps its local (scan) coordinates into the file's
  object frame: ``x_obj = R(w, x, y, z) x_scan + t``, i.e. exactly kinreg's ``T_obj_scan``.
  A missing ``rotation`` is the identity, a missing ``translation`` is zero, a missing ``pose``
  is the identity pose (E57 standard, 8.4.4); :func:`read_e57_scan` may insist on a pose.
- **Times.** The E57 standard defines a point's ``timeStamp`` relative to the entry's
  ``acquisitionStart``. Reading, the absolute time is ``acquisitionStart/dateTimeValue +
  timeStamp`` where ``acquisitionStart`` exists, else ``timeStamp`` as it is. Writing, kinreg
  stores ``acquisitionStart = scan.t_start_s`` and ``timeStamp = t - t_start_s`` in double
  precision, so the round trip is exact (the difference of two nearby float64 numbers is exact).
  ``dateTimeValue`` holds the input's time scale unchanged (GPS or Unix seconds, not converted
  to the GPS epoch the standard asks for) and ``isAtomicClockReferenced`` is 0.
- **Coordinates.** Cartesian coordinates are read as they are (any E57 representation, converted
  to float64 by libE57Format); a scan with spherical coordinates only is converted with the
  E57 formula ``x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el)``. Records flagged
  by ``cartesianInvalidState``/``sphericalInvalidState`` != 0 carry no usable position and are
  dropped (logged).
- **Bounds.** ``cartesianBounds`` are in the scan frame (E57 standard 8.4.3); the object-frame
  bounds in :class:`~kinreg.io.reader.CloudInfo` are the box around the posed corners.
  pye57's own writer stores object-frame bounds instead, so treat them as informative only.

The writer of the quasi-static sequence is :mod:`kinreg.io.e57_writer`.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pye57 import libe57

from kinreg.errors import CloudError
from kinreg.geometry import FloatArray, Pose, quat_normalize
from kinreg.io.reader import DEFAULT_CHUNK_POINTS, CloudInfo, TimeFilter
from kinreg.types import CloudChunk, Scan, ScanKind

logger = logging.getLogger(__name__)

#: Version of what kinreg stores in its ``kinreg`` E57 extension; bump when a meaning changes.
E57_SCHEMA_VERSION = 1
KINREG_E57_PREFIX = "kinreg"
KINREG_E57_URI = "urn:kinreg:e57"

_E57_SIGNATURE = b"ASTM-E57"
_E57_HEADER_BYTES = 48
_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
# libE57Format's own exceptions, and what its bindings raise for damaged structures: a string where
# a number belongs (ValueError), undecodable bytes in a name or packet (UnicodeDecodeError), a
# count that makes them allocate or index beyond the file.
_E57_FAILURES = (libe57.E57Exception, RuntimeError)
_E57_READ_FAILURES = (*_E57_FAILURES, ValueError, TypeError, UnicodeDecodeError, IndexError, MemoryError,
                      OverflowError)


# --------------------------------------------------------------------------- headers


@dataclass(frozen=True, eq=False)
class E57ScanHeader:
    """What one ``data3D`` entry declares, read without decoding its points.

    ``T_obj_scan`` is ``None`` where the entry has no ``pose``. ``fields`` are the point fields
    of the prototype (``cartesianX``, ``timeStamp``, ...). Acquisition times are the
    ``dateTimeValue`` seconds of ``acquisitionStart``/``acquisitionEnd`` where present.
    ``bounds_min``/``bounds_max`` are the ``cartesianBounds`` (scan frame). ``scan_id`` and
    ``t_s`` are kinreg's own extension values (``None`` in files kinreg did not write).
    """

    index: int
    name: str
    guid: str
    n_points: int
    T_obj_scan: Pose | None
    has_time: bool
    fields: tuple[str, ...]
    acquisition_start_s: float | None = None
    acquisition_end_s: float | None = None
    bounds_min: tuple[float, float, float] | None = None
    bounds_max: tuple[float, float, float] | None = None
    scan_id: int | None = None
    t_s: float | None = None

    @property
    def label(self) -> str:
        """``scan 3 ('name')``, for messages."""
        return f"scan {self.index} ('{self.name}')"

    @property
    def coordinates(self) -> str:
        """``"cartesian"``, ``"spherical"`` or ``"none"``."""
        if all(f in self.fields for f in _CARTESIAN):
            return "cartesian"
        if all(f in self.fields for f in _SPHERICAL):
            return "spherical"
        return "none"


def _reason(exc: BaseException) -> str:
    """One line from a libE57Format exception (its message spans a dozen lines of debug info)."""
    if isinstance(exc, UnicodeDecodeError):  # the library's message quotes damaged bytes
        return "damaged data (the library's message is not readable text)"
    text = str(exc)
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    os_error = re.search(r"error='([^']*)'", text)
    return f"{first}: {os_error.group(1)}" if os_error else first


def _check_signature(path: Path) -> None:
    """Reject non-E57 and truncated files with a clear reason before libE57Format sees them."""
    try:
        size = path.stat().st_size
        with path.open("rb") as f:
            head = f.read(_E57_HEADER_BYTES)
    except OSError as exc:
        raise CloudError(f"cannot read: {exc.strerror or exc}", path) from exc
    if len(head) < len(_E57_SIGNATURE) or head[: len(_E57_SIGNATURE)] != _E57_SIGNATURE:
        raise CloudError("not an E57 file (no 'ASTM-E57' signature)", path)
    if len(head) < _E57_HEADER_BYTES:
        raise CloudError(f"truncated E57 file ({size} bytes, shorter than its header)", path)
    physical_length = int.from_bytes(head[16:24], "little")
    if physical_length != size:
        raise CloudError(
            f"truncated or damaged E57 file: header says {physical_length} bytes, file has {size}",
            path,
        )


def _child(node: Any, name: str) -> Any | None:
    """The named child of a structure node (already down-cast by the bindings), or ``None``."""
    return node[name] if node.isDefined(name) else None


def _number(node: Any) -> float:
    """The value of a Float, Integer or ScaledInteger node as a float (ValueError for any other)."""
    if isinstance(node, libe57.ScaledIntegerNode):
        return float(node.scaledValue())
    if not isinstance(node, libe57.FloatNode | libe57.IntegerNode):
        raise ValueError(f"'{node.pathName()}' is a {type(node).__name__}, not a number")
    return float(node.value())


def _string(node: Any | None, default: str = "") -> str:
    return str(node.value()) if isinstance(node, libe57.StringNode) else default


def _date_time(node: Any | None) -> float | None:
    if node is None:
        return None
    value = _child(node, "dateTimeValue")
    return None if value is None else _number(value)


def _parse_pose(node: Any | None, label: str, path: Path) -> Pose | None:
    if node is None:
        return None
    rotation = _child(node, "rotation")
    translation = _child(node, "translation")
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    t = np.zeros(3)
    if rotation is not None:
        quat = np.array([_number(rotation[k]) if rotation.isDefined(k) else 0.0 for k in "wxyz"])
        norm = float(np.linalg.norm(quat))
        if not np.isfinite(norm) or norm < 1e-12:
            raise CloudError(f"{label}: pose rotation quaternion {quat.tolist()} is not a rotation", path)
        if abs(norm - 1.0) > 1e-6:
            logger.warning("%s: %s: pose quaternion has norm %.9f; normalised", path, label, norm)
        quat = quat_normalize(quat)
    if translation is not None:
        t = np.array([_number(translation[k]) if translation.isDefined(k) else 0.0 for k in "xyz"])
        if not np.isfinite(t).all():
            raise CloudError(f"{label}: pose translation {t.tolist()} is not finite", path)
    return Pose(quat, t)


def _parse_header(index: int, node: Any, path: Path, kinreg_prefix: str | None) -> E57ScanHeader:
    name = _string(_child(node, "name"), default=f"scan {index}")
    label = f"scan {index} ('{name}')"
    points = _child(node, "points")
    if not isinstance(points, libe57.CompressedVectorNode):
        raise CloudError(f"{label} has no 'points' compressed vector", path)
    prototype = libe57.StructureNode(points.prototype())
    fields = tuple(prototype.get(i).elementName() for i in range(prototype.childCount()))
    bounds_min = bounds_max = None
    box = _child(node, "cartesianBounds")
    if box is not None and all(box.isDefined(f"{a}{m}") for a in "xyz" for m in ("Minimum", "Maximum")):
        lo = tuple(_number(box[f"{a}Minimum"]) for a in "xyz")
        hi = tuple(_number(box[f"{a}Maximum"]) for a in "xyz")
        bounds_min, bounds_max = (lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2])
    # An undeclared prefix is a malformed path name for libE57Format, so look only when declared.
    scan_id_node = t_s_node = None
    if kinreg_prefix is not None:
        scan_id_node = _child(node, f"{kinreg_prefix}:scanId")
        t_s_node = _child(node, f"{kinreg_prefix}:scanTime")
    return E57ScanHeader(
        index=index,
        name=name,
        guid=_string(_child(node, "guid")),
        n_points=int(points.childCount()),
        T_obj_scan=_parse_pose(_child(node, "pose"), label, path),
        has_time="timeStamp" in fields,
        fields=fields,
        acquisition_start_s=_date_time(_child(node, "acquisitionStart")),
        acquisition_end_s=_date_time(_child(node, "acquisitionEnd")),
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        scan_id=None if scan_id_node is None else int(_number(scan_id_node)),
        t_s=None if t_s_node is None else _number(t_s_node),
    )


# --------------------------------------------------------------------------- low-level reading


@dataclass(frozen=True, eq=False)
class _Block:
    """Decoded records of one scan: valid points only, scan frame, absolute times."""

    first_record: int  # index of the block's first record within its scan
    xyz_scan: FloatArray
    stamps_s: FloatArray | None
    intensity: NDArray[np.float32] | None


class _E57File:
    """An open E57 file with its parsed headers; wraps every libE57Format failure in CloudError."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise CloudError("file not found", self.path)
        if self.path.is_dir():
            raise CloudError("is a folder, not an E57 file", self.path)
        _check_signature(self.path)
        self._imf: Any = None
        with self._errors("cannot open E57 file"):
            self._imf = libe57.ImageFile(str(self.path), "r")
        try:
            with self._errors("cannot read E57 header"):
                root = self._imf.root()
                data3d = _child(root, "data3D")
                self._nodes = [] if data3d is None else [data3d[i] for i in range(data3d.childCount())]
                prefixes = {
                    self._imf.extensionsUri(i): self._imf.extensionsPrefix(i)
                    for i in range(self._imf.extensionsCount())
                }
                prefix = prefixes.get(KINREG_E57_URI)
                self.headers = [_parse_header(i, n, self.path, prefix) for i, n in enumerate(self._nodes)]
        except BaseException:
            self.close()
            raise

    @contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        try:
            yield
        except _E57_READ_FAILURES as exc:
            raise CloudError(f"{what}: {_reason(exc)}", self.path) from None

    def close(self) -> None:
        if self._imf is not None and self._imf.isOpen():
            with self._errors("cannot close E57 file"):
                self._imf.close()
        self._imf = None

    def iter_blocks(self, index: int, block_points: int, drop_invalid_time: bool) -> Iterator[_Block]:
        """Decode scan ``index`` in blocks of at most ``block_points`` records.

        Records whose position is flagged invalid are dropped; records whose time is flagged
        invalid are dropped with ``drop_invalid_time``, else get a ``nan`` time.
        """
        if self._imf is None:
            raise CloudError("E57 file is closed", self.path)
        header = self.headers[index]
        if header.n_points == 0:
            return
        coordinates = header.coordinates
        if coordinates == "none":
            raise CloudError(
                f"{header.label} has neither cartesianX/Y/Z nor sphericalRange/Azimuth/Elevation",
                self.path,
            )
        names = list(_CARTESIAN if coordinates == "cartesian" else _SPHERICAL)
        dtypes: dict[str, Any] = dict.fromkeys(names, np.float64)
        invalid_state = "cartesianInvalidState" if coordinates == "cartesian" else "sphericalInvalidState"
        optional = {
            invalid_state: np.int8,
            "timeStamp": np.float64,
            "isTimeStampInvalid": np.int8,
            "intensity": np.float32,
        }
        dtypes.update({k: v for k, v in optional.items() if k in header.fields})
        capacity = max(1, min(block_points, header.n_points))
        arrays = {name: np.empty(capacity, dtype) for name, dtype in dtypes.items()}
        time_offset = header.acquisition_start_s or 0.0
        n_dropped = 0
        reader: Any = None
        try:
            with self._errors(f"cannot read {header.label}"):
                buffers = libe57.VectorSourceDestBuffer()
                for name, array in arrays.items():
                    buffers.append(libe57.SourceDestBuffer(self._imf, name, array, capacity, True, True))
                reader = self._nodes[index]["points"].reader(buffers)
            first = 0
            while True:
                with self._errors(f"cannot read {header.label} at record {first}"):
                    n = int(reader.read())
                if n == 0:
                    break
                block, dropped = self._decode(arrays, n, coordinates, time_offset, drop_invalid_time, first)
                n_dropped += dropped
                first += n
                yield block
            if first != header.n_points:
                raise CloudError(f"{header.label}: read {first} of {header.n_points} records", self.path)
        finally:
            # The ImageFile may be closed already when an abandoned generator is collected.
            if reader is not None and self._imf is not None and reader.isOpen():
                with self._errors(f"cannot close the reader of {header.label}"):
                    reader.close()
        if n_dropped:
            logger.info("%s: %s: dropped %d records flagged invalid", self.path, header.label, n_dropped)

    @staticmethod
    def _decode(
        arrays: dict[str, NDArray[Any]],
        n: int,
        coordinates: str,
        time_offset: float,
        drop_invalid_time: bool,
        first: int,
    ) -> tuple[_Block, int]:
        if coordinates == "cartesian":
            xyz = np.column_stack([arrays[k][:n] for k in _CARTESIAN])
        else:
            r, az, el = (arrays[k][:n] for k in _SPHERICAL)
            r_cos_el = r * np.cos(el)
            xyz = np.column_stack([r_cos_el * np.cos(az), r_cos_el * np.sin(az), r * np.sin(el)])
        stamps = arrays["timeStamp"][:n] + time_offset if "timeStamp" in arrays else None
        intensity = arrays["intensity"][:n].copy() if "intensity" in arrays else None
        keep: NDArray[np.bool_] | None = None
        state = arrays.get("cartesianInvalidState", arrays.get("sphericalInvalidState"))
        if state is not None:
            keep = state[:n] == 0
        if stamps is not None and "isTimeStampInvalid" in arrays:
            bad_time = arrays["isTimeStampInvalid"][:n] != 0
            if drop_invalid_time:
                keep = ~bad_time if keep is None else keep & ~bad_time
            else:
                stamps[bad_time] = np.nan
        dropped = 0
        if keep is not None and not keep.all():
            dropped = int(n - keep.sum())
            xyz = xyz[keep]
            stamps = None if stamps is None else stamps[keep]
            intensity = None if intensity is None else intensity[keep]
        return _Block(first, xyz, stamps, intensity), dropped

    def read_scan(self, index: int, require_pose: bool, kind: ScanKind) -> Scan:
        header = self.headers[index]
        if header.T_obj_scan is None and require_pose:
            raise CloudError(
                f"{header.label} has no pose; static scans must carry their registered pose "
                "in the object frame",
                self.path,
            )
        blocks = list(self.iter_blocks(index, DEFAULT_CHUNK_POINTS, drop_invalid_time=False))
        xyz = np.concatenate([b.xyz_scan for b in blocks]) if blocks else np.zeros((0, 3))
        stamps = intensity = None
        if header.has_time:
            stamps = np.concatenate([np.zeros(0), *(b.stamps_s for b in blocks if b.stamps_s is not None)])
        if "intensity" in header.fields:
            intensity = np.concatenate(
                [np.zeros(0, np.float32), *(b.intensity for b in blocks if b.intensity is not None)]
            )
        times = {}
        if kind is ScanKind.QUASI_STATIC:
            start = np.nan if header.acquisition_start_s is None else header.acquisition_start_s
            end = np.nan if header.acquisition_end_s is None else header.acquisition_end_s
            # kinreg stores the window's centre time; other writers give the window only.
            centre = 0.5 * (start + end) if header.t_s is None else header.t_s
            times = {"t_start_s": start, "t_end_s": end, "t_s": centre}
        return Scan(
            scan_id=index if header.scan_id is None else header.scan_id,
            name=header.name,
            kind=kind,
            T_obj_scan=header.T_obj_scan if header.T_obj_scan is not None else Pose.identity(),
            points_xyz=xyz,
            stamps_s=stamps,
            intensity=intensity,
            **times,
        )


# --------------------------------------------------------------------------- kinematic cloud


class E57CloudReader:
    """Streams an E57 file's points, all ``data3D`` entries in order, in the object frame.

    Each entry's points are mapped with its pose (``x_obj = R x_scan + t``; no pose means
    identity). Times are absolute float64 seconds: ``acquisitionStart/dateTimeValue +
    timeStamp`` where the entry has ``acquisitionStart``, else ``timeStamp`` itself (see the
    module docstring). Spherical-only entries are converted to cartesian; records flagged
    invalid (position, or time with ``require_time``) are dropped, so a chunk can hold fewer
    points than records were read and ``info.n_points`` (the records declared) can exceed the
    points yielded.

    Raises :class:`CloudError` naming the file if it is not a readable E57 file, and with
    ``require_time`` if any entry lacks a ``timeStamp`` field.
    """

    def __init__(self, path: str | Path, require_time: bool = True, times: TimeFilter | None = None) -> None:
        self.path = Path(path)
        self.require_time = require_time
        self.times = times or TimeFilter()
        self._file = _E57File(self.path)
        try:
            self.scans: list[E57ScanHeader] = self._file.headers
            if not self.scans:
                raise CloudError("holds no scans (no data3D entries)", self.path)
            if require_time:
                for h in self.scans:
                    if not h.has_time:
                        raise CloudError(
                            f"no per-point timeStamp field in {h.label}; kinreg needs point times",
                            self.path,
                        )
            for h in self.scans:
                if h.coordinates == "none":
                    raise CloudError(f"{h.label} has no cartesian or spherical coordinates", self.path)
            self.info = self._make_info()
        except BaseException:
            self._file.close()
            raise
        logger.debug("opened %s: %d scans, %d points", self.path, len(self.scans), self.info.n_points)

    def _make_info(self) -> CloudInfo:
        scans = self.scans
        fields = tuple(dict.fromkeys(f for h in scans for f in h.fields))
        has_time = bool(scans) and all(h.has_time for h in scans)
        bounds_min = bounds_max = None
        filled = [h for h in scans if h.n_points > 0]  # an empty entry has no bounds to give
        if filled and all(h.bounds_min is not None and h.bounds_max is not None for h in filled):
            corners = []
            for h in filled:
                lo, hi = np.array(h.bounds_min), np.array(h.bounds_max)
                box = np.array(
                    [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
                )
                pose = h.T_obj_scan if h.T_obj_scan is not None else Pose.identity()
                corners.append(pose.apply(box))
            all_corners = np.concatenate(corners)
            lo_obj, hi_obj = all_corners.min(axis=0), all_corners.max(axis=0)
            bounds_min = (float(lo_obj[0]), float(lo_obj[1]), float(lo_obj[2]))
            bounds_max = (float(hi_obj[0]), float(hi_obj[1]), float(hi_obj[2]))
        time_range = None
        starts = [h.acquisition_start_s for h in scans]
        ends = [h.acquisition_end_s for h in scans]
        if has_time and all(s is not None for s in starts) and all(e is not None for e in ends):
            time_range = (min(s for s in starts if s is not None), max(e for e in ends if e is not None))
        return CloudInfo(
            path=str(self.path),
            format="E57",
            n_points=sum(h.n_points for h in scans),
            fields=fields,
            has_time=has_time,
            n_scans=len(scans),
            bounds_min=bounds_min,
            bounds_max=bounds_max,
            time_range_s=time_range,
        )

    def iter_chunks(self, chunk_points: int = DEFAULT_CHUNK_POINTS) -> Iterator[CloudChunk]:
        """Yield :class:`CloudChunk` blocks of at most ``chunk_points`` points, file order.

        ``xyz`` (n, 3) float64 in the object frame, ``stamps_s`` (n,) float64 absolute seconds
        (``None`` for entries without times when ``require_time`` is off), ``intensity`` (n,)
        float32 or ``None``, ``first_index`` the file-wide record index of the chunk's first
        record (records counted over all entries in order). A chunk never spans two entries.
        """
        if chunk_points < 1:
            raise ValueError(f"chunk_points must be positive, got {chunk_points}")
        record_offset = 0
        self.times.restart(self.info.n_points)
        for h in self.scans:
            pose = h.T_obj_scan
            for block in self._file.iter_blocks(h.index, chunk_points, drop_invalid_time=self.require_time):
                if len(block.xyz_scan) == 0:
                    continue
                xyz = block.xyz_scan if pose is None else pose.apply(block.xyz_scan)
                yield CloudChunk(
                    xyz=xyz,
                    stamps_s=None if block.stamps_s is None else self.times.apply(block.stamps_s, self.path),
                    intensity=block.intensity,
                    first_index=record_offset + block.first_record,
                )
            record_offset += h.n_points
        self.times.finish(self.path)

    def close(self) -> None:
        """Close the file; safe to call twice."""
        self._file.close()

    def __enter__(self) -> E57CloudReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- static scans


def list_e57_scans(path: str | Path) -> list[E57ScanHeader]:
    """Headers of every ``data3D`` entry of an E57 file, in file order, without reading points.

    Raises :class:`CloudError` if the file is missing or not a readable E57 file.
    """
    f = _E57File(path)
    try:
        return list(f.headers)
    finally:
        f.close()


def read_e57_scan(
    path: str | Path, index: int, require_pose: bool = True, kind: ScanKind = ScanKind.STATIC
) -> Scan:
    """Read one ``data3D`` entry as a :class:`Scan` with its points in the SCAN frame.

    ``points_xyz`` (n, 3) float64 scan frame, ``T_obj_scan`` from the entry's pose (missing
    rotation -> identity, missing translation -> zero), ``stamps_s`` absolute float64 seconds
    where the entry has ``timeStamp``, ``intensity`` float32 where present. ``scan_id`` is
    kinreg's stored id where the file has one, else ``index``. A ``STATIC`` scan has ``nan``
    times (the header's acquisition times are in :func:`list_e57_scans`); a ``QUASI_STATIC``
    one takes ``t_start_s``/``t_end_s`` from ``acquisitionStart``/``acquisitionEnd``.

    Raises :class:`CloudError` for an unreadable file, an index out of range, or (with
    ``require_pose``) an entry without ``pose``.
    """
    f = _E57File(path)
    try:
        if not 0 <= index < len(f.headers):
            raise CloudError(f"no scan {index}: the file holds {len(f.headers)} scans", f.path)
        return f.read_scan(index, require_pose, kind)
    finally:
        f.close()


def iter_e57_scans(
    path: str | Path, require_pose: bool = True, kind: ScanKind = ScanKind.STATIC
) -> Iterator[Scan]:
    """Yield every ``data3D`` entry as a :class:`Scan` (see :func:`read_e57_scan`), one at a time.

    The pose check runs for each scan as it is reached.
    """
    f = _E57File(path)
    try:
        for index in range(len(f.headers)):
            yield f.read_scan(index, require_pose, kind)
    finally:
        f.close()


def check_static_scans(path: str | Path) -> int:
    """Read every scan of a static E57 once, before the long work: each must have a pose and only
    finite points. Returns the number of scans. Raises :class:`CloudError` naming the file and the
    scan for no scans, a missing or non-finite pose, a scan without points or with non-finite ones."""
    f = _E57File(path)
    try:
        if not f.headers:
            raise CloudError("holds no scans (no data3D entries)", f.path)
        for h in f.headers:
            if h.T_obj_scan is None:
                raise CloudError(f"{h.label} has no pose; static scans must carry their registered pose "
                                 "in the object frame", f.path)
            n = 0
            with np.errstate(all="ignore"):
                for block in f.iter_blocks(h.index, DEFAULT_CHUNK_POINTS, drop_invalid_time=False):
                    bad = ~np.isfinite(block.xyz_scan).all(axis=1)
                    if bad.any():
                        k = block.first_record + int(np.argmax(bad))
                        raise CloudError(f"{h.label}: record {k} has a coordinate that is not finite", f.path)
                    n += len(block.xyz_scan)
            if n == 0:
                raise CloudError(f"{h.label} holds no valid points", f.path)
        return len(f.headers)
    finally:
        f.close()


# --------------------------------------------------------------------------- writing


