"""The trajectory's drift model: how fast the trajectory's error grows (prior and measured), and
what that does to the pairwise priors, the block's trajectory links, the planes of a window
(window deformation) and the stations' frames (window bias)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from kinreg.config import DriftConfig
from kinreg.geometry import FloatArray, Pose, quat_to_rotvec, skew
from kinreg.types import BlockResult, ObservationKind, Plane, RelativeObservation, ScanKind, Station


def drift_sigmas(dt_s: float, config: DriftConfig) -> FloatArray:
    """Prior standard deviations (tx, ty, tz [m], rx, ry, rz [rad]) of the trajectory's relative
    pose between two times ``dt_s`` apart: ``sqrt(floor^2 + (rate * dt)^2)`` per axis."""
    pos = np.hypot(config.sigma_pos_floor_m, config.sigma_pos_m_per_s * dt_s)
    rot = np.radians(np.hypot(config.sigma_rot_floor_deg, config.sigma_rot_deg_per_s * dt_s))
    return np.array([pos, pos, pos, rot, rot, rot])


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
        if self.coupling < 0.25:
            return "relative motion exact in the scan frame (SLAM-like)"
        if self.coupling > 0.75:
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


def deskewed_planes(stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]], result: BlockResult,
                    rates: DriftRates) -> tuple[list[tuple[Plane, ...]], float]:
    """The planes of every quasi-static scan with the shear that the trajectory's attitude error
    puts into a window where it is coupled (``rates.coupling``, GNSS/INS-like) taken out.

    A scan is assembled with the trajectory's poses relative to its centre pose; where positions
    are measured apart from the attitude, the relative step ``x(t) - x_c`` is turned into the scan
    frame with the erroneous attitude, so a point seen ``tau`` from the centre is off by
    ``R_c^T [phi]x (x(t) - x_c)`` (``phi``: the attitude correction, object axes). A plane seen
    ``t_offset_s`` from the centre moves by that at its mean time (platform velocity from the
    neighbouring stations): its offset, centroid and hull are moved back by ``kappa`` times it, and
    the uncertainty of the adjusted attitude it is made with is added to its offset's variance.
    On simulated GNSS/INS runs (0.4 deg attitude error, 0.4 m/s) that is 2-5 mm per plane, more
    than the drift inside the window. Static scans and runs without coupling are returned as they are.
    Returns the planes and the largest shift [m].
    """
    kappa = rates.coupling
    if kappa <= 0.0:
        return list(planes), 0.0
    phi = quat_to_rotvec(result.poses.compose(result.poses_initial.inverse()).quat_wxyz)
    R = result.poses.rotation_matrix
    phi_cov = R @ result.cov_xi[:, 3:, 3:] @ np.transpose(R, (0, 2, 1))  # attitude, object axes
    velocity = _platform_velocities(stations, result.poses_initial)
    out, largest = [], 0.0
    for k, scan_planes in enumerate(planes):
        if stations[k].kind is not ScanKind.QUASI_STATIC or not np.all(np.isfinite(velocity[k])):
            out.append(scan_planes)
            continue
        moved = []
        for p in scan_planes:
            tau = p.t_offset_s if np.isfinite(p.t_offset_s) else 0.0
            step = velocity[k] * tau
            shift = kappa * R[k].T @ np.cross(phi[k], step)
            largest = max(largest, float(np.linalg.norm(shift)))
            # The attitude it is made with is uncertain: d(shift) = -kappa R^T [step]x d(phi).
            J = -kappa * p.normal @ R[k].T @ skew(step)
            cov = p.cov_uvd.copy()
            cov[2, 2] += float(J @ phi_cov[k] @ J)
            moved.append(replace(p, d_m=float(p.d_m - p.normal @ shift), centroid_xyz=p.centroid_xyz - shift,
                                 hull_xyz=p.hull_xyz - shift, cov_uvd=cov))
        out.append(tuple(moved))
    return out, largest


def _platform_velocities(stations: Sequence[Station], poses: Pose) -> FloatArray:
    """Per station: the platform's velocity at its centre time [m/s], from its neighbours in the
    same run (central difference; one-sided at the ends; nan for static or lone stations)."""
    velocity = np.full((len(stations), 3), np.nan)
    seq = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC]
    for m, k in enumerate(seq):
        near = [seq[q] for q in (m - 1, m + 1) if 0 <= q < len(seq) and stations[seq[q]].run == stations[k].run]
        if not near:
            continue
        a, b = (near[0], near[-1]) if len(near) == 2 else ((near[0], k) if near[0] < k else (k, near[0]))
        dt = stations[b].t_s - stations[a].t_s
        if dt > 0:
            velocity[k] = (poses.t_xyz[b] - poses.t_xyz[a]) / dt
    return velocity


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
                         floor_share: float = 1.0, measure_correlation: bool = True) -> DriftRates:
    """The trajectory's error model measured by the adjustment, from consecutive quasi-static
    stations of each run: the adjusted step ``y`` against the two predictions of the trajectory's
    step, ``u`` (its step in the scan frame was right: the initial step turned by the first
    station's correction) and ``w`` (its object-frame step was right: the initial step itself).
    The coupling ``kappa`` (:class:`DriftRates`) is the least-squares share of ``w`` in
    ``y = u + kappa (w - u)``, within [0, 1], each link weighted by how far the planes control it
    (its redundancy share: a link that only the trajectory determines repeats the model it was
    adjusted with); the position rate is the RMS per object axis of what
    is left over the time difference (:func:`_rms_rate`), the rotation rate that of the change of
    the correction's rotation, each less the adjustment's own noise in it (the covariance of the
    adjusted relative pose, from the block's trajectory-link tests). The estimate is bounded below
    by ``floor_share`` times the prior rates (1: it only ever raises them); with too few stations
    to measure, the prior is returned.

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
    kappa = float(np.clip(np.sum(c * (W - U) * (Y - U)) / spread, 0.0, 1.0)) if spread > 1e-12 else 0.0
    pos_v = (Y - U - kappa * (W - U)) / np.array(dts)[:, None]
    pos_rate = _rms_rate(pos_v, np.array(pos_noise))
    rot_rate = _rms_rate(np.array(rot_v), np.array(rot_noise))
    correlation = prior.correlation_s
    if measure_correlation:
        correlation = _correlation_times(ends, np.array(dts), pos_v, np.array(rot_v))
    return DriftRates(np.maximum(floor_share * prior.pos_m_per_s, pos_rate),
                      np.maximum(floor_share * prior.rot_rad_per_s, rot_rate),
                      prior.pos_floor_m, prior.rot_floor_rad, estimated=True, coupling=kappa,
                      correlation_s=correlation)


def _correlation_times(ends: list[tuple[int, int]], dts: np.ndarray, pos_v: np.ndarray,
                       rot_v: np.ndarray) -> tuple[float, float]:
    """Correlation times (position, rotation) [s] of the drift velocity, from the correlation of
    the velocities of links two apart in a chain of consecutive links:
    ``rho = sum v_k v_k+2 / sum (v_k^2 + v_k+2^2) / 2`` and ``tau = -lag / ln rho`` (0 where
    rho <= 0), at most the run's length. Two apart, because links one apart share a station whose
    own noise correlates them negatively; the noise in the squares shortens ``tau`` (the
    cautious side). Stretches whose corrections show no drift (no plane fixes them) add to neither
    sum."""
    follows = np.array([ends[k + 1][0] == ends[k][1] for k in range(len(ends) - 1)], dtype=bool)
    k = np.flatnonzero(follows[:-1] & follows[1:]) if len(follows) > 1 else np.zeros(0, dtype=int)
    if not len(k):
        return (0.0, 0.0)
    span = float(np.sum(dts))
    lag = float(np.median(dts[k] + 2.0 * dts[k + 1] + dts[k + 2]) / 2.0)  # centre to centre
    out = []
    for v in (pos_v, rot_v):
        products = v[k] * v[k + 2]
        energy = 0.5 * (v[k] ** 2 + v[k + 2] ** 2)
        total = float(np.sum(energy))
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
