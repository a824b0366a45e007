"""The trajectory's drift model: how fast the trajectory's error grows (prior and measured), and
what that does to the pairwise priors, the block's trajectory links, the planes of a window
(window deformation) and the stations' frames (window bias)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from kinreg.config import DriftConfig
from kinreg.estimate.correction import POINT_GRID_S, DriftCorrection
from kinreg.estimate.snooping import f_quantile
from kinreg.geometry import FloatArray, Pose, quat_to_rotvec, rotvec_to_quat, skew
from kinreg.types import (
    BlockResult,
    Link,
    LinkStatus,
    ObservationKind,
    Plane,
    RelativeObservation,
    ScanKind,
    Station,
    Trajectory,
)


def drift_sigmas(dt_s: float, config: DriftConfig) -> FloatArray:
    """Prior standard deviations (tx, ty, tz [m], rx, ry, rz [rad]) of the trajectory's relative
    pose between two times ``dt_s`` apart: ``sqrt(floor^2 + (rate * dt)^2)`` per axis."""
    pos = np.hypot(config.sigma_pos_floor_m, config.sigma_pos_m_per_s * dt_s)
    rot = np.radians(np.hypot(config.sigma_rot_floor_deg, config.sigma_rot_deg_per_s * dt_s))
    return np.array([pos, pos, pos, rot, rot, rot])


# A measured coupling below the first is a SLAM-like trajectory, above the second a GNSS/INS-like one.
MIXED_COUPLING = (0.25, 0.75)


def regime_coupling(kappa: float) -> float:
    """A measured coupling that names a regime (:data:`MIXED_COUPLING`) is that regime's: 0 or 1.
    The measurement errs by about a tenth either way (a rigid drift of the world read 0.1, a
    GNSS/INS-like run 0.92), and a tenth of the coupling left in is a tenth of the shear left in
    the windows; a mixed trajectory keeps its measured share."""
    low, high = MIXED_COUPLING
    return 0.0 if kappa < low else 1.0 if kappa > high else kappa


@dataclass(frozen=True)
class DriftRates:
    """How fast the trajectory drifts, per object axis: position [m/s] and rotation [rad/s],
    plus the floors (short-term noise) [m], [rad]. ``sigma(dt)^2 = floor^2 + (rate dt)^2``.

    ``correlation_s`` (position, rotation) is the correlation time of the drift velocity
    (first-order Gauss-Markov, measured by :func:`estimate_drift_rates`): 0 where the drift of
    one link tells nothing of the next (independent links), long where the drift is smooth (a
    stretch that only the trajectory carries then errs by its length times the drift velocity,
    not by the square root of its length).

    ``coupling`` says how the trajectory's attitude error enters its positions (METHOD.md
    section 1), measured by :func:`estimate_drift_rates`: 0 where the relative motion is exact in
    the scan's own frame (SLAM, dead reckoning, a rigid drift of the whole world: the position
    integrates the heading error), 1 where the object-frame step is (GNSS/INS, a laser tracker:
    the positions are measured apart from the attitude, so an attitude error turns each step
    expressed in the scan's frame). The rates are those of the error left after the coupling.
    """

    pos_m_per_s: np.ndarray
    rot_rad_per_s: np.ndarray
    pos_floor_m: float
    rot_floor_rad: float
    estimated: bool = False
    coupling: float = 0.0
    correlation_s: tuple[float, float] = (0.0, 0.0)

    @property
    def state_space(self) -> bool:
        """Whether the drift velocity is correlated from one trajectory link to the next (then the
        block carries it as an unknown per link, :func:`drift_observation`)."""
        return max(self.correlation_s) > 0.0

    @property
    def regime(self) -> str:
        """The coupling in words, for the report."""
        if self.coupling < MIXED_COUPLING[0]:
            return "relative motion exact in the scan frame (SLAM-like)"
        if self.coupling > MIXED_COUPLING[1]:
            return "positions apart from attitude (GNSS/INS-like)"
        return "mixed"

    @classmethod
    def from_config(cls, drift: DriftConfig) -> DriftRates:
        return cls(np.full(3, drift.sigma_pos_m_per_s), np.full(3, np.radians(drift.sigma_rot_deg_per_s)),
                   drift.sigma_pos_floor_m, float(np.radians(drift.sigma_rot_floor_deg)))

    def covariance(self, dt_s: float, T_obj_station: Pose, floor: bool = True) -> np.ndarray:
        """6x6 covariance of a relative pose over ``dt_s`` in the station's frame (twist order)."""
        R = T_obj_station.rotation_matrix
        f_pos, f_rot = (self.pos_floor_m, self.rot_floor_rad) if floor else (0.0, 0.0)
        cov = np.zeros((6, 6))
        cov[:3, :3] = R.T @ np.diag(f_pos**2 + (self.pos_m_per_s * dt_s) ** 2) @ R
        cov[3:, 3:] = R.T @ np.diag(f_rot**2 + (self.rot_rad_per_s * dt_s) ** 2) @ R
        return cov


def drift_observation(rates: DriftRates, link: int, dt_s: float,
                      previous: tuple[int, float] | None) -> RelativeObservation:
    """The drift velocity of the trajectory link starting at station ``link`` (``dt_s`` long): a
    first-order Gauss-Markov process in object axes with the spread of the drift rates and their
    correlation times. Tied to the ``previous`` link of the run (its start station and length),
    or, for the first link of a run, observed as zero with the process's stationary spread."""
    variance = np.concatenate([rates.pos_m_per_s, rates.rot_rad_per_s]) ** 2
    if previous is None:
        return RelativeObservation(ObservationKind.DRIFT, link, -1, Pose.identity(), np.diag(1.0 / variance), 6)
    lag = 0.5 * (previous[1] + dt_s)
    tau = np.repeat(np.asarray(rates.correlation_s, dtype=float), 3)
    decay = np.where(tau > 0.0, np.exp(-lag / np.maximum(tau, 1e-12)), 0.0)
    return RelativeObservation(ObservationKind.DRIFT, previous[0], link, Pose.identity(),
                               np.diag(1.0 / (variance * (1.0 - decay**2))), 6, decay=decay)


def _timed_runs(stations: Sequence[Station]) -> dict[int, list[int]]:
    """Per run: its quasi-static stations with a time, in time order."""
    runs: dict[int, list[int]] = {}
    for k, s in enumerate(stations):
        if s.kind is ScanKind.QUASI_STATIC and np.isfinite(s.t_s):
            runs.setdefault(s.run, []).append(k)
    return {run: sorted(ks, key=lambda k: stations[k].t_s) for run, ks in sorted(runs.items())}


def deskewed_planes(stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]], result: BlockResult,
                    rates: DriftRates,
                    trajectories: Sequence[Trajectory] = ()) -> tuple[list[tuple[Plane, ...]], float]:
    """The planes of every quasi-static scan with the drift inside its window taken out, by the
    correction that the adjustment found, as far as it is known inside the window.

    A scan is assembled with the trajectory's poses relative to its centre pose ``T_c``; a point
    seen at ``t_c + tau`` belongs where the correction at that time puts it, so in the scan frame
    it moves by ``T_c_adjusted^-1 C(t_c + tau) T_c`` (the identity at ``tau = 0``). Each plane is
    moved by that map at its inliers' mean time (``t_offset_s``). The correction is
    ``x' = R(r)(x - p) + p + delta`` (:class:`~kinreg.estimate.correction.DriftCorrection`: ``r``,
    ``delta`` and the pivot ``p`` interpolated between the stations of a run); inside the window
    it is taken as the best prediction the drift model allows:

    - the rotation and the part of the shift that is not the centre's rotation about the moving
      pivot change as the interpolated correction does, times the correlation of the drift
      velocity over a station spacing (``exp(-spacing / correlation time)``: a smooth drift,
      SLAM- or world-like, is interpolated; a drift that decorrelates from one station to the next
      cannot be, and is not);
    - the shift keeps the centre's rotation about the moving pivot, ``(R_c - I)(p - p_c)``, in the
      share ``1 - coupling``: where the positions integrate the attitude error (SLAM) one rigid
      correction moves the whole window; where they are measured apart from it (GNSS/INS) the
      attitude error turns the trajectory's object-frame step and shears the window instead (a
      plane seen 2 s from the centre at 0.5 m/s and 5 mrad is 5 mm off); there the rotation
      turns each point about where the sensor was (``trajectories[run]``, the run's own
      trajectory: its sway and turns inside the window; without it, the stations' spline).

    The scan's frame is otherwise the frame its planes share, so this error is common to all
    links of a scan and no link residual shows it. Static scans and stations without a time are
    returned as they are. Returns the planes and the largest shift of a plane's centroid [m].
    """
    out = list(planes)
    largest = 0.0
    for k, window in window_maps(stations, result, rates, trajectories).items():
        if not out[k]:
            continue
        span = (stations[k].t_start_s - stations[k].t_s, stations[k].t_end_s - stations[k].t_s)
        out[k] = tuple(_deskewed(p, window, span, over_patch=rates.coupling > 0.0) for p in out[k])
        largest = max([largest] + [float(np.linalg.norm(a.centroid_xyz - b.centroid_xyz))
                                   for a, b in zip(out[k], planes[k], strict=True)])
    return out, largest


# Stations either side of a window whose correction a map sent to a worker keeps
# (:func:`window_maps`): the natural cubic spline through them differs from the one through the
# whole run by far less than the correction's own error inside the window, and the map stays small.
MAP_NEIGHBOURS = 4


def window_maps(stations: Sequence[Station], result: BlockResult, rates: DriftRates,
                trajectories: Sequence[Trajectory] = (), neighbours: int | None = None) -> dict[int, WindowMap]:
    """Per timed quasi-static station (of a run with at least two): the map that takes the drift
    inside its window out (:func:`deskewed_planes`, whose docstring says what it is), made from
    the correction of ``result`` over the whole run, or with ``neighbours`` over the station and
    that many either side (picklable and small: a map that goes to the worker that deskews the
    scan's points, :func:`kinreg.run.planes_stage.scan_planes`)."""
    maps: dict[int, WindowMap] = {}
    for run, ks in _timed_runs(stations).items():
        if len(ks) < 2:
            continue
        stamps = np.array([stations[k].t_s for k in ks])
        spacing = float(np.median(np.diff(stamps)))
        rho_pos, rho_rot = (float(np.exp(-spacing / c)) if c > 0.0 else 0.0 for c in rates.correlation_s)
        initial, adjusted = result.poses_initial[ks], result.poses[ks]
        own = trajectories[run] if run < len(trajectories) else Trajectory(stamps, initial)
        whole = (DriftCorrection.from_stations(stamps, initial, adjusted, own, coupling=rates.coupling)
                 if neighbours is None else None)  # a map per station of its neighbours only: never used
        for m, k in enumerate(ks):
            correction = whole
            if correction is None:
                n = neighbours or 0  # given: there is no whole run's correction without it
                near = slice(max(m - n, 0), min(m + n + 1, len(ks)))
                # the trajectory through the window: where the sensor was, for a point without its own
                rows = rows_covering(own.stamps_s, stations[k].t_start_s, stations[k].t_end_s)
                correction = DriftCorrection.from_stations(stamps[near], initial[near], adjusted[near],
                                                           Trajectory(own.stamps_s[rows], own.poses[rows]),
                                                           coupling=rates.coupling)
            maps[k] = WindowMap.at_centre(correction, float(stations[k].t_s), initial[m], adjusted[m],
                                          rates.coupling, rho_pos, rho_rot)
    return maps


def rows_covering(stamps_s: FloatArray, t0: float, t1: float) -> slice:
    """The rows of ``stamps_s`` (sorted) that cover ``[t0, t1]``, one beyond either end."""
    a = max(int(np.searchsorted(stamps_s, t0, side="right")) - 1, 0)
    b = min(int(np.searchsorted(stamps_s, t1, side="left")) + 1, len(stamps_s) - 1)
    return slice(a, b + 1)


@dataclass(frozen=True, eq=False)
class WindowMap:
    """The map of :func:`deskewed_planes` for one scan: scan-frame points seen ``tau`` from the
    centre time ``t_s`` to where the correction puts them, in the adjusted scan frame."""

    correction: DriftCorrection
    t_s: float
    initial: Pose
    adjusted: Pose
    coupling: float
    rho_pos: float
    rho_rot: float
    # the correction at the centre: rotation vector, shift, pivot, rotation matrix
    r_c: FloatArray
    delta_c: FloatArray
    p_c: FloatArray
    R_0: FloatArray

    @classmethod
    def at_centre(cls, correction: DriftCorrection, t_s: float, initial: Pose, adjusted: Pose, coupling: float,
                  rho_pos: float, rho_rot: float) -> WindowMap:
        (r_c,), (delta_c,), (p_c,) = correction.at(np.array([t_s]))
        return cls(correction, t_s, initial, adjusted, coupling, rho_pos, rho_rot, r_c, delta_c, p_c,
                   Pose(rotvec_to_quat(r_c), np.zeros(3)).rotation_matrix)

    def __call__(self, x: FloatArray, tau: FloatArray, sensor: FloatArray | None = None) -> FloatArray:
        """``x`` (n, 3) seen at ``tau`` (n,) from the centre, from the sensor at ``sensor`` (n, 3, scan
        frame; None: where the trajectory had it at that time)."""
        own = None if sensor is None else self.initial.apply(sensor)
        rotvec, delta, pivot = self.correction.at(self.t_s + tau, own)
        r_c, delta_c = self.r_c, self.delta_c
        # the centre's rotation about the moving pivot, in the share in which it is one rigid motion
        # of the window (where it turns about the sensor, the pivot's motion is the shear itself)
        rigid = (1.0 - self.coupling) * (pivot - self.p_c) @ (self.R_0 - np.eye(3)).T
        delta = delta_c + rigid + self.rho_pos * (delta - delta_c - rigid)
        R_c = Pose(rotvec_to_quat(r_c + self.rho_rot * (rotvec - r_c)), np.zeros_like(delta)).rotation_matrix
        y = x @ self.initial.rotation_matrix.T + self.initial.t_xyz
        y = np.einsum("nij,nj->ni", R_c, y - pivot) + pivot + delta
        return (y - self.adjusted.t_xyz) @ self.adjusted.rotation_matrix

    def key_parts(self) -> tuple[object, ...]:
        """What the map is made of, for a stage-cache key."""
        c = self.correction
        return (c.stamps_s, c.rotvec, c.delta_m, c.pivot_xyz, self.t_s, self.initial, self.adjusted, self.coupling,
                self.rho_pos, self.rho_rot)


# Points a deskew maps at a time (:func:`deskewed_points`): twelve coefficients each, 96 MB.
_POINTS_PER_MAP = 1_000_000
# The unit points whose images give the map's affine form at a time (:func:`deskewed_points`).
_AFFINE_BASIS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def deskewed_points(mapped: WindowMap, xyz: FloatArray, tau_s: FloatArray,
                    track: tuple[FloatArray, FloatArray]) -> FloatArray:
    """A scan's points (n, 3, its frame) seen ``tau_s`` (n,) from its centre time, with the drift
    inside its window taken out by ``mapped`` (:func:`window_maps`), each turned about where the
    sensor was when it saw it (``track``: times, sensor positions in the scan frame,
    :func:`~kinreg.estimate.slicing.sensor_track`). The exact form of what :func:`deskewed_planes`
    does to a plane's parameters: a plane detected on these points is chosen from points that are
    no longer sheared, where the band around a sheared plane took in the points of another surface
    and left out the plane's own at the window's ends.

    At a given time the map is affine (a turn about where the sensor was, and a shift): it is taken
    at the times of the correction's point grid (:data:`~kinreg.estimate.correction.POINT_GRID_S`,
    from the images of the origin and the unit points) and its twelve coefficients interpolated
    linearly to each point's time (the correction changes over seconds, the sensor moves a
    centimetre in a grid step: micrometres off, at a fifth of the cost of the map per point)."""
    out = np.empty_like(xyz, dtype=np.float64)
    if not len(xyz):
        return out
    times, positions = track
    lo, hi = float(np.min(tau_s)), float(np.max(tau_s))
    grid = lo + POINT_GRID_S * np.arange(int(np.ceil((hi - lo) / POINT_GRID_S)) + 2)
    sensor = np.column_stack([np.interp(grid + mapped.t_s, times, positions[:, i]) for i in range(3)])
    images = mapped(np.tile(_AFFINE_BASIS, (len(grid), 1)), np.repeat(grid, 4),
                    np.repeat(sensor, 4, axis=0)).reshape(len(grid), 4, 3)
    images[:, 1:] -= images[:, :1]  # (g, 4, 3): the origin's image, then the linear part's columns
    coefficients = images.reshape(len(grid), 12)
    for first in range(0, len(xyz), _POINTS_PER_MAP):
        rows = slice(first, first + _POINTS_PER_MAP)
        at = (tau_s[rows] - lo) / POINT_GRID_S  # the grid is regular: the node below and the weight
        below = np.minimum(at.astype(np.intp), len(grid) - 2)
        weight = (at - below)[:, None]
        c = coefficients[below]
        c += weight * (coefficients[below + 1] - c)
        x = xyz[rows]
        out[rows] = c[:, :3] + x[:, :1] * c[:, 3:6] + x[:, 1:2] * c[:, 6:9] + x[:, 2:] * c[:, 9:]
    return out


_STEP_M = 0.01  # along the tangents, for the tilt: the least half-distance of the points


def _deskewed(p: Plane, mapped: WindowMap, span_s: tuple[float, float] = (-np.inf, np.inf),
              over_patch: bool = True) -> Plane:
    """Plane ``p`` moved by ``mapped``: its centroid at its mean time, and its tilt from points on
    either side of it along each tangent, each at the time it was seen there (its time slope);
    where the map turns about the sensor (``over_patch``), each from where the sensor was on
    average while it saw that part of the plane (``sensor_xyz``, ``sensor_slope``), not where it was
    at the mean time (a walk that slows down inside the window puts the two 0.3 m apart). The
    points lie half the patch's size apart (at least ``_STEP_M``): a plane fit averages the motion
    over the time it took to see the patch, so the tilt is the map's change over that time, not its
    rate at one instant (which would carry the sensor's sway into it where the map turns about the
    sensor, a GNSS/INS-like drift: 7 mrad x 0.6 m/s of sway x 2.5 s/m is 10 mrad of tilt). The
    points' times stay inside the window ``span_s`` (about the centre time; the patch was seen
    there): along a tangent whose time slope would take them out, they come nearer. Where the map
    turns about the stations' spline (no coupling: SLAM-like; ``over_patch`` false), it is smooth,
    its rate at the mean time is its average, and the points stay ``_STEP_M`` apart (as before the coupled pivot; over
    half a patch, a run with 0.5 m / 2 deg of world-like drift no longer converged)."""
    tau = p.t_offset_s if np.isfinite(p.t_offset_s) else 0.0
    slope = np.nan_to_num(np.asarray(p.t_slope_s_per_m, dtype=float))
    room = max(min(tau - span_s[0], span_s[1] - tau), 0.0)  # [s] either side of the mean time
    patch = 0.5 * float(np.sqrt(max(p.area_m2, 0.0))) if over_patch else 0.0
    h = np.maximum(_STEP_M, np.minimum(patch, room / np.maximum(np.abs(slope), 1e-12)))
    u, v = h[0] * p.basis_uv[0], h[1] * p.basis_uv[1]
    slope = h * slope
    c0 = p.centroid_xyz
    sensor = None
    if over_patch and p.sensor_xyz is not None and p.sensor_slope is not None:
        # where the sensor was, on average, while it saw each of the five points' neighbourhoods
        gu, gv = h[0] * p.sensor_slope[:, 0], h[1] * p.sensor_slope[:, 1]
        s0 = p.sensor_xyz
        sensor = np.array([s0, s0 + gu, s0 - gu, s0 + gv, s0 - gv])
    c, cu1, cu0, cv1, cv0 = mapped(np.array([c0, c0 + u, c0 - u, c0 + v, c0 - v]),
                                   tau + np.array([0.0, slope[0], -slope[0], slope[1], -slope[1]]), sensor)
    du, dv = cu1 - cu0, cv1 - cv0
    normal = np.cross(du, dv)
    normal /= np.linalg.norm(normal) * (1.0 if normal @ p.normal > 0.0 else -1.0)
    u_new = du - (du @ normal) * normal
    u_new /= np.linalg.norm(u_new)
    return replace(p, normal=normal, d_m=float(normal @ c - (p.normal @ p.centroid_xyz - p.d_m)), centroid_xyz=c,
                   hull_xyz=mapped(p.hull_xyz, np.full(len(p.hull_xyz), tau),
                                   None if sensor is None else np.broadcast_to(sensor[0], p.hull_xyz.shape)),
                   basis_uv=np.array([u_new, np.cross(normal, u_new)]))


def window_bias_covariance(station: Station, T_obj_station: Pose, rates: DriftRates) -> np.ndarray:
    """Covariance (6x6, station frame) of a quasi-static scan's frame against the true sensor
    pose at its centre time: drift inside the window deforms the scan, and its planes fix the
    frame at their points' mean time rather than at the centre. Modelled as the drift velocity
    times the station's ``tau_s``, the RMS offset of its planes' mean point times from the centre
    (measured by :func:`plane_time_offsets`; without it, ``W/sqrt(12)``, the RMS offset of a
    uniformly random time in the window). Link residuals cannot reveal this error (it is common
    to all links of a scan), so it is added explicitly: to the trajectory's links (which tie
    sensor poses, not scan frames) and to the reported station covariances.
    """
    if np.isnan(station.t_s):
        return np.zeros((6, 6))
    tau = station.tau_s if np.isfinite(station.tau_s) else (station.t_end_s - station.t_start_s) / np.sqrt(12.0)
    return rates.covariance(tau, T_obj_station, floor=False)


# Planes whose candidate points one float32 product selects (K x N float32 at a time).
_PLANES_PER_PASS = 8
_EPS32 = float(np.finfo(np.float32).eps)
# A plane's extent is widened by this: its hull's extreme vertices are points of the plane, on the
# edge to the last bit, and a hull that a refit moved by 1e-14 m would put them in or out.
_EXTENT_MARGIN_M = 1e-9


class PlaneTimes(NamedTuple):
    """When and from where each plane of a scan was seen (:func:`plane_time_offsets`)."""

    offsets: np.ndarray  # (n,) [s]
    slopes: np.ndarray  # (n, 2) [s/m]
    sensor: np.ndarray  # (n, 3) [m]
    sensor_slopes: np.ndarray  # (n, 3, 2) [m/m]

    def applied(self, planes: Sequence[Plane]) -> tuple[Plane, ...]:
        """The planes with their times (and sensor positions, where known) set; a plane without
        points keeps its own."""
        out = []
        for k, p in enumerate(planes):
            if not np.isfinite(self.offsets[k]):
                out.append(p)
                continue
            g = self.slopes[k]
            slope = (float(g[0]), float(g[1])) if np.all(np.isfinite(g)) else p.t_slope_s_per_m
            known = bool(np.all(np.isfinite(self.sensor[k])))
            out.append(replace(p, t_offset_s=float(self.offsets[k]), t_slope_s_per_m=slope,
                               sensor_xyz=self.sensor[k].copy() if known else p.sensor_xyz,
                               sensor_slope=np.nan_to_num(self.sensor_slopes[k]) if known else p.sensor_slope))
        return tuple(out)


def plane_time_offsets(points_xyz: np.ndarray, stamps_s: np.ndarray, t_s: float, planes: Sequence[Plane],
                       band_m: float, track: tuple[np.ndarray, np.ndarray] | None = None) -> PlaneTimes:
    """Per plane: the mean time of its points minus ``t_s`` [s], and the slope of their time
    across the plane along its ``basis_uv`` [s/m] (least squares; (n, 2)); the points of a plane
    are those within ``band_m`` of it and inside its extent (``nan`` for a plane without such
    points). With ``track`` (times (m,), sensor positions (m, 3) in the scan's frame, covering the
    points' times), also the mean of the sensor's position at the points' times (n, 3) and its
    slope across the plane (n, 3, 2), else ``nan``."""
    offsets = np.full(len(planes), np.nan)
    slopes = np.full((len(planes), 2), np.nan)
    sensor = np.full((len(planes), 3), np.nan)
    sensor_slopes = np.full((len(planes), 3, 2), np.nan)
    if not planes or not len(points_xyz):
        return PlaneTimes(offsets, slopes, sensor, sensor_slopes)
    # Candidates from a float32 product for several planes at once (a float64 pass over every
    # point per plane cost more than the rest of this function); a margin of several float32
    # roundings of the largest coordinate keeps every point the float64 test takes, and that test
    # decides. The slope's sums on contiguous columns (an (N, 2) array reduces along its first axis
    # several times slower).
    points32 = points_xyz.astype(np.float32)
    # The largest absolute coordinate without an absolute copy; NaN points are never candidates.
    scale = max(float(np.fmax.reduce(points32, axis=None)), -float(np.fmin.reduce(points32, axis=None))) * np.sqrt(3.0)
    for first in range(0, len(planes), _PLANES_PER_PASS):
        group = planes[first:first + _PLANES_PER_PASS]
        normals32 = np.array([p.normal for p in group], dtype=np.float32)
        resid32 = normals32 @ points32.T  # (K, N), rows contiguous
        for j, plane in enumerate(group):
            k = first + j
            margin = 16 * _EPS32 * (scale + abs(plane.d_m)) + 1e-9
            if np.isfinite(margin):
                r32 = resid32[j]
                r32 -= np.float32(plane.d_m)
                cand = np.flatnonzero(np.abs(r32, out=r32) <= band_m + margin)
            else:
                cand = np.arange(len(points_xyz))
            # The float64 tests on the candidates' rows: a matrix-vector product gives each row the
            # bits of a pass over every point, so a point on the band's edge, or a hull vertex on
            # the extent's, falls on the same side as there. The rows are not compressed by the
            # band test (nearly every candidate passes it): it joins the extent's test, and the
            # centroid is taken off column by column (an (n, 3) array minus a 3-vector runs an
            # inner loop of three per point).
            local = points_xyz.take(cand, axis=0)
            r = local @ plane.normal
            r -= plane.d_m
            keep = np.abs(r, out=r) <= band_m
            for i in range(3):
                local[:, i] -= plane.centroid_xyz[i]
            hull = plane.hull_xyz - plane.centroid_xyz
            along = []
            for axis in plane.basis_uv:
                a = local @ axis
                h = hull @ axis
                keep &= a >= h.min() - _EXTENT_MARGIN_M
                keep &= a <= h.max() + _EXTENT_MARGIN_M
                along.append(a)
            if not keep.any():
                continue
            t = stamps_s[cand[keep]]
            s, v = (a[keep] for a in along)
            s -= s.mean()
            v -= v.mean()
            # numpy's sums, not BLAS's dot: the same bits for any number of BLAS threads. The
            # products go into one buffer (it stays in the cache; fresh arrays cost as much again).
            product = np.empty(len(t))
            sv = np.sum(np.multiply(s, v, out=product))
            A = np.array([[np.sum(np.multiply(s, s, out=product)), sv], [sv, np.sum(np.multiply(v, v, out=product))]])
            # Rows: the time, and with a track the sensor's position at it (np.interp per axis: the
            # same values as interpolate_positions, a fifth of its time).
            seen = np.empty((1 if track is None else 4, len(t)))
            seen[0] = t
            if track is not None:
                for i in range(3):
                    seen[1 + i] = np.interp(t, track[0], track[1][:, i])
            means = np.array([np.mean(row) for row in seen])
            offsets[k] = float(means[0]) - t_s
            if track is not None:
                sensor[k] = means[1:]
            if len(t) >= 3 and np.linalg.cond(A) < 1e8:
                # their slopes across the plane: one least-squares fit for all rows
                seen -= means[:, None]
                rhs = np.array([[np.sum(np.multiply(row, axis, out=product)) for row in seen] for axis in (s, v)])
                g = np.linalg.solve(A, rhs)
                slopes[k] = g[:, 0]
                if track is not None:
                    sensor_slopes[k] = g[:, 1:].T
    return PlaneTimes(offsets, slopes, sensor, sensor_slopes)


def rms_time_offset(offsets: np.ndarray) -> float:
    """RMS of the planes' time offsets (``nan`` without any)."""
    finite = offsets[np.isfinite(offsets)]
    return float(np.sqrt(np.mean(np.square(finite)))) if len(finite) else float("nan")


def plane_motion_jacobian(p: Plane, tau_s: float = 1.0, slope_s_per_m: FloatArray | None = None) -> FloatArray:
    """The change (3, 6) of a plane's (tilt towards u, tilt towards v, offset at the origin)
    (:class:`~kinreg.types.Plane`) when its points move by ``tau(x) (rho + phi x x)`` for a twist
    ``(rho, phi)`` in the scan frame, with ``tau(x) = tau_s + slope . (x - c)`` along ``basis_uv``:
    with ``tau = 1`` and no slope, a motion of the scan's frame; with the plane's time offset
    and slope, what a drift velocity ``(rho, phi)`` does to a plane seen over the window.

    The normal displacement is ``w(x) = tau(x) (n.rho + (x x n).phi)``; a tilt ``a`` towards u
    moves a point ``s`` along u by ``-a s``, and the offset at the origin is
    ``e_c + a (u.c) + b (v.c)`` (:func:`~kinreg.estimate.planes.plane_covariance`)."""
    n, c = p.normal, p.centroid_xyz
    g = np.zeros(2) if slope_s_per_m is None else np.asarray(slope_s_per_m, dtype=float)
    w0 = np.concatenate([n, np.cross(c, n)])
    rows = []
    for axis, slope in zip(p.basis_uv, g, strict=True):
        rows.append(-(slope * w0 + tau_s * np.concatenate([np.zeros(3), np.cross(axis, n)])))
    J = np.zeros((3, 6))
    J[0], J[1] = rows
    J[2] = tau_s * w0 + (p.basis_uv[0] @ c) * J[0] + (p.basis_uv[1] @ c) * J[1]
    return J


def window_deformation_jacobian(p: Plane) -> FloatArray:
    """:func:`plane_motion_jacobian` at the plane's own time offset and time slope (zero for a
    plane without a time)."""
    if not np.isfinite(p.t_offset_s):
        return np.zeros((3, 6))
    return plane_motion_jacobian(p, p.t_offset_s, np.nan_to_num(np.asarray(p.t_slope_s_per_m, dtype=float)))


def with_window_deformation(planes: Sequence[Plane], T_obj_scan: Pose, rates: DriftRates,
                            velocity_cov: FloatArray | None = None) -> tuple[Plane, ...]:
    """The planes with the drift inside the scan's window added to their covariances: a plane
    seen ``t_offset_s`` from the centre time is moved by the drift velocity times that time, and
    a plane swept over while walking (``t_slope_s_per_m``) is tilted by it
    (:func:`window_deformation_jacobian`). Each plane of a scan moves by its own times, so the
    scan is deformed, not just displaced. The drift velocity's covariance (6x6, scan axes) is
    ``velocity_cov`` where given (what is left once the planes are deskewed,
    :func:`window_velocity_covariance`), else the drift rates'."""
    cov_v = rates.covariance(1.0, T_obj_scan, floor=False) if velocity_cov is None else velocity_cov
    out = []
    for p in planes:
        G = window_deformation_jacobian(p)
        if not G.any():
            out.append(p)
            continue
        out.append(replace(p, cov_uvd=p.cov_uvd + G @ cov_v @ G.T))
    return tuple(out)


def window_velocity_covariance(stations: Sequence[Station], result: BlockResult, rates: DriftRates) -> FloatArray:
    """Per station (n, 6, 6, scan axes): the covariance of the drift velocity inside its window
    that :func:`deskewed_planes` leaves, when it deskews with ``result``: the part of the drift
    velocity at the planes' times that the velocity at the centre does not predict (``1 - rho^2``
    of the rates' spread, ``rho`` the correlation over the station's ``tau_s``, the RMS time offset
    of its planes) plus the adjustment's own uncertainty of the velocity, the covariance of the
    adjusted relative pose of the trajectory's links on either side over their length squared
    (the mean of the two). Where the attitude error is coupled (``rates.coupling``), the deskew
    turns each plane about the sensor where it was with the station's adjusted attitude, whose
    own error ``dphi`` then shears the window as a drift velocity ``v x dphi`` would (``v`` the
    walk's velocity): that spread is added, in the share ``coupling``. Static stations and
    stations without trajectory links: the rates'."""
    n = len(stations)
    out = np.array([rates.covariance(1.0, s.T_obj_scan, floor=False) for s in stations]).reshape(n, 6, 6)
    timed = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC and np.isfinite(s.t_s)]
    if len(timed) < 2:
        return out
    spacing = float(np.median(np.diff(sorted(stations[k].t_s for k in timed))))
    posterior: dict[int, list[FloatArray]] = {}
    for t in result.tests:
        if t.kind is ObservationKind.TRAJECTORY and t.cov_adjusted is not None and t.j >= 0:
            dt = abs(stations[t.j].t_s - stations[t.i].t_s)
            if dt > 0:
                for k in (t.i, t.j):
                    posterior.setdefault(k, []).append(t.cov_adjusted / dt**2)
    for k in timed:
        if k not in posterior:
            continue
        # its planes are seen about tau_s from the centre: the drift velocity's correlation over that
        lag = stations[k].tau_s if np.isfinite(stations[k].tau_s) else spacing / np.sqrt(12.0)
        rho = np.repeat([float(np.exp(-lag / c)) if c > 0.0 else 0.0 for c in rates.correlation_s], 3)
        left = np.sqrt(1.0 - rho**2)
        out[k] = left[:, None] * out[k] * left[None, :] + np.mean(posterior[k], axis=0)
    if rates.coupling > 0.0:
        for k, v in _walk_velocities(stations, result.poses_initial).items():
            S = skew(v)
            out[k][:3, :3] += rates.coupling**2 * S @ result.cov_xi[k][3:, 3:] @ S.T
    return out


def _walk_velocities(stations: Sequence[Station], poses: Pose) -> dict[int, FloatArray]:
    """Per timed station with a neighbour in its run: the walk's mean velocity about it (from the
    neighbouring stations' positions), in its scan axes."""
    out: dict[int, FloatArray] = {}
    for ks in _timed_runs(stations).values():
        for m, k in enumerate(ks):
            a, b = ks[max(m - 1, 0)], ks[min(m + 1, len(ks) - 1)]
            if a == b:
                continue
            v = (poses.t_xyz[b] - poses.t_xyz[a]) / (stations[b].t_s - stations[a].t_s)
            out[k] = poses[k].rotation_matrix.T @ v
    return out


def estimate_drift_rates(stations: Sequence[Station], result: BlockResult, prior: DriftRates,
                         floor_share: float = 1.0, measure_correlation: bool = True,
                         links: Sequence[Link] = (), coupling: float | None = None) -> DriftRates:
    """The trajectory's error model measured by the adjustment, from consecutive quasi-static
    stations of each run: the adjusted step ``y`` against the two predictions of the trajectory's
    step, ``u`` (its step in the scan frame was right: the initial step turned by the first
    station's correction) and ``w`` (its object-frame step was right: the initial step itself).
    The coupling ``kappa`` (:class:`DriftRates`) is the least-squares share of ``w`` in
    ``y = u + kappa (w - u)``, within [0, 1]: with ``links``, measured on the planes' own relative
    poses (:func:`coupling_from_links`), which do not lean on the coupling the adjustment was made
    with; without (or with too few), on the adjusted steps, each link weighted by how far the
    planes control it (its redundancy share: a link that only the trajectory determines repeats
    the model it was adjusted with); the position rate is the RMS per object axis of what
    is left over the time difference (:func:`_rms_rate`), the rotation rate that of the change of
    the correction's rotation, each less the adjustment's own noise in it (the covariance of the
    adjusted relative pose, from the block's trajectory-link tests). The estimate is bounded below
    by ``floor_share`` times the prior rates (1: it only ever raises them); with too few stations
    to measure, the prior is returned. A given ``coupling`` is taken as it is (the one the network
    fits best, :func:`coupling_by_fit`).

    Smooth drift is invisible in residuals (consecutive trajectory links err alike), but the
    corrections themselves show it wherever planes fix the stations; where no plane fixes a
    direction, the corrections follow the trajectory and show no drift, hence the floor.
    """
    trajectory = [t for t in result.tests if t.kind is ObservationKind.TRAJECTORY and not t.rejected]
    noise = {(t.i, t.j): t.cov_adjusted for t in trajectory if t.cov_adjusted is not None}
    # How far the planes control each trajectory link (its redundancy share): where they do not,
    # the adjusted step is the trajectory's own and says nothing of how its error couples.
    control = {(t.i, t.j): t.redundancy / t.dof for t in trajectory if t.dof > 0}
    seq = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC]
    if len(seq) < 3:
        return prior
    correction = result.poses.compose(result.poses_initial.inverse())  # C_k = T_adjusted T_initial^-1
    rot = quat_to_rotvec(correction.quat_wxyz)
    R_corr, R_adj = correction.rotation_matrix, result.poses.rotation_matrix
    p_adj, p_init = result.poses.t_xyz, result.poses_initial.t_xyz
    y, u, w, dts, rot_v, pos_noise, rot_noise, ends, weight = [], [], [], [], [], [], [], [], []
    for a, b in itertools.pairwise(seq):
        if stations[a].run != stations[b].run:
            continue  # consecutive stations of the same run only: runs are not tied by a trajectory
        ends.append((a, b))
        weight.append(float(np.clip(control.get((a, b), 1.0), 0.0, 1.0)))
        dt = stations[b].t_s - stations[a].t_s
        cov = noise.get((a, b), np.zeros((6, 6)))
        R = R_adj[a]
        pos_noise.append(np.diag(R @ cov[:3, :3] @ R.T) / dt**2)
        rot_noise.append(np.diag(R @ cov[3:, 3:] @ R.T) / dt**2)
        step = p_init[b] - p_init[a]
        y.append(p_adj[b] - p_adj[a])
        u.append(R_corr[a] @ step)
        w.append(step)
        dts.append(dt)
        rot_v.append((rot[b] - rot[a]) / dt)
    if len(y) < 2:
        return prior
    Y, U, W = np.array(y), np.array(u), np.array(w)
    c = np.array(weight)[:, None]
    spread = float(np.sum(c * (W - U) ** 2))
    kappa = coupling_from_links(stations, links, result, prior) if coupling is None else coupling
    if kappa is None:
        kappa = float(np.clip(np.sum(c * (W - U) * (Y - U)) / spread, 0.0, 1.0)) if spread > 1e-12 else 0.0
    pos_v = (Y - U - kappa * (W - U)) / np.array(dts)[:, None]
    pos_rate = _rms_rate(pos_v, np.array(pos_noise))
    rot_rate = _rms_rate(np.array(rot_v), np.array(rot_noise))
    correlation = prior.correlation_s
    if measure_correlation:
        correlation = _correlation_times(ends, np.array(dts), pos_v, np.array(rot_v), np.array(pos_noise),
                                         np.array(rot_noise))
    return DriftRates(np.maximum(floor_share * prior.pos_m_per_s, pos_rate),
                      np.maximum(floor_share * prior.rot_rad_per_s, rot_rate),
                      prior.pos_floor_m, prior.rot_floor_rad, estimated=True, coupling=kappa,
                      correlation_s=correlation)


def coupling_by_fit(couplings: Sequence[float], costs: Sequence[float]) -> float:
    """The coupling (:class:`DriftRates`) at which a network's least-squares cost is least, within
    [0, 1], from its ``costs`` at three ``couplings``: the vertex of the parabola through them, or
    the cheaper end where it opens downwards or is flat. The coupling enters each trajectory link
    linearly, so the cost is close to a parabola in it; a non-finite cost (an adjustment that
    failed) leaves the coupling at the cheapest one tried."""
    x, y = np.asarray(couplings, dtype=float), np.asarray(costs, dtype=float)
    if not np.all(np.isfinite(y)):
        return float(x[np.argmin(np.where(np.isfinite(y), y, np.inf))])
    a, b, _ = np.polyfit(x, y, 2)
    if a <= 0.0:
        return float(x[np.argmin(y)])
    return float(np.clip(-b / (2.0 * a), 0.0, 1.0))


def fits_better(cost: float, cost_against: float, redundancy: float, alpha: float) -> bool:
    """Whether a network's least-squares ``cost`` with one coupling is significantly lower than its
    ``cost_against`` with another (the coupling as one more unknown: F-test with 1 and
    ``redundancy`` degrees of freedom at ``alpha``, the cost's own sigma0 as the unit). A network
    with no redundancy tells nothing."""
    if not (redundancy > 0 and np.isfinite(cost) and cost > 0.0):
        return False
    return bool((cost_against - cost) / (cost / redundancy) > f_quantile(1.0 - alpha, 1.0, float(redundancy)))


# Fewer plane links of consecutive-enough stations than this leave the coupling to the adjusted steps.
_MIN_COUPLING_LINKS = 5
# The planes tell the coupling where its two regimes (0 and 1) lie at least this many of its sigmas
# apart. A short run with little attitude drift reads nearly any value at a sigma as wide as the
# gap, and a wrong regime misplaces its stations by more than the trajectory's own steps, read
# instead, would.
_COUPLING_APART = 3.0
# Plane links over more than this many station spacings carry too much of the trajectory's own drift.
_COUPLING_SPACINGS = 3.0


def coupling_from_links(stations: Sequence[Station], links: Sequence[Link], result: BlockResult,
                        rates: DriftRates) -> float | None:
    """The coupling ``kappa`` (:class:`DriftRates`) that the plane links between stations of one run
    point to, or None with fewer than a handful of them or where they do not tell its two regimes
    apart (:data:`_COUPLING_APART`).

    For a link of scans ``a`` and ``b``, the trajectory predicts the step in scan ``a``'s frame in
    two ways: ``u = R_a^T (x_b - x_a)`` with the trajectory's own attitude (its relative motion is
    right in the scan's frame: SLAM, or one rigid drift of the world) and ``w = R'_a^T (x_b - x_a)``
    with the adjusted attitude (its object-frame step is right, the attitude error turns it:
    GNSS/INS, a tracker). The planes alone measure the step (``T_i_j_planes``); ``kappa`` is the
    generalised least-squares share of ``w - u`` in the planes' step less ``u``, weighted by the
    planes' information together with the trajectory's drift over the link. Unlike the adjusted
    steps, the planes' relative poses do not depend on the coupling the adjustment used, where the
    planes leave a direction to the trajectory (the adjustment then repeats its own model); the
    adjusted attitude ``R'_a`` is fixed by the planes' rotations, whatever the coupling."""
    spacing = {run: float(np.median(np.diff([stations[k].t_s for k in ks])))
               for run, ks in _timed_runs(stations).items() if len(ks) > 1}
    num, den, n = 0.0, 0.0, 0
    cov_xi = getattr(result, "cov_xi", None)
    for link in links:
        a, b = link.scan_i, link.scan_j
        sa, sb = stations[a], stations[b]
        if (link.status is not LinkStatus.OK or sa.kind is not ScanKind.QUASI_STATIC
                or sb.kind is not ScanKind.QUASI_STATIC or sa.run != sb.run or sa.run not in spacing
                or not (np.isfinite(sa.t_s) and np.isfinite(sb.t_s))):
            continue
        dt = abs(sb.t_s - sa.t_s)
        if dt > _COUPLING_SPACINGS * spacing[sa.run]:
            continue
        Ta, Tb = result.poses_initial[a], result.poses_initial[b]
        step = Tb.t_xyz - Ta.t_xyz
        T_u = Ta.inverse().compose(Tb)
        R_u = T_u.rotation_matrix
        u = T_u.t_xyz
        w = result.poses[a].rotation_matrix.T @ step
        # Right-perturbation twists of the planes' pose and of w about the prediction u (scan b's axes).
        e = np.zeros(6)
        e[:3] = R_u.T @ (link.T_i_j_planes.t_xyz - u)
        e[3:] = T_u.inverse().compose(link.T_i_j_planes).log()[3:]
        g = np.zeros(6)
        g[:3] = R_u.T @ (w - u)
        info = 0.5 * (link.info_planes + link.info_planes.T)
        cov = np.linalg.inv(info + 1e-6 * np.eye(6)) + rates.covariance(dt, Tb)
        W = np.linalg.inv(cov)
        num += float(g @ W @ e)
        den += float(g @ W @ g)
        if cov_xi is not None:
            # w's own error (the adjusted attitude's, dw = [w]x dphi) inflates g'W g by its trace:
            # taken out, or the noise of the attitude would pull kappa towards 0.
            J = R_u.T @ skew(w)
            den -= float(np.trace(W[:3, :3] @ J @ cov_xi[a][3:, 3:] @ J.T))
        n += 1
    if n < _MIN_COUPLING_LINKS or den < _COUPLING_APART**2:
        return None  # too few links, or the two regimes are not told apart (kappa's sigma 1/sqrt(den))
    return float(np.clip(num / den, 0.0, 1.0))


def _correlation_times(ends: list[tuple[int, int]], dts: np.ndarray, pos_v: np.ndarray,
                       rot_v: np.ndarray, pos_noise: np.ndarray | None = None,
                       rot_noise: np.ndarray | None = None) -> tuple[float, float]:
    """Correlation times (position, rotation) [s] of the drift velocity, from the correlation of
    the velocities of links two apart in a chain of consecutive links:
    ``rho = sum v_k v_k+2 / sum ((v_k^2 + v_k+2^2) / 2 - noise)`` and ``tau = -lag / ln rho`` (0
    where rho <= 0), at most the run's length. Two apart, because links one apart share a station
    whose own noise correlates them negatively; links two apart share none, so their products hold
    no noise, while the squares hold the adjustment's own noise in the velocities (``pos_noise``,
    ``rot_noise``: per link and axis, as :func:`_rms_rate` takes them), taken out, or a smooth drift
    measured from noisy stations would read as decorrelated. Stretches whose corrections show no
    drift (no plane fixes them) add to neither sum."""
    follows = np.array([ends[k + 1][0] == ends[k][1] for k in range(len(ends) - 1)], dtype=bool)
    k = np.flatnonzero(follows[:-1] & follows[1:]) if len(follows) > 1 else np.zeros(0, dtype=int)
    if not len(k):
        return (0.0, 0.0)
    span = float(np.sum(dts))
    lag = float(np.median(dts[k] + 2.0 * dts[k + 1] + dts[k + 2]) / 2.0)  # centre to centre
    out = []
    for v, noise in ((pos_v, pos_noise), (rot_v, rot_noise)):
        products = v[k] * v[k + 2]
        energy = 0.5 * (v[k] ** 2 + v[k + 2] ** 2)
        if noise is not None:
            energy = energy - 0.5 * (noise[k] + noise[k + 2])
        total = max(float(np.sum(energy)), float(np.sum(products)))  # rho <= 1
        rho = float(np.sum(products) / total) if total > 0.0 else 0.0
        tau = float(-lag / np.log(rho)) if 0.0 < rho < 1.0 else (0.0 if rho <= 0.0 else np.inf)
        out.append(min(tau, span))  # the run cannot show a correlation longer than itself
    return (out[0], out[1])


def _rms_rate(velocity: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Per axis: the RMS drift velocity less the adjustment's noise in it, over changes within
    five robust sigmas (1.4826 MAD about zero): a jump the detector missed is one huge change, not
    drift. RMS rather than median: the drift speeds up and slows down along a run, and the links of
    its fast stretches must not read as outliers."""
    robust = 1.4826 * np.median(np.abs(velocity), axis=0)
    usual = np.abs(velocity) <= 5.0 * np.maximum(robust, 1e-12)
    mean_sq = np.sum(np.where(usual, velocity**2, 0.0), axis=0) / np.maximum(usual.sum(axis=0), 1)
    return np.sqrt(np.maximum(mean_sq - np.median(noise, axis=0), 0.0))


def with_window_bias(result: BlockResult, stations: Sequence[Station], rates: DriftRates) -> BlockResult:
    """The block result with each free station's covariance increased by the window bias of the
    station and of the datum station (positions are relative to the datum's scan frame: its turn
    moves a station by the lever from it)."""
    cov_xi = result.cov_xi.copy()
    datum = [int(k) for k in np.flatnonzero(result.fixed)]
    # The datum station's bias in object axes: its frame's shift and turn, which move every station
    # with it, the turn by the lever from the datum station (a rotation of the whole network).
    datum_bias = [(window_bias_covariance(stations[d], Pose.identity(), rates), result.poses.t_xyz[d])
                  for d in datum[:1]]
    for k, s in enumerate(stations):
        if result.fixed[k]:
            continue
        cov_xi[k] += window_bias_covariance(s, result.poses[k], rates)
        R_t = result.poses[k].rotation_matrix.T
        for bias, x_datum in datum_bias:
            J = np.zeros((6, 6))  # (shift, turn) of the datum frame in object axes -> station k's twist
            J[:3, :3] = J[3:, 3:] = R_t
            J[:3, 3:] = -R_t @ skew(result.poses.t_xyz[k] - x_datum)
            cov_xi[k] += J @ bias @ J.T
    R = result.poses.rotation_matrix
    cov_position = R @ cov_xi[:, :3, :3] @ np.transpose(R, (0, 2, 1))
    return replace(result, cov_xi=cov_xi, cov_position=cov_position)
