"""E57 files written with libE57 directly: for reader tests, shapes kinreg's writer never makes; for the
writer's tests and benchmark, the sequence as libE57 writes it."""

from __future__ import annotations

import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from pye57 import libe57

from kinreg import __version__
from kinreg.io.e57 import E57_SCHEMA_VERSION, KINREG_E57_PREFIX, KINREG_E57_URI
from kinreg.types import Scan


def write_raw_e57_scan(path: Path, name: str, columns: dict[str, np.ndarray]) -> None:
    """One ``data3D`` entry named ``name`` without a ``pose``, holding ``columns`` (float arrays as
    double fields, integer arrays as integer fields over their value range)."""
    n = len(next(iter(columns.values())))
    imf = libe57.ImageFile(str(path), "w")
    try:
        root = imf.root()
        root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
        root.set("guid", libe57.StringNode(imf, f"{{{name}-test}}"))
        root.set("versionMajor", libe57.IntegerNode(imf, 1))
        root.set("versionMinor", libe57.IntegerNode(imf, 0))
        data3d = libe57.VectorNode(imf, True)
        root.set("data3D", data3d)
        entry = libe57.StructureNode(imf)
        entry.set("guid", libe57.StringNode(imf, "{s0}"))
        entry.set("name", libe57.StringNode(imf, name))
        prototype = libe57.StructureNode(imf)
        for field, values in columns.items():
            if np.issubdtype(values.dtype, np.integer):
                prototype.set(field, libe57.IntegerNode(imf, 0, int(values.min()), int(values.max())))
            else:
                prototype.set(field, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
        points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
        entry.set("points", points)
        data3d.append(entry)
        buffers = libe57.VectorSourceDestBuffer()
        for field, values in columns.items():
            buffers.append(libe57.SourceDestBuffer(imf, field, np.ascontiguousarray(values), n, True, True))
        writer = points.writer(buffers)
        writer.write(n)
        writer.close()
    finally:
        imf.close()


def _guid(*parts: object) -> str:
    return f"{{{uuid.uuid5(uuid.NAMESPACE_URL, ':'.join(['kinreg', *map(str, parts)]))}}}"


def write_libe57_sequence(path: Path, scans: Iterable[Scan], coordinate_metadata: str = "",
                          block_points: int = 1_000_000) -> None:
    """The quasi-static sequence as kinreg wrote it through libE57 before its own writer
    (``kinreg.io.e57_writer``): the reference that the test of that writer and
    ``benchmarks/bench_e57_writer.py`` compare with. Same nodes, same values, same order; only the
    root's ``e57LibraryVersion`` names libE57. Guids are made from ``path.name`` as kinreg does."""
    imf = libe57.ImageFile(str(path), "w")
    try:
        imf.extensionsAdd("", libe57.E57_V1_0_URI)
        imf.extensionsAdd(KINREG_E57_PREFIX, KINREG_E57_URI)
        root = imf.root()
        root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
        root.set("guid", libe57.StringNode(imf, _guid(path.name)))
        root.set("versionMajor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MAJOR))
        root.set("versionMinor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MINOR))
        root.set("e57LibraryVersion", libe57.StringNode(imf, f"kinreg {__version__} / {libe57.E57_LIBRARY_ID}"))
        root.set("coordinateMetadata", libe57.StringNode(imf, coordinate_metadata))
        root.set(f"{KINREG_E57_PREFIX}:schemaVersion", libe57.IntegerNode(imf, E57_SCHEMA_VERSION))
        data3d = libe57.VectorNode(imf, True)
        root.set("data3D", data3d)
        root.set("images2D", libe57.VectorNode(imf, True))
        for scan in scans:
            _add_libe57_scan(imf, data3d, path, scan, block_points)
    except BaseException:
        imf.cancel()
        raise
    imf.close()


def _add_libe57_scan(imf: Any, data3d: Any, path: Path, scan: Scan, block_points: int) -> None:
    xyz = np.asarray(scan.points_xyz, dtype=np.float64)
    stamps = None if scan.stamps_s is None else np.asarray(scan.stamps_s, dtype=np.float64)
    intensity = None if scan.intensity is None else np.asarray(scan.intensity, dtype=np.float32)
    n = len(xyz)
    node = libe57.StructureNode(imf)
    node.set("guid", libe57.StringNode(imf, _guid(path.name, "scan", scan.scan_id)))
    node.set("name", libe57.StringNode(imf, scan.name))
    node.set("description", libe57.StringNode(imf, f"kinreg {scan.kind.value} scan"))
    node.set(f"{KINREG_E57_PREFIX}:scanId", libe57.IntegerNode(imf, int(scan.scan_id)))
    node.set(f"{KINREG_E57_PREFIX}:scanKind", libe57.StringNode(imf, scan.kind.value))
    node.set(f"{KINREG_E57_PREFIX}:pointsSize", libe57.IntegerNode(imf, n))
    if np.isfinite(scan.t_s):
        node.set(f"{KINREG_E57_PREFIX}:scanTime", libe57.FloatNode(imf, float(scan.t_s)))
    pose = libe57.StructureNode(imf)
    rotation = libe57.StructureNode(imf)
    for key, value in zip("wxyz", scan.T_obj_scan.quat_wxyz, strict=True):
        rotation.set(key, libe57.FloatNode(imf, float(value)))
    translation = libe57.StructureNode(imf)
    for key, value in zip("xyz", scan.T_obj_scan.t_xyz, strict=True):
        translation.set(key, libe57.FloatNode(imf, float(value)))
    pose.set("rotation", rotation)
    pose.set("translation", translation)
    node.set("pose", pose)
    t_start = scan.t_start_s if np.isfinite(scan.t_start_s) else None
    t_end = scan.t_end_s if np.isfinite(scan.t_end_s) else None
    if stamps is not None and n > 0:
        t_start = float(stamps.min()) if t_start is None else t_start
        t_end = float(stamps.max()) if t_end is None else t_end
    for key, value in (("acquisitionStart", t_start), ("acquisitionEnd", t_end)):
        if value is not None:
            when = libe57.StructureNode(imf)
            when.set("dateTimeValue", libe57.FloatNode(imf, float(value)))
            when.set("isAtomicClockReferenced", libe57.IntegerNode(imf, 0))
            node.set(key, when)
    if n > 0:
        box = libe57.StructureNode(imf)
        for i, axis in enumerate("xyz"):
            box.set(f"{axis}Minimum", libe57.FloatNode(imf, float(xyz[:, i].min())))
            box.set(f"{axis}Maximum", libe57.FloatNode(imf, float(xyz[:, i].max())))
        node.set("cartesianBounds", box)
    prototype = libe57.StructureNode(imf)
    for name in ("cartesianX", "cartesianY", "cartesianZ"):
        prototype.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
    if intensity is not None:
        i_min = float(intensity.min()) if n else 0.0
        i_max = float(intensity.max()) if n else 0.0
        prototype.set("intensity", libe57.FloatNode(imf, i_min, libe57.E57_SINGLE, i_min, i_max))
        limits = libe57.StructureNode(imf)
        limits.set("intensityMinimum", libe57.FloatNode(imf, i_min))
        limits.set("intensityMaximum", libe57.FloatNode(imf, i_max))
        node.set("intensityLimits", limits)
    if stamps is not None:
        prototype.set("timeStamp", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
    points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
    node.set("points", points)
    data3d.append(node)

    capacity = max(1, min(block_points, n))
    columns: list[tuple[str, np.ndarray, np.ndarray, float]] = [
        (name, np.empty(capacity, np.float64), xyz[:, i], 0.0)
        for i, name in enumerate(("cartesianX", "cartesianY", "cartesianZ"))
    ]
    if intensity is not None:
        columns.append(("intensity", np.empty(capacity, np.float32), intensity, 0.0))
    if stamps is not None:
        columns.append(("timeStamp", np.empty(capacity, np.float64), stamps, t_start or 0.0))
    buffers = libe57.VectorSourceDestBuffer()
    for name, buffer, _, _ in columns:
        buffers.append(libe57.SourceDestBuffer(imf, name, buffer, capacity, True, True))
    writer = points.writer(buffers)  # also for an empty scan: its binary section
    for start in range(0, n, capacity):
        m = min(capacity, n - start)
        for _, buffer, values, offset in columns:
            np.subtract(values[start:start + m], offset, out=buffer[:m], casting="same_kind")
        writer.write(m)
    writer.close()
