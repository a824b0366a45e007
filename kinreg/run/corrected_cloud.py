"""``corrected.laz``: the input cloud streamed through a drift correction, written chunk by chunk."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from kinreg.errors import CloudError
from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import FloatArray, Pose
from kinreg.io.atomic import atomic_path
from kinreg.progress import NullProgress, Progress

# The extra-bytes dimensions kinreg adds to every point of corrected.laz (float32; name and
# description each at most 32 characters, the LAS 1.4 extra-bytes record's fields).
SIGMA_DIMENSION = "sigma_3d_mm"
SIGMA_DESCRIPTION = "3D position sigma, 1-sigma [mm]"
CORRECTION_DIMENSION = "correction_mm"
CORRECTION_DESCRIPTION = "length of drift correction [mm]"
# Both are rounded to 1/128 mm: a float32's low mantissa bits are then zero, which LAZ compresses
# (the extra bytes add 16 % to the file instead of 43 %, benchmarks/RESULTS.md); 0.004 mm at most.
PER_POINT_QUANTUM_MM = 2.0 ** -7
_EXTRA_BYTES_MIN, _EXTRA_BYTES_MAX = 2, 4  # the options bits of an extra-bytes record (LAS 1.4 R15)


class PointObserver(Protocol):
    """Sees every chunk as it is written (e.g. :class:`kinreg.report.cloud_views.CloudViews`):
    the points before and after the correction (n, 3), their times (n,), and each point's 3D
    position sigma and correction length [mm] (n,), as written to the cloud's extra bytes."""

    def add(self, xyz_before: FloatArray, xyz_after: FloatArray, stamps_s: FloatArray,
            sigma_mm: FloatArray | None = None, correction_mm: FloatArray | None = None) -> None: ...


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
    records: Path | None = None,
) -> int:
    """Stream a LAS/LAZ file, correct every point by its time, write it with the same header,
    point format, order and attributes (only X, Y, Z change), plus two float32 extra-bytes
    dimensions per point (:func:`with_per_point_dimensions`): :data:`SIGMA_DIMENSION`, the point's 3D
    position sigma [mm] from the adjusted stations (:meth:`DriftCorrection.sigma_at_points`; NaN
    where the correction has no station sigmas), and :data:`CORRECTION_DIMENSION`, the length of
    its drift correction [mm] in the object frame (``|x' - x|``, an ``[initial_transform]`` not
    counted). The input's own extra bytes are kept, their records in the VLR too; an input that
    has the two already (a corrected cloud processed again) gets their values replaced. Returns
    the number of points.

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

    ``records`` (optional) holds the file's points as decoded (slicing's copy,
    :meth:`~kinreg.io.las.LasCloudReader.iter_raw_chunks`): they are read from there instead of
    decoding ``source`` again.
    """
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
            header = with_per_point_dimensions(reader.header)
            if T_obj_cloud is not None:
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
                buffers = _Buffers()
                widened = _Widened(header.point_format)
                chunks = (_chunks(reader, chunk_points, source) if records is None else
                          read_record_chunks(records, reader.header.point_format, reader.header.scales,
                                             reader.header.offsets, reader.header.point_count, chunk_points))
                ahead = decoding.submit(next, chunks, None)
                written: Future[None] | None = None
                try:
                    while (points := ahead.result()) is not None:
                        ahead = decoding.submit(next, chunks, None)
                        # the previous chunk's encoding lets go of the widened records before this
                        # chunk's go there (one buffer: lazrs overlaps little anyway, see above)
                        points, extremes, seen = _corrected(points, correction, header, source, T_obj_cloud,
                                                            time_offset_s, None, buffers, widened,
                                                            None if written is None else written.result)
                        written = encoding.submit(_write_points, writer, points, extremes)
                        if observer is not None:  # while the chunk is encoded
                            observer.add(*seen)
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


def with_per_point_dimensions(header: Any) -> Any:
    """A copy of the laspy ``header`` whose point format has :data:`SIGMA_DIMENSION` and
    :data:`CORRECTION_DIMENSION` (float32, with their descriptions) after the input's dimensions,
    unless it has them already. The input's extra-bytes records (their options, statistics and
    descriptions) are kept as they were; laspy rebuilds the VLR from the point format otherwise."""
    import copy

    import laspy

    header = copy.deepcopy(header)
    names = set(header.point_format.dimension_names)
    params = [laspy.ExtraBytesParams(name, np.float32, description)
              for name, description in ((SIGMA_DIMENSION, SIGMA_DESCRIPTION),
                                        (CORRECTION_DIMENSION, CORRECTION_DESCRIPTION)) if name not in names]
    if not params:
        return header
    old = header.vlrs.get("ExtraBytesVlr")
    kept = list(old[0].extra_bytes_structs) if old else []
    header.add_extra_dims(params)
    new = header.vlrs.get("ExtraBytesVlr")[0]
    new.extra_bytes_structs[:len(kept)] = kept
    for added in new.extra_bytes_structs[len(kept):]:
        # no min / max in the record: laspy's running statistics of an added extra dimension did
        # not come out as the points' range over several chunks, and a viewer takes the range
        # from the points
        added.options &= ~(_EXTRA_BYTES_MIN | _EXTRA_BYTES_MAX)
    return header


class _Widened:
    """The records of the output's point format (the input's and the two per-point dimensions
    after them), in one buffer kept from chunk to chunk (a fresh one costs its pages each time)."""

    def __init__(self, point_format: Any) -> None:
        self.point_format = point_format
        self.dtype = point_format.dtype()
        self.array: NDArray[Any] = np.empty(0, dtype=self.dtype)

    def of(self, points: Any) -> Any:
        """``points`` (a laspy record of the input's format) in the output's format: the same
        bytes, the per-point dimensions after them left to be filled."""
        import laspy

        array = points.array
        if array.dtype == self.dtype:
            return points
        n = len(array)
        if len(self.array) < n:
            self.array = np.empty(n, dtype=self.dtype)
        out = self.array[:n]
        # The input's fields are the first bytes of each output record (laspy appends extra
        # dimensions): each record copied as one opaque value (a copy per field, or of a 2D view
        # of the bytes, is a loop over small items: 20-60 times slower).
        size = array.dtype.itemsize
        head = np.dtype({"names": ["head"], "formats": [np.dtype((np.void, size))], "offsets": [0],
                         "itemsize": self.dtype.itemsize})
        out.view(head)["head"] = np.ascontiguousarray(array).view(np.dtype((np.void, size)))
        return laspy.ScaleAwarePointRecord(out, self.point_format, points.scales, points.offsets)


class _Buffers:
    """The float64 arrays of a chunk's correction, kept from chunk to chunk: a fresh array of a
    whole chunk costs more than the arithmetic on it (the kernel maps and zeroes its pages again
    for every chunk; about 5 % of the stage's CPU at 2 M points a chunk)."""

    def __init__(self) -> None:
        self.arrays: dict[str, FloatArray] = {}

    def get(self, name: str, rows: int, n: int) -> FloatArray:
        """An uninitialised (rows, n) view, each row contiguous, of the buffer ``name``."""
        array = self.arrays.get(name)
        if array is None or array.shape[0] != rows or array.shape[1] < n:
            array = self.arrays[name] = np.empty((rows, n))
        return array[:, :n]


def _corrected(points: Any, correction: DriftCorrection, header: Any, source: Path, T_obj_cloud: Pose | None,
               time_offset_s: float, observer: PointObserver | None,
               buffers: _Buffers | None = None, widened: _Widened | None = None,
               settle: Callable[[], object] | None = None) -> tuple[Any, list[tuple[float, float]], tuple[Any, ...]]:
    """One chunk's points (a laspy record) with X, Y, Z corrected and the per-point dimensions
    filled (in the point format of ``header``, :func:`with_per_point_dimensions`), points without
    a finite time left out; the range of the new raw integers of each of X, Y, Z (for the
    header, see :func:`_write_points`); and what ``observer`` sees (points before and after, times,
    sigmas, correction lengths), valid until the next chunk. ``settle`` (optional) is called before
    the chunk goes into ``widened``'s buffer (the encoding of the one before is done with it).

    The coordinates go from the raw integers to coordinate rows (3, n) and back with laspy's own
    formulas (``X * scale + offset``; ``round((x - offset) / scale)`` after its range check), the
    same bits, but without its scaled views' temporaries of a whole chunk and the copy of
    ``np.column_stack``: the points are handed on as ``rows.T``, (n, 3) with contiguous columns,
    which is how the correction and the report's views read them."""
    buffers = buffers or _Buffers()
    t = np.add(np.asarray(points.gps_time, dtype=np.float64), time_offset_s, out=buffers.get("t", 1, len(points))[0])
    finite = np.isfinite(t)
    if not finite.all():
        points, t = points[finite], t[finite]
    rows = buffers.get("rows", 3, len(t))
    for row, raw, scale, offset in zip(rows, _raw_xyz(points), points.scales, points.offsets, strict=True):
        np.multiply(raw, scale, out=row)
        row += offset
    xyz = rows.T
    if T_obj_cloud is not None:
        xyz = np.ascontiguousarray(T_obj_cloud.apply(xyz).T).T
        points.offsets = header.offsets  # X, Y, Z are overwritten below, in the new system
    fixed = correction.apply_to_points(xyz, t, out=buffers.get("fixed", 3, len(t)))
    if settle is not None:
        settle()
    points = (widened or _Widened(header.point_format)).of(points)
    sigma_mm, correction_mm = _fill_per_point(correction, xyz, fixed, t, points)
    seen = (xyz, fixed, t, sigma_mm, correction_mm)
    if observer is not None:
        observer.add(*seen)
    extremes = [_store(raw, fixed[:, i], float(scale), float(offset), source)
                for i, (raw, scale, offset) in enumerate(zip(_raw_xyz(points), points.scales, points.offsets,
                                                             strict=True))]
    return points, extremes, seen


_PER_POINT_BLOCK = 1 << 16  # points per block of the per-point values (temporaries stay in the cache)


def _fill_per_point(correction: DriftCorrection, xyz: FloatArray, fixed: FloatArray, t: FloatArray,
                    points: Any) -> tuple[Any, Any]:
    """Each point's 3D position sigma and correction length [mm] into the record's fields, in
    blocks (no array of a whole chunk: its pages would be mapped and zeroed for every chunk);
    returns the two fields (n,) as views."""
    sigma_mm, length_mm = points.array[SIGMA_DIMENSION], points.array[CORRECTION_DIMENSION]
    sigmas = getattr(correction, "sigma_3d_m", None) is not None
    if not sigmas:
        sigma_mm[:] = np.nan
    square = np.empty(min(len(t), _PER_POINT_BLOCK))
    total = np.empty_like(square)
    for a in range(0, len(t), _PER_POINT_BLOCK):
        b = min(a + _PER_POINT_BLOCK, len(t))
        part, sum_part = square[:b - a], total[:b - a]
        if sigmas:
            correction.sigma_at_points(t[a:b], out=sum_part)
            _to_quantum(sum_part, sigma_mm[a:b])
        np.subtract(fixed[a:b, 0], xyz[a:b, 0], out=sum_part)
        np.square(sum_part, out=sum_part)
        for i in (1, 2):
            np.subtract(fixed[a:b, i], xyz[a:b, i], out=part)
            np.square(part, out=part)
            sum_part += part
        np.sqrt(sum_part, out=sum_part)
        _to_quantum(sum_part, length_mm[a:b])
    return sigma_mm, length_mm


def _to_quantum(values_m: FloatArray, out_mm: Any) -> None:
    """``out_mm[:] = values_m`` in mm rounded to :data:`PER_POINT_QUANTUM_MM` (``values_m`` is
    overwritten)."""
    values_m *= 1000.0 / PER_POINT_QUANTUM_MM
    np.rint(values_m, out=values_m)
    np.multiply(values_m, PER_POINT_QUANTUM_MM, out=out_mm, casting="same_kind")


def _write_points(writer: Any, points: Any, extremes: list[tuple[float, float]]) -> None:
    """``writer.write_points(points)`` (a laspy ``LasWriter``), with the header's statistics
    taken from the chunk's raw X, Y, Z range ``extremes`` (:func:`_store` has it from the
    rounding) and one count of the return numbers, instead of ``LasHeader.grow``: that passes over
    the strided record once per field (and sorts the return numbers), about 0.1 s of 2 M points
    with the GIL held, as much as a tenth of the encoding. The header ends with the same values:
    the bounds by laspy's formula (``X.max() * scale + offset``), the point count and the points by
    return; extra-byte statistics still by laspy. (laspy also keeps the GPS time range on the
    header object; LAS has no field for it, so it is left out.)

    The points are those of the reader of the writer's header: the same point format, scales and
    offsets (laspy's ``write_points`` would rescale others), and no more than the input had."""
    if not len(points):
        return
    header = writer.header
    for i, (lo, hi) in enumerate(extremes):
        header.maxs[i] = max(header.maxs[i], hi * header.scales[i] + header.offsets[i])
        header.mins[i] = min(header.mins[i], lo * header.scales[i] + header.offsets[i])
    composed, sub_field = points.sub_fields_dict["return_number"]
    field = points.array[composed]
    if field.dtype.itemsize == 1:  # a count of each byte value, then of each return number in them
        per_byte = np.bincount(field.view(np.uint8), minlength=256)
        byte = np.arange(256, dtype=np.uint8)
        return_of_byte = (byte & sub_field.mask) >> ((sub_field.mask & -sub_field.mask).bit_length() - 1)
        numbers = np.unique(return_of_byte[per_byte > 0])
        counts = np.array([per_byte[return_of_byte == r].sum() for r in numbers], dtype=np.int64)
    else:
        numbers, counts = np.unique(points.return_number, return_counts=True)
    by_return = header.number_of_points_by_return
    for number, count in zip(numbers, counts, strict=True):  # laspy's loop over np.unique's values
        if number == 0:
            continue
        if number > len(by_return):
            break
        by_return[number - 1] += count
    header.point_count += len(points)
    extra_bytes = header.vlrs.get("ExtraBytesVlr")
    if extra_bytes:
        extra_bytes[0].grow(points)
    writer.point_writer.write_points(points)


def read_record_chunks(path: Path, point_format: Any, scales: Any, offsets: Any, n_points: int,
                       chunk_points: int) -> Iterator[Any]:
    """The point records slicing copied to ``path`` (``n_points`` of the laspy ``point_format``,
    :func:`~kinreg.io.las.read_records`), ``chunk_points`` at a time, as laspy records with the
    file's ``scales`` and ``offsets``: what laspy's chunk iterator gives, without decoding. A chunk
    lives in one of three buffers taken in turn: valid while the next is read and the one before
    is encoded, as :func:`write_corrected_las` uses them."""
    import laspy

    from kinreg.io.las import read_records

    for array in read_records(path, point_format.dtype(), n_points, chunk_points, n_buffers=3):
        yield laspy.ScaleAwarePointRecord(array, point_format, scales, offsets)


def _raw_xyz(points: Any) -> tuple[Any, Any, Any]:
    """The record's raw integer X, Y, Z (views into its array)."""
    return points.array["X"], points.array["Y"], points.array["Z"]


_STORE_BLOCK = 1 << 16  # values per block of the rounding (the temporaries stay in the cache)


def _store(raw: Any, values: FloatArray, scale: float, offset: float, source: Path) -> tuple[float, float]:
    """``raw[:] = round((values - offset) / scale)``: laspy's setter of a scaled coordinate (the same
    range check and rounding), in blocks. Returns the smallest and largest of the new integers
    (from the blocks while they are in the cache; ``(inf, -inf)`` for no values)."""
    if not len(values):
        return np.inf, -np.inf
    info = np.iinfo(raw.dtype)
    # laspy's check: the extremes against the integers' range mapped through scale and offset (a
    # NaN passes it, as there)
    if values.max() > info.max * scale + offset or values.min() < info.min * scale + offset:
        raise CloudError("a corrected coordinate does not fit the input's scale and offset "
                         "(32-bit integers)", source)
    block = np.empty(min(len(values), _STORE_BLOCK))
    lows, highs = [], []
    for a in range(0, len(values), _STORE_BLOCK):
        part = block[:len(values) - a] if a + _STORE_BLOCK > len(values) else block
        np.subtract(values[a:a + _STORE_BLOCK], offset, out=part)
        part /= scale
        np.rint(part, out=part)
        raw[a:a + _STORE_BLOCK] = part
        lows.append(part.min())
        highs.append(part.max())
    lo, hi = float(np.min(lows)), float(np.max(highs))  # NaN if there was one
    if not info.min <= lo <= hi <= info.max:  # a NaN: its integer is the cast's, as in the file
        lo, hi = float(raw.min()), float(raw.max())
    return lo, hi


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
