"""The quasi-static windows of a run (METHOD.md section 2, step 2): where the trajectory is cut,
and each window's virtual scanner centre ``T_obj_scan`` (the trajectory row nearest its middle).
Streaming the points into the windows is :mod:`kinreg.run.spill`."""

from __future__ import annotations

import numpy as np

from kinreg.config import SlicingConfig, WindowMode
from kinreg.geometry import FloatArray
from kinreg.types import ScanWindow, SkippedWindow, Trajectory

# In POINTS mode the cloud is first spilled into bins of this length; windows are then formed
# from consecutive bins, so the point counts need no extra pass over the cloud.
POINT_MODE_BIN_S = 0.25


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


def choose_windows(trajectory: Trajectory, edges: FloatArray, counts: np.ndarray, config: SlicingConfig,
                   ) -> tuple[list[ScanWindow], list[tuple[int, int]], list[SkippedWindow], int]:
    """The scans' windows from the spill units (``edges``, ``counts`` points per unit): one unit
    per window, or (``WindowMode.POINTS``) consecutive units up to ``config.window_points``.
    Returns the windows with at least ``config.min_points`` points, their unit ranges, the
    skipped windows, and the number of windows considered."""
    if config.mode is WindowMode.POINTS:
        ranges = _group_point_bins(counts, config.window_points)
    else:
        ranges = [(k, k + 1) for k in range(len(edges) - 1)]
    windows: list[ScanWindow] = []
    kept_ranges: list[tuple[int, int]] = []
    skipped: list[SkippedWindow] = []
    for a, b in ranges:
        n = int(counts[a:b].sum())
        t_start, t_end = float(edges[a]), float(edges[b])
        if n < config.min_points:
            skipped.append(SkippedWindow(t_start, t_end, n))
            continue
        k = trajectory.nearest_index(0.5 * (t_start + t_end))
        windows.append(ScanWindow(len(windows), t_start, t_end, float(trajectory.stamps_s[k]),
                                  trajectory.poses[k]))
        kept_ranges.append((a, b))
    return windows, kept_ranges, skipped, len(ranges)
