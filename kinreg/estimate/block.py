"""Sparse block adjustment of the station network (METHOD.md section 2, step 7).

Unknowns: the poses ``T_obj_k`` of all stations, each as a right perturbation
``T_k = T_k^0 . exp(x_k)`` of its current value (``x_k = (rho, phi)``, rho in the station
frame). Observations: relative poses between stations with 6x6 (possibly rank-deficient)
information matrices (:class:`~kinreg.types.RelativeObservation`): the plane-only information
of every pairwise link, the trajectory's own relative pose between consecutive stations (once),
and direct observations of station poses. Gauss-Newton on SE(3) with a sparse normal matrix
(CHOLMOD where available). Fixed stations define the datum.

After convergence: the a-posteriori standard deviation of unit weight and the global test,
per-observation test statistics and redundancy numbers from the 6x6 blocks of the inverse
(selected inversion: the inverse is never formed densely), data snooping of the links and station
observations (the worst observation above the critical value is removed and the network
re-adjusted; the trajectory's links are tested but never removed), and optionally a variance
component per observation kind so that reported standard deviations follow the residuals.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import scipy.sparse as sp
from scipy import stats

from kinreg.config import BlockConfig
from kinreg.errors import EstimationError
from kinreg.estimate.sparse import factorize, selected_inverse
from kinreg.geometry import FloatArray, Pose, skew
from kinreg.progress import NullProgress, Progress
from kinreg.types import BlockResult, ObservationKind, ObservationTest, RelativeObservation

log = logging.getLogger(__name__)


def adjoint(T: Pose) -> FloatArray:
    """SE(3) adjoints ``(..., 6, 6)`` for twists ordered (rho, phi): ``[[R, [t]x R], [0, R]]``."""
    R = T.rotation_matrix
    A = np.zeros((*T.shape, 6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., :3, 3:] = skew(T.t_xyz) @ R
    return A


def _residuals(poses: Pose, obs_i: np.ndarray, obs_j: np.ndarray, Z: Pose, station: np.ndarray) -> FloatArray:
    """e = log(Z^-1 T_i^-1 T_j) for relative observations, log(Z^-1 T_i) for station ones."""
    T_i = poses[obs_i]
    rel = T_i.inverse().compose(poses[np.where(station, obs_i, obs_j)])
    rel = Pose(np.where(station[:, None], T_i.quat_wxyz, rel.quat_wxyz),
               np.where(station[:, None], T_i.t_xyz, rel.t_xyz))
    return Z.inverse().compose(rel).log()


def _jacobians(poses: Pose, obs_i: np.ndarray, obs_j: np.ndarray, station: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """de/dx_i and de/dx_j (k, 6, 6), to first order in the residual."""
    rel = poses[obs_i].inverse().compose(poses[np.where(station, obs_i, obs_j)])
    J_i = -adjoint(rel.inverse())
    J_j = np.broadcast_to(np.eye(6), J_i.shape).copy()
    J_i[station] = np.eye(6)
    J_j[station] = 0.0
    return J_i, J_j


def _assemble(n_free: int, col_i: np.ndarray, col_j: np.ndarray, J_i: FloatArray, J_j: FloatArray,
              P: FloatArray, e: FloatArray) -> tuple[sp.csc_matrix, FloatArray]:
    """Normal matrix (6 n_free square, sparse) and right-hand side from per-observation blocks.

    ``col_i``/``col_j`` are the unknown-block indices of the observation's stations (-1: fixed
    or absent). Vectorised COO assembly; duplicates are summed by the sparse constructor.
    """
    JiT_P = np.transpose(J_i, (0, 2, 1)) @ P
    JjT_P = np.transpose(J_j, (0, 2, 1)) @ P
    blocks_ii = JiT_P @ J_i
    blocks_jj = JjT_P @ J_j
    blocks_ij = JiT_P @ J_j
    g_i = (JiT_P @ e[:, :, None])[:, :, 0]
    g_j = (JjT_P @ e[:, :, None])[:, :, 0]
    rows, cols, vals = [], [], []
    r6 = np.arange(6)

    def put(bi: np.ndarray, bj: np.ndarray, blocks: FloatArray) -> None:
        ok = (bi >= 0) & (bj >= 0)
        if not ok.any():
            return
        bi, bj, blocks = bi[ok], bj[ok], blocks[ok]
        rows.append((6 * bi[:, None, None] + r6[None, :, None]).repeat(6, axis=2).ravel())
        cols.append((6 * bj[:, None, None] + r6[None, None, :]).repeat(6, axis=1).ravel())
        vals.append(blocks.ravel())

    put(col_i, col_i, blocks_ii)
    put(col_j, col_j, blocks_jj)
    put(col_i, col_j, blocks_ij)
    put(col_j, col_i, np.transpose(blocks_ij, (0, 2, 1)))
    size = 6 * n_free
    N = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))
    b = np.zeros(size)
    for bi, g in ((col_i, g_i), (col_j, g_j)):
        ok = bi >= 0
        np.add.at(b, (6 * bi[ok, None] + r6[None, :]).ravel(), -g[ok].ravel())
    return N, b


def _components(observations: list[RelativeObservation]) -> np.ndarray:
    """Connected components of the station graph (label per station)."""
    from scipy.sparse.csgraph import connected_components

    n = 1 + max(max(o.i, o.j) for o in observations)
    pairs = np.array([(o.i, o.j) for o in observations if o.j >= 0 and o.rank > 0], dtype=int).reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def adjust_block(
    poses_initial: Pose,
    observations: list[RelativeObservation],
    fixed: np.ndarray,
    config: BlockConfig,
    progress: Progress | None = None,
) -> BlockResult:
    """Adjust the network.

    ``poses_initial`` (n,) are the approximate station poses ``T_obj_scan``; ``fixed`` (n,) bool
    marks the datum stations (held at their initial poses). Raises :class:`EstimationError` when
    the datum leaves parts of the network undetermined (a disconnected part without a fixed or
    directly observed station) or the normal matrix is singular.
    """
    progress = progress or NullProgress()
    n = len(poses_initial)
    fixed = np.asarray(fixed, dtype=bool)
    if not fixed.any() and not any(o.kind is ObservationKind.STATION for o in observations):
        raise EstimationError("no datum: fix at least one station or observe station poses directly")
    _check_datum(observations, fixed, n)

    active = np.ones(len(observations), dtype=bool)
    kinds = np.array([o.kind.value for o in observations])
    weights = {k.value: 1.0 for k in ObservationKind}
    rejected_order: list[int] = []
    last_round: list[int] = []  # rejected in the previous round
    protected: set[int] = set()  # taken back after a rejection left the network undetermined
    variance_before = np.zeros(0)
    vce_rounds = 0
    # Reduced to a local origin (the first station): at survey coordinates (UTM, 5e6 m) a pose's
    # last bits are 1e-9 m, and the updates would never fall below the convergence threshold.
    origin = poses_initial.t_xyz[0].copy()
    observations = [_moved(o, -origin) for o in observations]
    start = _moved_poses(poses_initial, -origin)
    progress.start("block adjustment", total=None, unit="iterations")
    while True:
        try:
            if last_round:
                _check_datum([o for o, a in zip(observations, active, strict=True) if a], fixed, n)
            poses, iterations, factor, N, free_index, converged = _levenberg_marquardt(
                start, observations, active, fixed, weights, config, progress)
            tests, omega, redundancy, Qxx_blocks = _test_observations(poses, observations, active, fixed,
                                                                      free_index, weights, factor, N, config)
        except EstimationError:
            if not last_round:
                raise
            back = last_round  # singular or apart without the last round's rejections: all back
        else:
            variance = np.trace(Qxx_blocks[:, :3, :3], axis1=1, axis2=2)
            back = _taken_back(last_round, observations, free_index, variance, variance_before)
        if back:
            log.info("block: observations %s taken back (without them the network is undetermined)", back)
            for k in back:
                active[k] = True
                rejected_order.remove(k)
            protected.update(back)
            last_round = []
            continue
        last_round = []
        if config.variance_components and vce_rounds < config.max_variance_rounds:
            new_weights = _variance_components(tests, weights)
            changed = any(abs(new_weights[k] / weights[k] - 1.0) > 0.02 for k in weights)
            weights = new_weights
            vce_rounds += 1
            if changed:
                start = poses
                continue
        budget = config.max_rejections - len(rejected_order)
        # The trajectory's own links are not snooped: its gross errors (jumps) are found in the
        # trajectory itself (kinreg.estimate.jumps), and a link that does not fit says that the
        # drift model is off, which the variance components answer. Rejecting it would leave the
        # direction it carries to the planes, which may not fix it (a corridor): the walks of the
        # accuracy matrix lost alternate links there and drifted by 10-20 mm.
        candidates = [t for t in tests if t.index not in protected and t.kind is not ObservationKind.TRAJECTORY]
        worst = _worst_outliers(candidates, config.alpha, budget) if config.data_snooping and budget > 0 else []
        if worst:
            for t in worst:
                log.info("block: rejecting observation %d (%s %d-%d, statistic %.1f)", t.index, t.kind.value,
                         t.i, t.j, t.statistic)
                active[t.index] = False
                rejected_order.append(t.index)
                last_round.append(t.index)
            variance_before = variance
            start = poses  # warm start: the next round begins at the current solution
            continue
        break
    progress.finish()
    poses = _moved_poses(poses, origin)

    sigma0 = float(np.sqrt(omega / redundancy)) if redundancy > 0 else float("nan")
    failure = _failure(converged, iterations, poses, omega, redundancy, Qxx_blocks)
    passed = not failure and bool(redundancy <= 0 or omega <= stats.chi2.ppf(1.0 - config.alpha, redundancy))
    factor_scale = sigma0**2 if (not passed and np.isfinite(sigma0)) else 1.0
    cov_xi = np.zeros((n, 6, 6))
    cov_xi[~fixed] = Qxx_blocks * factor_scale
    R = poses.rotation_matrix
    cov_position = R @ cov_xi[:, :3, :3] @ np.transpose(R, (0, 2, 1))
    all_tests = list(tests) + [
        ObservationTest(k, observations[k].kind, observations[k].i, observations[k].j, float("nan"),
                        observations[k].rank, 0.0, float("nan"), True)
        for k in rejected_order
    ]
    all_tests.sort(key=lambda t: t.index)
    return BlockResult(
        poses=poses,
        poses_initial=poses_initial,
        fixed=fixed,
        cov_xi=cov_xi,
        cov_position=cov_position,
        sigma0=sigma0,
        redundancy=float(redundancy),
        global_test_passed=passed,
        variance_factor=factor_scale,
        iterations=iterations,
        tests=tuple(all_tests),
        variance_components={k: 1.0 / w for k, w in weights.items() if (kinds == k).any()},
        failure=failure,
    )


def _failure(converged: bool, iterations: int, poses: Pose, omega: float, redundancy: float,
             cov_blocks: FloatArray) -> str:
    """Why the adjustment is not a result, in words; empty when it is one."""
    if not converged:
        return f"no convergence after {iterations} iterations"
    if not (np.all(np.isfinite(poses.t_xyz)) and np.all(np.isfinite(poses.quat_wxyz))):
        return "non-finite station poses"
    if not np.isfinite(omega) or not np.all(np.isfinite(cov_blocks)):
        return "non-finite residuals or covariances"
    if redundancy < -1e-6:
        return f"negative redundancy ({redundancy:.1f})"
    return ""


def _moved_poses(poses: Pose, shift: FloatArray) -> Pose:
    return Pose(poses.quat_wxyz, poses.t_xyz + shift)


def _moved(observation: RelativeObservation, shift: FloatArray) -> RelativeObservation:
    """A station observation (an absolute pose) with the origin moved by ``shift``; relative
    observations do not depend on the origin."""
    if observation.kind is not ObservationKind.STATION:
        return observation
    return dataclasses.replace(observation, Z=_moved_poses(observation.Z, shift))


def loose_parts(observations: list[RelativeObservation], fixed: np.ndarray, n: int) -> list[np.ndarray]:
    """Connected parts of the station graph with neither a fixed station nor a direct observation
    of a station (each part as its sorted station indices)."""
    labels = _components(observations + [RelativeObservation(ObservationKind.PLANES, n - 1, n - 1,
                                                               Pose.identity(), np.zeros((6, 6)), 0)])
    anchored = set(labels[np.flatnonzero(fixed)])
    anchored |= {labels[o.i] for o in observations if o.kind is ObservationKind.STATION}
    return [np.flatnonzero(labels == c) for c in sorted(set(labels) - anchored)]


def _check_datum(observations: list[RelativeObservation], fixed: np.ndarray, n: int) -> None:
    parts = loose_parts(observations, fixed, n)
    if parts:
        described = ", ".join(f"stations {p[0]}-{p[-1]}" if len(p) > 1 else f"station {p[0]}" for p in parts[:5])
        raise EstimationError(
            f"the network has {len(parts)} part(s) without datum ({described}); they are not linked to the "
            "fixed stations"
        )


def _arrays(observations: list[RelativeObservation], active: np.ndarray):
    idx = np.flatnonzero(active)
    obs = [observations[k] for k in idx]
    obs_i = np.array([o.i for o in obs])
    obs_j = np.array([max(o.j, 0) for o in obs])
    station = np.array([o.kind is ObservationKind.STATION for o in obs])
    Z = Pose.stack([o.Z for o in obs])
    P = np.stack([o.info for o in obs])
    kinds = np.array([o.kind.value for o in obs])
    return idx, obs_i, obs_j, station, Z, P, kinds


def _cost(poses: Pose, obs_i: np.ndarray, obs_j: np.ndarray, Z: Pose, station: np.ndarray, P: FloatArray) -> float:
    """The weighted sum of squared residuals ``sum e^T P e``."""
    e = _residuals(poses, obs_i, obs_j, Z, station)
    return float(np.einsum("ki,kij,kj->", e, P, e))


# Marquardt's damping: the first try of every iteration is the undamped Gauss-Newton step; a step
# that raises the cost is tried again with the normal matrix's diagonal raised by lambda times
# itself, lambda growing tenfold, up to _MAX_DAMPING (then no descent is left: a minimum).
_FIRST_DAMPING = 1e-4
_MAX_DAMPING = 1e8


def _levenberg_marquardt(poses_initial, observations, active, fixed, weights, config, progress):
    """Damped Gauss-Newton (Levenberg-Marquardt) on SE(3). Converged when no unknown changes by
    more than ``config.convergence`` or the cost falls by less than ``config.cost_tolerance`` of
    itself; returns the poses, the iterations, the factor and normal matrix of the undamped
    problem at the solution (for the covariances), the free-unknown index and whether it converged."""
    _, obs_i, obs_j, station, Z, P, kinds = _arrays(observations, active)
    P = P * np.array([weights[k] for k in kinds])[:, None, None]
    free_index = -np.ones(len(poses_initial), dtype=int)
    free_index[~fixed] = np.arange(np.count_nonzero(~fixed))
    n_free = int(np.count_nonzero(~fixed))
    col_i = free_index[obs_i]
    col_j = np.where(station, -1, free_index[obs_j])
    poses = poses_initial
    cost = _cost(poses, obs_i, obs_j, Z, station, P)
    factor = N = None
    converged = damped = False
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):  # noqa: B007  (the count is returned)
        e = _residuals(poses, obs_i, obs_j, Z, station)
        J_i, J_j = _jacobians(poses, obs_i, obs_j, station)
        N, b = _assemble(n_free, col_i, col_j, J_i, J_j, P, e)
        lam = 0.0
        while True:
            damped = lam > 0.0
            factor = factorize(N + lam * sp.diags(N.diagonal()) if damped else N)
            dx = factor.solve(b).reshape(-1, 6)
            step = np.zeros((len(poses), 6))
            step[~fixed] = dx
            trial = poses.compose(Pose.exp(step))
            trial_cost = _cost(trial, obs_i, obs_j, Z, station, P)
            if np.isfinite(trial_cost) and trial_cost <= cost * (1.0 + 1e-12):
                break
            lam = _FIRST_DAMPING if lam == 0.0 else 10.0 * lam
            if lam > _MAX_DAMPING:
                break
        progress.advance(1)
        if lam > _MAX_DAMPING:  # no step lowers the cost: at a minimum if the gradient vanishes there
            converged = bool(np.max(np.abs(dx)) < max(config.convergence, 1e-6))
            break
        poses, fell = trial, cost - trial_cost
        cost = trial_cost
        if np.max(np.abs(dx)) < config.convergence or fell <= config.cost_tolerance * cost:
            converged = True
            break
    if not converged:
        log.info("block adjustment: no convergence after %d iterations", iterations)
    if damped:  # the covariances need the undamped normal matrix at the solution
        e = _residuals(poses, obs_i, obs_j, Z, station)
        J_i, J_j = _jacobians(poses, obs_i, obs_j, station)
        N, _ = _assemble(n_free, col_i, col_j, J_i, J_j, P, e)
        factor = factorize(N)
    return poses, iterations, factor, N, free_index, converged


def _test_observations(poses, observations, active, fixed, free_index, weights, factor, N, config):
    """Per-observation statistics from the cofactor of the residuals, Q_ee = P^+ - J Qxx J^T,
    vectorised over observations (each restricted to the directions its information determines)."""
    idx, obs_i, obs_j, station, Z, P, kinds = _arrays(observations, active)
    P = P * np.array([weights[k] for k in kinds])[:, None, None]
    e = _residuals(poses, obs_i, obs_j, Z, station)
    J_i, J_j = _jacobians(poses, obs_i, obs_j, station)
    col_i = free_index[obs_i]
    col_j = np.where(station, -1, free_index[obs_j])
    both = (col_i >= 0) & (col_j >= 0)
    pairs = np.column_stack([col_i[both], col_j[both]]).astype(int).reshape(-1, 2)
    diag, off = selected_inverse(N, 6, pairs, factor=factor)

    JQJ = np.zeros((len(idx), 6, 6))
    for cols, J in ((col_i, J_i), (col_j, J_j)):
        ok = cols >= 0
        JQJ[ok] += J[ok] @ diag[cols[ok]] @ np.transpose(J[ok], (0, 2, 1))
    cross = J_i[both] @ off @ np.transpose(J_j[both], (0, 2, 1))
    JQJ[both] += cross + np.transpose(cross, (0, 2, 1))

    w, V = np.linalg.eigh(0.5 * (P + np.transpose(P, (0, 2, 1))))
    determined = w > 1e-9 * np.maximum(w[:, -1:], 1e-300)
    w = np.where(determined, w, 1.0)
    z = np.where(determined, np.einsum("kai,ka->ki", V, e), 0.0)
    VJV = np.transpose(V, (0, 2, 1)) @ JQJ @ V
    mask2 = determined[:, :, None] & determined[:, None, :]
    Q_zz = np.where(mask2, np.eye(6) / w[:, :, None] - VJV, np.eye(6) * (~mask2))
    dof = determined.sum(axis=1)
    r_k = np.sum(np.where(determined, 1.0 - w * np.diagonal(VJV, axis1=1, axis2=2), 0.0), axis=1)
    # Redundancy per direction: eigenvalues of I - W^1/2 V^T J Qxx J^T V W^1/2 (determined part).
    sw = np.where(determined, np.sqrt(w), 0.0)
    R_dir = np.eye(6) * determined[:, :, None] - sw[:, :, None] * VJV * sw[:, None, :]
    r_dir = np.linalg.eigvalsh(R_dir + np.eye(6) * (~determined)[:, :, None])  # undetermined: 1, never least
    vtpv = np.sum(np.where(determined, w * z**2, 0.0), axis=1)
    statistic = np.einsum("ki,kij,kj->k", z, np.linalg.pinv(Q_zz, rcond=1e-9, hermitian=True), z)
    # An uncontrolled observation (redundancy ~ 0) cannot be tested.
    statistic = np.where(r_k > 1e-6, statistic, np.nan)
    keep = dof > 0
    tests = [
        ObservationTest(int(idx[k]), ObservationKind(kinds[k]), int(obs_i[k]), int(observations[idx[k]].j),
                        float(statistic[k]), int(dof[k]), float(r_k[k]), float(np.sqrt(statistic[k] / dof[k])),
                        False, float(vtpv[k]), min_redundancy=float(r_dir[k, 0]), cov_adjusted=JQJ[k])
        for k in np.flatnonzero(keep)
    ]
    return tests, float(vtpv[keep].sum()), float(r_k[keep].sum()), diag


def _taken_back(last_round: list[int], observations: list[RelativeObservation], free_index: np.ndarray,
                variance: np.ndarray, variance_before: np.ndarray) -> list[int]:
    """The last round's rejections to take back: together they left some direction of some
    stations resting on nothing (none alone was its only support), seen as a position variance
    grown by ``_MAX_VARIANCE_GROWTH``. Those touching such a station come back (all of the round
    if none does); the others may be rejected again in the next round."""
    if not last_round:
        return []
    grown = np.flatnonzero(variance > _MAX_VARIANCE_GROWTH * variance_before)
    if not len(grown):
        return []
    stations = set(np.flatnonzero(np.isin(free_index, grown)).tolist())
    return [k for k in last_round if {observations[k].i, observations[k].j} & stations] or last_round


_MIN_DIRECTION_REDUNDANCY = 0.02
# A rejection round after which some station's position variance grows by this factor is undone.
_MAX_VARIANCE_GROWTH = 100.0


def _worst_outliers(tests: list[ObservationTest], alpha: float, budget: int) -> list[ObservationTest]:
    """Observations to reject in one round: those above the critical value that are the worst
    among all such observations touching either of their stations (one per neighbourhood, so
    that an outlier's effect on its neighbours does not reject them too). An observation that
    alone determines some direction (its redundancy there below ``_MIN_DIRECTION_REDUNDANCY``) is
    never rejected: without it the network would be undetermined in that direction (a stretch
    whose planes leave it free, carried by the trajectory alone)."""
    critical = {dof: stats.chi2.ppf(1.0 - alpha, dof) for dof in {t.dof for t in tests}}
    bad = [t for t in tests if np.isfinite(t.statistic) and t.redundancy > 0.05 and t.statistic > critical[t.dof]
           and not t.min_redundancy < _MIN_DIRECTION_REDUNDANCY]
    bad.sort(key=lambda t: t.statistic / critical[t.dof], reverse=True)
    taken: set[int] = set()
    chosen = []
    for t in bad:
        if t.i in taken or (t.j >= 0 and t.j in taken):
            continue
        chosen.append(t)
        taken.update((t.i, t.j))
        if len(chosen) >= budget:
            break
    return chosen


def _variance_components(tests: list[ObservationTest], weights: dict[str, float]) -> dict[str, float]:
    """Förstner's estimate per observation kind: sigma_g^2 = (e^T P e)_g / r_g with the current
    weights; the new weight is the current one divided by sigma_g^2, never above the a-priori
    weight. Kinds with too little redundancy (< 5) keep their weight: their component cannot be
    estimated."""
    new = dict(weights)
    for kind in weights:
        group = [t for t in tests if t.kind.value == kind and not t.rejected]
        r = sum(t.redundancy for t in group)
        if r < 5:
            continue
        omega = sum(t.vtpv for t in group)
        # Only ever inflate the a-priori model: errors shared by all links of a scan (plane-fit
        # systematics) and the trajectory's drift (smooth in time) are invisible in residuals,
        # so a factor below 1 would make the reported sigmas too optimistic.
        new[kind] = min(1.0, weights[kind] / max(omega / r, 1e-6))
    return new

