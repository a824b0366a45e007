"""Sparse block adjustment of the station network (METHOD.md section 2, step 7).

Unknowns: the poses ``T_obj_k`` of all stations, each as a right perturbation
``T_k = T_k^0 . exp(x_k)`` of its current value (``x_k = (rho, phi)``, rho in the station
frame), and, where the trajectory's drift is modelled as a process, the drift velocity of each
trajectory link (6 values, object axes). Observations (:class:`~kinreg.types.RelativeObservation`,
each on up to three of these nodes, with 6x6 possibly rank-deficient information matrices): the
plane-only information of every pairwise link, the trajectory's own relative pose between
consecutive stations (once; less its drift velocity times its duration), the drift velocity's
change from one link to the next, direct observations of station poses, and surveyed points on
the pose interpolated between two stations (control points). Damped Gauss-Newton
on SE(3) with a sparse normal matrix (CHOLMOD where available). Fixed stations define the datum.

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
from kinreg.estimate.snooping import taken_back, variance_components, worst_outliers
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


@dataclasses.dataclass(frozen=True)
class _Active:
    """The active observations as arrays. Unknowns are numbered as nodes: the stations 0..n-1
    (poses on SE(3)), then the drift velocities n..n+m-1 (6-vectors, one per trajectory link
    that has one). ``nodes`` (k, 3): per observation its nodes in slot order (-1: none): pose
    observations (first station, second station, drift velocity), drift observations (velocity
    of the first link, of the second), point observations (first station, second station)."""

    idx: np.ndarray
    kinds: np.ndarray
    nodes: np.ndarray
    pose: np.ndarray  # PLANES, TRAJECTORY, STATION
    station: np.ndarray  # STATION
    point: np.ndarray  # POINT
    levers: FloatArray  # (k, 2, 3) POINT: the point in its stations' frames
    share: FloatArray  # (k,) POINT: the second station's weight (0 without one)
    Z: Pose
    P: FloatArray
    dt: np.ndarray
    decay: np.ndarray  # (k, 6)
    coupling: np.ndarray  # (k,)
    step: np.ndarray  # (k, 3): the coupled trajectory links' object-frame steps


def velocity_nodes(observations: list[RelativeObservation], n: int) -> np.ndarray:
    """Per station: the node of the drift velocity of the trajectory link starting there (-1:
    none). A link has one where ``DRIFT`` observations name it (:class:`RelativeObservation`)."""
    keys = sorted({o.i for o in observations if o.kind is ObservationKind.DRIFT}
                  | {o.j for o in observations if o.kind is ObservationKind.DRIFT and o.j >= 0})
    node = -np.ones(n, dtype=int)
    node[np.array(keys, dtype=int)] = n + np.arange(len(keys))
    return node


def _arrays(observations: list[RelativeObservation], active: np.ndarray, vnode: np.ndarray,
            weights: dict[str, float]) -> _Active:
    idx = np.flatnonzero(active)
    obs = [observations[k] for k in idx]
    kinds = np.array([o.kind.value for o in obs])
    drift = kinds == ObservationKind.DRIFT.value
    station = kinds == ObservationKind.STATION.value
    point = kinds == ObservationKind.POINT.value
    i = np.array([o.i for o in obs], dtype=int)
    j = np.array([o.j for o in obs], dtype=int)
    nodes = -np.ones((len(obs), 3), dtype=int)
    nodes[point, 0] = i[point]
    nodes[point, 1] = j[point]
    pose = ~drift & ~point
    nodes[pose, 0] = i[pose]
    nodes[pose & ~station, 1] = j[pose & ~station]
    trajectory = kinds == ObservationKind.TRAJECTORY.value
    nodes[trajectory, 2] = vnode[i[trajectory]]
    nodes[drift, 0] = vnode[i[drift]]
    nodes[drift, 1] = np.where(j[drift] >= 0, vnode[np.maximum(j[drift], 0)], -1)
    P = np.stack([o.info for o in obs]) * np.array([weights[k] for k in kinds])[:, None, None]
    levers = np.array([np.zeros((2, 3)) if o.levers_m is None else o.levers_m for o in obs]).reshape(-1, 2, 3)
    share = np.array([o.share if o.j >= 0 else 0.0 for o in obs]).reshape(-1)
    return _Active(idx, kinds, nodes, pose, station, point, levers, share, Pose.stack([o.Z for o in obs]), P,
                   np.array([o.dt_s for o in obs]),
                   np.array([np.broadcast_to(o.decay, (6,)) for o in obs]).reshape(-1, 6),
                   np.array([o.coupling for o in obs]),
                   np.array([np.zeros(3) if o.step_obj is None else o.step_obj for o in obs]).reshape(-1, 3))


def _to_station_axes(R: FloatArray) -> FloatArray:
    """``S`` (k, 6, 6): a twist in object axes into the axes of the stations with rotations R."""
    S = np.zeros((len(R), 6, 6))
    S[:, :3, :3] = np.transpose(R, (0, 2, 1))
    S[:, 3:, 3:] = S[:, :3, :3]
    return S


def _linearise(poses: Pose, velocity: FloatArray, a: _Active,
               jacobians: bool = True) -> tuple[FloatArray, FloatArray]:
    """Residuals ``e`` (k, 6) and, with ``jacobians``, de/dx per slot (k, 3, 6, 6; else empty) to first order
    in the residual. Pose observations: ``e = log(Z^-1 T_i^-1 T_j) - dt S_j v`` (``log(Z^-1 T_i)``
    for a station's pose); drift observations ``e = v_j - decay v_i`` (``v_i``); point observations
    ``e = ((1 - s) T_i l_0 + s T_j l_1 - Z.t, 0)`` (object axes)."""
    k = len(a.idx)
    e = np.zeros((k, 6))
    J = np.zeros((k if jacobians else 0, 3, 6, 6))  # empty without jacobians
    p = np.flatnonzero(a.pose)
    if len(p):
        st = a.station[p]
        i = a.nodes[p, 0]
        j = np.where(st, i, a.nodes[p, 1])
        T_i = poses[i]
        rel = T_i.inverse().compose(poses[j])
        rel = Pose(np.where(st[:, None], T_i.quat_wxyz, rel.quat_wxyz), np.where(st[:, None], T_i.t_xyz, rel.t_xyz))
        Z = a.Z[p]
        kappa = a.coupling[p]
        coupled = np.flatnonzero(kappa > 0.0)
        if len(coupled):  # the translation turned by the adjusted attitude of station i
            turned = np.einsum("kji,kj->ki", T_i.rotation_matrix[coupled], a.step[p[coupled]])
            t = Z.t_xyz.copy()
            t[coupled] = (1.0 - kappa[coupled, None]) * t[coupled] + kappa[coupled, None] * turned
            Z = Pose(Z.quat_wxyz, t)
        e[p] = Z.inverse().compose(rel).log()
        v = a.nodes[p, 2]
        has_v = np.flatnonzero(v >= 0)
        S = None
        if len(has_v):
            S = -a.dt[p[has_v], None, None] * _to_station_axes(poses[j[has_v]].rotation_matrix)
            e[p[has_v]] += (S @ velocity[v[has_v] - len(poses)][:, :, None])[:, :, 0]
        if jacobians:
            J_i = -adjoint(rel.inverse())
            J_i[st] = np.eye(6)
            J_j = np.broadcast_to(np.eye(6), J_i.shape).copy()
            J_j[st] = 0.0
            if len(coupled):  # d(R_i^T s)/d(phi_i) = [R_i^T s]x for a right perturbation
                R_Zt = np.transpose(Z.rotation_matrix[coupled], (0, 2, 1))
                J_i[coupled, :3, 3:] -= kappa[coupled, None, None] * R_Zt @ skew(turned)
            J[p, 0], J[p, 1] = J_i, J_j
            if S is not None:
                J[p[has_v], 2] = S  # S_j's own dependence on T_j is of the order dt |v| and left out
    q = np.flatnonzero(a.point)
    if len(q):
        _point_residuals(poses, a, q, e, J if jacobians else None)
    d = np.flatnonzero(~a.pose & ~a.point)
    if len(d):
        n = len(poses)
        first, second = a.nodes[d, 0] - n, a.nodes[d, 1] - n
        pair = a.nodes[d, 1] >= 0
        decay = np.where(pair[:, None], a.decay[d], -1.0)  # a prior (no second link): e = v_i
        e[d] = np.where(pair[:, None], velocity[np.where(pair, second, 0)], 0.0) - decay * velocity[first]
        if jacobians:
            J[d, 0] = -decay[:, :, None] * np.eye(6)
            J[d[pair], 1] = np.eye(6)
    return e, J


def _point_residuals(poses: Pose, a: _Active, q: np.ndarray, e: FloatArray, J: FloatArray | None) -> None:
    """Point observations ``q``: their residuals into ``e`` and (with ``J``) their Jacobians, for a
    right perturbation ``(rho, phi)`` of each station: ``d(T l) = R (rho - [l]x phi)``."""
    s = a.share[q]
    predicted = np.zeros((len(q), 3))
    for slot, weight in ((0, 1.0 - s), (1, s)):
        node = a.nodes[q, slot]
        has = np.flatnonzero(node >= 0)
        if not len(has):
            continue
        T = poses[node[has]]
        lever = a.levers[q[has], slot]
        predicted[has] += weight[has, None] * T.apply(lever)
        if J is not None:
            R = T.rotation_matrix
            J[q[has], slot, :3, :3] = weight[has, None, None] * R
            J[q[has], slot, :3, 3:] = -weight[has, None, None] * R @ skew(lever)
    e[q, :3] = predicted - a.Z[q].t_xyz


def _cost(poses: Pose, velocity: FloatArray, a: _Active) -> float:
    """The weighted sum of squared residuals ``sum e^T P e``."""
    e, _ = _linearise(poses, velocity, a, jacobians=False)
    return float(np.einsum("ki,kij,kj->", e, a.P, e))


def _assemble(n_free: int, cols: np.ndarray, J: FloatArray, P: FloatArray,
              e: FloatArray) -> tuple[sp.csc_matrix, FloatArray]:
    """Normal matrix (6 n_free square, sparse) and right-hand side from per-observation blocks.

    ``cols`` (k, slots) are the unknown-block indices of each observation's nodes (-1: fixed or
    absent), ``J`` (k, slots, 6, 6) its Jacobians. Vectorised COO assembly; duplicates are summed
    by the sparse constructor."""
    JT_P = np.transpose(J, (0, 1, 3, 2)) @ P[:, None]
    rows, columns, vals = [], [], []
    r6 = np.arange(6)
    size = 6 * n_free
    b = np.zeros(size)
    slots = cols.shape[1]
    for s in range(slots):
        for t in range(slots):
            ok = (cols[:, s] >= 0) & (cols[:, t] >= 0)
            if not ok.any():
                continue
            bi, bj = cols[ok, s], cols[ok, t]
            rows.append((6 * bi[:, None, None] + r6[None, :, None]).repeat(6, axis=2).ravel())
            columns.append((6 * bj[:, None, None] + r6[None, None, :]).repeat(6, axis=1).ravel())
            vals.append((JT_P[ok, s] @ J[ok, t]).ravel())
        ok = cols[:, s] >= 0
        g = (JT_P[ok, s] @ e[ok][:, :, None])[:, :, 0]
        np.add.at(b, (6 * cols[ok, s, None] + r6[None, :]).ravel(), -g.ravel())
    N = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(columns))), shape=(size, size))
    return N, b


def _components(observations: list[RelativeObservation]) -> np.ndarray:
    """Connected components of the station graph (label per station)."""
    from scipy.sparse.csgraph import connected_components

    n = 1 + max(max(o.i, o.j) for o in observations)
    pairs = np.array([(o.i, o.j) for o in observations
                      if o.j >= 0 and o.rank > 0 and o.kind is not ObservationKind.DRIFT], dtype=int).reshape(-1, 2)
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
    if not fixed.any() and not any(o.kind in (ObservationKind.STATION, ObservationKind.POINT) for o in observations):
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
    vnode = velocity_nodes(observations, n)
    start = (_moved_poses(poses_initial, -origin), np.zeros((int(np.count_nonzero(vnode >= 0)), 6)))
    progress.start("block adjustment", total=None, unit="iterations")
    while True:
        try:
            if last_round:
                _check_datum([o for o, a in zip(observations, active, strict=True) if a], fixed, n)
            state, iterations, factor, N, free_index, converged = _levenberg_marquardt(
                start, observations, active, fixed, vnode, weights, config, progress)
            tests, omega, redundancy, Qxx_blocks = _test_observations(state, observations, active, fixed, vnode,
                                                                      free_index, weights, factor, N, config)
        except EstimationError:
            if not last_round:
                raise
            back = last_round  # singular or apart without the last round's rejections: all back
        else:
            variance = np.trace(Qxx_blocks[:, :3, :3], axis1=1, axis2=2)
            back = taken_back(last_round, observations, free_index[:n], variance, variance_before)
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
            new_weights = variance_components(tests, weights, config.alpha)
            changed = any(abs(new_weights[k] / weights[k] - 1.0) > 0.02 for k in weights)
            weights = new_weights
            vce_rounds += 1
            if changed:
                start = state
                continue
        budget = config.max_rejections - len(rejected_order)
        # The trajectory's own links are not snooped: its gross errors (jumps) are found in the
        # trajectory itself (kinreg.estimate.jumps), and a link that does not fit says that the
        # drift model is off, which the variance components answer. Rejecting it would leave the
        # direction it carries to the planes, which may not fix it (a corridor): the walks of the
        # accuracy matrix lost alternate links there and drifted by 10-20 mm.
        candidates = [t for t in tests if t.index not in protected
                      and t.kind not in (ObservationKind.TRAJECTORY, ObservationKind.DRIFT, ObservationKind.FRAME)]
        worst = worst_outliers(candidates, config.alpha, budget) if config.data_snooping and budget > 0 else []
        if worst:
            for t in worst:
                log.info("block: rejecting observation %d (%s %d-%d, statistic %.1f)", t.index, t.kind.value,
                         t.i, t.j, t.statistic)
                active[t.index] = False
                rejected_order.append(t.index)
                last_round.append(t.index)
            variance_before = variance
            start = state  # warm start: the next round begins at the current solution
            continue
        break
    progress.finish()
    poses = _moved_poses(state[0], origin)

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
    if observation.kind not in (ObservationKind.STATION, ObservationKind.POINT):
        return observation
    return dataclasses.replace(observation, Z=_moved_poses(observation.Z, shift))


def loose_parts(observations: list[RelativeObservation], fixed: np.ndarray, n: int) -> list[np.ndarray]:
    """Connected parts of the station graph with neither a fixed station nor a direct observation
    of a station (each part as its sorted station indices)."""
    labels = _components(observations + [RelativeObservation(ObservationKind.PLANES, n - 1, n - 1,
                                                               Pose.identity(), np.zeros((6, 6)), 0)])
    anchored = set(labels[np.flatnonzero(fixed)])
    anchored |= {labels[o.i] for o in observations if o.kind in (ObservationKind.STATION, ObservationKind.POINT)}
    return [np.flatnonzero(labels == c) for c in sorted(set(labels) - anchored)]


def _check_datum(observations: list[RelativeObservation], fixed: np.ndarray, n: int) -> None:
    parts = loose_parts(observations, fixed, n)
    if parts:
        described = ", ".join(f"stations {p[0]}-{p[-1]}" if len(p) > 1 else f"station {p[0]}" for p in parts[:5])
        raise EstimationError(
            f"the network has {len(parts)} part(s) without datum ({described}); they are not linked to the "
            "fixed stations"
        )


def _free_index(fixed: np.ndarray, n_velocities: int) -> np.ndarray:
    """Per node: its unknown-block index (-1: held fixed); the velocities after the stations."""
    n_free = int(np.count_nonzero(~fixed))
    free_index = -np.ones(len(fixed) + n_velocities, dtype=int)
    free_index[np.flatnonzero(~fixed)] = np.arange(n_free)
    free_index[len(fixed):] = n_free + np.arange(n_velocities)
    return free_index


def _columns(a: _Active, free_index: np.ndarray) -> np.ndarray:
    return np.where(a.nodes >= 0, free_index[np.maximum(a.nodes, 0)], -1)


def _stepped(poses: Pose, velocity: FloatArray, fixed: np.ndarray, dx: FloatArray) -> tuple[Pose, FloatArray]:
    n_free = int(np.count_nonzero(~fixed))
    step = np.zeros((len(poses), 6))
    step[~fixed] = dx[:n_free]
    return poses.compose(Pose.exp(step)), velocity + dx[n_free:]


# Marquardt's damping: the first try of every iteration is the undamped Gauss-Newton step; a step
# that raises the cost is tried again with the normal matrix's diagonal raised by lambda times
# itself, lambda growing tenfold, up to _MAX_DAMPING (then no descent is left: a minimum).
_FIRST_DAMPING = 1e-4
_MAX_DAMPING = 1e8


def _levenberg_marquardt(start, observations, active, fixed, vnode, weights, config, progress):
    """Damped Gauss-Newton (Levenberg-Marquardt) on SE(3) (the drift velocities are plain vectors).
    Converged when no unknown changes by more than ``config.convergence`` or the cost falls by less
    than ``config.cost_tolerance`` of itself; returns the state (poses, velocities), the
    iterations, the factor and normal matrix of the undamped problem at the solution (for the
    covariances), the node-to-unknown index and whether it converged."""
    poses, velocity = start
    a = _arrays(observations, active, vnode, weights)
    free_index = _free_index(fixed, len(velocity))
    n_free = int(free_index.max()) + 1
    cols = _columns(a, free_index)
    cost = _cost(poses, velocity, a)
    factor = N = None
    converged = damped = False
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):  # noqa: B007  (the count is returned)
        e, J = _linearise(poses, velocity, a)
        N, b = _assemble(n_free, cols, J, a.P, e)
        lam = 0.0
        while True:
            damped = lam > 0.0
            factor = factorize(N + lam * sp.diags(N.diagonal()) if damped else N)
            dx = factor.solve(b).reshape(-1, 6)
            trial = _stepped(poses, velocity, fixed, dx)
            trial_cost = _cost(*trial, a)
            if np.isfinite(trial_cost) and trial_cost <= cost * (1.0 + 1e-12):
                break
            lam = _FIRST_DAMPING if lam == 0.0 else 10.0 * lam
            if lam > _MAX_DAMPING:
                break
        progress.advance(1)
        if lam > _MAX_DAMPING:  # no step lowers the cost: at a minimum if the gradient vanishes there
            converged = bool(np.max(np.abs(dx)) < max(config.convergence, 1e-6))
            break
        (poses, velocity), fell = trial, cost - trial_cost
        cost = trial_cost
        if np.max(np.abs(dx)) < config.convergence or fell <= config.cost_tolerance * cost:
            converged = True
            break
    if not converged:
        log.info("block adjustment: no convergence after %d iterations", iterations)
    if damped:  # the covariances need the undamped normal matrix at the solution
        e, J = _linearise(poses, velocity, a)
        N, _ = _assemble(n_free, cols, J, a.P, e)
        factor = factorize(N)
    return (poses, velocity), iterations, factor, N, free_index, converged


def _test_observations(state, observations, active, fixed, vnode, free_index, weights, factor, N, config):
    """Per-observation statistics from the cofactor of the residuals, Q_ee = P^+ - J Qxx J^T,
    vectorised over observations (each restricted to the directions its information determines)."""
    a = _arrays(observations, active, vnode, weights)
    P = a.P
    e, J = _linearise(*state, a)
    cols = _columns(a, free_index)
    slot_pairs = [(s, t) for s in range(3) for t in range(s + 1, 3)]
    both = [(cols[:, s] >= 0) & (cols[:, t] >= 0) for s, t in slot_pairs]
    pairs = np.concatenate([np.column_stack([cols[ok, s], cols[ok, t]]) for (s, t), ok in zip(slot_pairs, both,
                                                                                              strict=True)])
    diag, off = selected_inverse(N, 6, pairs.astype(int).reshape(-1, 2), factor=factor)

    offsets = np.cumsum([0] + [int(np.count_nonzero(ok)) for ok in both])
    JQJ = np.zeros((len(a.idx), 6, 6))
    for group in ((0, 1), (2,)):  # the relative pose's slots, then the drift velocity's
        for s in group:
            ok = cols[:, s] >= 0
            JQJ[ok] += J[ok, s] @ diag[cols[ok, s]] @ np.transpose(J[ok, s], (0, 2, 1))
        for m, ((s, t), ok) in enumerate(zip(slot_pairs, both, strict=True)):
            if t not in group:
                continue
            cross = J[ok, s] @ off[offsets[m]:offsets[m + 1]] @ np.transpose(J[ok, t], (0, 2, 1))
            JQJ[ok] += cross + np.transpose(cross, (0, 2, 1))
        if group == (0, 1):
            cov_adjusted = JQJ.copy()  # of the adjusted relative pose (without the drift's share)

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
    # An uncontrolled observation (redundancy ~ 0) cannot be tested, nor one whose cofactor is not
    # positive (an unconverged state: the normal matrix is not its residuals' own).
    statistic = np.where((r_k > 1e-6) & (statistic > -1e-9), np.maximum(statistic, 0.0), np.nan)
    keep = dof > 0
    # A negative statistic (an indefinite Q_zz, far from the solution) has no normalised value.
    normalised = np.sqrt(np.where(statistic >= 0, statistic, np.nan) / np.maximum(dof, 1))
    tests = [
        ObservationTest(int(a.idx[k]), ObservationKind(a.kinds[k]), int(observations[a.idx[k]].i),
                        int(observations[a.idx[k]].j), float(statistic[k]), int(dof[k]), float(r_k[k]),
                        float(normalised[k]), False, float(vtpv[k]),
                        min_redundancy=float(r_dir[k, 0]), cov_adjusted=cov_adjusted[k])
        for k in np.flatnonzero(keep)
    ]
    n_stations = int(np.count_nonzero(~fixed))
    return tests, float(vtpv[keep].sum()), float(r_k[keep].sum()), diag[:n_stations]
