"""The input checks that run before the long work of ``kinreg process``/``slice``/``link``.

Each reader checks its own file's structure when it opens it; what needs two inputs or a look at
the points (the cloud's time base against the trajectory, the share of points without a finite
time, the static scans' points) is run from here, in seconds, before the slicing pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from kinreg.io.cloud import TimeFilter
from kinreg.io.timebase import check_cloud_times
from kinreg.types import Trajectory

if TYPE_CHECKING:
    from kinreg.config import InputConfig


def time_filter(config: InputConfig) -> TimeFilter:
    """The reader's handling of point times under ``[input]``: offset and dropped share."""
    return TimeFilter(config.cloud_time_offset_s, config.max_dropped_share)


def check_inputs(clouds: Sequence[str | Path], trajectories: Sequence[Trajectory], static: str | Path | None,
                 config: InputConfig) -> None:
    """Check each cloud against its trajectory (:func:`~kinreg.io.timebase.check_cloud_times`)
    and the static scans' poses and points (:func:`~kinreg.io.e57.check_static_scans`).
    Raises :class:`~kinreg.errors.InputError` naming the file."""
    for cloud, trajectory in zip(clouds, trajectories, strict=True):
        check_cloud_times(cloud, trajectory, config.cloud_time_offset_s, config.max_dropped_share,
                          config.check_time_base)
    if static is not None:
        from kinreg.io.e57 import check_static_scans

        check_static_scans(static)
