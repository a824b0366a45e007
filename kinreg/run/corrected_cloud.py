"""``corrected.laz``: the input cloud streamed through a drift correction, written chunk by chunk."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from kinreg.errors import CloudError
from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import FloatArray, Pose
from kinreg.io.atomic import atomic_path
from kinreg.progress import NullProgress, Progress


class PointObserver(Protocol):
    """Sees every chunk as it is written (e.g. :class:`kinreg.report.cloud_views.CloudViews`)."""

    def add(self, xyz_before: FloatArray, xyz_after: FloatArray, stamps_s: FloatArray) -> None: ...


def write_corrected_las(
    source: str | Path,
    target: str | Path,
    correction: DriftCorrection,
    chunk_points: int = 2_000_000,
    overwrite: bool = False,
    progress: Progress | None = None,
    T_obj_cloud: Pose | None = None,
    time_offset_s: float = 0.0,
    observer: PointObserver | None = None,
) -> int:
    """Stream a LAS/LAZ file, correct every point by its time, write it with the same header,
    point format, order and attributes (only X, Y, Z change). Returns the number of points.

    ``T_obj_cloud`` maps the file's coordinates into the frame of ``correction`` (its stations and
    trajectory) before the correction, when the two differ (``[initial_transform]`` of the
    reference planes); the output's header offsets are then mapped with it, so that the integer
    coordinates keep their range and the scale its resolution. ``time_offset_s`` puts the point
    times into the trajectory's time base (the stored times are kept). Points without a finite
    time are left out (they have no pose).

    The header is the input's: VLRs (the CRS as WKT or GeoTIFF keys among them), EVLRs (LAS 1.4),
    point format, scales, system identifier, software, date, GUID; laspy updates the point counts
    and bounds. ``observer`` (optional) gets each chunk's points before and after the correction
    (object frame) and their times, to gather the report's views of the cloud in the same pass.
    """
    import copy

    import laspy

    from kinreg.io.las import _DECODE_ERRORS, _laz_backend

    progress = progress or NullProgress()
    source = Path(source)
    n = 0
    with atomic_path(target, overwrite=overwrite) as tmp:
        try:
            reader = laspy.open(source, laz_backend=_laz_backend())
        except _DECODE_ERRORS as e:
            raise CloudError(f"cannot open as LAS/LAZ: {e}", source) from None
        with reader:
            header = reader.header
            if T_obj_cloud is not None:
                header = copy.deepcopy(header)
                header.offsets = np.round(T_obj_cloud.apply(np.asarray(header.offsets, dtype=np.float64)), 3)
            compress = Path(target).suffix.lower() == ".laz"
            progress.start("write cloud", total=header.point_count, unit="points")
            with laspy.open(tmp, mode="w", header=header, do_compress=compress,
                            laz_backend=_laz_backend() if compress else None) as writer, \
                    ThreadPoolExecutor(max_workers=1, thread_name_prefix="kinreg-decode") as decoding, \
                    ThreadPoolExecutor(max_workers=1, thread_name_prefix="kinreg-encode") as encoding:
                # The next chunk is decoded and the previous one encoded on threads while this one is
                # corrected; one chunk in flight each way keeps memory bounded. lazrs holds the GIL
                # for a whole call, so they overlap little (about 5 % here, benchmarks/RESULTS.md).
                chunks = _chunks(reader, chunk_points, source)
                ahead = decoding.submit(next, chunks, None)
                written: Future[None] | None = None
                try:
                    while (points := ahead.result()) is not None:
                        ahead = decoding.submit(next, chunks, None)
                        points = _corrected(points, correction, header, source, T_obj_cloud, time_offset_s, observer)
                        if written is not None:
                            written.result()
                        written = encoding.submit(writer.write_points, points)
                        n += len(points)
                        progress.advance(len(points))
                    if written is not None:
                        written.result()
                        written = None
                finally:
                    for future in (ahead, written):  # after an error: settled before the writer closes
                        if future is not None and not future.cancel():
                            future.exception()
                if header.evlrs and header.version.minor >= 4:  # laspy's writer leaves them out
                    writer.write_evlrs(header.evlrs)
            progress.finish()
    return n


def _corrected(points: Any, correction: DriftCorrection, header: Any, source: Path, T_obj_cloud: Pose | None,
               time_offset_s: float, observer: PointObserver | None) -> Any:
    """One chunk's points (a laspy record) with X, Y, Z corrected; points without a finite time
    left out.

    The coordinates go from the raw integers to coordinate rows (3, n) and back with laspy's own
    formulas (``X * scale + offset``; ``round((x - offset) / scale)`` after its range check), the
    same bits, but without its scaled views' temporaries of a whole chunk and the copy of
    ``np.column_stack``: the points are handed on as ``rows.T``, (n, 3) with contiguous columns,
    which is how the correction and the report's views read them."""
    t = np.asarray(points.gps_time, dtype=np.float64) + time_offset_s
    finite = np.isfinite(t)
    if not finite.all():
        points, t = points[finite], t[finite]
    rows = np.empty((3, len(t)))
    for row, raw, scale, offset in zip(rows, _raw_xyz(points), points.scales, points.offsets, strict=True):
        np.multiply(raw, scale, out=row)
        row += offset
    xyz = rows.T
    if T_obj_cloud is not None:
        xyz = np.ascontiguousarray(T_obj_cloud.apply(xyz).T).T
        points.offsets = header.offsets  # X, Y, Z are overwritten below, in the new system
    fixed = correction.apply_to_points(xyz, t)
    if observer is not None:
        observer.add(xyz, fixed, t)
    for i, (raw, scale, offset) in enumerate(zip(_raw_xyz(points), points.scales, points.offsets, strict=True)):
        _store(raw, fixed[:, i], float(scale), float(offset), source)
    return points


def _raw_xyz(points: Any) -> tuple[Any, Any, Any]:
    """The record's raw integer X, Y, Z (views into its array)."""
    return points.array["X"], points.array["Y"], points.array["Z"]


_STORE_BLOCK = 1 << 16  # values per block of the rounding (the temporaries stay in the cache)


def _store(raw: Any, values: FloatArray, scale: float, offset: float, source: Path) -> None:
    """``raw[:] = round((values - offset) / scale)``: laspy's setter of a scaled coordinate (the same
    range check and rounding), in blocks."""
    if not len(values):
        return
    info = np.iinfo(raw.dtype)
    # laspy's check: the extremes against the integers' range mapped through scale and offset (a
    # NaN passes it, as there)
    if values.max() > info.max * scale + offset or values.min() < info.min * scale + offset:
        raise CloudError("a corrected coordinate does not fit the input's scale and offset "
                         "(32-bit integers)", source)
    block = np.empty(min(len(values), _STORE_BLOCK))
    for a in range(0, len(values), _STORE_BLOCK):
        part = block[:len(values) - a] if a + _STORE_BLOCK > len(values) else block
        np.subtract(values[a:a + _STORE_BLOCK], offset, out=part)
        part /= scale
        np.rint(part, out=part)
        raw[a:a + _STORE_BLOCK] = part


def _chunks(reader, chunk_points: int, source: Path) -> Iterator:
    from kinreg.io.las import _DECODE_ERRORS

    iterator = reader.chunk_iterator(chunk_points)
    while True:
        try:
            points = next(iterator)
        except StopIteration:
            return
        except _DECODE_ERRORS as e:
            raise CloudError(f"decoding failed (truncated or corrupted?): {e}", source) from None
        if len(points) == 0:
            return
        yield points
