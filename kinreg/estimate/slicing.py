"""The quasi-static windows of a run (METHOD.md section 2, step 2): where the trajectory is cut,
and each window's virtual scanner centre ``T_obj_scan`` (the trajectory row nearest its middle).
Streaming the points into the windows is :mod:`kinreg.run.spill`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from kinreg.config import SlicingConfig, WindowMode
from kinreg.estimate.drift import DriftRates, rows_covering
from kinreg.geometry import FloatArray
from kinreg.types import Plane, ScanKind, ScanWindow, SkippedWindow, Station, Trajectory

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


# The sensor's positions through one window, in its scan frame: times (m,), positions (m, 3).
SensorTrack = tuple[FloatArray, FloatArray]


def sensor_track(trajectory: Trajectory, window: ScanWindow) -> SensorTrack:
    """The trajectory's rows that cover ``window`` (one beyond either end), the positions in the
    window's scan frame (``T_obj_scan^-1``): where the sensor was when it saw each point."""
    rows = rows_covering(trajectory.stamps_s, window.t_start_s, window.t_end_s)
    return trajectory.stamps_s[rows], window.T_obj_scan.apply_inverse(trajectory.poses.t_xyz[rows])


def window_smear_m(stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]], rates: DriftRates) -> FloatArray:
    """Per station: how far the measured drift moves a plane over half its window [m], the
    position rate and the rotation rate times the median distance of the station's planes
    (``nan`` for static stations and stations without planes). Drift inside a window smears the
    planes of a quasi-static scan: the scan is quasi-static only while this stays below the
    planes' noise (METHOD.md section 2, step 2)."""
    pos = float(np.linalg.norm(rates.pos_m_per_s))
    rot = float(np.linalg.norm(rates.rot_rad_per_s))
    smear = np.full(len(stations), np.nan)
    for k, (s, found) in enumerate(zip(stations, planes, strict=True)):
        if s.kind is not ScanKind.QUASI_STATIC or not found:
            continue
        half = 0.5 * (s.t_end_s - s.t_start_s)
        reach = float(np.median([np.linalg.norm(p.centroid_xyz) for p in found]))
        smear[k] = half * float(np.hypot(pos, rot * reach))
    return smear


def shorter_window_s(window_s: float, smear_m: FloatArray, planes: Sequence[tuple[Plane, ...]],
                     config: SlicingConfig, planes_show_it: bool = True) -> float | None:
    """A window length [s] that keeps the median smear (:func:`window_smear_m`) within
    ``config.max_smear_share`` of the planes' median noise, in half seconds, not below
    ``config.min_window_s``; ``None`` where the current windows are short enough (or cannot be
    made shorter, or the windows are not cut by duration). A smear within
    ``config.shown_smear_share`` of the noise counts only where ``planes_show_it`` (the planes'
    residuals show it): shorter windows hold fewer planes, a weaker network, and below the noise
    the window deformation the block carries can account for the smear, so that shorter windows
    would cost more accuracy than they gain. Beyond the noise the windows' length is also the
    correction's time resolution, which no plane residual shows: a fast drift leaves planes that
    fit their model and a corrected cloud whose planes are thicker than shorter windows make them."""
    finite = smear_m[np.isfinite(smear_m)]
    noise = [p.rms_m for found in planes for p in found]
    if not config.adaptive or config.mode is not WindowMode.DURATION or not len(finite) or not noise:
        return None
    allowed = config.max_smear_share * float(np.median(noise))
    smear = float(np.median(finite))
    if smear <= allowed or (not planes_show_it and smear <= config.shown_smear_share * float(np.median(noise))):
        return None
    shorter = max(config.min_window_s, math.floor(2.0 * window_s * allowed / smear) / 2.0)
    return shorter if shorter < 0.8 * window_s else None
