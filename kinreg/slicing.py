"""Cut a kinematic run into quasi-static scans (METHOD.md section 2, step 2).

The trajectory is split into short windows; each window's virtual scanner centre ``T_obj_scan``
is the trajectory row nearest the window's middle, and the window's points are expressed in that
frame: ``p_scan = T_obj_scan^-1 p_obj``. The geometry is unchanged, only the parametrisation.

The cloud is streamed once. Each point goes to the spill file of its window in a temporary folder
(float32 offsets from the window's origin, float64 time, float32 intensity: 24 bytes a point), so memory
stays bounded whatever the cloud's size and whether or not it is time-sorted. Scans are then
handed out one at a time.

A finished spill can be reopened (:meth:`QuasiStaticSequence.reopen`) from its small index
(:meth:`QuasiStaticSequence.index_arrays`, plain arrays for the stage cache): ``kinreg process
--resume`` does so after an interrupted run instead of streaming the cloud again. A spill folder
is complete only when it holds the ``.complete`` mark, written after the last point.
"""

from __future__ import annotations

import errno
import logging
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from kinreg.cache import windows_from_arrays, windows_to_arrays
from kinreg.config import SlicingConfig, WindowMode
from kinreg.errors import ConfigError, InputError, OutputError
from kinreg.geometry import FloatArray
from kinreg.io.cloud import DEFAULT_CHUNK_POINTS, CloudReader
from kinreg.progress import NullProgress, Progress
from kinreg.types import CloudChunk, Scan, ScanKind, ScanWindow, Trajectory

log = logging.getLogger(__name__)

# Coordinates are float32 offsets from the unit's origin (the trajectory position at the unit's
# middle): points within a few hundred metres of it keep better than 0.02 mm, and the spill
# (the slicing stage's disk traffic) is a third smaller than with float64 coordinates.
SPILL_RECORD = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<f8"), ("intensity", "<f4")])

# In POINTS mode the cloud is first spilled into bins of this length; windows are then formed
# from consecutive bins, so the point counts need no extra pass over the cloud.
POINT_MODE_BIN_S = 0.25

# Open spill files kept at once; a time-sorted cloud touches one or two per chunk.
_MAX_OPEN_FILES = 64

SPILL_PREFIX = "kinreg-slices-"  # name prefix of every spill folder
SPILL_COMPLETE = ".complete"  # written into a spill folder after its last point


@dataclass(frozen=True)
class SkippedWindow:
    """A window that had too few points to become a scan."""

    t_start_s: float
    t_end_s: float
    n_points: int


@dataclass(frozen=True)
class SlicingSummary:
    """What slicing did, for reports."""

    n_points_read: int
    n_points_in_scans: int
    n_points_outside_trajectory: int
    n_points_in_skipped_windows: int
    n_scans: int
    skipped: tuple[SkippedWindow, ...]

    @property
    def share_outside(self) -> float:
        return self.n_points_outside_trajectory / self.n_points_read if self.n_points_read else 0.0


def unit_edges(trajectory: Trajectory, config: SlicingConfig) -> FloatArray:
    """Time edges (seconds, increasing) of the spill units covering the trajectory.

    DURATION and PATH: one unit per window, of about equal duration / path length.
    POINTS: bins of ``POINT_MODE_BIN_S``, grouped into windows after counting.
    """
    t0, t1 = trajectory.t_start_s, trajectory.t_end_s
    duration = t1 - t0
    if config.mode is WindowMode.DURATION:
        n = max(1, round(duration / config.window_s))
        return np.linspace(t0, t1, n + 1)
    if config.mode is WindowMode.PATH:
        step = np.linalg.norm(np.diff(trajectory.poses.t_xyz, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(step)])
        n = max(1, round(s[-1] / config.window_path_m))
        # Standing still adds no path; interpolating on the strictly increasing part avoids
        # ambiguous edges there.
        keep = np.concatenate([[True], np.diff(s) > 0])
        edges = np.interp(np.linspace(0.0, s[-1], n + 1), s[keep], trajectory.stamps_s[keep])
        edges[0], edges[-1] = t0, t1
        return np.unique(edges)
    n = max(1, int(np.ceil(duration / POINT_MODE_BIN_S)))
    return np.linspace(t0, t1, n + 1)


def _group_point_bins(counts: np.ndarray, target: int) -> list[tuple[int, int]]:
    """Consecutive bin ranges [a, b) holding about ``target`` points each."""
    groups: list[tuple[int, int]] = []
    start, acc = 0, 0
    for k, c in enumerate(counts):
        acc += int(c)
        if acc >= target:
            groups.append((start, k + 1))
            start, acc = k + 1, 0
    if start < len(counts):
        if groups and acc < target // 2:
            groups[-1] = (groups[-1][0], len(counts))  # a short remainder joins the last window
        else:
            groups.append((start, len(counts)))
    return groups


class _SpillWriter:
    """Appends point records to one file per unit, keeping a bounded number of files open."""

    def __init__(self, folder: Path, origins: FloatArray) -> None:
        self.folder = folder
        self.origins = origins  # (n_units, 3) object-frame origin of each unit's offsets
        self.counts = np.zeros(len(origins), dtype=np.int64)
        self._open: OrderedDict[int, BinaryIO] = OrderedDict()

    def path(self, unit: int) -> Path:
        return self.folder / f"unit_{unit:06d}.bin"

    def append(self, unit: int, records: np.ndarray) -> None:
        f = self._open.pop(unit, None)
        if f is None:
            if len(self._open) >= _MAX_OPEN_FILES:
                _, oldest = self._open.popitem(last=False)
                oldest.close()
            f = open(self.path(unit), "ab")  # noqa: SIM115  (kept open across chunks, closed in close())
        self._open[unit] = f
        records.tofile(f)
        self.counts[unit] += len(records)

    def close(self) -> None:
        for f in self._open.values():
            f.close()
        self._open.clear()


def _records(chunk: CloudChunk, stamps_s: FloatArray, index: np.ndarray | slice,
             origin: FloatArray) -> np.ndarray:
    xyz = chunk.xyz[index] - origin
    rec = np.empty(len(xyz), dtype=SPILL_RECORD)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["t"] = stamps_s[index]
    rec["intensity"] = 0.0 if chunk.intensity is None else chunk.intensity[index]
    return rec


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
        parts = [np.fromfile(self._store.path(u), dtype=SPILL_RECORD) for u in units]
        rec = np.concatenate(parts) if len(parts) != 1 else parts[0]
        origin = np.repeat(self._store.origins[units], [len(p) for p in parts], axis=0)
        xyz_obj = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64) + origin
        return Scan(
            scan_id=w.scan_id,
            name=w.name,
            kind=ScanKind.QUASI_STATIC,
            T_obj_scan=w.T_obj_scan,
            points_xyz=w.T_obj_scan.apply_inverse(xyz_obj),
            stamps_s=np.ascontiguousarray(rec["t"]),
            intensity=np.ascontiguousarray(rec["intensity"]),
            t_s=w.t_s,
            t_start_s=w.t_start_s,
            t_end_s=w.t_end_s,
        )

    def iter_scans(self) -> Iterator[Scan]:
        for i in range(len(self.windows)):
            yield self.read_scan(i)

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
    """
    progress = progress or NullProgress()
    edges = unit_edges(trajectory, config)
    n_units = len(edges) - 1
    owns_folder = folder is None
    if folder is None:
        folder = make_spill_folder(config, workdir)
    mid = 0.5 * (edges[:-1] + edges[1:])
    store = _SpillWriter(folder, trajectory.pose_at(np.clip(mid, trajectory.t_start_s, trajectory.t_end_s)).t_xyz)
    n_read = n_outside = 0
    try:
        progress.start("slice", total=cloud.info.n_points, unit="points")
        for chunk in cloud.iter_chunks(chunk_points):
            if chunk.stamps_s is None:
                raise InputError("the cloud has no point times", cloud.path)
            n_read += len(chunk)
            t = chunk.stamps_s
            unit = np.searchsorted(edges, t, side="right") - 1
            unit[t == edges[-1]] = n_units - 1  # the last edge belongs to the last window
            inside = (unit >= 0) & (unit < n_units)
            n_outside += len(t) - int(np.count_nonzero(inside))
            if not inside.all():
                keep = np.flatnonzero(inside)
                chunk = CloudChunk(chunk.xyz[keep], t[keep],
                                   None if chunk.intensity is None else chunk.intensity[keep])
                unit, t = unit[keep], t[keep]
            try:
                _spill_chunk(store, chunk, t, unit)
            except OSError as e:
                raise _spill_error(e, folder.parent, n_read) from None
            progress.advance(len(inside))
        progress.finish()
        store.close()
        try:
            (folder / SPILL_COMPLETE).write_bytes(b"")
        except OSError as e:
            raise _spill_error(e, folder.parent, n_read) from None
    except BaseException:
        store.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise

    if config.mode is WindowMode.POINTS:
        ranges = _group_point_bins(store.counts, config.window_points)
    else:
        ranges = [(k, k + 1) for k in range(n_units)]

    windows: list[ScanWindow] = []
    kept_ranges: list[tuple[int, int]] = []
    skipped: list[SkippedWindow] = []
    for a, b in ranges:
        n = int(store.counts[a:b].sum())
        t_start, t_end = float(edges[a]), float(edges[b])
        if n < config.min_points:
            skipped.append(SkippedWindow(t_start, t_end, n))
            continue
        k = trajectory.nearest_index(0.5 * (t_start + t_end))
        windows.append(ScanWindow(len(windows), t_start, t_end, float(trajectory.stamps_s[k]),
                                  trajectory.poses[k]))
        kept_ranges.append((a, b))

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
            f"no window has at least {config.min_points} points ({len(ranges)} windows); "
            "use longer windows or a smaller min_points", cloud.path)
    return QuasiStaticSequence(tuple(windows), tuple(kept_ranges), store, summary, owns_folder=owns_folder)


def _spill_error(e: OSError, folder: Path, n_read: int) -> OutputError:
    """The one-line error for a failed write to the temporary spill folder."""
    if e.errno == errno.ENOSPC:
        return OutputError(
            f"disk full while spilling points to the temporary folder after {n_read:,} points "
            f"({SPILL_RECORD.itemsize} bytes a point; set [slicing] temp_dir to a larger disk)", folder)
    return OutputError(f"cannot write the temporary slices: {e.strerror or e}", folder)


def _spill_chunk(store: _SpillWriter, chunk: CloudChunk, stamps_s: FloatArray, unit: np.ndarray) -> None:
    """Append the chunk's points to their units' files, keeping file order within a unit."""
    if len(unit) == 0:
        return
    if np.all(unit[1:] >= unit[:-1]):
        order: np.ndarray | None = None
        sorted_unit = unit
    else:
        # A stable sort keeps the file order of points within each window.
        order = np.argsort(unit, kind="stable")
        sorted_unit = unit[order]
    cuts = np.flatnonzero(np.diff(sorted_unit)) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [len(sorted_unit)]])
    for a, b in zip(starts, stops, strict=True):
        index = slice(a, b) if order is None else order[a:b]
        target = int(sorted_unit[a])
        store.append(target, _records(chunk, stamps_s, index, store.origins[target]))
