"""Streaming LAS/LAZ 1.2-1.4 reader (laspy chunk iterator, parallel lazrs decoder)."""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import laspy
import lazrs
import numpy as np

from kinreg.errors import CloudError
from kinreg.io.direct_io import read_pieces
from kinreg.io.las_header import check_las_file
from kinreg.io.quiet import library_calls
from kinreg.io.reader import DEFAULT_CHUNK_POINTS, CloudInfo, RawChunk, TimeFilter
from kinreg.types import CloudChunk

log = logging.getLogger(__name__)

# What laspy and its lazrs backend raise for unreadable, truncated or corrupted files.
_DECODE_ERRORS = (laspy.LaspyException, lazrs.LazrsError, ValueError, OSError, EOFError, RuntimeError, IndexError,
                  MemoryError, OverflowError, struct.error, UnicodeDecodeError)

# Only the fields kinreg uses are decompressed: LAS 1.4 layered LAZ (point formats 6-10) skips
# the others entirely, which speeds up decoding; older formats ignore the selection.
_SELECTION = (
    laspy.DecompressionSelection.XY_RETURNS_CHANNEL
    | laspy.DecompressionSelection.Z
    | laspy.DecompressionSelection.GPS_TIME
    | laspy.DecompressionSelection.INTENSITY
)


def _laz_backend() -> tuple[laspy.LazBackend, ...]:
    return tuple(b for b in (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs) if b.is_available())


class ByteSink(Protocol):
    """Where :meth:`LasCloudReader.iter_raw_chunks` copies the decoded records (a binary file)."""

    def write(self, data: memoryview, /) -> Any: ...


class LasCloudReader:
    """Stream a LAS/LAZ file as :class:`CloudChunk` blocks of float64 object-frame points.

    ``require_time`` (default) raises :class:`CloudError` when the point format has no
    ``gps_time``. The header is checked against the file first (:func:`check_las_file`). Decoding
    errors (truncated or corrupted files) become :class:`CloudError` naming the file and the
    point where decoding stopped. ``times`` (a :class:`TimeFilter`) shifts every point time into
    the trajectory's time base and counts the points whose time is not finite.
    """

    def __init__(self, path: str | Path, require_time: bool = True, times: TimeFilter | None = None,
                 decoded: Path | None = None) -> None:
        self.path = Path(path)
        self.decoded = decoded  # the file's points as decoded before (iter_raw_chunks' copy_to)
        self._every_field = False  # opened to decode every field, not only those kinreg reads
        self.times = times or TimeFilter()
        self.facts = check_las_file(self.path)
        try:
            with library_calls(self.path):
                self._reader = laspy.open(self.path, laz_backend=_laz_backend(), decompression_selection=_SELECTION)
        except _DECODE_ERRORS as e:
            raise CloudError(f"cannot open as LAS/LAZ: {_describe(e)}", self.path) from None
        header = self._reader.header
        dims = tuple(header.point_format.dimension_names)
        self._has_time = "gps_time" in dims
        if require_time and not self._has_time:
            self._reader.close()
            raise CloudError(
                f"no gps_time field (LAS point format {header.point_format.id}); kinreg needs point times",
                self.path,
            )
        compressed = self.path.suffix.lower() == ".laz" or header.are_points_compressed
        self.compressed = bool(compressed)
        self.record_size = int(header.point_format.size)  # bytes per point record
        self.info = CloudInfo(
            path=str(self.path),
            format=f"{'LAZ' if compressed else 'LAS'} {header.version} point format {header.point_format.id}",
            n_points=int(header.point_count),
            fields=dims,
            has_time=self._has_time,
            bounds_min=tuple(float(v) for v in header.mins),  # type: ignore[arg-type]
            bounds_max=tuple(float(v) for v in header.maxs),  # type: ignore[arg-type]
            details={
                "scales": " ".join(f"{v:g}" for v in header.scales),
                "offsets": " ".join(f"{v:.3f}" for v in header.offsets),
                "software": str(getattr(header, "generating_software", "")).strip("\x00 "),
            },
        )
        self._scales = np.asarray(header.scales, dtype=np.float64)
        self._offsets = np.asarray(header.offsets, dtype=np.float64)

    def iter_chunks(self, chunk_points: int = DEFAULT_CHUNK_POINTS) -> Iterator[CloudChunk]:
        """Yield the points in file order, ``chunk_points`` at a time (the last chunk may be short)."""
        for raw in self.iter_raw_chunks(chunk_points):
            n = len(raw)
            xyz = np.empty((n, 3), dtype=np.float64)
            for k in range(3):
                raw.coordinate(k, slice(None), xyz[:, k])
            stamps = None if raw.stamps_s is None else np.array(raw.stamps_s, dtype=np.float64)  # shifted already
            intensity = None if raw.intensity is None else np.array(raw.intensity, dtype=np.float32)
            yield CloudChunk(xyz=xyz, stamps_s=stamps, intensity=intensity, first_index=raw.first_index)

    def iter_raw_chunks(self, chunk_points: int = DEFAULT_CHUNK_POINTS,
                        copy_to: ByteSink | None = None) -> Iterator[RawChunk]:
        """Yield the points in file order as stored (integer coordinates, see :class:`RawChunk`),
        ``chunk_points`` at a time. LAZ points are decompressed into one buffer reused for every
        chunk, so a chunk's arrays are valid only until the next one is requested.

        ``copy_to`` (a binary file) gets every point record as decoded, every field of it, in file
        order and before the time filter shifts a time: the file's points in the layout of its
        point format (``record_size`` bytes each). A reader given such a copy (``decoded``) reads
        the points from there instead of decoding them."""
        first = 0
        n_total = self.info.n_points
        self.times.restart(n_total)
        arrays = (self._decoded_arrays(chunk_points, every_field=copy_to is not None) if self.decoded is None
                  else self._copied_arrays(chunk_points))
        for array in arrays:  # never empty: both sources end instead
            n = len(array)
            if copy_to is not None:
                copy_to.write(array.view(np.uint8).data)  # an OSError is the caller's (its disk)
            stamps = self.times.apply(array["gps_time"], self.path) if self._has_time else None
            yield RawChunk(
                ints=(array["X"], array["Y"], array["Z"]),
                scales=(self._scales[0], self._scales[1], self._scales[2]),
                offsets=(self._offsets[0], self._offsets[1], self._offsets[2]),
                stamps_s=stamps,
                intensity=array["intensity"] if "intensity" in self.info.fields else None,
                first_index=first,
            )
            first += n
        if first < n_total:
            raise CloudError(f"file ends after {first:,} of {n_total:,} points (truncated?)", self.path)
        self.times.finish(self.path)

    def _decoded_arrays(self, chunk_points: int, every_field: bool = False) -> Iterator[np.ndarray]:
        """The file's point records decoded from the start, ``chunk_points`` at a time, each in
        one buffer reused for every chunk; the fields kinreg reads, or ``every_field``."""
        first = 0
        n_total = self.info.n_points
        point_format = self._reader.header.point_format
        dtype = point_format.dtype()
        try:
            with library_calls(self.path):
                if every_field and not self._every_field:
                    self._reader.close()
                    self._reader = laspy.open(self.path, laz_backend=_laz_backend(),
                                              decompression_selection=laspy.DecompressionSelection.all())
                    self._every_field = True
                self._reader.seek(0)  # from the start again: laspy's reader only goes forwards
                source = self._reader.point_source
        except _DECODE_ERRORS as e:
            raise CloudError(f"cannot decode the points (truncated or corrupted?): {_describe(e)}", self.path) from None
        # laspy's own read allocates (and zeroes) a new buffer of every chunk: ~30 ms per 2 M points,
        # a tenth of the decoding. lazrs decompresses into any writable buffer.
        decompressor = getattr(source, "decompressor", None)
        decompress_into = getattr(decompressor, "decompress_many", None)
        buffer: bytearray | None = None
        while first < n_total:
            n = min(chunk_points, n_total - first)
            try:
                with library_calls(self.path):
                    if decompress_into is not None and dtype.itemsize == point_format.size:
                        if buffer is None:
                            buffer = bytearray(n * dtype.itemsize)
                        view = memoryview(buffer)[: n * dtype.itemsize]
                        decompress_into(view)
                        array = np.frombuffer(view, dtype=dtype)
                    else:
                        array = np.frombuffer(source.read_n_points(n), dtype=dtype)
            except _DECODE_ERRORS as e:
                raise CloudError(
                    f"decoding failed after {first:,} of {n_total:,} points (truncated or corrupted?): {_describe(e)}",
                    self.path,
                ) from None
            if len(array) == 0:
                return
            yield array
            first += len(array)

    def _copied_arrays(self, chunk_points: int) -> Iterator[np.ndarray]:
        """The point records of the decoded copy ``decoded``, ``chunk_points`` at a time (each
        valid until the next is taken, and writable)."""
        assert self.decoded is not None
        return read_records(self.decoded, self._reader.header.point_format.dtype(), self.info.n_points,
                            chunk_points, n_buffers=2)

    def sample_times(self, n_samples: int = 16, points_per_sample: int = 1000) -> np.ndarray:
        """Point times (shifted by the time filter's offset, unfiltered) of ``n_samples`` runs of
        ``points_per_sample`` points spread evenly over the file: a cheap look at the time range
        and the share of non-finite times, without decoding the whole file."""
        n_total = self.info.n_points
        if not self._has_time or n_total == 0:
            return np.zeros(0)
        starts = np.unique(np.linspace(0, max(n_total - points_per_sample, 0), n_samples).astype(np.int64))
        parts = []
        start = 0
        try:
            with library_calls(self.path):
                for start in starts:
                    self._reader.seek(int(start))
                    points = self._reader.read_points(min(points_per_sample, n_total - int(start)))
                    parts.append(np.asarray(points["gps_time"], dtype=np.float64))
        except _DECODE_ERRORS as e:
            raise CloudError(f"decoding failed at point {start:,} of {n_total:,} points (truncated or corrupted?): "
                             f"{_describe(e)}", self.path) from None
        return np.concatenate(parts) + self.times.offset_s if parts else np.zeros(0)

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> LasCloudReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_records(path: Path, dtype: np.dtype, n_points: int, chunk_points: int,
                 n_buffers: int) -> Iterator[np.ndarray]:
    """The ``n_points`` point records (``dtype``: the point format's) of a decoded copy
    (:meth:`LasCloudReader.iter_raw_chunks`' ``copy_to``), ``chunk_points`` at a time, read past
    the page cache into ``n_buffers`` buffers taken in turn (:func:`~kinreg.io.direct_io.read_pieces`:
    a chunk stays valid until ``n_buffers - 1`` more are taken). A copy of another size is a
    :class:`CloudError` naming it."""
    size = path.stat().st_size
    if size != n_points * dtype.itemsize:
        raise CloudError(f"the decoded copy holds {size:,} bytes, not {n_points:,} points of {dtype.itemsize} bytes",
                         path)
    for piece in read_pieces(path, chunk_points * dtype.itemsize, n_buffers=n_buffers):
        yield np.frombuffer(piece, dtype=dtype)


def _describe(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__



WKT_RECORD_ID, GEOKEYS_RECORD_ID = 2112, 34735  # LASF_Projection records (LAS 1.4 R15, section 2.5)


@dataclass(frozen=True)
class LasCrs:
    """The coordinate reference system a LAS/LAZ header declares: the OGC WKT of its
    ``LASF_Projection`` (E)VLR 2112, and the GeoTIFF keys (key id -> value) of record 34735."""

    wkt: str = ""
    geo_keys: dict[int, int] = field(default_factory=dict)


def read_las_crs(path: str | Path) -> LasCrs:
    """The CRS records of a LAS/LAZ file's VLRs and EVLRs (empty when it has none); raises
    :class:`CloudError` when the file cannot be opened."""
    path = Path(path)
    try:
        with laspy.open(path) as reader:
            records = list(reader.header.vlrs) + list(reader.header.evlrs or [])
    except _DECODE_ERRORS as e:
        raise CloudError(f"cannot open as LAS/LAZ: {_describe(e)}", path) from None
    wkt, keys = "", {}
    for record in records:
        if getattr(record, "user_id", "") != "LASF_Projection":
            continue
        if record.record_id == WKT_RECORD_ID and not wkt:
            text = getattr(record, "string", "")
            wkt = (text.decode("utf-8", "replace") if isinstance(text, bytes) else str(text)).strip("\x00 \n")
        elif record.record_id == GEOKEYS_RECORD_ID:
            keys = {int(k.id): int(k.value_offset) for k in getattr(record, "geo_keys", [])
                    if int(k.tiff_tag_location) == 0}  # values stored in the key itself
    return LasCrs(wkt, keys)
