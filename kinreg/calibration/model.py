"""Lever arm and boresight of a kinematic scanner from reference planes (Gauss-Helmert model).

Chain (METHOD.md section 3, seed 000 eq. 1-3)::

    P_l = t_lb + R_lb (t_bs + R_bs P_s),   condition  n_i . P_l - d_i = 0  for every point on plane i

``T_l_b = (R_lb, t_lb)`` is the measured platform pose (laser tracker / T-probe) at the point's
time, ``T_b_s = (R_bs, t_bs)`` the calibration: lever arm ``t_bs`` (body frame, metres) and the
boresight ``R_bs = Rz(kappa) @ Ry(phi) @ Rx(omega)`` (radians).

Stochastic model (seed 000 eq. 4, section 4.2) and how the correlations are kept:

* Every scanner point is observed in polar form; its covariance follows from sigma_d, sigma_phi,
  sigma_theta (the full 3x3, not only its diagonal as in the seed). The condition is linear in
  ``P_s`` with ``B = n^T R_lb R_bs``, so each condition gets the variance ``B Sigma_P B^T``
  (:func:`~kinreg.calibration.arrangement.projected_variance`).
* Pose errors are shared by all points of a tracker epoch, so conditions of one epoch are
  correlated. Instead of a block-diagonal (dense per epoch) Sigma_ww, every tracker epoch gets six
  nuisance unknowns ``(dt, dtheta)`` (translation in l, small rotation ``R = Exp(dtheta) R_meas``)
  with a direct pseudo-observation of zero and the tracker covariance. This mixed model gives the
  same estimate and covariance as the Gauss-Helmert model with the full Sigma_ll (Woodbury
  identity). Points between two epochs use the interpolated pose, so their pose error is
  ``(1 - u) e_i + u e_{i+1}``: the nuisance normal matrix is block-tridiagonal and sparse.
* Optionally the plane parameters are observations (tilt of the normal in two tangent
  directions and the offset), again as nuisance unknowns with pseudo-observations.

The nuisance unknowns are eliminated per iteration with a sparse factorisation (Schur
complement), so the cost is linear in the number of points and epochs. Iterations re-linearise
``A`` at the observations plus residuals (rigorous Gauss-Helmert). sigma0 is tested with the
two-sided chi-square global test on the redundancy ``n_conditions - 6`` (the pseudo-observations
add as many observations as unknowns). With tens of thousands of conditions that test refuses a
sigma0 1.5 % off 1 (alpha 0.001), finer than any a-priori model of a scanner holds: a sigma0
within ``sigma0_band`` (0.9-1.1) is a model a few per cent off, and the sigmas are scaled by it
(:attr:`GlobalTest.scaled`); :func:`~kinreg.calibration.assignment.calibration_problems` refuses
outside it, or inside it where the residuals show structure, and says which.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.sparse.linalg import splu
from scipy.stats import chi2

from kinreg.calibration.arrangement import projected_variance
from kinreg.errors import ConfigError, EstimationError, InputError
from kinreg.geometry import (
    FloatArray,
    Pose,
    quat_multiply,
    quat_normalize,
    quat_slerp,
    quat_to_matrix,
    rotvec_to_quat,
    skew,
)
from kinreg.survey import ReferencePlanes
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)

PARAMETER_NAMES = ("tx", "ty", "tz", "omega", "phi", "kappa")
_EX, _EY, _EZ = np.eye(3)


# --------------------------------------------------------------------------- parameters


def boresight_matrix(omega_rad: float, phi_rad: float, kappa_rad: float) -> FloatArray:
    """``R_bs = Rz(kappa) @ Ry(phi) @ Rx(omega)`` (3, 3)."""
    return _boresight_and_derivatives(np.array([omega_rad, phi_rad, kappa_rad]))[0]


def _boresight_and_derivatives(angles: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``R_bs`` and ``dR_bs/d(omega, phi, kappa)`` as (3, 3, 3) (derivative index first)."""
    om, ph, ka = angles
    co, so, cp, spp, ck, sk = (math.cos(om), math.sin(om), math.cos(ph), math.sin(ph),
                               math.cos(ka), math.sin(ka))
    Rx = np.array([[1, 0, 0], [0, co, -so], [0, so, co]])
    Ry = np.array([[cp, 0, spp], [0, 1, 0], [-spp, 0, cp]])
    Rz = np.array([[ck, -sk, 0], [sk, ck, 0], [0, 0, 1]])
    Kx, Ky, Kz = skew(_EX), skew(_EY), skew(_EZ)
    R = Rz @ Ry @ Rx
    # d/da exp(a K) = K exp(a K) = exp(a K) K for each elementary rotation.
    dR = np.stack([R @ Kx, Rz @ Ry @ Ky @ Rx, Kz @ R])
    return R, dR


@dataclass(frozen=True, eq=False)
class SystemCalibration:
    """Lever arm ``lever_arm_m`` (3,) in the body frame and boresight ``boresight_rad`` (3,) =
    ``(omega, phi, kappa)`` with ``R_bs = Rz(kappa) Ry(phi) Rx(omega)``: together ``T_b_s``."""

    lever_arm_m: FloatArray
    boresight_rad: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, "lever_arm_m", np.asarray(self.lever_arm_m, dtype=np.float64).reshape(3))
        object.__setattr__(self, "boresight_rad",
                           np.asarray(self.boresight_rad, dtype=np.float64).reshape(3))

    @classmethod
    def from_vector(cls, x: ArrayLike) -> SystemCalibration:
        """From ``(tx, ty, tz, omega, phi, kappa)`` in metres and radians."""
        v = np.asarray(x, dtype=np.float64).reshape(6)
        return cls(v[:3], v[3:])

    def as_vector(self) -> FloatArray:
        return np.concatenate([self.lever_arm_m, self.boresight_rad])

    @property
    def rotation_matrix(self) -> FloatArray:
        return boresight_matrix(*self.boresight_rad)

    def as_pose(self) -> Pose:
        """``T_b_s``: maps scanner coordinates into the body frame."""
        return Pose.from_rotation_translation(self.rotation_matrix, self.lever_arm_m)


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class ScannerSigmas:
    """Standard deviations of the scanner's polar observations (seed 000, section 4.2)."""

    sigma_d_m: float = 0.5e-3
    sigma_phi_rad: float = math.radians(0.004)
    sigma_theta_rad: float = math.radians(0.004)


def tracker_translation_sigma_m(distance_m: float = 2.0) -> float:
    """Per-axis sigma of the tracker translations: half the MPE ``15 um + 6 um/m`` as a 3D value
    ``a``, turned into a standard uncertainty ``a / sqrt(3)`` (seed 000, section 4.2)."""
    return (7.5e-6 + 3.0e-6 * distance_m) / math.sqrt(3.0)


@dataclass(frozen=True)
class TrackerSigmas:
    """Standard deviations of one tracker pose (T_l_b): per axis, translation in metres, small
    rotation in radians. Defaults: seed 000 section 4.2 at 2 m (7.8 um) and 0.002 deg."""

    sigma_t_m: float = tracker_translation_sigma_m(2.0)
    sigma_rot_rad: float = math.radians(0.002)


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of :func:`estimate_calibration`.

    ``plane_sigma_d_m``/``plane_sigma_normal_rad``: when set, the plane parameters are observations
    with these sigmas (offset, tilt of the normal); ``None`` holds them fixed.
    ``scale_by_sigma0``: report ``sigma0_hat * sigma`` instead of the a-priori sigmas.
    """

    scanner: ScannerSigmas = field(default_factory=ScannerSigmas)
    tracker: TrackerSigmas = field(default_factory=TrackerSigmas)
    plane_sigma_d_m: float | None = None
    plane_sigma_normal_rad: float | None = None
    max_iterations: int = 20
    # Far below the seed's stop criterion (0.1 mm, 0.1 mdeg): the iterations are cheap.
    tol_translation_m: float = 1e-8
    tol_angle_rad: float = 1e-9
    alpha: float = 0.05
    scale_by_sigma0: bool = False
    # A sigma0 in this band is not a failed calibration even where the chi-square test refuses
    # it: with tens of thousands of conditions that test accepts only +-1.5 % at alpha 0.001,
    # and no a-priori model of a real scanner is right to 1 %. There the sigmas are scaled by
    # sigma0 (GlobalTest.scaled) and the report says so.
    sigma0_band: tuple[float, float] = (0.9, 1.1)
    # Relative eigenvalue of the 6x6 normal matrix (angles scaled by the mean range) below which
    # a direction counts as undetermined: its sigma would be > 1e4 times the best one. Tracker
    # noise alone makes parallel planes "determined" at ~1e-9, so this must stay well above it.
    rank_tolerance: float = 1e-8
    # Acceptance (:func:`~kinreg.calibration.assignment.calibration_problems`): a plate that was
    # scanned gives hundreds of points per second of profiles; fewer than this means it was
    # missed or its points were not found, and its planes' leverage is gone.
    min_points_per_plane: int = 30


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class GlobalTest:
    """Two-sided chi-square test of ``Omega / sigma0_prior^2`` on ``redundancy`` degrees of freedom."""

    statistic: float
    lower: float
    upper: float
    alpha: float
    passed: bool
    # Refused by the chi-square bounds with sigma0 inside CalibrationConfig.sigma0_band: the
    # covariance is scaled by sigma0^2 and the calibration is not refused for it.
    scaled: bool = False


@dataclass(frozen=True)
class PlaneResidualStats:
    """Orthogonal point-to-plane residuals of one plane after the adjustment (millimetres)."""

    name: str
    n_points: int
    mean_mm: float
    rms_mm: float
    max_abs_mm: float
    normalized_rms: float  # RMS of residual / its a-priori sigma (1 if the model fits)


class CovarianceFigures:
    """Standard deviations and correlations of a result's 6x6 ``covariance`` (m, rad)."""

    covariance: FloatArray

    @property
    def sigmas(self) -> FloatArray:
        """Standard deviations ``(6,)`` (m, rad)."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def correlation(self) -> FloatArray:
        s = self.sigmas
        return self.covariance / np.outer(s, s)


@dataclass(frozen=True, eq=False)
class CalibrationResult(CovarianceFigures):
    """Estimated calibration with its covariance ``(6, 6)`` (order :data:`PARAMETER_NAMES`,
    m and rad), sigma0 and the global test, per-plane residuals and per-point residuals
    ``residuals_m`` ``(N,)`` (``nan`` for points not used)."""

    calibration: SystemCalibration
    covariance: FloatArray
    sigma0: float
    redundancy: int
    global_test: GlobalTest
    plane_stats: tuple[PlaneResidualStats, ...]
    residuals_m: FloatArray
    n_points: int
    n_epochs: int
    iterations: int
    converged: bool
    plane_corrections: FloatArray | None = None  # (k, 3): tilt u, tilt v (rad), offset (m)
    # A-priori sigma (N,) of each point's misclosure from the scanner noise (nan for points not
    # used): residuals_m / residual_sigma_m is the standardised residual of the data snooping.
    residual_sigma_m: FloatArray | None = None



# --------------------------------------------------------------------------- plane assignment


def _require_planes_frame(planes: ReferencePlanes) -> None:
    # The tracker measures in the planes' frame; a rough SLAM-frame transform has no place here,
    # and ignoring one silently would calibrate against the wrong geometry.
    if planes.T_ref_traj is not None:
        raise ConfigError("[initial_transform] is for `kinreg process --reference` only: calibration needs the "
                          "trajectory in the planes' frame", planes.source)


def assign_points_to_planes(points_s: FloatArray, stamps_s: FloatArray, trajectory: Trajectory,
                            planes: ReferencePlanes, approximate: SystemCalibration,
                            gate_m: float, ambiguity_factor: float = 3.0) -> np.ndarray:
    """Plane index ``(N,)`` of each point (-1: none) by gating with the approximate calibration.

    The simple assignment for plate-only clouds (see :func:`calibrate_with_gating`).

    Points are mapped into the object frame with the measured poses and ``approximate``; a point
    belongs to plane i if it lies within ``gate_m`` of it and farther than
    ``ambiguity_factor * gate_m`` from every other plane. The margin matters: reference planes
    are infinite here, planes of a calibration field intersect near the profile, and with an
    approximate calibration a point of one plane can look closer to its neighbour. Points outside
    the trajectory's time range get -1.
    """
    _require_planes_frame(planes)
    P = np.asarray(points_s, dtype=np.float64)
    t = np.asarray(stamps_s, dtype=np.float64)
    out = np.full(len(P), -1, dtype=np.int64)
    inside = trajectory.covers(t)
    if not np.any(inside):
        return out
    T_l_b = trajectory.pose_at(t[inside])
    P_l = T_l_b.apply(approximate.as_pose().apply(P[inside]))
    dist = np.abs(P_l @ planes.normals.T - planes.d_m)  # (n, k)
    nearest = np.argmin(dist, axis=1)
    d_near = np.take_along_axis(dist, nearest[:, None], axis=1)[:, 0]
    others = dist.copy()
    np.put_along_axis(others, nearest[:, None], np.inf, axis=1)
    ok = (d_near <= gate_m) & (others.min(axis=1) > ambiguity_factor * gate_m)
    out[np.flatnonzero(inside)] = np.where(ok, nearest, -1)
    return out


# --------------------------------------------------------------------------- estimation


@dataclass(frozen=True, eq=False)
class _Epochs:
    """Interpolation of points between tracker epochs: compact epoch ids ``ia``/``ib`` and the
    weight ``u`` of ``ib``; measured epoch rotations ``R`` (E, 3, 3), quats and translations."""

    ia: np.ndarray
    ib: np.ndarray
    u: FloatArray
    quat_wxyz: FloatArray
    t_xyz: FloatArray


def _epochs_for(trajectory: Trajectory, stamps_s: FloatArray) -> _Epochs:
    s = trajectory.stamps_s
    if len(s) == 1:
        i = np.zeros(len(stamps_s), dtype=np.int64)
        j, u = i, np.zeros(len(stamps_s))
    else:
        i = np.clip(np.searchsorted(s, stamps_s, side="right") - 1, 0, len(s) - 2)
        u = np.clip((stamps_s - s[i]) / (s[i + 1] - s[i]), 0.0, 1.0)
        j = i + 1
    used, inverse = np.unique(np.concatenate([i, j]), return_inverse=True)
    n = len(stamps_s)
    return _Epochs(inverse[:n], inverse[n:], u, trajectory.poses.quat_wxyz[used],
                   trajectory.poses.t_xyz[used])


def _tangent_bases(normals: FloatArray) -> FloatArray:
    """Two unit tangent vectors per normal: ``(k, 2, 3)``."""
    out = np.empty((len(normals), 2, 3))
    for i, n in enumerate(normals):
        a = _EX if abs(n[0]) < 0.9 else _EY
        u = np.cross(n, a)
        u /= np.linalg.norm(u)
        out[i] = (u, np.cross(n, u))
    return out


def undetermined_parameters(N6: FloatArray, length_m: float, tol: float) -> list[str]:
    """Names of the calibration parameters in the (near) null space of a 6x6 normal matrix.

    Angles are scaled by ``length_m`` (a typical range) so that all six are in metres; an
    eigenvalue below ``tol`` times the largest is a rank defect (its direction would have a sigma
    more than ``1/sqrt(tol)`` times the best-determined one). A parameter is named if it takes
    part in such a direction with a weight above 0.1.
    """
    scale = np.array([1.0, 1.0, 1.0, 1.0 / length_m, 1.0 / length_m, 1.0 / length_m])
    M = N6 * np.outer(scale, scale)
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    null = V[:, w <= tol * max(float(w.max()), 1e-300)]
    return [PARAMETER_NAMES[i] for i in range(6) if null.shape[1] and np.max(np.abs(null[i])) > 0.1]


def estimate_calibration(points_s: ArrayLike, stamps_s: ArrayLike, plane_index: ArrayLike,
                         trajectory: Trajectory, planes: ReferencePlanes,
                         approximate: SystemCalibration,
                         config: CalibrationConfig | None = None) -> CalibrationResult:
    """Estimate lever arm and boresight from scanner points on known planes.

    Inputs:
        points_s: ``(N, 3)`` points in the scanner frame, metres.
        stamps_s: ``(N,)`` their times, seconds, on the trajectory's time scale.
        plane_index: ``(N,)`` index into ``planes`` of the plane each point lies on, -1 for none
            (e.g. from :func:`assign_points_to_planes`).
        trajectory: measured platform poses ``T_l_b`` (tracker epochs; each row has its own
            independent errors with ``config.tracker`` sigmas).
        planes: reference planes in the object frame l.
        approximate: starting values of the calibration.

    Returns a :class:`CalibrationResult`. Raises :class:`InputError` for inconsistent inputs and
    :class:`EstimationError` naming the undetermined parameters when the data do not determine
    all six (e.g. all planes parallel), or when too few points remain.
    """
    _require_planes_frame(planes)
    cfg = config or CalibrationConfig()
    P_all = np.asarray(points_s, dtype=np.float64)
    t_all = np.asarray(stamps_s, dtype=np.float64)
    idx_all = np.asarray(plane_index, dtype=np.int64)
    if P_all.ndim != 2 or P_all.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {P_all.shape}")
    if t_all.shape != (len(P_all),) or idx_all.shape != (len(P_all),):
        raise InputError("points, stamps and plane indices must have the same length")
    k = len(planes)
    if k == 0:
        raise InputError("no reference planes")
    if np.any(idx_all >= k) or np.any(idx_all < -1):
        raise InputError(f"plane indices must lie in -1..{k - 1}")
    used = idx_all >= 0
    inside = trajectory.covers(t_all)
    if np.any(used & ~inside):
        logger.warning("%d points lie outside the trajectory's time range and are left out",
                       int(np.sum(used & ~inside)))
    used &= inside
    N = int(used.sum())
    if N < 6:
        raise EstimationError(f"only {N} points on reference planes within the trajectory; need > 6")

    P = P_all[used]
    plane = idx_all[used]
    ep = _epochs_for(trajectory, t_all[used])
    E = len(ep.t_xyz)
    n0 = planes.normals
    d0 = planes.d_m
    observe_planes = cfg.plane_sigma_d_m is not None or cfg.plane_sigma_normal_rad is not None
    tangents = _tangent_bases(n0)
    n_plane_par = 3 * k if observe_planes else 0
    m = 6 + n_plane_par
    if observe_planes:
        s_tilt = cfg.plane_sigma_normal_rad
        s_off = cfg.plane_sigma_d_m
        if not s_tilt or not s_off or s_tilt <= 0 or s_off <= 0:
            raise InputError("plane observations need both plane_sigma_d_m and plane_sigma_normal_rad > 0")
        prior_plane = np.tile([1 / s_tilt**2, 1 / s_tilt**2, 1 / s_off**2], k)
    else:
        prior_plane = np.zeros(0)
    st, sr = cfg.tracker.sigma_t_m, cfg.tracker.sigma_rot_rad
    if st <= 0 or sr <= 0:
        raise InputError("tracker sigmas must be > 0")
    prior_pose = np.tile([1 / st**2] * 3 + [1 / sr**2] * 3, E)
    sc = cfg.scanner

    x = approximate.as_vector().copy()
    q = np.zeros((k, 3))  # plane corrections: tilt u, tilt v, offset
    p = np.zeros((E, 6))  # pose corrections per epoch: dt (l frame), dtheta (left, l frame)
    v = np.zeros_like(P)  # observation residuals of the points (scanner frame)
    w_a, w_b = 1.0 - ep.u, ep.u
    rows = np.arange(N)

    converged = False
    it = 0
    for it in range(1, cfg.max_iterations + 1):
        # ---- current values
        R_bs, dR_bs = _boresight_and_derivatives(x[3:])
        t_bs = x[:3]
        q_ep = quat_multiply(rotvec_to_quat(p[:, 3:]), ep.quat_wxyz)
        t_ep = ep.t_xyz + p[:, :3]
        R_pt = quat_to_matrix(quat_normalize(quat_slerp(q_ep[ep.ia], q_ep[ep.ib], ep.u)))
        t_pt = w_a[:, None] * t_ep[ep.ia] + w_b[:, None] * t_ep[ep.ib]
        raw_n = n0 + np.einsum("kj,kjc->kc", q[:, :2], tangents)
        norm_n = np.linalg.norm(raw_n, axis=1)
        n_cur = raw_n / norm_n[:, None]
        d_cur = d0 + q[:, 2]
        n = n_cur[plane]

        # ---- misclosures with the original observations, A at observations + residuals
        qb = t_bs + P @ R_bs.T
        P_l = t_pt + np.einsum("nij,nj->ni", R_pt, qb)
        f = np.einsum("ni,ni->n", n, P_l) - d_cur[plane]
        P0 = P + v
        qb0 = t_bs + P0 @ R_bs.T
        Rq0 = np.einsum("nij,nj->ni", R_pt, qb0)
        n_b = np.einsum("nji,nj->ni", R_pt, n)  # R_lb^T n
        n_s = n_b @ R_bs  # R_bs^T R_lb^T n: B^T
        var = projected_variance(P, n_s, sc.sigma_d_m, sc.sigma_phi_rad, sc.sigma_theta_rad)
        w = 1.0 / var

        a_cal = np.empty((N, 6))
        a_cal[:, :3] = n_b
        a_cal[:, 3:] = np.einsum("ni,kij,nj->nk", n_b, dR_bs, P0)
        a_rot = np.cross(Rq0, n)  # d f / d dtheta of the pose
        cols = [np.tile(np.arange(6), (N, 1))]
        vals = [a_cal]
        if observe_planes:
            # d n / d tilt = (I - n n^T) e / |raw_n|; f depends on n through n . P_l.
            proj = P_l - np.einsum("ni,ni->n", n, P_l)[:, None] * n
            a_pl = np.empty((N, 3))
            a_pl[:, :2] = np.einsum("ni,nji->nj", proj, tangents[plane]) / norm_n[plane][:, None]
            a_pl[:, 2] = -1.0
            cols.append(6 + 3 * plane[:, None] + np.arange(3))
            vals.append(a_pl)
        g = np.concatenate([n, a_rot], axis=1)
        cols.append(m + 6 * ep.ia[:, None] + np.arange(6))
        vals.append(g * w_a[:, None])
        cols.append(m + 6 * ep.ib[:, None] + np.arange(6))
        vals.append(g * w_b[:, None])
        C = np.concatenate(cols, axis=1)
        V = np.concatenate(vals, axis=1)
        J = sp.csr_matrix((V.ravel(), (np.repeat(rows, C.shape[1]), C.ravel())), shape=(N, m + 6 * E))

        JW = J.T.multiply(w[None, :]).tocsr()
        Nfull = (JW @ J).tocsc()
        rhs = -(JW @ f)
        z_prior = np.concatenate([q.ravel() if observe_planes else np.zeros(0), p.ravel()])
        prior = np.concatenate([prior_plane, prior_pose])
        rhs[6:] -= prior * z_prior
        Nfull = Nfull + sp.diags(np.concatenate([np.zeros(6), prior]), format="csc")

        # ---- eliminate the pose nuisances (block-tridiagonal) by a sparse factorisation
        N_xx = Nfull[:m, :m].toarray()
        N_xp = Nfull[:m, m:].toarray()
        lu = splu(Nfull[m:, m:].tocsc())
        X = lu.solve(np.ascontiguousarray(N_xp.T))  # N_pp^-1 N_px, (6E, m)
        Nbar = N_xx - N_xp @ X
        Nbar = 0.5 * (Nbar + Nbar.T)
        if it == 1:
            # The plane corrections always have a prior: reduce them too and test the six alone.
            N6 = Nbar[:6, :6] - (Nbar[:6, 6:] @ np.linalg.solve(Nbar[6:, 6:], Nbar[6:, :6])
                                 if observe_planes else 0.0)
            bad = undetermined_parameters(N6, float(np.sqrt(np.mean(np.sum(P**2, axis=1)))),
                                          cfg.rank_tolerance)
            if bad:
                raise EstimationError(
                    "the data do not determine the calibration parameter(s) " + ", ".join(bad)
                    + " (all reference planes parallel, or too few differently oriented planes?)")
        y_p = lu.solve(rhs[m:])
        try:
            L = np.linalg.cholesky(Nbar)
        except np.linalg.LinAlgError:
            raise EstimationError("normal matrix of the calibration is not positive definite") from None
        dx = _chol_solve(L, rhs[:m] - N_xp @ y_p)
        dp = y_p - X @ dx

        x += dx[:6]
        if observe_planes:
            q += dx[6:].reshape(k, 3)
        p += dp.reshape(E, 6)
        lin = f + J @ np.concatenate([dx, dp])
        # v = Sigma_P B^T w (-(f + J dz)): the residual of each point observation (scanner frame)
        v = -_sigma_times(P, n_s, sc) * (w * lin)[:, None]
        step_t = float(np.max(np.abs(dx[:3])))
        step_a = float(np.max(np.abs(dx[3:6])))
        logger.debug("iteration %d: |dt| %.3g m, |dangle| %.3g rad", it, step_t, step_a)
        if step_t < cfg.tol_translation_m and step_a < cfg.tol_angle_rad:
            converged = True
            break
    if not converged:
        logger.warning("calibration did not converge in %d iterations", cfg.max_iterations)

    # ---- final quantities (at convergence dz ~ 0, the linearised misclosure is the final one)
    Q = np.linalg.inv(Nbar)
    Q = 0.5 * (Q + Q.T)
    omega = float(np.sum(w * lin**2) + np.sum(prior_pose * (p.ravel()) ** 2)
                  + (np.sum(prior_plane * q.ravel() ** 2) if observe_planes else 0.0))
    redundancy = N - 6
    sigma0 = math.sqrt(omega / redundancy) if redundancy > 0 else float("nan")
    lower = float(chi2.ppf(cfg.alpha / 2, redundancy)) if redundancy > 0 else float("nan")
    upper = float(chi2.ppf(1 - cfg.alpha / 2, redundancy)) if redundancy > 0 else float("nan")
    passed = bool(lower <= omega <= upper)
    scaled = not passed and cfg.sigma0_band[0] <= sigma0 <= cfg.sigma0_band[1]
    test = GlobalTest(omega, lower, upper, cfg.alpha, passed, scaled)
    cov = Q[:6, :6] * (sigma0**2 if cfg.scale_by_sigma0 or scaled else 1.0)

    # Orthogonal residual of each point to its (adjusted) plane: the final misclosure f.
    resid = np.full(len(P_all), np.nan)
    resid[used] = f
    resid_sigma = np.full(len(P_all), np.nan)
    resid_sigma[used] = np.sqrt(var)
    stats = []
    for i, pl in enumerate(planes.planes):
        sel = plane == i
        if not np.any(sel):
            stats.append(PlaneResidualStats(pl.name, 0, math.nan, math.nan, math.nan, math.nan))
            continue
        r = f[sel]
        stats.append(PlaneResidualStats(
            pl.name, int(sel.sum()), float(r.mean() * 1e3), float(np.sqrt(np.mean(r**2)) * 1e3),
            float(np.max(np.abs(r)) * 1e3), float(np.sqrt(np.mean(r**2 * w[sel])))))
    logger.info("calibration: %d points, %d epochs, %d iterations, sigma0 %.3f", N, E, it, sigma0)
    return CalibrationResult(
        calibration=SystemCalibration.from_vector(x), covariance=cov, sigma0=sigma0,
        redundancy=redundancy, global_test=test, plane_stats=tuple(stats), residuals_m=resid,
        n_points=N, n_epochs=E, iterations=it, converged=converged,
        plane_corrections=q.copy() if observe_planes else None, residual_sigma_m=resid_sigma)


def _chol_solve(L: FloatArray, b: FloatArray) -> FloatArray:
    from scipy.linalg import solve_triangular

    return solve_triangular(L.T, solve_triangular(L, b, lower=True), lower=False)


def _sigma_times(P: FloatArray, directions: FloatArray, sc: ScannerSigmas) -> FloatArray:
    """``Sigma_P @ n`` ``(N, 3)`` for the polar covariance of points ``P`` and vectors ``n``."""
    from kinreg.calibration.arrangement import polar_jacobian_columns

    out = np.zeros_like(P)
    sigmas = (sc.sigma_d_m, sc.sigma_phi_rad, sc.sigma_theta_rad)
    for col, s in zip(polar_jacobian_columns(P), sigmas, strict=True):
        out += (s**2 * np.einsum("ij,ij->i", col, directions))[:, None] * col
    return out


def calibrate_with_gating(points_s: ArrayLike, stamps_s: ArrayLike, trajectory: Trajectory,
                          planes: ReferencePlanes, approximate: SystemCalibration,
                          config: CalibrationConfig | None = None,
                          gates_m: tuple[float, ...] = (0.05, 0.0125, 0.003)
                          ) -> tuple[CalibrationResult, np.ndarray]:
    """Assign points to planes by gating, estimate, and repeat with the next (smaller) gate.

    Only for clouds that hold nothing but plate points: surfaces round the plates (floor, walls,
    mounts) defeat it, and its result depends on the gates. The command line uses
    :func:`~kinreg.calibration.assignment.calibrate_robust`.

    The first gate must cover the error of ``approximate`` at the plane distances; later gates
    use the previous estimate and recover the points that were ambiguous or outside at first.
    Returns the last result and the plane index ``(N,)`` it used.
    """
    P = np.asarray(points_s, dtype=np.float64)
    t = np.asarray(stamps_s, dtype=np.float64)
    if not gates_m:
        raise InputError("at least one gate is needed")
    current = approximate
    result: CalibrationResult | None = None
    index = np.full(len(P), -1, dtype=np.int64)
    for gate in gates_m:
        index = assign_points_to_planes(P, t, trajectory, planes, current, gate)
        logger.info("gate %.4f m: %d of %d points assigned", gate, int(np.sum(index >= 0)), len(P))
        result = estimate_calibration(P, t, index, trajectory, planes, current, config)
        current = result.calibration
    if result is None:
        raise ConfigError("no gate given: gating needs at least one distance")
    return result, index
