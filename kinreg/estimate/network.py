"""The network of stations: pairwise links over candidate pairs, and the block's observations.

A *station* is a scan with a pose ``T_obj_scan`` (from the trajectory for quasi-static scans).
Quasi-static stations may come from several runs (trajectory + cloud each) in one frame: the
trajectory ties only consecutive stations of the same run; stations of different runs are tied by
their planes alone, like loop closures.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from kinreg.config import DriftConfig, MatchingConfig, PairwiseConfig, StaticConfig
from kinreg.estimate.matching import candidate_pairs, coarse_translation, count_directions, match_planes
from kinreg.estimate.pairwise import adjust_pair
from kinreg.geometry import Pose, quat_to_rotvec
from kinreg.progress import NullProgress, Progress
from kinreg.run.executor import ExecutorContext, in_process, parallel_map
from kinreg.types import (
    BlockResult,
    Link,
    LinkStatus,
    ObservationKind,
    Plane,
    PlaneMatch,
    RelativeObservation,
    ScanKind,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Station:
    """A node of the network: a scan's id, kind, time (nan for static) and initial pose, and the
    run (0-based index of the trajectory + cloud) a quasi-static station was sliced from."""

    scan_id: int
    name: str
    kind: ScanKind
    t_s: float
    t_start_s: float
    t_end_s: float
    T_obj_scan: Pose
    n_points: int
    tau_s: float = float("nan")  # effective time offset of the scan's planes from t_s (window bias)
    run: int = 0


def station_pairs(stations: Sequence[Station], matching: MatchingConfig,
                  static: StaticConfig | None = None) -> list[tuple[int, int]]:
    """Candidate pairs: sequence neighbours and nearby stations among the quasi-static stations of
    each run, stations of different runs within ``matching.radius_m`` of each other, and every
    station within ``static.link_radius_m`` of a static one."""
    positions = np.array([s.T_obj_scan.t_xyz for s in stations])
    quasi = np.array([s.kind is ScanKind.QUASI_STATIC for s in stations])
    runs = np.array([s.run for s in stations])
    pairs: set[tuple[int, int]] = set()
    for run in np.unique(runs[quasi]):
        qs = np.flatnonzero(quasi & (runs == run))
        pairs |= {(int(qs[a]), int(qs[b])) for a, b in candidate_pairs(positions[qs], matching)}
    pairs |= _cross_run_pairs(positions, runs, quasi, matching.radius_m)
    if static is not None and (~quasi).any():
        for k in np.flatnonzero(~quasi):
            near = np.flatnonzero(np.linalg.norm(positions - positions[k], axis=1) <= static.link_radius_m)
            pairs |= {(int(min(k, j)), int(max(k, j))) for j in near if j != k}
    return sorted(pairs)


def _cross_run_pairs(positions: np.ndarray, runs: np.ndarray, quasi: np.ndarray,
                     radius_m: float) -> set[tuple[int, int]]:
    """Pairs of quasi-static stations of different runs whose centres are within ``radius_m``."""
    qs = np.flatnonzero(quasi)
    if len(np.unique(runs[qs])) < 2 or radius_m <= 0:
        return set()
    near = cKDTree(positions[qs]).query_pairs(radius_m)
    return {(int(min(qs[a], qs[b])), int(max(qs[a], qs[b]))) for a, b in near if runs[qs[a]] != runs[qs[b]]}


def link_pair(
    i: int, j: int, si: Station, sj: Station, planes_i: tuple[Plane, ...], planes_j: tuple[Plane, ...],
    matching: MatchingConfig, drift: DriftConfig, pairwise: PairwiseConfig, static: StaticConfig | None,
) -> Link | None:
    """Match and adjust one candidate pair; ``None`` where too few planes match. The planes'
    covariances are expected to carry the drift inside their windows already
    (:func:`with_window_deformation`, as :func:`link_stations` passes them)."""
    T_prior = si.T_obj_scan.inverse().compose(sj.T_obj_scan)
    matches = match_planes(planes_i, planes_j, T_prior, matching)
    sigma = None
    if matching.max_jump_m > 0 and _directions(matches, planes_i) < 3:
        # Robust step: the trajectory may have jumped between the two scans, so that the planes
        # across the jump no longer match (those along it still may).
        tau = coarse_translation(planes_i, planes_j, T_prior, matching)
        if tau is not None and np.linalg.norm(tau) > matching.max_offset_m:
            shifted = Pose(np.array([1.0, 0, 0, 0]), tau).compose(T_prior)
            realigned = match_planes(planes_i, planes_j, shifted, matching)
            if (len(realigned) >= matching.min_matches
                    and _directions(realigned, planes_i) > _directions(matches, planes_i)):
                log.info("pair %s-%s: trajectory off by %.3f m; linked after a translation search",
                         si.name, sj.name, float(np.linalg.norm(tau)))
                matches, T_prior = realigned, shifted
                loose = float(np.linalg.norm(tau)) + matching.max_offset_m
                sigma = np.array([loose] * 3 + [np.radians(1.0)] * 3)
    if len(matches) < matching.min_matches:
        return None
    if static is not None and ScanKind.STATIC in (si.kind, sj.kind):
        sigma = np.array([static.prior_sigma_m] * 3 + [np.radians(static.prior_sigma_deg)] * 3)
    elif si.run != sj.run:
        sigma = np.array([pairwise.cross_run_prior_sigma_m] * 3 + [np.radians(pairwise.cross_run_prior_sigma_deg)] * 3)
    return adjust_pair(i, j, planes_i, planes_j, T_prior, _dt(si, sj), matches, drift, pairwise, sigma_prior=sigma)


# Pairs per task on an executor: a pair takes milliseconds, so single pairs would drown in overhead.
_PAIRS_PER_TASK = 64


def _link_batch(task: tuple) -> list[Link | None]:
    """A batch of pairs (a top-level function: it runs on worker processes)."""
    pairs, stations, planes, configs = task
    return [link_pair(i, j, stations[i], stations[j], planes[i], planes[j], *configs) for i, j in pairs]


def link_stations(
    stations: Sequence[Station],
    planes: Sequence[tuple[Plane, ...]],
    matching: MatchingConfig,
    drift: DriftConfig,
    pairwise: PairwiseConfig,
    progress: Progress | None = None,
    static: StaticConfig | None = None,
    executor: ExecutorContext | None = None,
    rates: DriftRates | None = None,
) -> list[Link]:
    """Pairwise links over all candidate pairs (see :func:`station_pairs`), on ``executor`` in
    batches (in this process without one). ``planes[k]`` are the planes of ``stations[k]``. Pairs
    with fewer than ``matching.min_matches`` plane matches are not linked. A pair with a static
    station has no trajectory between them: its prior comes from ``static.prior_sigma_*``; nor has
    a pair of two runs: its prior comes from ``pairwise.cross_run_prior_sigma_*``.
    ``rates`` are the drift rates for the planes' window deformation (default: the prior's).
    Returns the links in pair order, whatever the number of workers.
    """
    progress = progress or NullProgress()
    pairs = station_pairs(stations, matching, static)
    # Once per station, not once per pair: matching does not look at the covariances.
    rates = rates or DriftRates.from_config(drift)
    planes = [with_window_deformation(p, s.T_obj_scan, rates) for s, p in zip(stations, planes, strict=True)]
    configs = (matching, drift, pairwise, static)
    batches = [pairs[k:k + _PAIRS_PER_TASK] for k in range(0, len(pairs), _PAIRS_PER_TASK)]
    progress.start("link", total=len(batches), unit="batches")

    def task(batch: list[tuple[int, int]]) -> tuple:
        # Each task gets only the stations and planes of its own pairs.
        used = {k for pair in batch for k in pair}
        return batch, {k: stations[k] for k in used}, {k: planes[k] for k in used}, configs

    results = parallel_map(_link_batch, (task(b) for b in batches), executor or in_process(), progress)
    progress.finish()
    links = [link for batch in results for link in batch if link is not None]
    n_rejected = sum(link.status is LinkStatus.REJECTED for link in links)
    log.info("%d candidate pairs, %d links (%d rejected)", len(pairs), len(links), n_rejected)
    return links


def _directions(matches: tuple[PlaneMatch, ...], planes_i: tuple[Plane, ...]) -> int:
    """Distinct normal directions among the matched planes of scan i."""
    by_id = {p.plane_id: p for p in planes_i}
    return count_directions(np.array([by_id[m.plane_i].normal for m in matches]).reshape(-1, 3))


def _dt(a: Station, b: Station) -> float:
    """Time between two stations; static stations and stations of two runs are treated as far
    apart in time (no prior information from the trajectory ties them)."""
    if np.isnan(a.t_s) or np.isnan(b.t_s) or a.run != b.run:
        return float("inf")
    return abs(b.t_s - a.t_s)


@dataclass(frozen=True)
class DriftRates:
    """How fast the trajectory drifts, per object axis: position [m/s] and rotation [rad/s],
    plus the floors (short-term noise) [m], [rad]. ``sigma(dt)^2 = floor^2 + (rate dt)^2``."""

    pos_m_per_s: np.ndarray
    rot_rad_per_s: np.ndarray
    pos_floor_m: float
    rot_floor_rad: float
    estimated: bool = False

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


def plane_time_offsets(points_xyz: np.ndarray, stamps_s: np.ndarray, t_s: float, planes: Sequence[Plane],
                       band_m: float) -> np.ndarray:
    """Per plane: the mean time of its points minus ``t_s`` [s]; the points of a plane are those
    within ``band_m`` of it and inside its extent (``nan`` for a plane without such points)."""
    offsets = np.full(len(planes), np.nan)
    for k, plane in enumerate(planes):
        near = np.abs(points_xyz @ plane.normal - plane.d_m) <= band_m
        local = points_xyz[near] - plane.centroid_xyz
        hull = plane.hull_xyz - plane.centroid_xyz
        inside = np.ones(len(local), dtype=bool)
        for axis in plane.basis_uv:
            lo, hi = (hull @ axis).min(), (hull @ axis).max()
            inside &= (local @ axis >= lo) & (local @ axis <= hi)
        if inside.any():
            offsets[k] = float(np.mean(stamps_s[near][inside])) - t_s
    return offsets


def rms_time_offset(offsets: np.ndarray) -> float:
    """RMS of the planes' time offsets (``nan`` without any)."""
    finite = offsets[np.isfinite(offsets)]
    return float(np.sqrt(np.mean(np.square(finite)))) if len(finite) else float("nan")


def with_window_deformation(planes: Sequence[Plane], T_obj_scan: Pose, rates: DriftRates) -> tuple[Plane, ...]:
    """The planes with the drift inside the scan's window added to their covariances: a plane
    seen ``t_offset_s`` from the centre time is moved by the trajectory's drift over that time
    (position ``rate * |t_offset|`` along its normal, rotation ``rate * |t_offset|`` about its
    tangents; the drift rates are per object axis). Each plane of a scan moves by its own time
    offset, so the scan is deformed, not just displaced: on simulated runs the offsets of small
    wall patches seen 2 s from the centre were off by 2 mm, which this predicts to 0.3 mm.
    """
    R = T_obj_scan.rotation_matrix
    out = []
    for p in planes:
        tau = abs(p.t_offset_s) if np.isfinite(p.t_offset_s) else 0.0
        if tau == 0.0:
            out.append(p)
            continue
        n_obj = R @ p.normal
        var_d = float(np.sum((n_obj * rates.pos_m_per_s) ** 2)) * tau**2
        tangents = p.basis_uv @ R.T  # rows in object axes
        # a rotation about the tangent direction orthogonal to u tilts the normal towards u
        var_uv = [float(np.sum((np.cross(n_obj, t) * rates.rot_rad_per_s) ** 2)) * tau**2 for t in tangents]
        cov = p.cov_uvd + np.diag([var_uv[0], var_uv[1], var_d])
        out.append(replace(p, cov_uvd=cov))
    return tuple(out)


def estimate_drift_rates(stations: Sequence[Station], result: BlockResult, prior: DriftRates,
                         floor_share: float = 1.0) -> DriftRates:
    """The drift velocity measured by the adjustment: the error of the trajectory's relative motion
    between consecutive quasi-static stations (the adjusted step against the initial one turned by
    the first station's correction; the change of the correction's rotation) over their time difference,
    RMS per object axis (:func:`_rms_rate`), less the adjustment's own noise in that change (the covariance of the
    adjusted relative pose, from the block's trajectory-link tests). The estimate is bounded below
    by ``floor_share`` times the prior rates (1: it only ever raises them); with too few
    stations to measure, the prior is returned.

    Smooth drift is invisible in residuals (consecutive trajectory links err alike), but the
    corrections themselves show it wherever planes fix the stations; where no plane fixes a
    direction, the corrections follow the trajectory and show no drift, hence the floor.
    """
    noise = {(t.i, t.j): t.cov_adjusted for t in result.tests
             if t.kind is ObservationKind.TRAJECTORY and t.cov_adjusted is not None and not t.rejected}
    seq = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC]
    if len(seq) < 3:
        return prior
    correction = result.poses.compose(result.poses_initial.inverse())  # C_k = T_adjusted T_initial^-1
    rot = quat_to_rotvec(correction.quat_wxyz)
    R_corr, R_adj = correction.rotation_matrix, result.poses.rotation_matrix
    p_adj, p_init = result.poses.t_xyz, result.poses_initial.t_xyz
    pos_v, rot_v, pos_noise, rot_noise = [], [], [], []
    for a, b in itertools.pairwise(seq):
        if stations[a].run != stations[b].run:
            continue  # consecutive stations of the same run only: runs are not tied by a trajectory
        dt = stations[b].t_s - stations[a].t_s
        cov = noise.get((a, b), np.zeros((6, 6)))
        R = R_adj[a]
        pos_noise.append(np.diag(R @ cov[:3, :3] @ R.T) / dt**2)
        rot_noise.append(np.diag(R @ cov[3:, 3:] @ R.T) / dt**2)
        # The relative motion's error, not the change of the shifts: a rotation error already
        # there (C_a) turns the whole step, which is no drift between the two stations.
        pos_v.append(((p_adj[b] - p_adj[a]) - R_corr[a] @ (p_init[b] - p_init[a])) / dt)
        rot_v.append((rot[b] - rot[a]) / dt)
    if len(pos_v) < 2:
        return prior
    pos_rate = _rms_rate(np.array(pos_v), np.array(pos_noise))
    rot_rate = _rms_rate(np.array(rot_v), np.array(rot_noise))
    return DriftRates(np.maximum(floor_share * prior.pos_m_per_s, pos_rate),
                      np.maximum(floor_share * prior.rot_rad_per_s, rot_rate),
                      prior.pos_floor_m, prior.rot_floor_rad, estimated=True)


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
    station and of the datum station (positions are relative to the datum's scan frame)."""
    cov_xi = result.cov_xi.copy()
    datum = [int(k) for k in np.flatnonzero(result.fixed)]
    for k, s in enumerate(stations):
        if result.fixed[k]:
            continue
        cov_xi[k] += window_bias_covariance(s, result.poses[k], rates)
        for d in datum[:1]:
            cov_xi[k] += window_bias_covariance(stations[d], result.poses[k], rates)
    R = result.poses.rotation_matrix
    cov_position = R @ cov_xi[:, :3, :3] @ np.transpose(R, (0, 2, 1))
    return replace(result, cov_xi=cov_xi, cov_position=cov_position)


def block_observations(
    stations: Sequence[Station], links: Sequence[Link], rates: DriftRates
) -> list[RelativeObservation]:
    """The block's observations: every usable link's plane-only information, and the trajectory's
    relative pose between consecutive quasi-static stations of the same run, once, weighted by the
    drift rates (plus both scans' window bias: the block's unknowns are scan frames)."""
    observations = [
        RelativeObservation(ObservationKind.PLANES, link.scan_i, link.scan_j, link.T_i_j_planes,
                            link.info_planes, link.rank)
        for link in links
        if link.status is LinkStatus.OK and link.rank > 0
    ]
    sequence = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC]
    for a, b in itertools.pairwise(sequence):
        sa, sb = stations[a], stations[b]
        if sa.run != sb.run:
            continue  # no trajectory between two runs
        Z = sa.T_obj_scan.inverse().compose(sb.T_obj_scan)
        cov = (rates.covariance(_dt(sa, sb), sa.T_obj_scan) + window_bias_covariance(sa, sa.T_obj_scan, rates)
               + window_bias_covariance(sb, sa.T_obj_scan, rates))
        observations.append(RelativeObservation(ObservationKind.TRAJECTORY, a, b, Z, np.linalg.inv(cov), 6))
    return observations
