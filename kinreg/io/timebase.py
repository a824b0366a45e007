"""Do the cloud's point times and the trajectory's poses share one time base?

A cloud in GPS time and a trajectory in UTC are 18 s apart (the GPS-UTC leap seconds since 2017);
Unix and GPS seconds differ by 315,964,800 s less the leap seconds; GPS "adjusted standard time"
(LAS global encoding bit 0) is GPS time less 1e9 s; GPS week seconds restart every 604,800 s.
Sliced with the wrong base, every window takes its pose from another moment: the adjustment
passes its tests and the result is metres off. :func:`diagnose_time_base` compares a sample of the
cloud's times with the trajectory's range and names the likely offset; :func:`check_cloud_times`
runs it on a file before the long work.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinreg.errors import CloudError
from kinreg.io.cloud import TimeFilter, open_cloud
from kinreg.types import Trajectory

GPS_UNIX_EPOCH_S = 315_964_800.0  # 1980-01-06 minus 1970-01-01, in seconds
GPS_ADJUSTED_OFFSET_S = 1e9  # GPS adjusted standard time = GPS time - 1e9 s
GPS_WEEK_S = 604_800.0
MAX_LEAP_S = 18  # GPS - UTC since 2017-01-01
MIN_LEAP_S = 10  # GPS - UTC since 1994; smaller counts predate kinematic laser scanning
# Outside share of the cloud's times an offset must leave at most, and beat the unshifted share by.
_FIT_SHARE = 0.001
# Unshifted share outside the trajectory from which a fitting recognised offset is reported.
_MIN_SHARE_FOR_OFFSET = 0.002


@dataclass(frozen=True)
class TimeBaseProblem:
    """The cloud's times do not fit the trajectory's: ``share_outside`` of the sampled times lie
    outside its range; ``offset_s`` (added to the cloud's times) and ``offset_name`` name the
    recognised offset that makes them fit, ``None`` when none does."""

    cloud_range_s: tuple[float, float]
    trajectory_range_s: tuple[float, float]
    share_outside: float
    offset_s: float | None
    offset_name: str

    def message(self) -> str:
        c0, c1 = self.cloud_range_s
        t0, t1 = self.trajectory_range_s
        text = (f"point times {c0:.3f} .. {c1:.3f} s do not fit the trajectory's {t0:.3f} .. {t1:.3f} s "
                f"({100 * self.share_outside:.1f} % outside); ")
        if self.offset_s is None:
            return text + "no recognised time-base offset explains it"
        return text + (f"likely offset {self.offset_s:+.0f} s ({self.offset_name}): "
                       f"set [input] cloud_time_offset_s = {self.offset_s:.0f}")


def recognised_offsets(cloud_mid_s: float, trajectory_mid_s: float) -> list[tuple[float, str]]:
    """Offsets (added to cloud times) that a time-base mix-up produces, most likely first.

    >>> recognised_offsets(0.0, 0.0)[0]
    (-18.0, 'GPS-UTC leap seconds')
    """
    found: list[tuple[float, str]] = []
    leaps = sorted(range(MIN_LEAP_S, MAX_LEAP_S + 1), key=lambda n: MAX_LEAP_S - n)
    for n in leaps:
        found += [(-float(n), "GPS-UTC leap seconds"), (float(n), "UTC-GPS leap seconds")]
    for n in [*leaps, 0]:  # 0: a conversion that ignored the leap seconds
        unix_minus_gps = GPS_UNIX_EPOCH_S - n
        found += [(unix_minus_gps, "GPS seconds to Unix"), (-unix_minus_gps, "Unix seconds to GPS")]
    found += [(GPS_ADJUSTED_OFFSET_S, "GPS adjusted standard time to GPS time"),
              (-GPS_ADJUSTED_OFFSET_S, "GPS time to GPS adjusted standard time")]
    for n in [*leaps, 0]:  # 0: a conversion that ignored the leap seconds
        found += [(GPS_ADJUSTED_OFFSET_S + GPS_UNIX_EPOCH_S - n, "GPS adjusted standard time to Unix"),
                  (-(GPS_ADJUSTED_OFFSET_S + GPS_UNIX_EPOCH_S - n), "Unix to GPS adjusted standard time")]
    # GPS week seconds on one side: whole weeks plus one of the bases above.
    for base, name in [(0.0, "GPS time"), (-GPS_ADJUSTED_OFFSET_S, "GPS adjusted standard time"),
                       (GPS_UNIX_EPOCH_S - MAX_LEAP_S, "Unix time")]:
        weeks = round((trajectory_mid_s - cloud_mid_s - base) / GPS_WEEK_S)
        if weeks:
            found.append((weeks * GPS_WEEK_S + base, f"GPS week seconds to {name}, week {abs(weeks)}"))
    return found


def diagnose_time_base(
    cloud_times_s: np.ndarray, trajectory_range_s: tuple[float, float], max_outside_share: float
) -> TimeBaseProblem | None:
    """``None`` when the cloud's (sampled) times fit the trajectory's range ``(t_start, t_end)``.

    A problem when more than ``max_outside_share`` of the finite times lie outside the range, or
    when some lie outside and a recognised offset (:func:`recognised_offsets`) puts (almost) all
    of them inside. Non-finite times are ignored (they are counted elsewhere).
    """
    t = np.asarray(cloud_times_s, dtype=np.float64)
    t = t[np.isfinite(t)]
    if len(t) == 0:
        return None
    t0, t1 = trajectory_range_s

    def outside(shift: float) -> float:
        s = t + shift
        return float(np.count_nonzero((s < t0) | (s > t1))) / len(t)

    share = outside(0.0)
    if share == 0.0:
        return None
    mid = 0.5 * (float(t.min()) + float(t.max()))
    best: tuple[float, str] | None = None
    best_share = share
    for offset, name in recognised_offsets(mid, 0.5 * (t0 + t1)):
        s = outside(offset)
        if s < best_share and s <= _FIT_SHARE:
            best, best_share = (offset, name), s
            if s == 0.0:
                break
    cloud_range = (float(t.min()), float(t.max()))
    if best is not None and share >= _MIN_SHARE_FOR_OFFSET:
        return TimeBaseProblem(cloud_range, (t0, t1), share, best[0], best[1])
    if share > max_outside_share:
        return TimeBaseProblem(cloud_range, (t0, t1), share, None, "")
    return None


def check_cloud_times(
    cloud_path: str | Path,
    trajectory: Trajectory,
    offset_s: float = 0.0,
    max_dropped_share: float = 0.05,
    check_time_base: bool = True,
) -> None:
    """Before the long work: sample the cloud's point times (shifted by ``offset_s``) and refuse
    with :class:`CloudError` naming the cloud when more than ``max_dropped_share`` of them are not
    finite, or (with ``check_time_base``) when :func:`diagnose_time_base` finds a problem. Readers
    without ``sample_times`` (E57) are left to the counts of the full pass."""
    times = TimeFilter(offset_s, max_dropped_share)
    with open_cloud(cloud_path, times=times) as cloud:
        sample_times = getattr(cloud, "sample_times", None)
        if sample_times is None:
            return
        sample = sample_times()
    n_bad = int(np.count_nonzero(~np.isfinite(sample)))
    times.check_share(n_bad, len(sample), Path(cloud_path), sampled=True)
    finite = sample[np.isfinite(sample)]
    if len(finite) > 1 and finite.min() == finite.max():
        raise CloudError(f"all sampled point times are equal ({finite[0]:.6f} s): no time to slice by", cloud_path)
    if not check_time_base:
        return
    problem = diagnose_time_base(sample, (trajectory.t_start_s, trajectory.t_end_s), max_dropped_share)
    if problem is not None:
        raise CloudError(problem.message() + f" (trajectory {trajectory.source})", cloud_path)
