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

import logging
import math

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
    """The observations and the linearised model of one pair for a set of matches, as arrays over
    the matches (a pair has tens of them, a run tens of thousands of pairs a round)."""

    def __init__(self, planes_i: dict[int, Plane], planes_j: dict[int, Plane], matches: list[PlaneMatch]):
        self.matches = matches
        used_i = sorted({m.plane_i for m in matches})
        used_j = sorted({m.plane_j for m in matches})
        # Observation blocks: 3 per used plane, first those of scan i, then those of scan j.
        self.block_i = {pid: 3 * k for k, pid in enumerate(used_i)}
        self.block_j = {pid: 3 * (len(used_i) + k) for k, pid in enumerate(used_j)}
        n_obs = 3 * (len(used_i) + len(used_j))
        self.Q_ll = np.zeros((n_obs, n_obs))
        for pid, k in self.block_i.items():
            self.Q_ll[k:k + 3, k:k + 3] = planes_i[pid].cov_uvd
        for pid, k in self.block_j.items():
            self.Q_ll[k:k + 3, k:k + 3] = planes_j[pid].cov_uvd
        self.a = [planes_i[m.plane_i] for m in matches]
        self.b = [planes_j[m.plane_j] for m in matches]
        self.n_a = np.array([p.normal for p in self.a]).reshape(-1, 3)
        self.d_a = np.array([p.d_m for p in self.a])
        self.uv_a = np.array([p.basis_uv for p in self.a]).reshape(-1, 2, 3)
        self.n_b = np.array([p.normal for p in self.b]).reshape(-1, 3)
        self.d_b = np.array([p.d_m for p in self.b])
        self.uv_b = np.array([p.basis_uv for p in self.b]).reshape(-1, 2, 3)
        self.skew_b = skew(self.n_b)
        # B: rows 3k..3k+2 of match k are -I against the columns of its plane a and a block set by
        # linearise against those of its plane b.
        m_count = len(matches)
        rows = np.broadcast_to(3 * np.arange(m_count)[:, None, None] + np.arange(3)[None, :, None], (m_count, 3, 3))
        cols_i = np.array([self.block_i[m.plane_i] for m in matches], dtype=int).reshape(-1, 1, 1)
        cols_j = np.array([self.block_j[m.plane_j] for m in matches], dtype=int).reshape(-1, 1, 1)
        self.B_i = np.zeros((3 * m_count, n_obs))
        self.B_i[rows, cols_i + np.arange(3)[None, None, :]] = -np.eye(3)
        self.B_j_index = (rows, cols_j + np.arange(3)[None, None, :])

    def linearise(self, R: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Misclosures w (3m,), A = dc/dxi (3m, 6) and B = dc/dl (3m, n_obs) at ``T = (R, t)``."""
        m_count = len(self.matches)
        m = self.n_b @ R.T  # R n_b of every match
        w = np.empty((m_count, 3))
        w[:, :2] = np.einsum("kci,ki->kc", self.uv_a, m - self.n_a)
        w[:, 2] = self.d_b + m @ t - self.d_a
        dm_dphi = -(R @ self.skew_b)  # (m, 3, 3)
        A = np.zeros((m_count, 3, 6))
        A[:, :2, 3:] = np.einsum("kci,kij->kcj", self.uv_a, dm_dphi)
        A[:, 2, :3] = self.n_b  # d(m . (t + R rho))/drho = m^T R = n_b^T
        A[:, 2, 3:] = t @ dm_dphi
        B = self.B_i.copy()
        Ruv_b = self.uv_b @ R.T  # (m, 2, 3): R u_b, R v_b
        block = np.zeros((m_count, 3, 3))
        block[:, :2, :2] = np.einsum("kci,kdi->kcd", self.uv_a, Ruv_b)
        block[:, 2, :2] = Ruv_b @ t
        block[:, 2, 2] = 1.0
        B[self.B_j_index] = block
        return w.reshape(-1), A.reshape(-1, 6), B


def _pinv_symmetric(Q: FloatArray) -> FloatArray:
    """``np.linalg.pinv(Q, hermitian=True)`` of a symmetric ``Q`` from its eigenvectors, without
    the SVD wrapper's cost (the same cutoff, 1e-15 of the largest eigenvalue's size)."""
    eigval, eigvec = np.linalg.eigh(Q)
    size = np.abs(eigval)
    large = size > 1e-15 * size.max(initial=0.0)
    inverse = np.divide(1.0, eigval, out=np.zeros_like(eigval), where=large)
    return (eigvec * inverse) @ eigvec.T


def _so3(phi: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """The rotation matrix of the rotation vector ``phi`` (3,) and its left Jacobian:
    :meth:`Pose.exp`'s formulas for one small twist, without the quaternions between them
    (a pair's solve takes a handful of steps, and the poses' general code cost more than the rest)."""
    x, y, z = phi.tolist()
    theta = math.sqrt(x * x + y * y + z * z)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    if theta < 1e-5:
        a, b, c = 1.0 - theta**2 / 6.0, 0.5 - theta**2 / 24.0, 1.0 / 6.0 - theta**2 / 120.0
    else:
        a, b, c = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta**2, (theta - math.sin(theta)) / theta**3
    K2 = K @ K
    return _EYE3 + a * K + b * K2, _EYE3 + b * K + c * K2


def _log(R: FloatArray, t: FloatArray) -> FloatArray:
    """The twist ``(rho, phi)`` (6,) of the pose ``(R, t)``, as :meth:`Pose.log` (angles below pi)."""
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # sin(angle) axis
    sine = math.sqrt(float(v @ v))
    theta = math.atan2(sine, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0))
    phi = v * (theta / sine) if sine > 0.0 else v
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-5:
        c = 1.0 / 12.0 + theta**2 / 720.0
    else:
        c = 1.0 / theta**2 - (1.0 + math.cos(theta)) / (2.0 * theta * math.sin(theta))
    return np.concatenate([(_EYE3 - 0.5 * K + c * (K @ K)) @ t, phi])


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def _solve(design: _Design, T_prior: Pose, P_prior: FloatArray, max_iterations: int) -> dict:
    # The iterate as a rotation matrix and a translation: T <- T exp(step), xi = log(T_prior^-1 T).
    R_prior, t_prior = T_prior.rotation_matrix, T_prior.t_xyz
    R, t = R_prior, t_prior
    xi = np.zeros(6)
    for _ in range(max_iterations):
        w, A, B = design.linearise(R, t)
        Q_ww = B @ design.Q_ll @ B.T
        # pinv: conditions that repeat one another (one plane matched to two coplanar patches
        # twice over) leave Q_ww singular; they then count once.
        W = _pinv_symmetric(Q_ww)
        AtW = A.T @ W
        N_p = AtW @ A
        N = N_p + P_prior
        step = np.linalg.solve(N, -(AtW @ w + P_prior @ xi))
        R_step, J_step = _so3(step[3:])
        R, t = R @ R_step, R @ (J_step @ step[:3]) + t
        xi = _log(R_prior.T @ R, R_prior.T @ (t - t_prior))
        if np.max(np.abs(step)) < 1e-11:
            break
    w, A, B = design.linearise(R, t)
    Q_ww = B @ design.Q_ll @ B.T
    W = _pinv_symmetric(Q_ww)
    N_p = A.T @ W @ A
    Q_xx = np.linalg.inv(N_p + P_prior)
    Q_ee = Q_ww - A @ Q_xx @ A.T
    # The quaternion on the prior's side, as composing small steps onto the prior's kept it.
    q = matrix_to_quat(R)
    T = Pose(-q if float(q @ T_prior.quat_wxyz) < 0.0 else q, t)
    return {"T": T, "xi": xi, "w": w, "A": A, "W": W, "N_p": N_p, "Q_xx": Q_xx,
            "Q_ee": Q_ee, "omega": float(w @ W @ w + xi @ P_prior @ xi)}


def _match_statistics(sol: dict, n_matches: int) -> tuple[FloatArray, FloatArray]:
    """Per match: the 3-dof test statistic e^T Q_ee^+ e, and the largest normalised residual."""
    e = sol["w"].reshape(n_matches, 3)
    k = np.arange(n_matches)
    blocks = sol["Q_ee"].reshape(n_matches, 3, n_matches, 3)[k, :, k, :]  # (m, 3, 3) diagonal blocks
    test = np.einsum("ki,kij,kj->k", e, np.linalg.pinv(blocks, rcond=1e-10), e)
    diag = np.diagonal(blocks, axis1=1, axis2=2)
    normalised = np.max(np.abs(e) / np.sqrt(np.maximum(diag, 1e-30)), axis=1)
    return test, normalised


def _plane_only(sol: dict) -> tuple[Pose, FloatArray, int, FloatArray]:
    """Plane-only estimate: the pose the planes alone point to (moved only along determined
    directions), the information matrix, its rank, and per-axis standard deviations."""
    N_p = 0.5 * (sol["N_p"] + sol["N_p"].T)
    eigval, eigvec = np.linalg.eigh(N_p)
    determined = eigval > _RANK_TOLERANCE * max(float(eigval[-1]), 1e-300)
    rank = int(np.count_nonzero(determined))
    g = sol["A"].T @ sol["W"] @ sol["w"]
    inv = (eigvec[:, determined] / eigval[determined]) @ eigvec[:, determined].T
    step = -inv @ g
    T_planes = sol["T"].compose(Pose.exp(step))
    null_share = np.sum(eigvec[:, ~determined] ** 2, axis=1)
    axis_sigma = np.where(null_share > 1e-2, np.inf, np.sqrt(np.maximum(np.diag(inv), 0.0)))
    return T_planes, N_p, rank, axis_sigma


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
    if sigma_prior is None:
        sigma_prior = drift_sigmas(abs(dt_s), drift)
    P_prior = np.diag(1.0 / sigma_prior**2)
    by_id_i = {p.plane_id: p for p in planes_i}
    by_id_j = {p.plane_id: p for p in planes_j}
    # A plane pair stated twice would make two identical conditions (a singular Q_ww).
    active = list({(m.plane_i, m.plane_j): m for m in matches}.values())
    rejected: list[PlaneMatch] = []
    max_rejected = int(np.floor(config.max_rejected_share * len(matches)))
    sol: dict | None = None
    normalised = np.zeros(0)
    while active:
        sol = _solve(_Design(by_id_i, by_id_j, active), T_prior, P_prior, config.max_iterations)
        test, normalised = _match_statistics(sol, len(active))
        critical = chi2_quantile(1.0 - config.alpha, 3)
        worst = int(np.argmax(test))
        if test[worst] <= critical or len(rejected) >= max_rejected:
            break
        log.debug("link %d-%d: rejected plane pair %s (test %.1f > %.1f)", scan_i, scan_j, active[worst],
                  test[worst], critical)
        rejected.append(active.pop(worst))
        sol = None

    if sol is None:
        zeros = np.zeros((6, 6))
        return Link(scan_i, scan_j, LinkStatus.PRIOR_ONLY, T_prior, np.diag(sigma_prior**2), T_prior, T_prior,
                    zeros, 0, np.full(6, np.inf), 0, float("nan"), 0, True, (), tuple(rejected), 0.0, dt_s)

    redundancy = 3 * len(active)
    sigma0 = float(np.sqrt(sol["omega"] / redundancy))
    passed = bool(sol["omega"] <= chi2_quantile(1.0 - config.alpha, redundancy))
    T_planes, N_p, rank, axis_sigma = _plane_only(sol)
    R_i = np.array([by_id_i[m.plane_i].normal for m in active])
    # A failed global test alone is reported, not fatal (it happens at rate alpha by chance); a link
    # is rejected when snooping hit its cap and the test still fails: too many wrong matches.
    status = LinkStatus.REJECTED if (not passed and len(rejected) >= max(max_rejected, 1)) else LinkStatus.OK
    return Link(
        scan_i=scan_i,
        scan_j=scan_j,
        status=status,
        T_i_j=sol["T"],
        cov_xi=sol["Q_xx"],
        T_i_j_prior=T_prior,
        T_i_j_planes=T_planes,
        info_planes=N_p,
        rank=rank,
        axis_sigma_planes=axis_sigma,
        n_directions=count_directions(R_i),
        sigma0=sigma0,
        redundancy=redundancy,
        global_test_passed=passed,
        matches=tuple(active),
        rejected=tuple(rejected),
        max_normalised_residual=float(normalised.max()),
        dt_s=dt_s,
    )
