"""Control and check points (METHOD.md section 2, item 10): surveyed points the unit stood on, and
targets in static scans.

A *stand-still* is a stretch of the trajectory of at least ``[control] min_still_s`` where the
unit's ``reference_point_m`` (platform frame) stays within ``max_radius_m`` of its mean and the
unit within ``max_rotation_deg`` of its middle orientation, over every ``window_s`` of it and over
the whole stretch; the reference point touches the control point there. It is judged from where
the unit stays, not from its speed: a hand holding the unit sways it by a few cm/s (above a speed
threshold that slow walking would pass) but within a centimetre or two. A
point with ``t_start,t_end`` uses that interval; one without is assigned to the nearest
stand-still within ``gate_m`` (one to one; ambiguous or unassigned points are named and left out).

A control point becomes one observation of the block (``ObservationKind.POINT``): the position
of the reference point on the trajectory's pose at the stand-still's mean time, interpolated
between the two quasi-static stations around it as the corrected trajectory is (its correction
runs from one station's to the other's), so the block adjusts what the report and the check
points measure. With ``q_a``, ``q_b`` the reference point at that time in the two stations'
scan frames (from the trajectory's own relative poses) and ``s = (t - t_a) / (t_b - t_a)``, the
point is ``X = (1 - s) T_a q_a + s T_b q_b``; before the first or after the last station of the
run, where the correction is held, ``X = T_k q_k`` of that station alone. Its covariance ``C`` is
the survey's ``sigma^2`` per axis plus the reference point's scatter over the stand-still plus
the trajectory's drift over the time to the nearer station and that station's window bias, both
carried through ``J = R [I, -[q]x]`` (a right perturbation ``(rho, phi)`` of the station).

Tying the point to the nearest station alone instead errs by the drift over the time to it and
reports the point where the corrected trajectory is not: on the simulated runs of
``benchmarks/eval_control.py`` (6 s windows, stand-stills 0.75-2.25 s from the nearest centre)
by up to 0.85 mm.

A *target in a static scan* (a row with ``station, sx, sy, sz``) is an observation of that static
station's pose alone: ``X = R_s s + t_s`` with ``s`` the target's coordinates in the scan's frame,
the same ``POINT`` observation on one node (no second station, no trajectory), with covariance
``(sigma^2 + target_sigma^2) I``: the survey's ``sigma_mm`` and the scan's own measurement of the
target centre, ``[control] target_sigma_mm``. Such a static scan is held by its targets, not by
``[static] datum`` (:func:`kinreg.estimate.datum.build_network`); targets and stand-still points
together are the datum as control points are (three or more off one line fix every direction).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from kinreg.config import ControlConfig
from kinreg.errors import InputError
from kinreg.estimate.drift import DriftRates, window_bias_covariance
from kinreg.geometry import FloatArray, Pose, skew
from kinreg.survey import ControlPoint, ControlPoints
from kinreg.types import BlockResult, ObservationKind, RelativeObservation, ScanKind, Station, Trajectory

log = logging.getLogger(__name__)


# A stand-still is looked for on the trajectory thinned to about this many rows per second: a
# hand's sway (1-3 Hz) keeps its extent there, and the window's test stays cheap at 200-500 Hz.
_STILL_RATE_HZ = 20.0


@dataclass(frozen=True, eq=False)
class StandStill:
    """A stretch of one run's trajectory where the unit stood still: its interval and mean time
    [s], the reference point's mean position (3,) [m] in the trajectory's frame and its scatter
    (3, 3) [m^2] over the stretch; ``detected``: found in the trajectory (else the file gave the
    times)."""

    run: int
    t_start_s: float
    t_end_s: float
    t_s: float
    xyz: FloatArray
    scatter_m2: FloatArray
    detected: bool = False

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    @property
    def scatter_mm(self) -> float:
        """The reference point's RMS distance [mm] from its mean over the stretch."""
        return 1000.0 * math.sqrt(max(float(np.trace(self.scatter_m2)), 0.0))


def stand_still_between(trajectory: Trajectory, t_start_s: float, t_end_s: float, reference_point_m: FloatArray,
                        run: int = 0) -> StandStill:
    """The stand-still of ``trajectory`` over the given interval (its rows inside it; at least
    the interpolated poses at both ends)."""
    inside = (trajectory.stamps_s >= t_start_s) & (trajectory.stamps_s <= t_end_s)
    stamps = np.union1d(trajectory.stamps_s[inside], [t_start_s, t_end_s])
    points = trajectory.pose_at(stamps).apply(np.broadcast_to(reference_point_m, (len(stamps), 3)))
    centred = points - points.mean(axis=0)
    return StandStill(run, float(t_start_s), float(t_end_s), float(stamps.mean()), points.mean(axis=0),
                      centred.T @ centred / len(points))


def _held(points: FloatArray, quats: FloatArray, config: ControlConfig) -> bool:
    """Whether the reference points (m, 3) lie within ``max_radius_m`` of their mean and the
    orientations (m, 4) within ``max_rotation_deg`` of the middle one."""
    radius = float(np.max(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    cos_half = float(np.min(np.abs(quats @ quats[len(quats) // 2])))
    return radius <= config.max_radius_m and 2.0 * math.degrees(math.acos(min(cos_half, 1.0))) <= \
        config.max_rotation_deg


def find_stand_stills(trajectory: Trajectory, config: ControlConfig, run: int = 0) -> list[StandStill]:
    """Every stretch of ``trajectory`` where the unit stood still (see the module's docstring):
    each row whose ``window_s`` around it is held (:func:`_held`) makes that window still; the
    union of overlapping still windows, trimmed and held as a whole (:func:`_held_pieces`), is a
    stand-still if it lasts ``min_still_s``."""
    t_all = trajectory.stamps_s
    if len(t_all) < 3:
        return []
    stride = max(1, int(len(t_all) / max((t_all[-1] - t_all[0]) * _STILL_RATE_HZ, 1.0)))
    t, quats = t_all[::stride], trajectory.poses.quat_wxyz[::stride]
    points = trajectory.poses[::stride].apply(np.broadcast_to(np.asarray(config.reference_point_m), (len(t), 3)))
    half = 0.5 * config.window_s
    lo = np.searchsorted(t, t - half)
    hi = np.searchsorted(t, t + half, side="right") - 1
    count = (hi - lo + 1)[:, None]
    sums = np.vstack([np.zeros(3), np.cumsum(points, axis=0)])
    mean = (sums[hi + 1] - sums[lo]) / count
    radius, cos_half = np.zeros(len(t)), np.ones(len(t))
    rows = np.arange(len(t))
    for k in range(int(np.max(rows - lo)), -int(np.max(hi - rows)) - 1, -1):
        j = np.clip(rows - k, 0, len(t) - 1)
        inside = (j >= lo) & (j <= hi)
        radius = np.where(inside, np.maximum(radius, np.linalg.norm(points[j] - mean, axis=1)), radius)
        cos_half = np.where(inside, np.minimum(cos_half, np.abs(np.sum(quats[j] * quats, axis=1))), cos_half)
    turn_deg = 2.0 * np.degrees(np.arccos(np.minimum(cos_half, 1.0)))
    # Windows cut short by the trajectory's ends are not judged.
    still = ((radius <= config.max_radius_m) & (turn_deg <= config.max_rotation_deg)
             & (t[hi] - t[lo] >= 0.9 * config.window_s))
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    found = []
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1, strict=True):
        for first, last in _held_pieces(points[lo[a]:hi[b] + 1], quats[lo[a]:hi[b] + 1], config):
            t0, t1 = float(t[lo[a] + first]), float(t[lo[a] + last])
            if t1 - t0 >= config.min_still_s:
                still_there = stand_still_between(trajectory, t0, t1, np.asarray(config.reference_point_m), run)
                found.append(dataclasses.replace(still_there, detected=True))
    return found


def _held_pieces(points: FloatArray, quats: FloatArray, config: ControlConfig) -> list[tuple[int, int]]:
    """The held pieces (first, last row) of a stretch whose windows are still: the stretch without
    its ends outside the ball about its median position (or turned from its middle orientation):
    the last centimetres of the stop and the first of the start, which the still windows at its
    ends reach into. Where the rest is not held as a whole (the unit crept), its longest held
    pieces from the start on."""
    distance = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    turn_deg = 2.0 * np.degrees(np.arccos(np.minimum(np.abs(quats @ quats[len(quats) // 2]), 1.0)))
    inside = np.flatnonzero((distance <= config.max_radius_m) & (turn_deg <= config.max_rotation_deg))
    if len(inside) < 2:
        return []
    first, last = int(inside[0]), int(inside[-1])
    if _held(points[first:last + 1], quats[first:last + 1], config):
        return [(first, last)]
    pieces = []
    while first < last:
        end = first + 1
        while end < last and _held(points[first:end + 2], quats[first:end + 2], config):
            end += 1
        pieces.append((first, end))
        first = end + 1
    return pieces


@dataclass(frozen=True, eq=False)
class StaticTarget:
    """A point measured as a target in a static scan: its name, the scan (its 0-based position in
    the static E57 file, and its name), the target's coordinates (3,) [m] in the scan's frame, the
    surveyed coordinates (3,) [m] and their standard deviation per axis [m]."""

    name: str
    scan: int
    scan_name: str
    scan_xyz: FloatArray
    xyz: FloatArray
    sigma_m: float


@dataclass(frozen=True, eq=False)
class Assignment:
    """Control points with the stand-still each stands for (the same order as ``names``), the
    targets in static scans, and the problems met, one line each (points left out)."""

    names: tuple[str, ...]
    xyz: FloatArray  # (n, 3) surveyed coordinates [m]
    sigma_m: FloatArray  # (n,)
    stand_stills: tuple[StandStill, ...]
    problems: tuple[str, ...]
    targets: tuple[StaticTarget, ...] = ()

    @property
    def all_names(self) -> tuple[str, ...]:
        """The stand-still points' names, then the targets'."""
        return self.names + tuple(t.name for t in self.targets)


def static_target(point: ControlPoint, static_scans: Sequence[str] | None, source: str,
                  what: str = "control") -> StaticTarget:
    """The target row ``point`` tied to its static scan: ``point.station`` is a scan's name in
    ``static_scans`` (the static E57 file's scan names, in file order; ``None``: no ``--static``
    given), or else its 0-based position there. Raises :class:`InputError` naming the file and
    the row when there are no static scans or no such scan."""
    if point.scan_xyz is None:
        raise ValueError(f"point {point.name} is not a target in a static scan")
    where = f"line {point.line}: {what} target {point.name}"
    if static_scans is None:
        raise InputError(f"{where} names static scan {point.station!r}, but no static scans are given (--static)",
                         source)
    if point.station in static_scans:
        k = list(static_scans).index(point.station)
    elif point.station.isdigit() and int(point.station) < len(static_scans):
        k = int(point.station)
    else:
        listed = ", ".join(static_scans[:8]) + (", ..." if len(static_scans) > 8 else "")
        raise InputError(f"{where}: no static scan {point.station!r} (the static scans are {listed}, or their "
                         f"positions 0-{len(static_scans) - 1})", source)
    return StaticTarget(point.name, k, static_scans[k], point.scan_xyz, point.xyz, point.sigma_m)


def assign_points(points: ControlPoints, trajectories: Sequence[Trajectory], config: ControlConfig,
                  what: str = "control", static_scans: Sequence[str] | None = None) -> Assignment:
    """Each point's stand-still: its own interval where the file gives one (an interval outside
    every run's trajectory raises :class:`InputError`), else the nearest detected stand-still
    within ``config.gate_m``, one to one. Points that are ambiguous or too far from every
    stand-still are left out with one line each in ``problems`` (logged as warnings); when no point
    is left, :class:`InputError` names the file and the reason. Targets in static scans are tied
    to their scan in ``static_scans`` (:func:`static_target`, which raises for an unknown one)."""
    reference = np.asarray(config.reference_point_m)
    problems: list[str] = []
    chosen: dict[int, StandStill] = {}
    targets = tuple(static_target(p, static_scans, points.source, what) for p in points.targets)
    standing = any(not p.is_target for p in points.points)
    detected = ([s for k, traj in enumerate(trajectories) for s in find_stand_stills(traj, config, k)]
                if standing else [])
    claims: dict[int, list[int]] = {}
    for n, p in enumerate(points.points):
        if p.is_target:
            continue
        if p.has_times:
            run = next((k for k, traj in enumerate(trajectories)
                        if traj.t_start_s <= p.t_start_s and p.t_end_s <= traj.t_end_s), None)
            if run is None:
                raise InputError(f"point {p.name}: its interval {p.t_start_s:.3f}-{p.t_end_s:.3f} s is outside the "
                                 "trajectory's time range" + _ranges(trajectories), points.source)
            chosen[n] = stand_still_between(trajectories[run], p.t_start_s, p.t_end_s, reference, run)
            continue
        if not detected:
            problems.append(f"{what} point {p.name}: no stand-still found in the trajectory (give t_start,t_end, "
                            "or widen [control] max_radius_m or max_rotation_deg)")
            continue
        d = np.array([np.linalg.norm(s.xyz - p.xyz) for s in detected])
        order = np.argsort(d)
        if d[order[0]] > config.gate_m:
            problems.append(f"{what} point {p.name}: no stand-still within {config.gate_m:g} m (the nearest is "
                            f"{d[order[0]]:.2f} m away, at {detected[order[0]].t_s:.2f} s)")
            continue
        if len(d) > 1 and d[order[1]] <= config.gate_m and d[order[1]] < config.ambiguity_ratio * d[order[0]]:
            problems.append(f"{what} point {p.name}: ambiguous, stand-stills at {detected[order[0]].t_s:.2f} s and "
                            f"{detected[order[1]].t_s:.2f} s are both within {config.gate_m:g} m (give t_start,t_end)")
            continue
        claims.setdefault(int(order[0]), []).append(n)
    for s, claimants in claims.items():
        if len(claimants) > 1:
            names = ", ".join(points.points[n].name for n in claimants)
            problems.append(f"{what} points {names}: all nearest to the stand-still at {detected[s].t_s:.2f} s "
                            "(ambiguous, left out)")
        else:
            chosen[claimants[0]] = detected[s]
    for line in problems:
        log.warning("%s", line)
    kept = sorted(chosen)
    if not kept and not targets:
        raise InputError(f"no {what} point could be tied to the trajectory: " + "; ".join(problems[:3]),
                         points.source)
    return Assignment(tuple(points.points[n].name for n in kept),
                      np.array([points.points[n].xyz for n in kept]).reshape(-1, 3),
                      np.array([points.points[n].sigma_m for n in kept]), tuple(chosen[n] for n in kept),
                      tuple(problems), targets)


def _ranges(trajectories: Sequence[Trajectory]) -> str:
    return " (" + ", ".join(f"{t.t_start_s:.3f}-{t.t_end_s:.3f} s" for t in trajectories) + ")"


@dataclass(frozen=True, eq=False)
class ControlTie:
    """A control point tied to the stations around its stand-still: the nearer station's index,
    the reference point ``q_scan`` (3,) in its scan frame, the surveyed coordinates ``xyz`` (3,),
    their covariance ``cov_m2`` (3, 3) (survey plus scatter), the stand-still's time and its
    distance in time to that station [s]; the other station around it (``other``, -1: none), the
    point in its frame (``q_other``) and its weight ``share`` in the interpolated pose. A target in
    a static scan (``target``) has that static station alone, the target in its frame as
    ``q_scan``, and no time (``t_s`` nan, ``dt_s`` 0)."""

    name: str
    station: int
    q_scan: FloatArray
    xyz: FloatArray
    cov_m2: FloatArray
    t_s: float
    dt_s: float
    other: int = -1
    q_other: FloatArray = field(default_factory=lambda: np.zeros(3))
    share: float = 0.0
    target: bool = False

    def predicted(self, poses: Pose) -> FloatArray:
        """The reference point (3,) on the interpolated pose of the stations ``poses`` (all)."""
        x = poses[self.station].apply(self.q_scan[None, :])[0]
        if self.other < 0:
            return x
        return (1.0 - self.share) * x + self.share * poses[self.other].apply(self.q_other[None, :])[0]


def tie_points(assignment: Assignment, stations: Sequence[Station], trajectories: Sequence[Trajectory],
               config: ControlConfig) -> tuple[ControlTie, ...]:
    """One :class:`ControlTie` per assigned point: the quasi-static stations of its run before and
    after the stand-still's mean time (the first or last alone beyond them); then one per target
    in a static scan, on that scan's station (:func:`target_ties`)."""
    reference = np.asarray(config.reference_point_m)
    ties = []
    for name, xyz, sigma, still in zip(assignment.names, assignment.xyz, assignment.sigma_m,
                                       assignment.stand_stills, strict=True):
        own = sorted((k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC and s.run == still.run),
                     key=lambda k: stations[k].t_s)
        times = np.array([stations[k].t_s for k in own])
        after = int(np.searchsorted(times, still.t_s))
        around = [own[m] for m in (after - 1, after) if 0 <= m < len(own)]
        around.sort(key=lambda k: abs(stations[k].t_s - still.t_s))  # the nearer first
        traj = trajectories[still.run]
        poses = traj.pose_at(np.array([still.t_s] + [stations[k].t_s for k in around]))
        q = [poses[m + 1].inverse().compose(poses[0]).apply(reference[None, :])[0] for m in range(len(around))]
        k = around[0]
        other, q_other, share = -1, np.zeros(3), 0.0
        if len(around) == 2:
            other, q_other = around[1], q[1]
            share = abs(still.t_s - stations[k].t_s) / abs(stations[other].t_s - stations[k].t_s)
        ties.append(ControlTie(name, k, q[0], np.asarray(xyz, dtype=np.float64),
                               sigma**2 * np.eye(3) + still.scatter_m2, still.t_s, still.t_s - stations[k].t_s,
                               other, q_other, float(share)))
    return tuple(ties) + target_ties(assignment.targets, stations, config)


def static_station_index(stations: Sequence[Station], scan: int) -> int:
    """The index in ``stations`` of the static E57 file's scan ``scan`` (the static stations are
    the file's scans, in file order)."""
    return [k for k, s in enumerate(stations) if s.kind is ScanKind.STATIC][scan]


def target_ties(targets: Sequence[StaticTarget], stations: Sequence[Station],
                config: ControlConfig) -> tuple[ControlTie, ...]:
    """One :class:`ControlTie` per target in a static scan: its static station, the target in the
    scan's frame, the covariance ``(sigma^2 + target_sigma^2) I`` (see the module's docstring)."""
    target_sigma_m = config.target_sigma_mm / 1000.0
    return tuple(ControlTie(t.name, static_station_index(stations, t.scan), np.asarray(t.scan_xyz, dtype=np.float64),
                            np.asarray(t.xyz, dtype=np.float64), (t.sigma_m**2 + target_sigma_m**2) * np.eye(3),
                            math.nan, 0.0, target=True) for t in targets)


def control_observations(ties: Sequence[ControlTie], stations: Sequence[Station], rates: DriftRates,
                         previous: BlockResult | None = None, window_bias: bool = True) -> list[RelativeObservation]:
    """The block's observations of the control points (see the module's docstring), their
    covariances at the ``previous`` adjustment's station rotations where given (else the
    initial ones)."""
    observations = []
    for tie in ties:
        C = control_covariance(tie, stations, rates, previous, window_bias)
        info = np.zeros((6, 6))
        info[:3, :3] = np.linalg.inv(C)
        observations.append(RelativeObservation(
            ObservationKind.POINT, tie.station, tie.other, Pose(np.array([1.0, 0.0, 0.0, 0.0]), tie.xyz),
            0.5 * (info + info.T), 3, levers_m=np.array([tie.q_scan, tie.q_other]), share=tie.share))
    return observations


def control_covariance(tie: ControlTie, stations: Sequence[Station], rates: DriftRates,
                       previous: BlockResult | None = None, window_bias: bool = True) -> FloatArray:
    """The covariance (3, 3) [m^2] of a control observation (see the module's docstring); without
    ``window_bias`` it observes the sensor pose, not the scan frame (:mod:`kinreg.estimate.frames`)."""
    if tie.target:  # a static scan: no trajectory between the target and its station
        return tie.cov_m2
    k = tie.station
    T = previous.poses[k] if previous is not None else stations[k].T_obj_scan
    R = T.rotation_matrix
    J = R @ np.hstack([np.eye(3), -skew(tie.q_scan)])
    trajectory = rates.covariance(abs(tie.dt_s), T)
    if window_bias:
        trajectory = trajectory + window_bias_covariance(stations[k], T, rates)
    return tie.cov_m2 + J @ trajectory @ J.T


def free_rotations(ties: Sequence[ControlTie]) -> tuple[FloatArray, str]:
    """The rotation axes (m, 3) (object frame, orthonormal) that the control points leave free:
    all three for one point, the line through them for two (or for points within 0.1 m of one
    line), none from three points on; and what the points fix, in words."""
    xyz = np.array([t.xyz for t in ties])
    if len(xyz) == 1:
        return np.eye(3), "translations"
    centred = xyz - xyz.mean(axis=0)
    _, sing, Vt = np.linalg.svd(centred)
    if len(xyz) >= 3 and sing[1] / math.sqrt(len(xyz)) > 0.1:
        return np.zeros((0, 3)), "translations and rotations"
    axis = Vt[0]
    k = int(np.argmax(np.abs(axis)))
    name = "xyz"[k] if abs(axis[k]) > 0.99 else "(" + ", ".join(f"{c:.2f}" for c in axis) + ")"
    return axis[None, :], f"translations and rotations except about the line through them ({name})"


def first_station_rotation(axes: FloatArray, station: int, T: Pose, sigma_rad: float) -> RelativeObservation:
    """A datum observation of station ``station``'s rotation about the object-frame ``axes``
    (m, 3) only, held at ``T`` with ``sigma_rad`` (the directions the control points leave free)."""
    A = axes @ T.rotation_matrix  # rows: the axes in the station frame (phi is a right perturbation)
    info = np.zeros((6, 6))
    info[3:, 3:] = A.T @ A / sigma_rad**2
    return RelativeObservation(ObservationKind.STATION, station, -1, T, info, len(axes))
