"""Pairwise adjustment of two scans through identical planes (METHOD.md section 2, step 6).

Gauss-Helmert model. Unknown: the pairwise transform ``T_i_j = T_prior . exp(xi)`` (right
perturbation, ``xi = (rho, phi)``). For every matched plane pair (a in scan i, b in scan j) three
conditions say that plane b, mapped into scan i, is plane a::

    c1 = u_a . (R n_b - n_a)    (normal difference along a's first tangent)
    c2 = v_a . (R n_b - n_a)    (... along its second tangent)
    c3 = d_b + (R n_b) . t - d_a

The observations are the plane parameters with their 3x3 covariances (two normal tilts and the
offset, :class:`~kinreg.types.Plane`). The trajectory's relative pose enters as a direct
observation of the unknowns (``xi = 0``) with standard deviations from the drift model, so pairs
whose planes fix only one or two directions still solve. Data snooping removes the worst plane
pair while its test statistic exceeds the chi-square quantile, then the global test judges the
rest.

Besides the combined result, each link keeps its plane-only information (normal matrix and the
relative pose it points to), so that a block adjustment can add the trajectory once by itself
instead of once per link.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from kinreg.config import DriftConfig, PairwiseConfig
from kinreg.estimate.drift import drift_sigmas
from kinreg.estimate.matching import count_directions
from kinreg.estimate.snooping import chi2_quantile
from kinreg.geometry import FloatArray, Pose, matrix_to_quat, skew
from kinreg.types import Link, LinkStatus, Plane, PlaneMatch

log = logging.getLogger(__name__)

# Eigenvalues of the plane-only normal matrix below this share of the largest count as zero.
_RANK_TOLERANCE = 1e-9


class _Design:
    """The observations and the linearised model of a group of pairs with the same number of
    matches, stacked along a leading axis (a run solves tens of thousands of pairs a round, of
    about six matches each: numpy's cost per call, not the arithmetic, sets the pace, so the
    group's pairs go through each call together)."""

    def __init__(self, pairs: list[_PairState]):
        self.pairs = pairs
        g_count, m_count = len(pairs), len(pairs[0].active)
        a = [p.by_id_i[m.plane_i] for p in pairs for m in p.active]
        b = [p.by_id_j[m.plane_j] for p in pairs for m in p.active]
        self.n_a = np.array([p.normal for p in a]).reshape(g_count, m_count, 3)
        self.d_a = np.array([p.d_m for p in a]).reshape(g_count, m_count)
        self.uv_a = np.array([p.basis_uv for p in a]).reshape(g_count, m_count, 2, 3)
        self.n_b = np.array([p.normal for p in b]).reshape(g_count, m_count, 3)
        self.d_b = np.array([p.d_m for p in b]).reshape(g_count, m_count)
        self.uv_b = np.array([p.basis_uv for p in b]).reshape(g_count, m_count, 2, 3)
        self.skew_b = skew(self.n_b)
        self.cov_a = np.array([p.cov_uvd for p in a]).reshape(g_count, m_count, 3, 3)
        self.cov_b = np.array([p.cov_uvd for p in b]).reshape(g_count, m_count, 3, 3)
        # Conditions of two matches that share a plane are correlated through its covariance.
        id_a = np.array([m.plane_i for p in pairs for m in p.active]).reshape(g_count, m_count)
        id_b = np.array([m.plane_j for p in pairs for m in p.active]).reshape(g_count, m_count)
        self.same_a = (id_a[:, :, None] == id_a[:, None, :])[..., None, None]
        self.same_b = (id_b[:, :, None] == id_b[:, None, :])[..., None, None]
        self.p_prior = np.array([p.p_prior for p in pairs])
        self.R_prior = np.array([p.R_prior for p in pairs])
        self.t_prior = np.array([p.t_prior for p in pairs])

    def take(self, index: np.ndarray) -> _Design:
        """The design of the pairs at ``index`` (those still iterating)."""
        part = object.__new__(_Design)
        part.__dict__.update({k: v if k == "pairs" else v[index] for k, v in self.__dict__.items()})
        return part

    def linearise(self, R: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Misclosures w (g, 3m), A = dc/dxi (g, 3m, 6) and the conditions' covariance
        Q_ww = B Q_ll B^T (g, 3m, 3m) at ``T = (R, t)`` (g, 3, 3), (g, 3)."""
        g_count, m_count = self.d_a.shape
        m = self.n_b @ R.swapaxes(1, 2)  # R n_b of every match
        w = np.empty((g_count, m_count, 3))
        w[..., :2] = np.einsum("gkci,gki->gkc", self.uv_a, m - self.n_a)
        w[..., 2] = self.d_b + np.einsum("gki,gi->gk", m, t) - self.d_a
        dm_dphi = -(R[:, None] @ self.skew_b)  # (g, m, 3, 3)
        A = np.zeros((g_count, m_count, 3, 6))
        A[..., :2, 3:] = np.einsum("gkci,gkij->gkcj", self.uv_a, dm_dphi)
        A[..., 2, :3] = self.n_b  # d(m . (t + R rho))/drho = m^T R = n_b^T
        A[..., 2, 3:] = np.einsum("gi,gkij->gkj", t, dm_dphi)
        return w.reshape(g_count, -1), A.reshape(g_count, -1, 6), self.conditions_covariance(R, t, self.cov_a,
                                                                                            self.cov_b)

    def conditions_covariance(self, R: FloatArray, t: FloatArray, cov_a: FloatArray,
                              cov_b: FloatArray) -> FloatArray:
        """Q_ww = B Q_ll B^T (g, 3m, 3m) at ``T = (R, t)`` for the planes' covariances ``cov_a``,
        ``cov_b`` (g, m, 3, 3): the design's own, or one variance component's
        (:func:`_component_sums`)."""
        g_count, m_count = self.d_a.shape
        # B is -I against the observations of plane a and J against those of plane b, so that
        # B Q_ll B^T is C_a where two matches share plane a and J_k C_b J_l^T where they share b
        # (forming B over all observations cost more than these blocks).
        Ruv_b = self.uv_b @ R[:, None].swapaxes(2, 3)  # (g, m, 2, 3): R u_b, R v_b
        J = np.zeros((g_count, m_count, 3, 3))
        J[..., :2, :2] = np.einsum("gkci,gkdi->gkcd", self.uv_a, Ruv_b)
        J[..., 2, :2] = np.einsum("gkci,gi->gkc", Ruv_b, t)
        J[..., 2, 2] = 1.0
        JC = J @ cov_b
        Q = self.same_a * cov_a[:, :, None] + self.same_b * np.einsum("gkac,glbc->gklab", JC, J)
        return Q.transpose(0, 1, 3, 2, 4).reshape(g_count, 3 * m_count, 3 * m_count)


def _pinv_symmetric(Q: FloatArray) -> FloatArray:
    """``np.linalg.pinv(Q, hermitian=True)`` of symmetric matrices ``Q`` (..., n, n) from their
    eigenvectors, without the SVD wrapper's cost (the same cutoff, 1e-15 of each matrix's largest
    eigenvalue's size)."""
    eigval, eigvec = np.linalg.eigh(Q)
    size = np.abs(eigval)
    large = size > 1e-15 * size.max(axis=-1, keepdims=True, initial=0.0)
    inverse = np.divide(1.0, eigval, out=np.zeros_like(eigval), where=large)
    return (eigvec * inverse[..., None, :]) @ eigvec.swapaxes(-1, -2)


def _so3(phi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The rotation matrices of rotation vectors ``phi`` (g, 3) and their left Jacobians:
    :meth:`Pose.exp`'s formulas for small twists, without the quaternions between them."""
    theta = np.sqrt(np.sum(phi * phi, axis=-1))
    small = theta < 1e-5
    safe = np.where(small, 1.0, theta)  # the series below 1e-5, where the closed forms cancel
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    K = skew(phi)
    K2 = K @ K
    return (_EYE3 + a[:, None, None] * K + b[:, None, None] * K2,
            _EYE3 + b[:, None, None] * K + c[:, None, None] * K2)


def _log(R: FloatArray, t: FloatArray) -> FloatArray:
    """The twists ``(rho, phi)`` (g, 6) of the poses ``(R, t)``, as :meth:`Pose.log` (angles
    below pi)."""
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=-1)
    sine = np.sqrt(np.sum(v * v, axis=-1))  # v is the axis times the sine of the angle
    theta = np.arctan2(sine, 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0))
    phi = v * np.divide(theta, sine, out=np.ones_like(sine), where=sine > 0.0)[:, None]
    small = theta < 1e-5
    safe = np.where(small, 1.0, theta)
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0,
                 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    K = skew(phi)
    V = _EYE3 - 0.5 * K + c[:, None, None] * (K @ K)
    return np.concatenate([np.einsum("gij,gj->gi", V, t), phi], axis=-1)


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def _solve(design: _Design, max_iterations: int) -> dict:
    """Gauss-Newton for every pair of the group; a pair stops iterating at its own convergence,
    so its steps are those it would take alone."""
    # The iterate as a rotation matrix and a translation: T <- T exp(step), xi = log(T_prior^-1 T).
    R, t = design.R_prior.copy(), design.t_prior.copy()
    xi = np.zeros((len(R), 6))
    running = np.arange(len(R))
    for _ in range(max_iterations):
        part = design if len(running) == len(R) else design.take(running)
        w, A, Q_ww = part.linearise(R[running], t[running])
        # pinv: conditions that repeat one another (one plane matched to two coplanar patches
        # twice over) leave Q_ww singular; they then count once.
        W = _pinv_symmetric(Q_ww)
        AtW = A.swapaxes(1, 2) @ W
        N = AtW @ A + _diag(part.p_prior)
        rhs = -(np.einsum("gij,gj->gi", AtW, w) + part.p_prior * xi[running])
        step = np.linalg.solve(N, rhs[..., None])[..., 0]
        R_step, J_step = _so3(step[:, 3:])
        R_now, t_now = R[running], t[running]
        R[running] = R_now @ R_step
        t[running] = np.einsum("gij,gj->gi", R_now, np.einsum("gij,gj->gi", J_step, step[:, :3])) + t_now
        R_prior_T = part.R_prior.swapaxes(1, 2)
        xi[running] = _log(R_prior_T @ R[running], np.einsum("gij,gj->gi", R_prior_T, t[running] - part.t_prior))
        running = running[np.max(np.abs(step), axis=1) >= 1e-11]
        if len(running) == 0:
            break
    w, A, Q_ww = design.linearise(R, t)
    W = _pinv_symmetric(Q_ww)
    AtW = A.swapaxes(1, 2) @ W
    N_p = AtW @ A
    Q_xx = np.linalg.inv(N_p + _diag(design.p_prior))
    Q_ee = Q_ww - A @ Q_xx @ A.swapaxes(1, 2)
    omega = np.einsum("gi,gij,gj->g", w, W, w) + np.einsum("gi,gi,gi->g", xi, design.p_prior, xi)
    return {"R": R, "t": t, "xi": xi, "w": w, "W": W, "AtW": AtW, "N_p": N_p, "Q_xx": Q_xx, "Q_ee": Q_ee,
            "omega": omega}


def _diag(p: FloatArray) -> FloatArray:
    """Diagonal matrices (g, n, n) of ``p`` (g, n)."""
    out = np.zeros((*p.shape, p.shape[-1]))
    np.einsum("gii->gi", out)[...] = p
    return out


def _match_statistics(sol: dict) -> tuple[FloatArray, FloatArray]:
    """Per pair and match (g, m): the 3-dof test statistic e^T Q_ee^+ e, and the largest
    normalised residual."""
    g_count = len(sol["w"])
    e = sol["w"].reshape(g_count, -1, 3)
    m_count = e.shape[1]
    Q = sol["Q_ee"].reshape(g_count, m_count, 3, m_count, 3)
    blocks = np.moveaxis(np.diagonal(Q, axis1=1, axis2=3), -1, 1)  # (g, m, 3, 3) diagonal blocks
    test = np.einsum("gki,gkij,gkj->gk", e, np.linalg.pinv(blocks, rcond=1e-10), e)
    diag = np.diagonal(blocks, axis1=2, axis2=3)
    normalised = np.max(np.abs(e) / np.sqrt(np.maximum(diag, 1e-30)), axis=2)
    return test, normalised


def _plane_only(sol: dict, T: Pose) -> tuple[Pose, FloatArray, FloatArray, FloatArray]:
    """Plane-only estimates of the group's pairs at poses ``T``: the poses the planes alone point
    to (moved only along determined directions), the information matrices, their ranks, and
    per-axis standard deviations."""
    N_p = 0.5 * (sol["N_p"] + sol["N_p"].swapaxes(1, 2))
    eigval, eigvec = np.linalg.eigh(N_p)
    determined = eigval > _RANK_TOLERANCE * np.maximum(eigval[:, -1:], 1e-300)
    rank = np.count_nonzero(determined, axis=1)
    g = np.einsum("gij,gj->gi", sol["AtW"], sol["w"])
    inverse = np.divide(1.0, eigval, out=np.zeros_like(eigval), where=determined)
    inv = (eigvec * inverse[:, None, :]) @ eigvec.swapaxes(1, 2)
    step = -np.einsum("gij,gj->gi", inv, g)
    T_planes = T.compose(Pose.exp(step))
    null_share = np.sum(np.where(determined[:, None, :], 0.0, eigvec**2), axis=2)
    axis_sigma = np.where(null_share > 1e-2, np.inf, np.sqrt(np.maximum(np.diagonal(inv, axis1=1, axis2=2), 0.0)))
    return T_planes, N_p, rank, axis_sigma


@dataclass(frozen=True, eq=False)
class PairInput:
    """One pair for :func:`adjust_pairs`: the arguments of :func:`adjust_pair` but the configs."""

    scan_i: int
    scan_j: int
    planes_i: tuple[Plane, ...]
    planes_j: tuple[Plane, ...]
    T_prior: Pose
    dt_s: float
    matches: tuple[PlaneMatch, ...]
    sigma_prior: FloatArray | None = None


class _PairState:
    """A pair between rounds of data snooping: its prior and the matches still in."""

    def __init__(self, pair: PairInput, drift: DriftConfig, config: PairwiseConfig, model: LinkModel | None = None):
        self.pair = pair
        self.sigma_prior = drift_sigmas(abs(pair.dt_s), drift) if pair.sigma_prior is None else pair.sigma_prior
        planes_i, planes_j = pair.planes_i, pair.planes_j
        if model is not None and model.estimated:
            self.sigma_prior = self.sigma_prior * np.sqrt(model.prior_variance_factor)
            planes_i, planes_j = model.apply(planes_i), model.apply(planes_j)
        self.p_prior = 1.0 / self.sigma_prior**2
        self.R_prior, self.t_prior = pair.T_prior.rotation_matrix, pair.T_prior.t_xyz
        self.by_id_i = {p.plane_id: p for p in planes_i}
        self.by_id_j = {p.plane_id: p for p in planes_j}
        # A plane pair stated twice would make two identical conditions (a singular Q_ww).
        self.active = list({(m.plane_i, m.plane_j): m for m in pair.matches}.values())
        self.rejected: list[PlaneMatch] = []
        self.max_rejected = int(np.floor(config.max_rejected_share * len(pair.matches)))

    def prior_only(self) -> Link:
        """The link of a pair without a usable match: the prior alone, zero plane information."""
        p = self.pair
        return Link(p.scan_i, p.scan_j, LinkStatus.PRIOR_ONLY, p.T_prior, np.diag(self.sigma_prior**2), p.T_prior,
                    p.T_prior, np.zeros((6, 6)), 0, np.full(6, np.inf), 0, float("nan"), 0, True, (),
                    tuple(self.rejected), 0.0, p.dt_s)


def adjust_pairs(pairs: Sequence[PairInput], drift: DriftConfig, config: PairwiseConfig,
                 model: LinkModel | None = None) -> list[Link]:
    """:func:`adjust_pair` for many pairs at once, in their order: pairs with the same number of
    matches are solved together on stacked arrays, each with its own iterations and data
    snooping, so each link is the one :func:`adjust_pair` gives (up to rounding). ``model``: the
    observations' model the links measured (:func:`estimate_link_model`), where it is not the
    a-priori one."""
    states = [_PairState(pair, drift, config, model) for pair in pairs]
    links: list[Link | None] = [None if s.active else s.prior_only() for s in states]
    critical = chi2_quantile(1.0 - config.alpha, 3)
    pending = [k for k, s in enumerate(states) if s.active]
    while pending:
        groups: dict[int, list[int]] = {}
        for k in pending:
            groups.setdefault(len(states[k].active), []).append(k)
        pending = []
        for members in groups.values():
            design = _Design([states[k] for k in members])
            sol = _solve(design, config.max_iterations)
            test, normalised = _match_statistics(sol)
            worst = np.argmax(test, axis=1)
            done = []
            for g, k in enumerate(members):
                s = states[k]
                if test[g, worst[g]] <= critical or len(s.rejected) >= s.max_rejected:
                    done.append(g)
                    continue
                log.debug("link %d-%d: rejected plane pair %s (test %.1f > %.1f)", s.pair.scan_i, s.pair.scan_j,
                          s.active[worst[g]], test[g, worst[g]], critical)
                s.rejected.append(s.active.pop(worst[g]))
                if s.active:
                    pending.append(k)
                else:
                    links[k] = s.prior_only()
            if done:
                index = np.array(done)
                kept = {key: value[index] for key, value in sol.items()}
                for k, link in zip([members[g] for g in done], _links([states[members[g]] for g in done], kept,
                                                                        normalised[index], config), strict=True):
                    links[k] = link
    return links  # type: ignore[return-value]


def _links(states: list[_PairState], sol: dict, normalised: FloatArray, config: PairwiseConfig) -> list[Link]:
    """The links of pairs whose data snooping has finished, from their group's solution."""
    # The quaternion on the prior's side, as composing small steps onto the prior's kept it.
    q = matrix_to_quat(sol["R"])
    q_prior = np.array([s.pair.T_prior.quat_wxyz for s in states])
    q = np.where(np.sum(q * q_prior, axis=1, keepdims=True) < 0.0, -q, q)
    T = Pose(q, sol["t"])
    T_planes, N_p, rank, axis_sigma = _plane_only(sol, T)
    links = []
    for g, s in enumerate(states):
        redundancy = 3 * len(s.active)
        omega = float(sol["omega"][g])
        passed = bool(omega <= chi2_quantile(1.0 - config.alpha, redundancy))
        R_i = np.array([s.by_id_i[m.plane_i].normal for m in s.active])
        # A failed global test alone is reported, not fatal (it happens at rate alpha by chance); a
        # link is rejected when snooping hit its cap and the test still fails: too many wrong matches.
        status = (LinkStatus.REJECTED if (not passed and len(s.rejected) >= max(s.max_rejected, 1))
                  else LinkStatus.OK)
        links.append(Link(
            scan_i=s.pair.scan_i,
            scan_j=s.pair.scan_j,
            status=status,
            T_i_j=T[g],
            cov_xi=sol["Q_xx"][g],
            T_i_j_prior=s.pair.T_prior,
            T_i_j_planes=T_planes[g],
            info_planes=N_p[g],
            rank=int(rank[g]),
            axis_sigma_planes=axis_sigma[g],
            n_directions=count_directions(R_i),
            sigma0=float(np.sqrt(omega / redundancy)),
            redundancy=redundancy,
            global_test_passed=passed,
            matches=tuple(s.active),
            rejected=tuple(s.rejected),
            max_normalised_residual=float(normalised[g].max()),
            dt_s=s.pair.dt_s,
        ))
    return links


def adjust_pair(
    scan_i: int,
    scan_j: int,
    planes_i: tuple[Plane, ...],
    planes_j: tuple[Plane, ...],
    T_prior: Pose,
    dt_s: float,
    matches: tuple[PlaneMatch, ...],
    drift: DriftConfig,
    config: PairwiseConfig,
    sigma_prior: FloatArray | None = None,
) -> Link:
    """Adjust one pair. ``T_prior`` is the trajectory's ``T_i_j`` (maps scan j into scan i),
    ``dt_s`` the time between the two scans (sets the prior's standard deviations, unless
    ``sigma_prior`` (6,) gives them, e.g. for a static scan that no trajectory ties).

    Returns a :class:`Link`; with no usable match its status is ``PRIOR_ONLY`` and it carries
    the prior alone (zero plane information).
    """
    return adjust_pairs([PairInput(scan_i, scan_j, planes_i, planes_j, T_prior, dt_s, matches, sigma_prior)],
                        drift, config)[0]


# The a-priori model of the planes and the trajectory is kept where the links' pooled sigma0 is
# within this factor of 1: no model of a real scanner is right to a few per cent, and a model
# that fits is not re-estimated (the estimate would only add its own noise).
MODEL_TOLERANCE = 1.1
# A link whose own variance factor exceeds this multiple of the links' median is left out of the
# pooled estimates (a wrong plane match, not the model: 3 times the median sigma0).
_OUTLYING_LINK = 9.0
_MODEL_ITERATIONS = 30
# The planes' departure is estimated per size class: a large floor's tilt departs less than a
# small patch's. The classes are half decades of area (1, 3.2, 10, 32, 100, 316 m^2, ...); a class
# with fewer matched planes than this joins the next smaller one.
_CLASS_EDGES_M2 = tuple(10.0 ** (k / 2) for k in range(8))
_MIN_CLASS_PLANES = 30


@dataclass(frozen=True)
class LinkModel:
    """What the links say of their observations' model, where the a-priori one does not fit them.

    A plane fitted to a real surface errs by the surface's own departure from a plane (floors by
    millimetres over metres, walls that bow, the quasi-static scan's own blur), which does not
    shrink with the number of points: two scans see different parts of the surface and their
    planes differ by it. It enters every plane as an additive covariance: a tilt about each
    tangent and an offset at the plane's centroid, per size class of the planes (half decades of
    area, ``area_edges_m2`` between the classes; ``departure_tilt_rad[k]``, ``departure_offset_m[k]`` of class k). The
    trajectory's relative poses (the pairs' priors) may err by more than the drift model says:
    their variances are multiplied by ``prior_variance_factor`` (never below 1). All are variance
    components estimated over all links at once (:func:`estimate_link_model`).
    ``sigma0_a_priori`` is the links' pooled sigma0 under the a-priori model, ``sigma0_estimated``
    under this one; ``n_links`` the links pooled.
    """

    departure_tilt_rad: tuple[float, ...] = ()
    departure_offset_m: tuple[float, ...] = ()
    prior_variance_factor: float = 1.0
    area_edges_m2: tuple[float, ...] = ()
    sigma0_a_priori: float = float("nan")
    sigma0_estimated: float = float("nan")
    n_links: int = 0

    @property
    def estimated(self) -> bool:
        """Whether the model differs from the a-priori one."""
        return bool(any(v > 0.0 for v in (*self.departure_tilt_rad, *self.departure_offset_m))
                    or self.prior_variance_factor > 1.0)

    def size_class(self, plane: Plane) -> int:
        return int(np.searchsorted(self.area_edges_m2, plane.area_m2))

    def departure_cov(self, plane: Plane) -> FloatArray:
        """The departure's covariance of ``plane``'s (tilt u, tilt v, d)."""
        k = self.size_class(plane)
        return _departure_cov(plane, self.departure_tilt_rad[k] ** 2, self.departure_offset_m[k] ** 2)

    def apply(self, planes: Sequence[Plane]) -> tuple[Plane, ...]:
        """``planes`` with the departure added to their covariances."""
        if not self.departure_tilt_rad:
            return tuple(planes)
        return tuple(replace(p, cov_uvd=p.cov_uvd + self.departure_cov(p)) for p in planes)

    def as_dict(self) -> dict[str, object]:
        def finite(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {"estimated": self.estimated, "n_links": self.n_links,
                "sigma0_a_priori": finite(self.sigma0_a_priori), "sigma0_estimated": finite(self.sigma0_estimated),
                "area_edges_m2": list(self.area_edges_m2),
                "size_classes_m2": self.size_classes() if self.departure_tilt_rad else [],
                "departure_tilt_mrad": [1000.0 * v for v in self.departure_tilt_rad],
                "departure_offset_mm": [1000.0 * v for v in self.departure_offset_m],
                "prior_sigma_factor": float(np.sqrt(self.prior_variance_factor))}

    def size_classes(self) -> list[str]:
        """The size classes' names (areas in m^2): "< 10", "10-32", ..., ">= 316"."""
        edges = [f"{e:.0f}" for e in self.area_edges_m2]
        if not edges:
            return ["all"]
        return [f"< {edges[0]}", *(f"{a}-{b}" for a, b in itertools.pairwise(edges)), f">= {edges[-1]}"]

    def describe(self) -> str:
        """The model in words, for a log line."""
        planes = ", ".join(f"{1000 * t:.1f} mrad / {1000 * o:.1f} mm ({c} m^2)" for c, t, o in
                           zip(self.size_classes(), self.departure_tilt_rad, self.departure_offset_m, strict=True))
        return (f"planes depart from their surfaces by {planes}; the trajectory's relative poses err "
                f"{np.sqrt(self.prior_variance_factor):.2f} times as much as the drift model says")


def _departure_cov(plane: Plane, var_tilt: float, var_offset: float) -> FloatArray:
    """(tilt u, tilt v, d) of a departure by ``var_tilt`` about each tangent and ``var_offset`` at
    the centroid: ``d = e_c + (u.c) a + (v.c) b``."""
    J = np.eye(3)
    J[2, :2] = plane.basis_uv @ plane.centroid_xyz
    return J @ np.diag([var_tilt, var_tilt, var_offset]) @ J.T


def pooled_sigma0(links: Sequence[Link]) -> tuple[float, int]:
    """The links' pooled sigma0 (sqrt of the sum of their weighted squared residuals over the sum
    of their redundancies), links far beyond the median left out (:data:`_OUTLYING_LINK`), and
    the number pooled. NaN without a link that has planes."""
    with_planes = [link for link in links if link.redundancy > 0 and np.isfinite(link.sigma0)]
    if not with_planes:
        return float("nan"), 0
    f = np.array([link.sigma0**2 for link in with_planes])
    r = np.array([link.redundancy for link in with_planes], dtype=float)
    keep = f <= _OUTLYING_LINK * max(float(np.median(f)), 1e-12)
    return float(np.sqrt(np.sum(f[keep] * r[keep]) / np.sum(r[keep]))), int(keep.sum())


def _area_edges(states: Sequence[_PairState]) -> tuple[float, ...]:
    """The edges between the size classes of the matched planes (:data:`_CLASS_EDGES_M2`), each
    class holding at least :data:`_MIN_CLASS_PLANES` of them where there are that many."""
    areas = np.array([p.area_m2 for s in states for m in s.active
                      for p in (s.by_id_i[m.plane_i], s.by_id_j[m.plane_j])])
    edges = [e for e in _CLASS_EDGES_M2 if areas.min() < e < areas.max()]
    while edges:
        counts = np.bincount(np.searchsorted(edges, areas), minlength=len(edges) + 1)
        sparse = np.flatnonzero(counts < _MIN_CLASS_PLANES)
        if not len(sparse):
            break
        k = int(sparse[-1])  # the largest sparse class joins the next smaller one (the first: the next larger)
        del edges[max(k - 1, 0)]
    return tuple(edges)


def estimate_link_model(pairs: Sequence[PairInput], drift: DriftConfig, config: PairwiseConfig,
                        start_tilt_rad: float = 1e-4, start_offset_m: float = 3e-4) -> LinkModel:
    """The observations' model that the links of ``pairs`` fit, estimated from all of them
    before any link is tested: the planes' departure from a plane (tilt, offset; additive; per
    size class) and a factor of the priors' variances, as variance components (Foerstner's
    iteration: each component scaled by its share of the weighted squared residuals over its
    share of the redundancy, ``e^T W C_k W e / tr(W C_k W Q_ee)``, pooled over the links; links far
    beyond the median left out, :data:`_OUTLYING_LINK`). The additive components start from
    ``start_tilt_rad`` and ``start_offset_m`` and stay positive; the prior's factor is not taken
    below 1. Returns the a-priori model (nothing estimated) where the links fit it within
    :data:`MODEL_TOLERANCE`."""
    states = [_PairState(pair, drift, config) for pair in pairs if pair.matches]
    if not states:
        return LinkModel()
    edges = _area_edges(states)
    n_classes = len(edges) + 1
    var = np.array([start_tilt_rad**2] * n_classes + [start_offset_m**2] * n_classes)
    factor = 1.0
    sigma0_prior = float("nan")
    for iteration in range(_MODEL_ITERATIONS + 1):
        model = LinkModel(tuple(np.sqrt(var[:n_classes])), tuple(np.sqrt(var[n_classes:])), factor, edges)
        sums = _component_sums([_PairState(s.pair, drift, config, model if iteration else None) for s in states],
                               config, model)
        f = sums[:, 0] / np.maximum(sums[:, 1], 1e-12)  # each link's own variance factor
        keep = f <= _OUTLYING_LINK * max(float(np.median(f)), 1e-12)
        total = sums[keep].sum(axis=0)
        sigma0 = float(np.sqrt(total[0] / total[1]))
        if iteration == 0:
            sigma0_prior = sigma0
            if sigma0 <= MODEL_TOLERANCE:
                return LinkModel(sigma0_a_priori=sigma0, sigma0_estimated=sigma0, n_links=int(keep.sum()))
            continue
        q, r = total[2::2], np.maximum(total[3::2], 1e-12)  # per component: tilt, offset per class; the prior
        new_var = var * q[:-1] / r[:-1]
        new_factor = max(1.0, factor * q[-1] / r[-1])
        moved = float(np.max(np.abs(np.log(np.maximum(np.append(new_var, new_factor), 1e-30)
                                           / np.maximum(np.append(var, factor), 1e-30)))))
        var, factor = new_var, new_factor
        if moved < 0.01:
            break
    model = LinkModel(tuple(float(v) for v in np.sqrt(var[:n_classes])),
                      tuple(float(v) for v in np.sqrt(var[n_classes:])), float(factor), edges, sigma0_prior, sigma0,
                      int(keep.sum()))
    log.warning("the links do not fit the a-priori model of the planes and the trajectory (pooled sigma0 %.2f over "
                "%d links); estimated from them: %s", sigma0_prior, model.n_links, model.describe())
    return model


def _component_sums(states: list[_PairState], config: PairwiseConfig, model: LinkModel) -> FloatArray:
    """Per pair (in order): its weighted squared residuals and redundancy, then for each
    component of ``model`` (tilt and offset departure per size class, the prior) its share of
    both: (n, 2 + 2 (2 C + 1)) for C size classes."""
    n_classes = len(model.area_edges_m2) + 1
    out = np.zeros((len(states), 2 + 2 * (2 * n_classes + 1)))
    groups: dict[int, list[int]] = {}
    for k, s in enumerate(states):
        groups.setdefault(len(s.active), []).append(k)
    for members in groups.values():
        design = _Design([states[k] for k in members])
        sol = _solve(design, config.max_iterations)
        W = sol["W"]
        We = np.einsum("gij,gj->gi", W, sol["w"])
        WQ = W @ sol["Q_ee"]
        part = [states[k] for k in members]
        for c in range(2 * n_classes):
            C = _component_q_ww(design, sol, part, model, c % n_classes, c < n_classes)
            out[members, 2 + 2 * c] = np.einsum("gi,gij,gj->g", We, C, We)
            out[members, 3 + 2 * c] = np.einsum("gij,gji->g", W @ C, WQ)
        P = design.p_prior
        out[members, -2] = np.einsum("gi,gi,gi->g", sol["xi"], P, sol["xi"])
        out[members, -1] = 6.0 - np.einsum("gi,gii->g", P, sol["Q_xx"])
        out[members, 0] = sol["omega"]
        out[members, 1] = 3.0 * np.array([len(s.active) for s in part])
    return out


def _component_q_ww(design: _Design, sol: dict, part: list[_PairState], model: LinkModel, size_class: int,
                    tilt: bool) -> FloatArray:
    """The conditions' covariance (g, 3m, 3m) from one departure component of unit size (the tilt
    or the offset of one size class) on the planes of that class, at the solution."""
    var_t, var_o = (1.0, 0.0) if tilt else (0.0, 1.0)

    def cov(p: Plane) -> FloatArray:
        return _departure_cov(p, var_t, var_o) if model.size_class(p) == size_class else np.zeros((3, 3))

    shape = design.cov_a.shape
    cov_a = np.array([cov(s.by_id_i[m.plane_i]) for s in part for m in s.active]).reshape(shape)
    cov_b = np.array([cov(s.by_id_j[m.plane_j]) for s in part for m in s.active]).reshape(shape)
    return design.conditions_covariance(sol["R"], sol["t"], cov_a, cov_b)
