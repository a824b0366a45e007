"""What every point cloud reader shares: the header's summary, raw LAS chunks, the filter of
point times, and the reader protocol. :func:`kinreg.io.cloud.open_cloud` picks the reader of a
file; the readers (:mod:`kinreg.io.las`, :mod:`kinreg.io.e57`) build on this module, never on
``cloud``, which imports them.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from kinreg.errors import CloudError
from kinreg.types import CloudChunk

log = logging.getLogger(__name__)

DEFAULT_CHUNK_POINTS = 2_000_000


@dataclass(frozen=True)
class CloudInfo:
    """What a cloud file holds, read from its header(s) without decoding the points.

    ``bounds_min``/``bounds_max`` are object-frame (x, y, z) where the header states them.
    ``time_range_s`` is filled only where the header states it (LAS does not).
    """

    path: str
    format: str
    n_points: int
    fields: tuple[str, ...]
    has_time: bool
    n_scans: int = 1
    bounds_min: tuple[float, float, float] | None = None
    bounds_max: tuple[float, float, float] | None = None
    time_range_s: tuple[float, float] | None = None
    details: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class RawChunk:
    """A block of points as a LAS file stores them, for a consumer that converts them itself
    (see :meth:`~kinreg.io.las.LasCloudReader.iter_raw_chunks`).

    Coordinate ``k`` of point ``i`` in the object frame is ``ints[k][i] * scales[k] + offsets[k]``,
    evaluated in float64 in that order (:meth:`coordinate`, which ``iter_chunks`` uses too). ``intensity`` holds
    the stored values (``iter_chunks`` gives them as float32). The arrays are strided views into a
    buffer the reader reuses: they are valid only until the next chunk is requested.
    """

    ints: tuple[np.ndarray, np.ndarray, np.ndarray]
    scales: tuple[np.float64, np.float64, np.float64]
    offsets: tuple[np.float64, np.float64, np.float64]
    stamps_s: np.ndarray | None
    intensity: np.ndarray | None
    first_index: int = 0

    def __len__(self) -> int:
        return len(self.ints[0])

    def coordinate(self, k: int, index: slice | np.ndarray, out: np.ndarray) -> np.ndarray:
        """Object-frame coordinate ``k`` (float64) of the points at ``index``, into ``out``."""
        np.multiply(self.ints[k][index], self.scales[k], out=out)
        return np.add(out, self.offsets[k], out=out)


class TimeFilter:
    """What a reader does with the point times it decodes: adds ``offset_s`` (the cloud's time
    base into the trajectory's, ``[input] cloud_time_offset_s``) and counts the points whose time
    is not finite. Such points are left in the chunk with their NaN/inf time, which every consumer
    treats as outside the trajectory (slicing skips them, the corrected cloud drops them).

    At the end of a full pass (:meth:`finish`) the count is logged, and above
    ``max_dropped_share`` of the points it raises :class:`CloudError` naming the file.
    """

    def __init__(self, offset_s: float = 0.0, max_dropped_share: float = 1.0) -> None:
        self.offset_s = float(offset_s)
        self.max_dropped_share = float(max_dropped_share)
        self.n_points = 0
        self.n_seen = 0
        self.n_nonfinite = 0

    def restart(self, n_points: int) -> None:
        self.n_points, self.n_seen, self.n_nonfinite = n_points, 0, 0

    def apply(self, stamps_s: np.ndarray, path: Path) -> np.ndarray:
        """``stamps_s`` shifted by the offset (in place where it is writable float64), counted."""
        if self.offset_s:
            if stamps_s.dtype == np.float64 and stamps_s.flags.writeable:
                stamps_s += self.offset_s
            else:
                stamps_s = stamps_s + self.offset_s
        finite = int(np.count_nonzero(np.isfinite(stamps_s)))
        self.n_seen += len(stamps_s)
        self.n_nonfinite += len(stamps_s) - finite
        return stamps_s

    def check_share(self, n_bad: int, n_total: int, path: Path, sampled: bool = False) -> None:
        """Raise :class:`CloudError` when ``n_bad`` of ``n_total`` exceeds ``max_dropped_share``."""
        if n_total and n_bad / n_total > self.max_dropped_share:
            what = "of a sample of" if sampled else "of"
            raise CloudError(f"{n_bad:,} {what} {n_total:,} points ({100 * n_bad / n_total:.1f} %) have no finite "
                             f"time; more than [input] max_dropped_share = {self.max_dropped_share:g}", path)

    def finish(self, path: Path) -> None:
        """After a full pass: log the points dropped for their time, refuse above the share."""
        if self.n_nonfinite:
            log.warning("%s: %d of %d points have no finite time and are left out", path, self.n_nonfinite,
                        self.n_seen)
        self.check_share(self.n_nonfinite, self.n_seen, path)


class CloudReader(Protocol):
    """A streaming reader. Use as a context manager; iterate ``iter_chunks`` once or more.

    A reader may also offer ``iter_raw_chunks(chunk_points)`` yielding :class:`RawChunk` blocks
    (the LAS/LAZ reader does); consumers that use it must fall back to ``iter_chunks`` without it.
    """

    path: Path
    info: CloudInfo
    times: TimeFilter

    def iter_chunks(self, chunk_points: int = DEFAULT_CHUNK_POINTS) -> Iterator[CloudChunk]: ...

    def close(self) -> None: ...

    def __enter__(self) -> CloudReader: ...

    def __exit__(self, *exc: object) -> None: ...
