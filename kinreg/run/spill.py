"""Cut a kinematic run into quasi-static scans (METHOD.md section 2, step 2).

The trajectory is split into short windows; each window's virtual scanner centre ``T_obj_scan``
is the trajectory row nearest the window's middle, and the window's points are expressed in that
frame: ``p_scan = T_obj_scan^-1 p_obj``. The geometry is unchanged, only the parametrisation.

The cloud is streamed once. Each point goes to the spill file of its window in a temporary folder
(float32 offsets from the window's origin, float64 time, float32 intensity: 24 bytes a point), so memory
stays bounded whatever the cloud's size and whether or not it is time-sorted. Scans are then
handed out one at a time. A LAZ cloud's decoded point records can be kept beside them
(:data:`RECORDS_FILE`, in file order), so that the corrected cloud is written without a second
decoding.

A finished spill can be reopened (:meth:`QuasiStaticSequence.reopen`) from its small index
(:meth:`QuasiStaticSequence.index_arrays`, plain arrays for the stage cache): ``kinreg process
--resume`` does so after an interrupted run instead of streaming the cloud again. A spill folder
is complete only when it holds the ``.complete`` mark, written after the last point.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
import tempfile
from bisect import bisect_left, bisect_right
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import BinaryIO

import numpy as np

from kinreg.config import SlicingConfig
from kinreg.errors import ConfigError, InputError, OutputError
from kinreg.estimate.slicing import choose_windows, unit_edges
from kinreg.geometry import FloatArray
from kinreg.io.cloud import DEFAULT_CHUNK_POINTS, CloudReader, RawChunk
from kinreg.io.direct_io import DirectWriter
from kinreg.progress import NullProgress, Progress
from kinreg.run.codecs import windows_from_arrays, windows_to_arrays
from kinreg.types import CloudChunk, Scan, ScanKind, ScanWindow, SkippedWindow, SlicingSummary, Trajectory

log = logging.getLogger(__name__)

# Coordinates are float32 offsets from the unit's origin (the trajectory position at the unit's
# middle): points within a few hundred metres of it keep better than 0.02 mm, and the spill
# (the slicing stage's disk traffic) is a third smaller than with float64 coordinates.
SPILL_RECORD = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<f8"), ("intensity", "<f4")])


# Open spill files kept at once; a time-sorted cloud touches one or two per chunk.
_MAX_OPEN_FILES = 64

# Records are assembled in two reused buffers of up to this many points (50 MB each), from
# blocks whose float64 temporaries (256 kB) stay in the per-core cache. Fresh arrays of whole
# chunks cost more than the arithmetic: the kernel maps and zeroes every page of every new
# large array.
_STAGING_POINTS = 1 << 21
_BLOCK_POINTS = 1 << 15

SPILL_PREFIX = "kinreg-slices-"  # name prefix of every spill folder
SPILL_COMPLETE = ".complete"  # written into a spill folder after its last point
# The cloud's point records as decoded, every field, in file order (LAZ input only): the
# corrected cloud is written from them instead of decoding the LAZ a second time.
RECORDS_FILE = "records.bin"
# Free space left beside the spill and the decoded copy; with less, the copy is not made.
_RECORDS_DISK_MARGIN = 1 << 30


class _SpillWriter:
    """Appends point records to one file per unit, keeping a bounded number of files open.

    The files are written by one background thread, in the order of :meth:`append`, so that the
    kernel's copying into the page cache (the largest cost of slicing after decoding) overlaps
    with decoding and assembling the next records; :meth:`append` hands back a future per write.
    """

    def __init__(self, folder: Path, origins: FloatArray) -> None:
        self.folder = folder
        self.origins = origins  # (n_units, 3) object-frame origin of each unit's offsets
        self.counts = np.zeros(len(origins), dtype=np.int64)
        self._open: OrderedDict[int, BinaryIO] = OrderedDict()  # used by the writer thread only
        self._writer: ThreadPoolExecutor | None = None

    def path(self, unit: int) -> Path:
        return self.folder / f"unit_{unit:06d}.bin"

    def append(self, unit: int, records: np.ndarray) -> Future[None]:
        """Queue ``records`` (contiguous) for appending to ``unit``'s file. They must stay
        unchanged until the returned future is done; its ``result()`` raises a failed write's
        :class:`OSError`."""
        if self._writer is None:
            self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kinreg-spill")
        self.counts[unit] += len(records)
        return self._writer.submit(self._write, unit, records)

    def _write(self, unit: int, records: np.ndarray) -> None:
        f = self._open.pop(unit, None)
        if f is None:
            if len(self._open) >= _MAX_OPEN_FILES:
                _, oldest = self._open.popitem(last=False)
                oldest.close()
            f = open(self.path(unit), "ab")  # noqa: SIM115  (kept open across chunks, closed in close())
        self._open[unit] = f
        f.write(records.view(np.uint8).data)

    def _close_files(self) -> None:
        try:
            for f in self._open.values():
                f.close()
        finally:
            self._open.clear()

    def close(self) -> None:
        """Wait for the queued writes and close the files; raises the :class:`OSError` of a
        failed close (a failed write raises from its future)."""
        if self._writer is not None:
            self._writer.submit(self._close_files).result()
            self._writer.shutdown(wait=True)
            self._writer = None
        self._close_files()


class QuasiStaticSequence:
    """The sliced run: windows kept as scans, what was skipped, and the spilled points.

    Hand out scans with :meth:`iter_scans` (one at a time) or :meth:`read_scan`. Call
    :meth:`close` (or use as a context manager) to delete the temporary store.
    """

    def __init__(
        self,
        windows: tuple[ScanWindow, ...],
        unit_ranges: tuple[tuple[int, int], ...],
        store: _SpillWriter,
        summary: SlicingSummary,
        owns_folder: bool,
    ) -> None:
        self.windows = windows
        self.summary = summary
        self._unit_ranges = unit_ranges
        self._store = store
        self._owns_folder = owns_folder

    def __len__(self) -> int:
        return len(self.windows)

    def n_points(self, i: int) -> int:
        a, b = self._unit_ranges[i]
        return int(self._store.counts[a:b].sum())

    def read_scan(self, i: int) -> Scan:
        """Scan ``i``: its points in its own frame (float64), times, intensities."""
        w = self.windows[i]
        a, b = self._unit_ranges[i]
        units = [u for u in range(a, b) if self._store.counts[u]]
        n = int(self._store.counts[units].sum())
        xyz, stamps, intensity = np.empty((n, 3)), np.empty(n), np.empty(n, dtype=np.float32)
        # p_scan = R^T (p_obj - t) with p_obj = offset + the unit's origin: the origin minus t
        # once per unit (float64, so UTM-sized values keep their precision), then blocks of
        # offsets whose temporaries stay in the cache.
        R = np.ascontiguousarray(w.T_obj_scan.rotation_matrix)
        start = 0
        for u in units:
            rec = np.fromfile(self._store.path(u), dtype=SPILL_RECORD)
            shift = self._store.origins[u] - w.T_obj_scan.t_xyz
            for k in range(0, len(rec), _BLOCK_POINTS):
                part = rec[k:k + _BLOCK_POINTS]
                local = np.empty((len(part), 3))
                for axis, name in enumerate("xyz"):
                    np.add(part[name], shift[axis], out=local[:, axis])
                np.matmul(local, R, out=xyz[start + k:start + k + len(part)])
            stamps[start:start + len(rec)] = rec["t"]
            intensity[start:start + len(rec)] = rec["intensity"]
            start += len(rec)
        return Scan(
            scan_id=w.scan_id,
            name=w.name,
            kind=ScanKind.QUASI_STATIC,
            T_obj_scan=w.T_obj_scan,
            points_xyz=xyz,
            stamps_s=stamps,
            intensity=intensity,
            t_s=w.t_s,
            t_start_s=w.t_start_s,
            t_end_s=w.t_end_s,
        )

    def iter_scans(self) -> Iterator[Scan]:
        for i in range(len(self.windows)):
            yield self.read_scan(i)

    @property
    def records(self) -> Path | None:
        """The cloud's decoded point records (:data:`RECORDS_FILE`), where slicing kept them."""
        path = self._store.folder / RECORDS_FILE
        return path if path.is_file() else None

    @property
    def folder(self) -> Path:
        """The spill folder."""
        return self._store.folder

    def index_arrays(self) -> dict[str, np.ndarray]:
        """The small index of the spill (windows, unit ranges, point counts and origins of the
        units, the summary) as plain arrays; :meth:`reopen` takes them back."""
        s = self.summary
        return {
            **windows_to_arrays(self.windows, self._unit_ranges, self._store.counts),
            "unit_origins": self._store.origins,
            "summary_counts": np.array([s.n_points_read, s.n_points_in_scans, s.n_points_outside_trajectory,
                                        s.n_points_in_skipped_windows, s.n_scans], dtype=np.int64),
            "skipped_times_s": np.array([(w.t_start_s, w.t_end_s) for w in s.skipped], dtype=np.float64).reshape(-1, 2),
            "skipped_n_points": np.array([w.n_points for w in s.skipped], dtype=np.int64),
        }

    @classmethod
    def reopen(cls, folder: Path, index: Mapping[str, np.ndarray]) -> QuasiStaticSequence | None:
        """The sequence of a finished spill in ``folder`` with its ``index`` (from
        :meth:`index_arrays`), or ``None`` when the folder is not complete (no ``.complete``
        mark, or a unit file of the wrong size). The returned sequence does not delete the
        folder on :meth:`close`."""
        windows, ranges, counts = windows_from_arrays(index)
        store = _SpillWriter(folder, np.asarray(index["unit_origins"], dtype=np.float64))
        store.counts = counts
        if not (folder / SPILL_COMPLETE).is_file():
            return None
        for unit, count in enumerate(counts):
            size = store.path(unit).stat().st_size if store.path(unit).is_file() else 0
            if size != int(count) * SPILL_RECORD.itemsize:
                return None
        return cls(tuple(windows), tuple(ranges), store, summary_from_arrays(index), owns_folder=False)

    def close(self) -> None:
        if self._owns_folder:
            shutil.rmtree(self._store.folder, ignore_errors=True)

    def __enter__(self) -> QuasiStaticSequence:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def summary_from_arrays(index: Mapping[str, np.ndarray]) -> SlicingSummary:
    """The slicing summary stored in a sequence's index (see
    :meth:`QuasiStaticSequence.index_arrays`)."""
    c = [int(x) for x in index["summary_counts"]]
    skipped = tuple(SkippedWindow(float(t[0]), float(t[1]), int(n))
                    for t, n in zip(index["skipped_times_s"], index["skipped_n_points"], strict=True))
    return SlicingSummary(c[0], c[1], c[2], c[3], c[4], skipped)


def make_spill_folder(config: SlicingConfig, workdir: str | Path | None = None) -> Path:
    """A new, empty spill folder in ``workdir`` (default ``config.temp_dir`` or the system
    temporary folder). Raises :class:`ConfigError` when it cannot be created."""
    base = workdir or config.temp_dir or None
    try:
        return Path(tempfile.mkdtemp(prefix=SPILL_PREFIX, dir=base))
    except OSError as e:
        where = base or tempfile.gettempdir()
        raise ConfigError(f"[slicing] temp_dir: cannot create the spill folder: {e.strerror or e}",
                          where) from None


def slice_quasi_static(
    trajectory: Trajectory,
    cloud: CloudReader,
    config: SlicingConfig,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    folder: Path | None = None,
    keep_records: bool = False,
) -> QuasiStaticSequence:
    """Slice the run into quasi-static scans.

    ``trajectory`` gives the poses (object frame), ``cloud`` the object-frame points with times.
    Points outside the trajectory's time range are counted and left out (warned about).
    Windows with fewer than ``config.min_points`` points are skipped and listed in the summary.
    ``workdir`` is where the spill folder is created (default ``config.temp_dir`` or the system
    temporary folder); the sequence deletes it on :meth:`~QuasiStaticSequence.close`. With
    ``folder`` (an empty folder from :func:`make_spill_folder`) the points are spilled there
    instead and the folder is the caller's to delete (it is deleted here only when slicing
    fails). Raises :class:`InputError` if no window gets enough points.

    With ``keep_records``, a compressed LAS cloud's decoded point records are also kept in the
    spill folder (:attr:`QuasiStaticSequence.records`), where the disk has room for them.
    """
    progress = progress or NullProgress()
    edges = unit_edges(trajectory, config)
    owns_folder = folder is None
    if folder is None:
        folder = make_spill_folder(config, workdir)
    mid = 0.5 * (edges[:-1] + edges[1:])
    store = _SpillWriter(folder, trajectory.pose_at(np.clip(mid, trajectory.t_start_s, trajectory.t_end_s)).t_xyz)
    n_read = n_outside = 0
    stack = contextlib.ExitStack()
    try:
        progress.start("slice", total=cloud.info.n_points, unit="points")
        stager = _Stager(store, chunk_points)
        # LAS/LAZ: the stored integers, converted while the records are assembled (no float64
        # copy of each chunk); other readers: their float64 chunks.
        iter_raw = getattr(cloud, "iter_raw_chunks", None)
        records = None
        if iter_raw is None:
            chunks = cloud.iter_chunks(chunk_points)
        else:
            records = _records_file(cloud, folder) if keep_records else None
            if records is not None:
                stack.enter_context(records)
            chunks = iter_raw(chunk_points, copy_to=records)
        try:
            for chunk in chunks:  # an OSError here is a write of the decoded copy
                if chunk.stamps_s is None:
                    raise InputError("the cloud has no point times", cloud.path)
                n_read += len(chunk)
                source = _RawSource(chunk) if isinstance(chunk, RawChunk) else _ChunkSource(chunk)
                outside, segments = _unit_segments(chunk.stamps_s, edges)
                n_outside += outside
                for unit, index in segments:
                    stager.spill(unit, source, index)
                progress.advance(len(chunk))
            progress.finish()
            stager.finish()
            store.close()
            if records is not None:
                records.close()
                Path(records.name).replace(folder / RECORDS_FILE)
            (folder / SPILL_COMPLETE).write_bytes(b"")
        except OSError as e:
            raise _spill_error(e, folder.parent, n_read) from None
    except BaseException:
        with contextlib.suppress(OSError):
            store.close()  # waits for queued writes, so that the folder can be deleted
        shutil.rmtree(folder, ignore_errors=True)
        raise
    finally:
        stack.close()

    windows, kept_ranges, skipped, n_ranges = choose_windows(trajectory, edges, store.counts, config)

    n_in_skipped = sum(s.n_points for s in skipped)
    summary = SlicingSummary(
        n_points_read=n_read,
        n_points_in_scans=n_read - n_outside - n_in_skipped,
        n_points_outside_trajectory=n_outside,
        n_points_in_skipped_windows=n_in_skipped,
        n_scans=len(windows),
        skipped=tuple(skipped),
    )
    if n_outside:
        log.warning("%s: %d of %d points (%.1f %%) lie outside the trajectory's time range and are left out",
                    cloud.path, n_outside, n_read, 100.0 * summary.share_outside)
    if skipped:
        log.warning("%d window(s) with fewer than %d points skipped", len(skipped), config.min_points)
    if not windows:
        shutil.rmtree(folder, ignore_errors=True)
        if n_read == n_outside:
            raise InputError(
                f"none of the {n_read:,} points lies in the trajectory's time range "
                f"[{trajectory.t_start_s:.3f}, {trajectory.t_end_s:.3f}] s", cloud.path)
        raise InputError(
            f"no window has at least {config.min_points} points ({n_ranges} windows); "
            "use longer windows or a smaller min_points", cloud.path)
    return QuasiStaticSequence(tuple(windows), tuple(kept_ranges), store, summary, owns_folder=owns_folder)


def _records_file(cloud: CloudReader, folder: Path) -> DirectWriter | None:
    """A new file for ``cloud``'s decoded point records in the spill ``folder`` (renamed to
    :data:`RECORDS_FILE` when complete); ``None`` when the cloud is not compressed (reading it is
    as cheap as reading a copy), the disk lacks room for the copy beside the spill, or the cloud
    is read from the copy in ``folder`` already (:func:`adopt_records`)."""
    decoded = getattr(cloud, "decoded", None)
    if not getattr(cloud, "compressed", False) or (decoded is not None and Path(decoded).parent == folder):
        return None
    n = cloud.info.n_points
    need = n * (int(getattr(cloud, "record_size", 0)) + SPILL_RECORD.itemsize) + _RECORDS_DISK_MARGIN
    free = shutil.disk_usage(folder).free
    if free < need:
        log.info("%s: the spill folder's disk has %.1f GB free, a decoded copy of the cloud beside the spill needs "
                 "%.1f GB: the corrected cloud decodes the cloud again", cloud.path, free / 1e9, need / 1e9)
        return None
    return DirectWriter(folder / f"{RECORDS_FILE}.part")


def adopt_records(decoded: Path | None, folder: Path) -> Path | None:
    """The decoded copy of another spill (``decoded``, of the same cloud) linked into the new
    spill ``folder``, so that slicing again reads it instead of decoding the cloud, and it
    outlives the other spill; ``None`` where there is none or the file system cannot link it."""
    if decoded is None or not decoded.is_file():
        return None
    try:
        os.link(decoded, folder / RECORDS_FILE)
    except OSError:
        return None
    return folder / RECORDS_FILE


def _spill_error(e: OSError, folder: Path, n_read: int) -> OutputError:
    """The one-line error for a failed write to the temporary spill folder."""
    if e.errno == errno.ENOSPC:
        return OutputError(
            f"disk full while spilling points to the temporary folder after {n_read:,} points "
            f"({SPILL_RECORD.itemsize} bytes a point; set [slicing] temp_dir to a larger disk)", folder)
    return OutputError(f"cannot write the temporary slices: {e.strerror or e}", folder)


def _unit_segments(t: np.ndarray, edges: FloatArray) -> tuple[int, list[tuple[int, slice | np.ndarray]]]:
    """The points of a chunk with times ``t`` by unit: the number outside the edges, and
    ``(unit, index)`` pairs in increasing unit order, ``index`` (a slice or an index array) in
    file order.

    Unit ``u`` holds ``edges[u] <= t < edges[u + 1]``; the last edge belongs to the last unit.
    A time-sorted chunk (the usual case) is cut by bisection at the few edges it spans; any other
    by a unit per point and a stable sort.
    """
    n, n_units = len(t), len(edges) - 1
    if n == 0:
        return 0, []
    if n == 1 or bool(np.all(t[1:] >= t[:-1])):  # false with a NaN time
        lo, hi = bisect_left(t, edges[0]), bisect_right(t, edges[-1])
        if lo >= hi:
            return n, []
        first, last = (min(int(np.searchsorted(edges, t[i], side="right")) - 1, n_units - 1) for i in (lo, hi - 1))
        segments: list[tuple[int, slice | np.ndarray]] = []
        a = lo
        for u in range(first, last + 1):
            b = hi if u == last else bisect_left(t, edges[u + 1], a, hi)
            if b > a:
                segments.append((u, slice(a, b)))
            a = b
        return n - (hi - lo), segments
    unit = np.searchsorted(edges, t, side="right") - 1
    unit[t == edges[-1]] = n_units - 1
    inside = (unit >= 0) & (unit < n_units)
    n_inside = int(np.count_nonzero(inside))
    keep: np.ndarray | None = None
    if n_inside < n:
        keep = np.flatnonzero(inside)
        unit = unit[keep]
    if n_inside == 0:
        return n, []
    order = keep
    if not np.all(unit[1:] >= unit[:-1]):
        # A stable sort keeps the file order of points within each window.
        by_unit = np.argsort(unit, kind="stable")
        unit = unit[by_unit]
        order = by_unit if keep is None else keep[by_unit]
    cuts = np.flatnonzero(np.diff(unit)) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [len(unit)]])
    return n - n_inside, [(int(unit[a]), slice(int(a), int(b)) if order is None else order[a:b])
                          for a, b in zip(starts, stops, strict=True)]


class _RawSource:
    """Spill fields of a :class:`RawChunk` (stored integers, converted here)."""

    def __init__(self, chunk: RawChunk) -> None:
        self.chunk = chunk
        self.stamps_s = chunk.stamps_s
        self.intensity = chunk.intensity

    def offsets(self, k: int, index: slice | np.ndarray, origin: float, out: FloatArray) -> None:
        """Coordinate ``k`` of the points at ``index`` minus ``origin`` into ``out`` (float64,
        the same operations in the same order as the reader's float64 coordinates minus origin)."""
        np.subtract(self.chunk.coordinate(k, index, out), origin, out=out)


class _ChunkSource:
    """Spill fields of a :class:`CloudChunk` (float64 coordinates)."""

    def __init__(self, chunk: CloudChunk) -> None:
        self.xyz = chunk.xyz
        self.stamps_s = chunk.stamps_s
        self.intensity = chunk.intensity

    def offsets(self, k: int, index: slice | np.ndarray, origin: float, out: FloatArray) -> None:
        np.subtract(self.xyz[index, k], origin, out=out)


class _Stager:
    """Assembles spill records (float32 offsets from the unit's origin, time, intensity) in two
    reused buffers of about a chunk each, handing each unit's run of points to the store as one
    write: the write (in the store's thread, without the GIL) then overlaps with decoding the
    next chunk, which holds the GIL. A full buffer is filled again once its writes are done."""

    def __init__(self, store: _SpillWriter, chunk_points: int) -> None:
        self.store = store
        capacity = max(_BLOCK_POINTS, min(chunk_points, _STAGING_POINTS))
        self.buffers = [np.empty(capacity, dtype=SPILL_RECORD) for _ in range(2)]
        self.pending: list[list[Future[None]]] = [[] for _ in self.buffers]
        self.current = 0  # the buffer being filled
        self.used = 0  # points in it
        self.tmp = np.empty(_BLOCK_POINTS, dtype=np.float64)

    def _wait(self, k: int) -> None:
        pending, self.pending[k] = self.pending[k], []
        for done in pending:
            done.result()

    def spill(self, unit: int, source: _RawSource | _ChunkSource, index: slice | np.ndarray) -> None:
        """Append the points of ``source`` at ``index`` (a slice or an index array), in that order,
        to ``unit``."""
        origin = self.store.origins[unit]
        start, n = (index.start, index.stop - index.start) if isinstance(index, slice) else (0, len(index))
        s = 0
        while s < n:
            rec = self.buffers[self.current]
            if self.used == len(rec):  # full: go on in the other buffer once its writes are done
                self.current = (self.current + 1) % len(self.buffers)
                self.used = 0
                self._wait(self.current)
                continue
            m = min(len(rec) - self.used, n - s)
            out = rec[self.used: self.used + m]
            xyz_out, t_out, i_out = (out["x"], out["y"], out["z"]), out["t"], out["intensity"]
            for a in range(0, m, _BLOCK_POINTS):
                b = min(a + _BLOCK_POINTS, m)
                sel = (slice(start + s + a, start + s + b) if isinstance(index, slice)
                       else index[s + a: s + b])
                tmp = self.tmp[: b - a]
                for k in range(3):
                    source.offsets(k, sel, origin[k], tmp)
                    xyz_out[k][a:b] = tmp
                t_out[a:b] = source.stamps_s[sel]  # type: ignore[index]
                i_out[a:b] = 0.0 if source.intensity is None else source.intensity[sel]
            self.pending[self.current].append(self.store.append(unit, out))
            self.used += m
            s += m

    def finish(self) -> None:
        """Wait for every write; raises the :class:`OSError` of a failed one."""
        for k in range(len(self.buffers)):
            self._wait(k)
