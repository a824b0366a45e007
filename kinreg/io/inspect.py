"""What a trajectory or cloud file contains, as (label, value) rows for display."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kinreg.io.cloud import open_cloud
from kinreg.io.trajectory import read_trajectory
from kinreg.progress import NullProgress, Progress


def _xyz(v: np.ndarray | tuple[float, ...]) -> str:
    return "  ".join(f"{c:.3f}" for c in v)


def describe_trajectory(path: str | Path, fmt: str | None = None) -> list[tuple[str, str]]:
    """Rows: poses, time range, rate, path length, extent."""
    traj = read_trajectory(path, fmt)
    xyz = traj.poses.t_xyz
    dt = np.diff(traj.stamps_s)
    return [
        ("kind", "trajectory"),
        ("poses", f"{len(traj):,}"),
        ("time range [s]", f"{traj.t_start_s:.6f} .. {traj.t_end_s:.6f}"),
        ("duration", f"{traj.duration_s:.3f} s ({traj.duration_s / 60:.1f} min)"),
        ("rate", f"{1.0 / np.median(dt):.1f} Hz (largest gap {dt.max():.3f} s)"),
        ("path length", f"{traj.path_length_m():.3f} m"),
        ("extent min [m]", _xyz(xyz.min(axis=0))),
        ("extent max [m]", _xyz(xyz.max(axis=0))),
    ]


def describe_cloud(path: str | Path, full: bool = False, progress: Progress | None = None) -> list[tuple[str, str]]:
    """Rows from the header; with ``full`` the whole cloud is streamed for its time range and order."""
    progress = progress or NullProgress()
    with open_cloud(path, require_time=False) as reader:
        info = reader.info
        rows = [
            ("kind", "point cloud"),
            ("format", info.format),
            ("points", f"{info.n_points:,}"),
            ("scans", f"{info.n_scans}"),
            ("fields", ", ".join(info.fields)),
            ("point times", "yes" if info.has_time else "NO (kinreg needs them)"),
        ]
        if info.bounds_min is not None and info.bounds_max is not None:
            rows += [("extent min [m]", _xyz(info.bounds_min)), ("extent max [m]", _xyz(info.bounds_max))]
        if info.time_range_s is not None:
            rows.append(("acquisition [s]", f"{info.time_range_s[0]:.6f} .. {info.time_range_s[1]:.6f}"))
        rows += [(k, v) for k, v in info.details.items() if v]
        if full and info.has_time:
            t_min, t_max, sorted_ok, last = np.inf, -np.inf, True, -np.inf
            progress.start("read", total=info.n_points, unit="points")
            for chunk in reader.iter_chunks():
                t = chunk.stamps_s
                t = None if t is None else t[np.isfinite(t)]  # counted by the reader (reader.times)
                if t is None or len(t) == 0:
                    continue
                t_min, t_max = min(t_min, float(t.min())), max(t_max, float(t.max()))
                sorted_ok = sorted_ok and t[0] >= last and bool(np.all(np.diff(t) >= 0))
                last = float(t[-1])
                progress.advance(len(t))
            progress.finish()
            rows.append(("time range [s]", f"{t_min:.6f} .. {t_max:.6f} ({t_max - t_min:.3f} s)"))
            rows.append(("time-sorted", "yes" if sorted_ok else "no"))
            rows.append(("points without finite time", f"{reader.times.n_nonfinite:,}"))
    return rows
