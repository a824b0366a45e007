"""Raw E57 files written with libE57 directly, for reader tests: shapes kinreg's writer never makes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pye57 import libe57


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
