"""Finding the reference plates' points in a scan of a whole room, and accepting a calibration.

A scan of a calibration field hits the plates and everything round them: floor, walls, ceiling,
the boards and posts the plates are mounted on. :func:`calibrate_robust` assigns points to the
reference planes coarse to fine:

1. **Pass 1, from the data.** The points are mapped into the object frame with the starting
   values. Per plane, the candidates are the points that project into the plane's extent (the
   plate's polygon; unbounded planes take every point) and lie within the search depth of the
   plane: ``max(gate, sqrt(area) / 2)`` for a plate (a box as deep as half its side, so that
   starting values that misplace the plate by centimetres still find it), the gate for an
   unbounded plane. In the candidates a least-median-of-squares plane (random three-point
   hypotheses) finds the plate as the dominant surface, wherever the starting values put it,
   and a robust scale of its residuals says how thick it is; points within
   ``min(gate, c * scale)`` of it are the plate's. A mount board parallel to the plate a few
   centimetres behind it stays out even when it covers a fifth of the candidates.
2. **Adjustment with data snooping.** The Gauss-Helmert adjustment (:mod:`.model`) on those
   points; points whose standardised residual exceeds ``c`` are removed, worst first (all
   within half the largest), and the adjustment repeated until none is left.
3. **Passes 2.., from the estimate.** Every point in a plane's search region (extent and depth
   as in pass 1) is tested against that plane with the current estimate: it belongs to the
   plane if its distance is within ``c * sigma0' * sqrt(var_obs + var_prop)``, ``var_obs`` from
   the scanner and tracker noise, ``var_prop`` the estimate's covariance propagated to the
   point, ``sigma0' = max(1, sigma0)``.
   The gate narrows as the estimate sharpens and never depends on the starting gate; step 2
   follows; the passes stop when the assignment no longer changes.

``c`` is the two-sided normal quantile of ``alpha / n`` for ``n`` tested points (Bonferroni:
with ``n`` good points the chance that any one is rejected is ``alpha``), so that clean data lose
no tail and the global test keeps its level.

:func:`calibration_problems` lists why a result must not be used (too few points on a plane, a
failed global test, no convergence, an estimate that stayed at starting values the data
contradict); the command line refuses such a result unless told to keep it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import chi2, norm

from kinreg.calibration.arrangement import projected_variance
from kinreg.calibration.model import (
    PARAMETER_NAMES,
    CalibrationConfig,
    CalibrationResult,
    SystemCalibration,
    _boresight_and_derivatives,
    _require_planes_frame,
    estimate_calibration,
)
from kinreg.errors import EstimationError, InputError
from kinreg.geometry import FloatArray
from kinreg.survey import ReferencePlanes
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class AssignmentConfig:
    """Settings of :func:`calibrate_robust` (module docstring).

    ``gate_m``: the starting gate, the widest distance from the plate found in pass 1 that is
    accepted (and the search depth of unbounded planes). ``alpha``: family-wise error rate of the
    gates and the data snooping. ``hypotheses``: three-point samples of the robust plane fit.
    """

    gate_m: float = 0.05
    alpha: float = 0.05
    max_passes: int = 8
    max_snooping_rounds: int = 30
    hypotheses: int = 400
    seed: int = 0


@dataclass(frozen=True)
class AssignmentPass:
    """Figures of one pass: points assigned, removed by the data snooping, sigma0 after it."""

    n_assigned: int
    n_snooped: int
    sigma0: float
    snooping_rounds: int


@dataclass(frozen=True, eq=False)
class RobustCalibration:
    """Result of :func:`calibrate_robust`: the last adjustment, the plane index ``(N,)`` it used
    (-1: not used), the passes, and ``start_misfit``: sigma0 of the starting values on the final
    points (the measured poses, no adjustment), ``start_misfit_upper`` its global-test bound."""

    result: CalibrationResult
    plane_index: np.ndarray
    passes: tuple[AssignmentPass, ...]
    start_misfit: float
    start_misfit_upper: float
    approximate: SystemCalibration
    n_outside_time: int = 0
    unbounded_planes: tuple[str, ...] = field(default_factory=tuple)


def bonferroni_quantile(alpha: float, n: int) -> float:
    """Two-sided normal quantile for a family of ``n`` tests at family-wise level ``alpha``.

    >>> round(bonferroni_quantile(0.05, 1), 3)
    1.96
    """
    return float(norm.isf(alpha / (2.0 * max(n, 1))))


def object_points(points_s: FloatArray, stamps_s: FloatArray, trajectory: Trajectory,
                  calibration: SystemCalibration) -> tuple[FloatArray, np.ndarray]:
    """Object-frame points ``(N, 3)`` (nan outside the trajectory's time range) and the mask of
    points inside it."""
    inside = trajectory.covers(stamps_s)
    out = np.full((len(points_s), 3), np.nan)
    if np.any(inside):
        T_l_b = trajectory.pose_at(stamps_s[inside])
        out[inside] = T_l_b.apply(calibration.as_pose().apply(points_s[inside]))
    return out, inside


def _robust_plane(X: FloatArray, rng: np.random.Generator, hypotheses: int
                  ) -> tuple[FloatArray, float, float] | None:
    """Least-median-of-squares plane of points ``(m, 3)``: unit normal, offset, robust scale."""
    m = len(X)
    if m < 6:
        return None
    centre = X.mean(axis=0)
    Y = X - centre  # conditioning: offsets near zero
    idx = rng.integers(0, m, size=(hypotheses, 3))
    a, b, c = Y[idx[:, 0]], Y[idx[:, 1]], Y[idx[:, 2]]
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n, axis=1)
    ok = ln > 1e-12
    if not np.any(ok):
        return None
    n = n[ok] / ln[ok, None]
    d = np.einsum("ij,ij->i", n, a[ok])
    best_med, best = np.inf, 0
    for k0 in range(0, len(n), 64):  # bounded memory: 64 hypotheses x m points at a time
        r2 = (Y @ n[k0:k0 + 64].T - d[k0:k0 + 64]) ** 2
        med = np.median(r2, axis=0)
        j = int(np.argmin(med))
        if med[j] < best_med:
            best_med, best = float(med[j]), k0 + j
    # Rousseeuw's consistency factor for the LMedS scale with p = 3 parameters.
    scale = 1.4826 * (1.0 + 5.0 / (m - 3)) * math.sqrt(best_med)
    nb, db = n[best], d[best]
    # Refine by least squares on the points within 2.5 scales (the usual LMedS reweighting).
    r = Y @ nb - db
    keep = np.abs(r) <= 2.5 * max(scale, 1e-12)
    if keep.sum() >= 3:
        Z = Y[keep]
        zc = Z.mean(axis=0)
        _, _, vt = np.linalg.svd(Z - zc, full_matrices=False)
        nb = vt[2]
        db = float(nb @ zc)
        r = Y @ nb - db
        scale = 1.4826 * (1.0 + 5.0 / (m - 3)) * float(np.median(np.abs(r)))
    return nb, float(db + nb @ centre), scale


def _search_depths(planes: ReferencePlanes, gate_m: float) -> FloatArray:
    return np.array([max(gate_m, 0.5 * math.sqrt(p.extent.area_m2)) if p.extent is not None else gate_m
                     for p in planes.planes])


def _in_extents(P_l: FloatArray, valid: np.ndarray, planes: ReferencePlanes) -> np.ndarray:
    """``(N, k)``: which valid points project into each plane's extent (all for unbounded)."""
    out = np.zeros((len(P_l), len(planes)), dtype=bool)
    for i, p in enumerate(planes.planes):
        out[valid, i] = True if p.extent is None else p.extent.contains(P_l[valid])
    return out


def _first_pass(P_l: FloatArray, valid: np.ndarray, planes: ReferencePlanes, cfg: AssignmentConfig
                ) -> np.ndarray:
    dist = np.abs(P_l @ planes.normals.T - planes.d_m)  # (N, k), nan outside the time range
    cand = _in_extents(P_l, valid, planes) & (dist <= _search_depths(planes, cfg.gate_m)[None, :])
    score = np.full(dist.shape, np.inf)
    for i in range(len(planes)):
        sel = np.flatnonzero(cand[:, i])
        fit = _robust_plane(P_l[sel], np.random.default_rng([cfg.seed, i]), cfg.hypotheses)
        if fit is None:
            continue
        n, d, scale = fit
        r = np.abs(P_l[sel] @ n - d)
        tol = min(cfg.gate_m, bonferroni_quantile(cfg.alpha, len(sel)) * scale)
        ok = r <= tol
        score[sel[ok], i] = r[ok] / max(tol, 1e-12)
        logger.debug("pass 1, plane %s: %d candidates, scale %.2f mm, %d within %.2f mm",
                     planes.planes[i].name, len(sel), scale * 1e3, int(ok.sum()), tol * 1e3)
    return _nearest(score)


def _nearest(score: FloatArray) -> np.ndarray:
    """Plane of the smallest finite score per row, -1 where none is finite."""
    if score.shape[1] == 0:
        return np.full(len(score), -1, dtype=np.int64)
    best = np.argmin(score, axis=1)
    return np.where(np.isfinite(score[np.arange(len(score)), best]), best, -1).astype(np.int64)


def _distance_sigmas(points_s: FloatArray, stamps_s: FloatArray, trajectory: Trajectory,
                     calibration: SystemCalibration, normals_l: FloatArray, config: CalibrationConfig
                     ) -> tuple[FloatArray, FloatArray]:
    """For points ``(n, 3)`` (inside the time range) against planes with object-frame normals
    ``(n, 3)``: variance of the distance from the scanner and tracker noise, and the rows
    ``(n, 6)`` of its derivative by the calibration (to propagate a covariance)."""
    T_l_b = trajectory.pose_at(stamps_s)
    R_lb = T_l_b.rotation_matrix
    R_bs, dR_bs = _boresight_and_derivatives(calibration.boresight_rad)
    n_b = np.einsum("nji,nj->ni", R_lb, normals_l)
    n_s = n_b @ R_bs
    sc, tr = config.scanner, config.tracker
    var = projected_variance(points_s, n_s, sc.sigma_d_m, sc.sigma_phi_rad, sc.sigma_theta_rad)
    arm = np.einsum("nij,nj->ni", R_lb, calibration.lever_arm_m + points_s @ R_bs.T)
    var = var + tr.sigma_t_m**2 + tr.sigma_rot_rad**2 * np.sum(np.cross(arm, normals_l) ** 2, axis=1)
    a = np.empty((len(points_s), 6))
    a[:, :3] = n_b
    a[:, 3:] = np.einsum("ni,kij,nj->nk", n_b, dR_bs, points_s)
    return var, a


def _gated_pass(points_s: FloatArray, stamps_s: FloatArray, trajectory: Trajectory,
                planes: ReferencePlanes, result: CalibrationResult, config: CalibrationConfig,
                cfg: AssignmentConfig) -> np.ndarray:
    cal = result.calibration
    P_l, valid = object_points(points_s, stamps_s, trajectory, cal)
    # The search region of pass 1 (extent x depth) bounds every pass: cheap to test first.
    with np.errstate(invalid="ignore"):
        near = np.abs(P_l @ planes.normals.T - planes.d_m) <= _search_depths(planes, cfg.gate_m)
    ext = _in_extents(P_l, valid, planes) & near
    rows, cols = np.nonzero(ext)
    score = np.full(ext.shape, np.inf)
    if len(rows) == 0:
        return _nearest(score)
    nl = planes.normals[cols]
    dist = np.einsum("ni,ni->n", P_l[rows], nl) - planes.d_m[cols]
    var_obs, a = _distance_sigmas(points_s[rows], stamps_s[rows], trajectory, cal, nl, config)
    # The covariance as computed (a priori): its sigma0 scaling is applied to the whole variance.
    var_prop = np.einsum("ni,ij,nj->n", a, result.covariance, a)
    s0 = max(1.0, result.sigma0) if math.isfinite(result.sigma0) else 1.0
    gate = bonferroni_quantile(cfg.alpha, len(rows)) * s0 * np.sqrt(var_obs + var_prop)
    ok = np.abs(dist) <= gate
    score[rows[ok], cols[ok]] = np.abs(dist[ok]) / gate[ok]
    return _nearest(score)


def _adjust_with_snooping(points_s: FloatArray, stamps_s: FloatArray, index: np.ndarray,
                          trajectory: Trajectory, planes: ReferencePlanes, start: SystemCalibration,
                          config: CalibrationConfig, cfg: AssignmentConfig
                          ) -> tuple[CalibrationResult, np.ndarray, int, int]:
    """Adjust, remove the worst standardised residuals above the Bonferroni bound, repeat."""
    idx = index.copy()
    n_removed = 0
    current = start
    for rounds in range(1, cfg.max_snooping_rounds + 1):
        result = estimate_calibration(points_s, stamps_s, idx, trajectory, planes, current, config)
        current = result.calibration
        assert result.residual_sigma_m is not None
        w = np.abs(result.residuals_m) / result.residual_sigma_m  # nan for unused points
        used = np.isfinite(w)
        crit = bonferroni_quantile(cfg.alpha, int(used.sum()))
        w_max = float(np.max(w[used])) if np.any(used) else 0.0
        if w_max <= crit:
            return result, idx, n_removed, rounds
        # Worst first: a gross outlier inflates its neighbours' residuals through the estimate.
        bad = used & (w > max(crit, 0.5 * w_max))
        idx[bad] = -1
        n_removed += int(bad.sum())
        if np.sum(idx >= 0) <= 6:
            raise EstimationError(f"the data snooping rejected all but {int(np.sum(idx >= 0))} points: no "
                                  "consistent set of plate points (starting values too far off?)")
    logger.warning("data snooping still finds outliers after %d rounds", cfg.max_snooping_rounds)
    return result, idx, n_removed, cfg.max_snooping_rounds


def start_misfit(points_s: FloatArray, stamps_s: FloatArray, index: np.ndarray, trajectory: Trajectory,
                 planes: ReferencePlanes, approximate: SystemCalibration, config: CalibrationConfig
                 ) -> tuple[float, float]:
    """sigma0 of the starting values on the assigned points (no adjustment) and the upper bound
    of the global test for it: above the bound, the starting values contradict the data."""
    used = np.flatnonzero(index >= 0)
    if len(used) <= 6:
        return math.nan, math.nan
    P_l, _ = object_points(points_s[used], stamps_s[used], trajectory, approximate)
    nl = planes.normals[index[used]]
    f = np.einsum("ni,ni->n", P_l, nl) - planes.d_m[index[used]]
    var, _ = _distance_sigmas(points_s[used], stamps_s[used], trajectory, approximate, nl, config)
    red = len(used) - 6
    return (math.sqrt(float(np.sum(f**2 / var)) / red),
            math.sqrt(float(chi2.ppf(1 - config.alpha / 2, red)) / red))


def check_time_overlap(stamps_s: ArrayLike, trajectory: Trajectory, cloud_source: str | None = None) -> int:
    """Number of point times outside the trajectory's time range; raises :class:`InputError`
    (naming the trajectory, with both time ranges) when none lies inside."""
    t = np.asarray(stamps_s, dtype=np.float64)
    inside = trajectory.covers(t)
    if len(t) and not np.any(inside):
        where = f" of {cloud_source}" if cloud_source else ""
        raise InputError(
            f"no point time lies in the trajectory's time range: the points{where} span "
            f"[{float(t.min()):.3f}, {float(t.max()):.3f}] s, the trajectory [{trajectory.t_start_s:.3f}, "
            f"{trajectory.t_end_s:.3f}] s", trajectory.source)
    return int(np.sum(~inside))


def calibrate_robust(points_s: ArrayLike, stamps_s: ArrayLike, trajectory: Trajectory,
                     planes: ReferencePlanes, approximate: SystemCalibration,
                     config: CalibrationConfig | None = None,
                     assignment: AssignmentConfig | None = None) -> RobustCalibration:
    """Assign points to the reference planes and estimate the calibration (module docstring).

    Inputs as :func:`~kinreg.calibration.model.estimate_calibration` without the plane index:
    points ``(N, 3)`` in the scanner frame, their times ``(N,)``. Points outside the
    trajectory's time range are left out and counted. Raises :class:`InputError` when no point
    lies in the trajectory's time range, :class:`EstimationError` when the data do not determine
    the calibration or no plate's points are found.
    """
    _require_planes_frame(planes)
    config = config or CalibrationConfig()
    cfg = assignment or AssignmentConfig()
    if not cfg.gate_m > 0:
        raise InputError(f"the starting gate must be > 0, got {cfg.gate_m} m")
    P = np.asarray(points_s, dtype=np.float64)
    t = np.asarray(stamps_s, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or t.shape != (len(P),):
        raise InputError(f"points must have shape (N, 3) with N times, got {P.shape} and {t.shape}")
    check_time_overlap(t, trajectory)
    P_l, valid = object_points(P, t, trajectory, approximate)
    index = _first_pass(P_l, valid, planes, cfg)
    logger.info("pass 1: %d of %d points on %d planes", int(np.sum(index >= 0)), len(P), len(planes))
    if np.sum(index >= 0) <= 6:
        raise EstimationError(
            f"no reference plate found: only {int(np.sum(index >= 0))} points near the planes with the "
            f"starting values (starting gate {cfg.gate_m * 1e3:.0f} mm): are the starting values, the "
            "planes' extents or the trajectory's frame right?")
    passes: list[AssignmentPass] = []
    current = approximate
    seen: list[np.ndarray] = []
    for k in range(cfg.max_passes):
        if np.sum(index >= 0) <= 6:
            raise EstimationError(
                f"the reference plates' points were lost in pass {k + 1} (only {int(np.sum(index >= 0))} "
                "left within the gates): the estimate ran away; are the starting values within the plates' "
                "search depth and the extents right?")
        result, used, n_snooped, rounds = _adjust_with_snooping(P, t, index, trajectory, planes, current,
                                                                config, cfg)
        passes.append(AssignmentPass(int(np.sum(index >= 0)), n_snooped, result.sigma0, rounds))
        logger.info("pass %d: %d points, %d removed by data snooping, sigma0 %.3f", k + 1,
                    int(np.sum(index >= 0)), n_snooped, result.sigma0)
        current = result.calibration
        new = _gated_pass(P, t, trajectory, planes, result, config, cfg)
        if np.array_equal(new, index) or any(np.array_equal(new, s) for s in seen):
            index = used
            break
        seen.append(index)
        index = new
    else:
        index = used
    misfit, upper = start_misfit(P, t, index, trajectory, planes, approximate, config)
    return RobustCalibration(result, index, tuple(passes), misfit, upper, approximate,
                             int(np.sum(~valid)),
                             tuple(p.name for p in planes.planes if p.extent is None))


def calibration_problems(robust: RobustCalibration, planes: ReferencePlanes,
                         config: CalibrationConfig | None = None) -> list[str]:
    """Why the calibration must not be used (empty: it may). One short clause per problem."""
    config = config or CalibrationConfig()
    res = robust.result
    out = []
    few = [f"{s.name} ({s.n_points})" for s in res.plane_stats if s.n_points < config.min_points_per_plane]
    if few:
        out.append(f"too few points (< {config.min_points_per_plane}) on plane(s) {', '.join(few)}")
    if not res.converged:
        out.append(f"the adjustment did not converge in {res.iterations} iterations")
    gt = res.global_test
    structure = residual_structure(res)
    if not gt.passed and not gt.scaled:
        cause = ("; ".join(structure) if structure else
                 "the residuals show no structure: the a-priori sigmas are off by this factor (the estimate may "
                 "hold, its sigmas do not; give the instrument's sigmas)")
        out.append(f"global test failed: sigma0 {res.sigma0:.3f} (statistic {gt.statistic:.1f} outside "
                   f"[{gt.lower:.1f}, {gt.upper:.1f}], and outside {config.sigma0_band[0]:g}-"
                   f"{config.sigma0_band[1]:g}): {cause}")
    elif structure:
        out.append(f"sigma0 {res.sigma0:.3f} but the residuals show structure: " + "; ".join(structure))
    moved = np.abs(res.calibration.as_vector() - robust.approximate.as_vector()) / res.sigmas
    far = math.isfinite(robust.start_misfit) and robust.start_misfit > robust.start_misfit_upper
    if far and np.all(moved < 1.0):
        out.append(f"the estimate stayed within one sigma of the starting values although these do not "
                   f"fit the data (sigma0 {robust.start_misfit:.1f} at the start)")
    return out


# Residuals "show structure" where a plate's mean residual is this share of its RMS (a plate
# off, or points of another surface on it: a clean run's means are 1-5 % of the RMS) or where
# the plates' RMS over their a-priori sigmas differ by this factor (0.95-1.05 on clean runs).
_MEAN_SHARE_OF_RMS = 0.3
_NORMALISED_RMS_RATIO = 1.5
# ... or where the standardised residuals' RMS exceeds their robust spread (1.4826 MAD) by this
# factor: points of other surfaces on the plates make long tails (1.00-1.02 on clean runs, where
# the residuals are as Gaussian as the scanner's noise; a stochastic model off by a factor alone
# scales both alike).
_RMS_OVER_ROBUST_SPREAD = 1.3


def residual_structure(result: CalibrationResult) -> list[str]:
    """What in the residuals says the model is wrong where it matters, one clause each (empty:
    nothing): a plate whose residuals are off its plane on the mean, and plates that fit much
    worse than others."""
    stats = [s for s in result.plane_stats if s.n_points > 0 and math.isfinite(s.rms_mm) and s.rms_mm > 0]
    out = []
    off = [s for s in stats if abs(s.mean_mm) > _MEAN_SHARE_OF_RMS * s.rms_mm]
    if off:
        out.append("the residuals show structure: mean residual on plate(s) " + ", ".join(
            f"{s.name} {s.mean_mm:+.3f} mm (RMS {s.rms_mm:.3f})" for s in off[:4]) + (", ..." if len(off) > 4 else ""))
    if result.residual_sigma_m is not None:
        u = result.residuals_m / result.residual_sigma_m
        u = u[np.isfinite(u)]
        spread = 1.4826 * float(np.median(np.abs(u))) if len(u) else 0.0
        rms = float(np.sqrt(np.mean(u**2))) if len(u) else 0.0
        if spread > 0 and rms > _RMS_OVER_ROBUST_SPREAD * spread:
            out.append(f"the residuals have long tails (RMS {rms:.2f} sigma, robust spread {spread:.2f} sigma: points "
                       "of other surfaces on the plates, or plates off)")
    if len(stats) > 1:
        worst = max(stats, key=lambda s: s.normalized_rms)
        best = min(stats, key=lambda s: s.normalized_rms)
        if worst.normalized_rms > _NORMALISED_RMS_RATIO * best.normalized_rms:
            out.append(f"the plates fit unequally: RMS/sigma {worst.normalized_rms:.2f} on {worst.name}, "
                       f"{best.normalized_rms:.2f} on {best.name}")
    return out


def moved_sigmas(robust: RobustCalibration) -> dict[str, float]:
    """How far each parameter moved from the starting values, in its sigmas."""
    res = robust.result
    moved = np.abs(res.calibration.as_vector() - robust.approximate.as_vector()) / res.sigmas
    return dict(zip(PARAMETER_NAMES, moved.tolist(), strict=True))
