"""Opening point clouds of any supported format as a stream of chunks.

Every reader yields :class:`~kinreg.types.CloudChunk` blocks in file order: float64 coordinates
in the object frame, float64 times. Nothing assumes the cloud fits in memory.
"""

from __future__ import annotations

from pathlib import Path

from kinreg.errors import CloudError

# What the readers share, importable from here as well (redundant aliases: re-exported).
from kinreg.io.reader import DEFAULT_CHUNK_POINTS as DEFAULT_CHUNK_POINTS
from kinreg.io.reader import CloudInfo as CloudInfo
from kinreg.io.reader import CloudReader as CloudReader
from kinreg.io.reader import RawChunk as RawChunk
from kinreg.io.reader import TimeFilter as TimeFilter

LAS_SUFFIXES = {".las", ".laz"}
E57_SUFFIXES = {".e57"}


def open_cloud(path: str | Path, require_time: bool = True, times: TimeFilter | None = None,
               decoded: Path | None = None) -> CloudReader:
    """Open a LAS/LAZ or E57 cloud for streaming.

    With ``require_time`` a file without per-point times (LAS ``gps_time``, E57 ``timeStamp``)
    raises :class:`CloudError` naming the file. ``times`` shifts and counts the point times
    (:class:`TimeFilter`; default: unchanged, counted, never refused). ``decoded`` (LAS/LAZ): the
    file's points as decoded before, read instead of decoding them
    (:meth:`~kinreg.io.las.LasCloudReader.iter_raw_chunks`).
    """
    p = Path(path)
    if not p.exists():
        raise CloudError("file not found", p)
    if p.is_dir():
        raise CloudError("is a folder, not a point cloud file", p)
    suffix = p.suffix.lower()
    if suffix in LAS_SUFFIXES:
        from kinreg.io.las import LasCloudReader

        return LasCloudReader(p, require_time=require_time, times=times, decoded=decoded)
    if suffix in E57_SUFFIXES:
        from kinreg.io.e57 import E57CloudReader

        return E57CloudReader(p, require_time=require_time, times=times)
    raise CloudError(f"unsupported point cloud format '{p.suffix}' (expected .las, .laz or .e57)", p)
