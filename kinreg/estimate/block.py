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
on SE(3) with a sparse normal matrix (CHOLMOD where available); a pose residual is the
translation difference in the observation's axes and the rotation vector (:func:`_linearise`).
Fixed stations define the datum.

After convergence: the a-posteriori standard deviation of unit weight and the global test,
per-observation test statistics and redundancy numbers from the 6x6 blocks of the inverse
(selected inversion: the inverse is never formed densely), data snooping of the links and station
observations (the worst observation above the critical value is removed and the network
re-adjusted; the trajectory's links are tested but never removed), and optionally a variance
component per observation kind so that reported standard deviations follow the residuals.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import logging
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp

from kinreg.config import BlockConfig
from kinreg.errors import EstimationError
from kinreg.estimate.normal import NormalEquations
from kinreg.estimate.snooping import (
    ObservationTests,
    chi2_quantile,
    observation_tests,
    taken_back,
    variance_components,
    worst_outliers,
)
from kinreg.estimate.sparse import in_threads, kept_heap, one_blas_thread
from kinreg.geometry import FloatArray, Pose, quat_conjugate, quat_to_matrix, quat_to_rotvec, relative_poses, skew
from kinreg.progress import NullProgress, Progress
from kinreg.types import SCAN_PLANE_RANK, BlockResult, ObservationKind, RelativeObservation

log = logging.getLogger(__name__)

# Kinds whose variance component may also fall below 1 (kinreg.estimate.snooping.variance_components):
# a scan plane against its physical plane shows its whole error in its residuals.
_SCAN_PLANES = tuple(kind.value for kind in SCAN_PLANE_RANK)
_LOWERABLE = frozenset(_SCAN_PLANES)
# Kinds never snooped (see _adjust_block)
_NOT_SNOOPED = [ObservationKind.TRAJECTORY.value, ObservationKind.DRIFT.value, ObservationKind.FRAME.value,
                *_SCAN_PLANES]


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
    Z_rotation: FloatArray  # (k, 3, 3): Z's rotation matrices
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
    return _subset(_gather(observations, vnode), active, weights)


def _gather(observations: list[RelativeObservation], vnode: np.ndarray, links: _Links | None = None) -> _Active:
    """All observations as arrays (``P`` their own information, unweighted); once per adjustment,
    :func:`_subset` takes the active ones from it. ``links``: their :meth:`_Links.of` if at hand."""
    obs = observations
    count = len(obs)
    links = _Links.of(obs) if links is None else links
    kinds, i, j = links.kind, links.i, links.j
    drift = kinds == ObservationKind.DRIFT.value
    station = kinds == ObservationKind.STATION.value
    point = kinds == ObservationKind.POINT.value
    nodes = -np.ones((count, 3), dtype=int)
    nodes[point, 0] = i[point]
    nodes[point, 1] = j[point]
    pose = ~drift & ~point
    nodes[pose, 0] = i[pose]
    nodes[pose & ~station, 1] = j[pose & ~station]
    trajectory = kinds == ObservationKind.TRAJECTORY.value
    nodes[trajectory, 2] = vnode[i[trajectory]]
    nodes[drift, 0] = vnode[i[drift]]
    nodes[drift, 1] = np.where(j[drift] >= 0, vnode[np.maximum(j[drift], 0)], -1)
    P = np.array([o.info for o in obs], dtype=float).reshape(-1, 6, 6)  # np.array: 3x np.stack's speed here
    levers = _optional([o.levers_m for o in obs], (2, 3))
    share = np.fromiter((o.share if o.j >= 0 else 0.0 for o in obs), dtype=float, count=count)
    decays = [o.decay for o in obs]
    scalar = [k for k, d in enumerate(decays) if isinstance(d, (float, int))]
    per_axis = [k for k, d in enumerate(decays) if not isinstance(d, (float, int))]
    decay = np.zeros((count, 6))
    decay[scalar] = np.array([decays[k] for k in scalar], dtype=float).reshape(-1, 1)
    if per_axis:
        decay[per_axis] = np.array([np.broadcast_to(decays[k], (6,)) for k in per_axis])
    Z = Pose(np.array([o.Z.quat_wxyz for o in obs], dtype=float).reshape(-1, 4),
             np.array([o.Z.t_xyz for o in obs], dtype=float).reshape(-1, 3))
    return _Active(np.arange(count), kinds, nodes, pose, station, point, levers, share, Z, Z.rotation_matrix, P,
                   np.fromiter((o.dt_s for o in obs), dtype=float, count=count), decay,
                   np.fromiter((o.coupling for o in obs), dtype=float, count=count),
                   _optional([o.step_obj for o in obs], (3,)))


def _optional(values: list, shape: tuple[int, ...]) -> FloatArray:
    """Per observation an optional array of ``shape``, zeros where ``None``."""
    out = np.zeros((len(values), *shape))
    given = [k for k, v in enumerate(values) if v is not None]
    if given:
        out[given] = np.array([values[k] for k in given]).reshape(-1, *shape)
    return out


def _subset(a: _Active, active: np.ndarray, weights: dict[str, float]) -> _Active:
    """The active observations of :func:`_gather`'s arrays, ``P`` weighted per kind."""
    sel = np.flatnonzero(active)
    parts = {f.name: getattr(a, f.name)[sel] for f in dataclasses.fields(a)}
    parts["P"] = parts["P"] * _weight_of(parts["kinds"], weights)[:, None, None]
    return _Active(**parts)


def _eigen_of(a: _Active, eigen: tuple[FloatArray, FloatArray],
              weights: dict[str, float]) -> tuple[FloatArray, FloatArray]:
    """The eigenvalues and vectors of the active observations' weights ``a.P``: the information's
    own (``eigen``, of all observations) scaled per kind."""
    return eigen[0][a.idx] * _weight_of(a.kinds, weights)[:, None], eigen[1][a.idx]


def _weight_of(kinds: np.ndarray, weights: dict[str, float]) -> FloatArray:
    """Per observation the weight of its kind."""
    present, kind_of = np.unique(kinds, return_inverse=True)
    return np.array([weights[k] for k in present], dtype=float)[kind_of.reshape(-1)]


# Observations per step of _linearise: temporaries of a few MB, which the allocator reuses, rather
# than arrays of all observations (at 500,000 observations a third of the CPU went to the kernel,
# giving fresh pages to each).
_CHUNK = 1 << 15


def _linearise(poses: Pose, velocity: FloatArray, a: _Active, jacobians: bool = True,
               out: tuple[FloatArray, FloatArray] | None = None) -> tuple[FloatArray, FloatArray]:
    """Residuals ``e`` (k, 6) and, with ``jacobians``, de/dx per slot (k, 3, 6, 6; else empty) (exact
    but for a drift velocity's turn, :func:`_pose_residuals`). Pose observations: with ``D = Z^-1
    T_i^-1 T_j`` (``Z^-1 T_i`` for a station's pose), ``e = (t_D, rotvec(R_D)) - dt S_j v``, the
    translation difference in Z's axes and the rotation vector (the right-perturbation twist to
    first order); a scan plane against its node: its tilts and offset (:func:`_scan_plane_residuals`);
    drift observations ``e = v_j - decay v_i`` (``v_i``); point observations
    ``e = ((1 - s) T_i l_0 + s T_j l_1 - Z.t, 0)`` (object axes). ``out``: an earlier result of the same
    ``a`` (with ``jacobians``) to write into: the same entries are written every time, the others
    stay zero."""
    k = len(a.idx)
    if out is not None:  # 100,000 stations: 0.3 GB of fresh pages per call otherwise, 0.5 s of page faults
        e, J = out
    else:
        e = np.zeros((k, 6))
        # Slot-major underneath: each slot's Jacobians ``J[:, s]`` are contiguous (the products take
        # them without a copy), and a slot that no observation has (no drift velocities) is never
        # written, so its pages are never touched.
        J = np.zeros((3, k if jacobians else 0, 6, 6)).transpose(1, 0, 2, 3)
    p = np.flatnonzero(a.pose)
    if len(p):
        R = poses.rotation_matrix  # per station, once

        def step(start: int) -> None:
            chunk = p[start:start + _CHUNK]
            # a run (nearly always): views, not gathered copies
            rows: np.ndarray | slice = (slice(int(chunk[0]), int(chunk[-1]) + 1)
                                        if chunk[-1] - chunk[0] == len(chunk) - 1 else chunk)
            _pose_residuals(poses, R, velocity, a, rows, e, J if jacobians else None)

        in_threads(step, range(0, len(p), _CHUNK), len(poses))
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


def _unit_slots(a: _Active) -> np.ndarray:
    """(k, 3) bool: where :func:`_linearise` makes a slot's Jacobian the identity, whatever the state
    (the second link of a drift observation)."""
    unit = np.zeros((len(a.idx), 3), dtype=bool)
    unit[:, 1] = ~a.pose & ~a.point & (a.nodes[:, 1] >= 0)
    return unit


def _so3_right_jacobian_inv(phi: FloatArray) -> FloatArray:
    """(k, 3, 3): SO(3)'s inverse right Jacobian at rotation vectors ``phi`` (k, 3), ``I + [phi]x / 2
    + c [phi]x^2`` with ``c = 1 / theta^2 - (1 + cos theta) / (2 theta sin theta)`` (1/12 near 0)."""
    theta = np.linalg.norm(phi, axis=1)
    small = theta < 1e-4
    th = np.where(small, 1.0, theta)
    c = np.where(small, 1.0 / 12.0, 1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th)))
    K = skew(phi)
    return np.eye(3) + 0.5 * K + c[:, None, None] * (K @ K)


def _pose_residuals(poses: Pose, R: FloatArray, velocity: FloatArray, a: _Active, p: np.ndarray | slice,
                    e: FloatArray, J: FloatArray | None) -> None:
    """Pose observations ``p`` (indices or a slice): their residuals into ``e`` and (with ``J``) their
    Jacobians (:func:`_linearise`); ``R`` the stations' rotation matrices. The relative poses are
    formed as :class:`Pose`'s algebra forms them, so the figures are the same to the last bit (the
    pipeline's loops of block, drift and relinking carry a last-bit difference to the 8th decimal)."""
    at = np.arange(p.start, p.stop) if isinstance(p, slice) else p
    st = a.station[p]
    i = a.nodes[p, 0]
    j = np.where(st, i, a.nodes[p, 1])
    R_i = R[i]
    q_i, t_i = poses.quat_wxyz[i], poses.t_xyz[i]
    q_rel, t_rel = relative_poses(q_i, t_i, R_i, poses.quat_wxyz[j], poses.t_xyz[j])
    q_rel = np.where(st[:, None], q_i, q_rel)
    t_rel = np.where(st[:, None], t_i, t_rel)
    q_Z, t_Z, R_Z = a.Z.quat_wxyz[p], a.Z.t_xyz[p], a.Z_rotation[p]
    kappa = a.coupling[p]
    coupled = np.flatnonzero(kappa > 0.0)
    if len(coupled):  # the translation turned by the adjusted attitude of station i
        turned = np.einsum("kji,kj->ki", R_i[coupled], a.step[at[coupled]])
        t_Z = t_Z.copy()
        t_Z[coupled] = (1.0 - kappa[coupled, None]) * t_Z[coupled] + kappa[coupled, None] * turned
    # The residual: the translation difference in Z's axes and the rotation vector of Z^-1 rel, not
    # the SE(3) logarithm. Both agree to first order; they part where the translation residual is
    # large, along a direction that a plane link's planes leave (nearly) free: there the log's
    # rho = J_l(phi)^-1 t turns every milliradian of the pair into rho x phi / 2 of shift across
    # that direction (3.5 mm at 7 m), which neither the information nor the Jacobians know of.
    # Gauss-Newton crawled on such links (the undamped step rose the cost in every iteration).
    q_e, t_e = relative_poses(q_Z, t_Z, R_Z, q_rel, t_rel)
    phi_e = quat_to_rotvec(q_e)
    e[p, :3] = t_e
    e[p, 3:] = phi_e
    v = a.nodes[p, 2]
    has_v = np.flatnonzero(v >= 0)
    S = None
    if len(has_v):  # S_j v: the velocity (object axes) in the axes of station j, times -dt
        S = np.zeros((len(has_v), 6, 6))
        S[:, :3, :3] = np.swapaxes(R[j[has_v]], 1, 2)
        S[:, 3:, 3:] = S[:, :3, :3]
        S = -a.dt[at[has_v], None, None] * S
        e[at[has_v]] += (S @ velocity[v[has_v] - len(poses)][:, :, None])[:, :, 0]
    if J is not None:
        # The Jacobians for right perturbations (rho, phi): of T_j, J_j = [[R_Z^T R, 0], [0, J_r^-1(e_r)]]
        # with rel = (R, t), and of T_i, J_i = -J_j Ad(rel^-1) (one motion of both leaves the residual
        # as it is: the network's turn about its datum stays free). J_j differs from the identity by
        # the residual's rotation only (a few milliradians), but taking the identity is not harmless:
        # Gauss-Newton's fixed point is then not the minimum, and near it the undamped step raises the
        # cost while the model says there is more to gain, so the adjustment never converges.
        R_inv = quat_to_matrix(quat_conjugate(q_rel))
        ad = np.zeros((len(at), 6, 6))  # Ad(rel^-1) = [[R', [t']x R'], [0, R']] with rel^-1 = (R', t') = (R^T, -R^T t)
        ad[:, :3, :3] = R_inv
        ad[:, 3:, 3:] = R_inv
        ad[:, :3, 3:] = skew(-np.einsum("...ij,...j->...i", R_inv, t_rel)) @ R_inv
        J_second = np.zeros((len(at), 6, 6))
        J_second[:, :3, :3] = np.transpose(R_Z, (0, 2, 1)) @ np.transpose(R_inv, (0, 2, 1))
        J_second[:, 3:, 3:] = _so3_right_jacobian_inv(phi_e)
        J_i = -(J_second @ ad)
        J_i[st] = J_second[st]  # a station's pose: e = (R_Z^T (t_i - t_Z), log(R_Z^T R_i))
        if len(coupled):  # d(R_i^T s)/d(phi_i) = [R_i^T s]x for a right perturbation
            R_Zt = np.transpose(R_Z[coupled], (0, 2, 1))
            J_i[coupled, :3, 3:] -= kappa[coupled, None, None] * R_Zt @ skew(turned)
        J[p, 0] = J_i
        J[at[~st], 1] = J_second[~st]
        if S is not None:  # S_j's own dependence on T_j is of the order dt |v| and left out
            J[at[has_v], 2] = S
    planes = np.flatnonzero(np.isin(a.kinds[at], _SCAN_PLANES))
    if len(planes):
        _scan_plane_residuals(R_Z[planes], t_Z[planes], q_rel[planes], t_rel[planes], e, J, at[planes])


def _scan_plane_residuals(R_Z: FloatArray, t_Z: FloatArray, q_rel: FloatArray, t_rel: FloatArray,
                          e: FloatArray, J: FloatArray | None, rows: np.ndarray) -> None:
    """A scan plane against its physical plane's node ``F`` (:mod:`kinreg.estimate.plane_nodes`):
    residuals that the node's free directions (its shift along the plane, its turn about the
    normal) leave exactly as they are, with their Jacobians, written over the pose residual's rows
    (``rel = T_k^-1 F``; the information is zero in the other rows). With ``n = R_Z^T R_rel e_z``
    (the node's normal in the observed plane's frame ``Z``) and ``p = R_Z^T (t_rel - t_Z)`` (the
    node's origin there): the tilts ``(-n_y, n_x)`` and the offset ``n . p`` (the node plane's
    distance from the observed plane's anchor, along its normal). To first order these are the
    pose residual's ``phi_x, phi_y, rho_z``; but the pose residual's offset is the height of the
    node's origin, which a tilt turns into a slope along the plane: the origin then slides towards
    where the tilt lowers the cost, held only by the node's 1 m gauge, and Gauss-Newton crawls (with
    the identity for the node's Jacobian it stops elsewhere than the minimum instead, and does
    not converge)."""
    R_rel = quat_to_matrix(q_rel)
    R_Zt = np.transpose(R_Z, (0, 2, 1))
    D = R_Zt @ R_rel
    m = R_rel[:, :, 2]  # the node's normal in scan k's frame
    n = D[:, :, 2]
    p = np.einsum("kij,kj->ki", R_Zt, t_rel - t_Z)
    e[rows] = 0.0
    e[rows, 2] = np.einsum("ki,ki->k", n, p)
    e[rows, 3] = -n[:, 1]
    e[rows, 4] = n[:, 0]
    if J is None:
        return
    # d n and d p per right perturbation: of F (rho, phi): dn = -R_Z^T R_rel [e_z]x phi, dp = R_Z^T R_rel rho;
    # of T_k (rho, phi): dn = R_Z^T [m]x phi, dp = R_Z^T (-rho + [t_rel]x phi).
    ez = skew(np.array([0.0, 0.0, 1.0]))
    dn_F = np.zeros((len(rows), 3, 6))
    dn_F[:, :, 3:] = -D @ ez
    dp_F = np.zeros((len(rows), 3, 6))
    dp_F[:, :, :3] = D
    dn_k = np.zeros((len(rows), 3, 6))
    dn_k[:, :, 3:] = R_Zt @ skew(m)
    dp_k = np.zeros((len(rows), 3, 6))
    dp_k[:, :, :3] = -R_Zt
    dp_k[:, :, 3:] = R_Zt @ skew(t_rel)
    for slot, dn, dp in ((0, dn_k, dp_k), (1, dn_F, dp_F)):
        Js = np.zeros((len(rows), 6, 6))
        Js[:, 2] = np.einsum("ki,kij->kj", p, dn) + np.einsum("ki,kij->kj", n, dp)
        Js[:, 3] = -dn[:, 1]
        Js[:, 4] = dn[:, 0]
        J[rows, slot] = Js


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


def _weighted_squares(e: FloatArray, P: FloatArray) -> float:
    """The weighted sum of squared residuals ``sum e^T P e``."""
    return float(np.einsum("ki,kij,kj->", e, P, e))


def _components(i: np.ndarray, j: np.ndarray, links: np.ndarray, n: int) -> np.ndarray:
    """Connected components of the station graph (label per station): stations ``i[links]`` and
    ``j[links]`` are linked."""
    from scipy.sparse.csgraph import connected_components

    pairs = np.column_stack([i[links], j[links]])
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
    # A large network: its arrays reuse freed pages, and one BLAS thread throughout (the numeric
    # factorisations and the selected inverse had one already; elsewhere, at 100,000 stations,
    # OpenBLAS's second thread spun 8 s of 58 s CPU waiting for work, on two busy cores).
    n = len(poses_initial)
    with kept_heap(n), one_blas_thread(n), _collector_paused():
        return _adjust_block(poses_initial, observations, fixed, config, progress)


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """Python's cyclic garbage collector paused (where it runs): the adjustment makes objects by
    the hundred thousand (the moved observations, the tests), and every few hundred of them the
    collector went through all that are alive, the caller's observations among them (at 100,000
    stations 1.3 s of 3 s making the tests). The adjustment makes no reference cycles to collect."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def _adjust_block(poses_initial: Pose, observations: list[RelativeObservation], fixed: np.ndarray,
                  config: BlockConfig, progress: Progress | None) -> BlockResult:
    progress = progress or NullProgress()
    n = len(poses_initial)
    fixed = np.asarray(fixed, dtype=bool)
    if not fixed.any() and not any(o.kind in (ObservationKind.STATION, ObservationKind.POINT) for o in observations):
        raise EstimationError("no datum: fix at least one station or observe station poses directly")
    links = _Links.of(observations)
    _check_datum(links, fixed, n)

    active = np.ones(len(observations), dtype=bool)
    weights = {k.value: 1.0 for k in ObservationKind}
    rejected_order: list[int] = []
    last_round: list[int] = []  # rejected in the previous round
    protected: set[int] = set()  # taken back after a rejection left the network undetermined
    variance_before = np.zeros(0)
    vce_rounds = 0
    # Reduced to a local origin (the first station): at survey coordinates (UTM, 5e6 m) a pose's
    # last bits are 1e-9 m, and the updates would never fall below the convergence threshold.
    origin = poses_initial.t_xyz[0].copy()
    observations = list(observations)
    for k in np.flatnonzero(np.isin(links.kind, [ObservationKind.STATION.value, ObservationKind.POINT.value])).tolist():
        observations[k] = _moved(observations[k], -origin)
    vnode = velocity_nodes(observations, n)
    start = (_moved_poses(poses_initial, -origin), np.zeros((int(np.count_nonzero(vnode >= 0)), 6)))
    everything = _gather(observations, vnode, links)
    kinds = everything.kinds
    free_index = _free_index(fixed, len(start[1]))
    # One pattern (that of all observations) and one symbolic factorisation for every iteration
    # and every round of the adjustment.
    normal = NormalEquations(int(free_index.max()) + 1, _columns(everything, free_index))
    # The information's eigenvectors, once: a weight per kind only scales the eigenvalues.
    eigen = np.linalg.eigh(0.5 * (everything.P + np.transpose(everything.P, (0, 2, 1))))
    progress.start("block adjustment", total=None, unit="iterations")
    while True:
        try:
            if last_round:
                _check_datum(links.subset(active), fixed, n)
            a = _subset(everything, active, weights)
            state, iterations, factor, converged, linearised = _levenberg_marquardt(start, a, fixed, free_index,
                                                                                    normal, config, progress)
            eig = _eigen_of(a, eigen, weights)
            tests, omega, redundancy, Qxx_blocks = _test_observations(state, a, links, fixed, free_index, factor,
                                                                      linearised, eig)
            del linearised
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
        if not converged:
            # A round that did not converge ends the adjustment, failed: its residuals are not the
            # minimum's, and variance components or rejections drawn from them can steer the network
            # to a wrong solution that then passes its global test (its weights were made to fit it).
            break
        if config.variance_components and vce_rounds < config.max_variance_rounds:
            new_weights = variance_components(tests, weights, config.alpha, _LOWERABLE)
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
        # direction it carries to the planes, which may not fix it (a corridor): the stations there
        # would lose alternate links and drift along it.
        # Nor are the scan planes against their physical planes (kinreg.estimate.plane_nodes): their
        # matches passed their pair's tests and the links' snooping before; what misfits now is the
        # window's model (a shear the drift model leaves), and rejecting it takes the planes from
        # the stations that need them: round by round, the stations a wall alone holds along a
        # direction would lose it and drift along that direction.
        candidates = ~np.isin(tests.index, list(protected)) & ~np.isin(tests.kind, _NOT_SNOOPED)
        worst = worst_outliers(tests, candidates, config.alpha, budget) if config.data_snooping and budget > 0 else []
        if worst:
            for t in worst:
                index = int(tests.index[t])
                log.info("block: rejecting observation %d (%s %d-%d, statistic %.1f)", index, tests.kind[t],
                         tests.i[t], tests.j[t], tests.statistic[t])
                active[index] = False
                rejected_order.append(index)
                last_round.append(index)
            variance_before = variance
            start = state  # warm start: the next round begins at the current solution
            continue
        break
    progress.finish()
    poses = _moved_poses(state[0], origin)

    sigma0 = float(np.sqrt(omega / redundancy)) if redundancy > 0 else float("nan")
    failure = _failure(converged, iterations, poses, omega, redundancy, Qxx_blocks,
                       n > 1 and not np.any(active & np.isin(kinds, _CHECKING_KINDS)))
    passed = not failure and bool(redundancy <= 0 or omega <= chi2_quantile(1.0 - config.alpha, float(redundancy)))
    factor_scale = sigma0**2 if (not passed and np.isfinite(sigma0)) else 1.0
    cov_xi = np.zeros((n, 6, 6))
    cov_xi[~fixed] = Qxx_blocks * factor_scale
    R = poses.rotation_matrix
    cov_position = R @ cov_xi[:, :3, :3] @ np.transpose(R, (0, 2, 1))
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
        tests=tuple(_with_rejected(tests, rejected_order, links).as_tests()),
        variance_components={k: 1.0 / w for k, w in weights.items() if (kinds == k).any()},
        failure=failure,
    )


# The kinds that check the trajectory: without one active the network is the trajectory itself.
_CHECKING_KINDS = [k.value for k in (ObservationKind.PLANES, ObservationKind.POINT, *SCAN_PLANE_RANK)]
# Below this redundancy nothing checks the network: its sigma0 and every sigma scaled by it mean nothing.
_MIN_REDUNDANCY = 0.5


def _failure(converged: bool, iterations: int, poses: Pose, omega: float, redundancy: float,
             cov_blocks: FloatArray, unchecked: bool = False) -> str:
    """Why the adjustment is not a result, in words; empty when it is one. ``unchecked``: no
    plane link, scan plane or control point is left in the network (every pairwise link rejected
    or none found), so the result would be the trajectory itself."""
    if not converged:
        return f"no convergence after {iterations} iterations"
    if not (np.all(np.isfinite(poses.t_xyz)) and np.all(np.isfinite(poses.quat_wxyz))):
        return "non-finite station poses"
    if not np.isfinite(omega) or not np.all(np.isfinite(cov_blocks)):
        return "non-finite residuals or covariances"
    if redundancy < -1e-6:
        return f"negative redundancy ({redundancy:.1f})"
    if unchecked:
        return ("no plane link and no control point is left to check the trajectory (every pairwise link was "
                "rejected or none was found): the result would be the input")
    if redundancy < _MIN_REDUNDANCY:
        return f"redundancy {redundancy:.2g}: nothing checks the network, its sigmas would say nothing"
    return ""


def _moved_poses(poses: Pose, shift: FloatArray) -> Pose:
    return Pose(poses.quat_wxyz, poses.t_xyz + shift)


def _moved(observation: RelativeObservation, shift: FloatArray) -> RelativeObservation:
    """A station observation (an absolute pose) with the origin moved by ``shift``; relative
    observations do not depend on the origin."""
    if observation.kind not in (ObservationKind.STATION, ObservationKind.POINT):
        return observation
    return dataclasses.replace(observation, Z=_moved_poses(observation.Z, shift))


# The kinds' values by a code per kind: one dictionary look-up per observation, not an enum's ``value``.
_KIND_CODE = {kind: code for code, kind in enumerate(ObservationKind)}
_KIND_VALUES = np.array([kind.value for kind in ObservationKind], dtype=str)


@dataclasses.dataclass(frozen=True)
class _Links:
    """What the datum check and the test list need of the observations, as arrays."""

    kind: np.ndarray
    i: np.ndarray
    j: np.ndarray
    rank: np.ndarray

    @classmethod
    def of(cls, observations: list[RelativeObservation]) -> _Links:
        count = len(observations)
        code = np.fromiter((_KIND_CODE[o.kind] for o in observations), dtype=np.intp, count=count)
        return cls(_KIND_VALUES[code],
                   np.fromiter((o.i for o in observations), dtype=int, count=count),
                   np.fromiter((o.j for o in observations), dtype=int, count=count),
                   np.fromiter((o.rank for o in observations), dtype=int, count=count))

    def subset(self, active: np.ndarray) -> _Links:
        return _Links(self.kind[active], self.i[active], self.j[active], self.rank[active])


def loose_parts(observations: list[RelativeObservation], fixed: np.ndarray, n: int) -> list[np.ndarray]:
    """Connected parts of the station graph with neither a fixed station nor a direct observation
    of a station (each part as its sorted station indices)."""
    return _loose_parts(_Links.of(observations), fixed, n)


def _loose_parts(links: _Links, fixed: np.ndarray, n: int) -> list[np.ndarray]:
    n = max(n, 1 + int(max(links.i.max(initial=-1), links.j.max(initial=-1))))
    linking = (links.j >= 0) & (links.rank > 0) & (links.kind != ObservationKind.DRIFT.value)
    labels = _components(links.i, links.j, linking, n)
    direct = np.isin(links.kind, [ObservationKind.STATION.value, ObservationKind.POINT.value])
    anchored = set(labels[np.flatnonzero(fixed)].tolist()) | set(labels[links.i[direct]].tolist())
    return [np.flatnonzero(labels == c) for c in sorted(set(labels.tolist()) - anchored)]


def _check_datum(links: _Links, fixed: np.ndarray, n: int) -> None:
    parts = _loose_parts(links, fixed, n)
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
# itself, lambda growing tenfold from _FIRST_DAMPING, up to _MAX_DAMPING (then no descent is left:
# a minimum). The ladder starts low: a direction that only a trajectory link's lever fixes has an
# eigenvalue a millionth of its diagonal, and there the undamped step overshoots by the valley's
# curvature; a first damping near 1e-4 shrinks the step along that direction to a hundredth, every
# iteration falls back to it, and the adjustment crawls along the valley (a fraction of a millimetre
# an iteration) until the iteration limit, where a damping of 1e-6 takes the step.
_FIRST_DAMPING = 1e-8
_MAX_DAMPING = 1e8
# Converged when the undamped step's predicted fall of the cost (the Newton decrement b^T N^-1 b, in
# units of the weighted squares) is below this: the model's minimum is then within a thousandth of
# a standard deviation of the unknowns (the step's length in the metric of their covariance, N),
# whatever their units and however many. Where the Jacobians are not quite the residuals' (a
# drift velocity's turn into station j's axes is left out), the cost can rise by a few 1e-7 along
# a step the model says gains 5e-10: without this test the damped steps would crawl by nanometres
# an iteration until the limit, and the adjustment would fail at its minimum.
_DECREMENT = 1e-6


def _levenberg_marquardt(start, a, fixed, free_index, normal, config, progress):
    """Damped Gauss-Newton (Levenberg-Marquardt) on SE(3) (the drift velocities are plain vectors)
    over the active observations ``a``. Converged when no unknown changes by more than
    ``config.convergence``, the cost falls by less than ``config.cost_tolerance`` of itself, or the
    undamped step's predicted fall is below :data:`_DECREMENT`; returns the state (poses,
    velocities), the iterations, the factor of the undamped normal matrix at the solution (for the
    covariances) and whether it converged."""
    poses, velocity = start
    selection = normal.select(_columns(a, free_index), _unit_slots(a))
    # Each trial is linearised with its Jacobians: an accepted one (nearly all) is where the next
    # iteration starts, so its residuals are not computed twice.
    e, J = _linearise(poses, velocity, a)
    spare = None  # the arrays of a trial not taken (or of the state before the last step), for the next
    cost = _weighted_squares(e, a.P)
    factor = None
    converged = damped = False
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):  # noqa: B007  (the count is returned)
        blocks, b = normal.assemble(selection, J, a.P, e)
        lam = 0.0
        at_minimum = False
        while True:
            damped = lam > 0.0
            factor = normal.factorize(blocks, lam)
            dx = factor.solve(b).reshape(-1, 6)
            if lam == 0.0:
                close = float(b @ dx.reshape(-1)) < _DECREMENT
            trial = _stepped(poses, velocity, fixed, dx)
            trial_e, trial_J = _linearise(*trial, a, out=spare)
            spare = None
            trial_cost = _weighted_squares(trial_e, a.P)
            if np.isfinite(trial_cost) and trial_cost <= cost * (1.0 + 1e-12):
                break
            spare = trial_e, trial_J
            # An undamped step this small that does not lower the cost is rounding at the minimum:
            # damping it only shrinks it further (at 235 M points 78 of the block's 116
            # factorisations were such retries, and one more for the covariances). Stop here,
            # with the undamped factor of this state.
            at_minimum = lam == 0.0 and (close or bool(np.max(np.abs(dx)) < max(config.convergence, 1e-6)))
            lam = _FIRST_DAMPING if lam == 0.0 else 10.0 * lam
            if at_minimum or lam > _MAX_DAMPING:
                break
        del blocks
        progress.advance(1)
        if at_minimum or lam > _MAX_DAMPING:  # no step lowers the cost: at a minimum if the gradient vanishes there
            converged = close or bool(np.max(np.abs(dx)) < max(config.convergence, 1e-6))
            break
        (poses, velocity), fell = trial, cost - trial_cost
        spare = e, J
        e, J, cost = trial_e, trial_J, trial_cost
        if close or np.max(np.abs(dx)) < config.convergence or fell <= config.cost_tolerance * cost:
            converged = True
            break
    if not converged:
        log.info("block adjustment: no convergence after %d iterations", iterations)
    del spare
    if damped:  # the covariances need the undamped normal matrix at the solution
        factor = normal.factorize(normal.assemble(selection, J, a.P, e)[0])
    return (poses, velocity), iterations, factor, converged, (e, J)


def _test_observations(state, a, links, fixed, free_index, factor, linearised=None, eig=None):
    """The observations' tests (:func:`~kinreg.estimate.snooping.observation_tests`) at ``state``,
    the total e^T P e and redundancy, and the stations' covariance blocks. ``linearised``: ``(e, J)``
    at ``state`` if at hand; ``eig``: the eigenvalues and vectors of ``a.P`` if at hand."""
    e, J = _linearise(*state, a) if linearised is None else linearised
    figures, diag = observation_tests(e, J, a.P, _columns(a, free_index), factor, eig)
    statistic, dof, r_k, normalised, vtpv, least, cov_adjusted = figures
    keep = dof > 0
    index = a.idx[keep]
    tests = ObservationTests(index, a.kinds[keep], links.i[index], links.j[index], statistic[keep], dof[keep],
                             r_k[keep], normalised[keep], np.zeros(len(index), dtype=bool), vtpv[keep],
                             least[keep], cov_adjusted[keep], e[keep])  # a copy: e may be written into later
    n_stations = int(np.count_nonzero(~fixed))
    return tests, float(vtpv[keep].sum()), float(r_k[keep].sum()), diag[:n_stations]


def _with_rejected(tests: ObservationTests, rejected: list[int], links: _Links) -> ObservationTests:
    """The tests and the rejected observations (untested), in the order of the observations."""
    k = np.asarray(rejected, dtype=int)
    index = np.concatenate([tests.index, k])
    order = np.argsort(index, kind="stable")
    nan = np.full(len(k), np.nan)
    cov = np.concatenate([tests.cov_adjusted, np.zeros((len(k), 6, 6))])
    merged = ObservationTests(
        index[order], np.concatenate([tests.kind, links.kind[k]])[order],
        np.concatenate([tests.i, links.i[k]])[order], np.concatenate([tests.j, links.j[k]])[order],
        np.concatenate([tests.statistic, nan])[order], np.concatenate([tests.dof, links.rank[k]])[order],
        np.concatenate([tests.redundancy, np.zeros(len(k))])[order], np.concatenate([tests.normalised, nan])[order],
        np.concatenate([tests.rejected, np.ones(len(k), dtype=bool)])[order],
        np.concatenate([tests.vtpv, nan])[order], np.concatenate([tests.min_redundancy, nan])[order], cov[order],
        None if tests.residual is None else np.concatenate([tests.residual, np.full((len(k), 6), np.nan)])[order])
    return merged
