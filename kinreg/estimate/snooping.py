"""Data snooping and variance components of the block adjustment (kinreg.estimate.block): which
observations one round rejects, which rejections come back, and the variance factor per
observation kind."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import numpy as np

from kinreg.estimate.sparse import SparseFactor, in_threads, selected_inverse
from kinreg.geometry import FloatArray
from kinreg.types import ObservationKind, ObservationTest, RelativeObservation


@dataclasses.dataclass(frozen=True)
class ObservationTests:
    """The figures of :class:`~kinreg.types.ObservationTest` for many observations, as arrays (k,)
    (``kind``: the :class:`~kinreg.types.ObservationKind` values; ``cov_adjusted`` (k, 6, 6))."""

    index: np.ndarray
    kind: np.ndarray
    i: np.ndarray
    j: np.ndarray
    statistic: np.ndarray
    dof: np.ndarray
    redundancy: np.ndarray
    normalised: np.ndarray
    rejected: np.ndarray
    vtpv: np.ndarray
    min_redundancy: np.ndarray
    cov_adjusted: np.ndarray | None = None
    residual: np.ndarray | None = None  # (k, 6)

    @classmethod
    def from_tests(cls, tests: Sequence[ObservationTest]) -> ObservationTests:
        def column(name: str, dtype: type) -> np.ndarray:
            return np.array([getattr(t, name) for t in tests], dtype=dtype).reshape(-1)

        return cls(column("index", int), np.array([t.kind.value for t in tests], dtype=str).reshape(-1),
                   column("i", int), column("j", int), column("statistic", float), column("dof", int),
                   column("redundancy", float), column("normalised", float), column("rejected", bool),
                   column("vtpv", float), column("min_redundancy", float))

    def __len__(self) -> int:
        return len(self.index)

    def as_tests(self) -> list[ObservationTest]:
        """One :class:`ObservationTest` per observation, in the order of the arrays."""
        kinds = {k.value: k for k in ObservationKind}
        # a rejected observation was not tested: no covariance of what it observes
        blocks = [None] * len(self) if self.cov_adjusted is None else list(self.cov_adjusted)  # views
        cov = [None if rejected else c for c, rejected in zip(blocks, self.rejected.tolist(), strict=True)]
        residual = [None] * len(self) if self.residual is None else list(self.residual)  # views
        rows = zip(self.index.tolist(), [kinds[k] for k in self.kind.tolist()], self.i.tolist(), self.j.tolist(),
                   self.statistic.tolist(), self.dof.tolist(), self.redundancy.tolist(), self.normalised.tolist(),
                   self.rejected.tolist(), self.vtpv.tolist(), self.min_redundancy.tolist(), cov, residual,
                   strict=True)
        return [ObservationTest(index, kind, i, j, statistic, dof, redundancy, normalised, rejected, vtpv,
                                min_redundancy=least, cov_adjusted=c, residual=e)
                for index, kind, i, j, statistic, dof, redundancy, normalised, rejected, vtpv, least, c, e in rows]


def taken_back(last_round: list[int], observations: list[RelativeObservation], free_index: np.ndarray,
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


# Observations per step of the tests: temporaries of a few MB, reused by the allocator, rather than
# (k, 6, 6) arrays of all observations (fresh pages from the kernel each).
_CHUNK = 1 << 14


def observation_tests(e: FloatArray, J: FloatArray, P: FloatArray, cols: np.ndarray, factor: SparseFactor,
                      eig: tuple[FloatArray, FloatArray] | None = None) -> tuple[tuple[np.ndarray, ...], FloatArray]:
    """Per-observation statistics from the cofactor of the residuals, Q_ee = P^+ - J Qxx J^T,
    vectorised over observations (each restricted to the directions its information determines).

    ``e`` (k, 6) residuals, ``J`` (k, slots, 6, 6) their Jacobians, ``P`` (k, 6, 6) weights,
    ``cols`` (k, slots) the unknown blocks of the slots (-1: none), ``factor`` of the normal matrix
    (block ordered), ``eig`` the eigenvalues and vectors of ``P`` if at hand. Returns
    ``(statistic, dof, redundancy, normalised, vtpv, min_redundancy, cov_adjusted)``
    (k,) each (``cov_adjusted`` (k, 6, 6): of the relative pose from the first two slots) and the
    diagonal blocks of Qxx.
    """
    slot_pairs = [(s, t) for s in range(3) for t in range(s + 1, 3)]
    both = [(cols[:, s] >= 0) & (cols[:, t] >= 0) for s, t in slot_pairs]
    pairs = np.concatenate([np.column_stack([cols[ok, s], cols[ok, t]]) for (s, t), ok in zip(slot_pairs, both,
                                                                                              strict=True)])
    diag, off = selected_inverse(None, 6, pairs.astype(int).reshape(-1, 2), factor=factor)
    # per slot pair and observation: its block in ``off`` (-1: not both slots free)
    offsets = np.cumsum([0] + [int(np.count_nonzero(ok)) for ok in both])
    off_at = []
    for m, ok in enumerate(both):
        at = -np.ones(len(e), dtype=np.int64)
        at[ok] = offsets[m] + np.arange(offsets[m + 1] - offsets[m])
        off_at.append(at)
    slots = [s for s in range(cols.shape[1]) if (cols[:, s] >= 0).any()]
    k = len(e)
    statistic, r_k, normalised, vtpv, least = (np.empty(k) for _ in range(5))
    dof = np.empty(k, dtype=np.int64)
    cov_adjusted = np.empty((k, 6, 6))

    def step(start: int) -> None:
        c = slice(start, min(start + _CHUNK, k))
        w, V = np.linalg.eigh(0.5 * (P[c] + np.transpose(P[c], (0, 2, 1)))) if eig is None else (eig[0][c], eig[1][c])
        figures = _figures(e[c], J[c], cols[c], slots, [at[c] for at in off_at], diag, off, w, V)
        statistic[c], dof[c], r_k[c], normalised[c], vtpv[c], least[c], cov_adjusted[c] = figures

    in_threads(step, range(0, k, _CHUNK), len(diag))
    return (statistic, dof, r_k, normalised, vtpv, least, cov_adjusted), diag


def _figures(e: FloatArray, J: FloatArray, cols: np.ndarray, slots: list[int], off_at: list[np.ndarray],
             diag: FloatArray, off: FloatArray, w: FloatArray, V: FloatArray) -> tuple[np.ndarray, ...]:
    """:func:`observation_tests`' figures of some observations (``off_at``: per slot pair their blocks
    in ``off``, -1: none; ``w``, ``V``: the eigenvalues and vectors of their weights)."""
    slot_pairs = [(s, t) for s in range(3) for t in range(s + 1, 3)]
    # Over all observations with contiguous operands (zero blocks where a slot is not free): numpy's
    # small-matrix products are several times faster so than on gathered or transposed views.
    J_s = {s: np.ascontiguousarray(J[:, s]) for s in slots}
    J_sT = {s: np.ascontiguousarray(np.transpose(Js, (0, 2, 1))) for s, Js in J_s.items()}
    JQJ = np.zeros((len(e), 6, 6))
    for group in ((0, 1), (2,)):  # the relative pose's slots, then the drift velocity's
        for s in group:
            if s in J_s:
                ok = cols[:, s] >= 0
                Q = np.zeros_like(JQJ)
                Q[ok] = diag[cols[ok, s]]
                JQJ += J_s[s] @ Q @ J_sT[s]
        for (s, t), at in zip(slot_pairs, off_at, strict=True):
            ok = at >= 0
            if t not in group or not ok.any():
                continue
            Q = np.zeros_like(JQJ)
            Q[ok] = off[at[ok]]
            cross = J_s[s] @ Q @ J_sT[t]
            JQJ += cross + np.transpose(cross, (0, 2, 1))
        if group == (0, 1):
            cov_adjusted = JQJ.copy()  # of the adjusted relative pose (without the drift's share)
    del J_s, J_sT
    determined = w > 1e-9 * np.maximum(w[:, -1:], 1e-300)
    w = np.where(determined, w, 1.0)
    z = np.where(determined, np.einsum("kai,ka->ki", V, e), 0.0)
    VJV = np.transpose(V, (0, 2, 1)) @ JQJ @ V
    del JQJ, V
    mask2 = determined[:, :, None] & determined[:, None, :]
    Q_zz = np.where(mask2, np.eye(6) / w[:, :, None] - VJV, np.eye(6) * (~mask2))
    dof = determined.sum(axis=1)
    r_k = np.sum(np.where(determined, 1.0 - w * np.diagonal(VJV, axis1=1, axis2=2), 0.0), axis=1)
    # Redundancy per direction: eigenvalues of I - W^1/2 V^T J Qxx J^T V W^1/2 (determined part).
    sw = np.where(determined, np.sqrt(w), 0.0)
    R_dir = np.eye(6) * determined[:, :, None] - sw[:, :, None] * VJV * sw[:, None, :]
    del VJV
    r_dir = np.linalg.eigvalsh(R_dir + np.eye(6) * (~determined)[:, :, None])  # undetermined: 1, never least
    del R_dir
    vtpv = np.sum(np.where(determined, w * z**2, 0.0), axis=1)
    # z^T Q_zz^+ z, the pseudo-inverse as numpy's pinv(rcond=1e-9, hermitian=True) forms it
    q, U = np.linalg.eigh(Q_zz)
    large = np.abs(q) > 1e-9 * np.max(np.abs(q), axis=1, keepdims=True)
    statistic = np.sum(np.where(large, np.einsum("kai,ka->ki", U, z) ** 2 / np.where(large, q, 1.0), 0.0), axis=1)
    # An uncontrolled observation (redundancy ~ 0) cannot be tested, nor one whose cofactor is not
    # positive (an unconverged state: the normal matrix is not its residuals' own).
    statistic = np.where((r_k > 1e-6) & (statistic > -1e-9), np.maximum(statistic, 0.0), np.nan)
    # A negative statistic (an indefinite Q_zz, far from the solution) has no normalised value.
    normalised = np.sqrt(np.where(statistic >= 0, statistic, np.nan) / np.maximum(dof, 1))
    return statistic, dof, r_k, normalised, vtpv, r_dir[:, 0], cov_adjusted


@functools.lru_cache(maxsize=1024)
def chi2_quantile(p: float, dof: float) -> float:
    """``scipy.stats.chi2.ppf(p, dof)``, once per (p, dof). scipy.stats is imported here, when a
    quantile is first needed: it costs about 0.7 CPU s, which the plane workers (that never test
    anything) would otherwise pay each; and scipy's call costs more than a small pair's solve."""
    from scipy import stats

    return float(stats.chi2.ppf(p, dof))


@functools.lru_cache(maxsize=1024)
def f_quantile(p: float, dof1: float, dof2: float) -> float:
    """``scipy.stats.f.ppf(p, dof1, dof2)``, once per arguments; scipy.stats imported as in
    :func:`chi2_quantile`."""
    from scipy import stats

    return float(stats.f.ppf(p, dof1, dof2))


def trajectory_misfits(tests: Sequence[ObservationTest], alpha: float) -> list[ObservationTest]:
    """The trajectory's links that disagree with the adjusted network beyond what one of them may
    (chi-square at ``alpha`` over their number), the worst first. They are never rejected, so such
    a misfit means that plane links moved stations against the trajectory (a wrong match the tests
    did not find) or a jump the detector missed; the global test can pass all the same."""
    links = [t for t in tests if t.kind is ObservationKind.TRAJECTORY and np.isfinite(t.statistic)]
    if not links:
        return []
    critical = {dof: chi2_quantile(1.0 - alpha / len(links), dof) for dof in {t.dof for t in links}}
    return sorted((t for t in links if t.statistic > critical[t.dof]), key=lambda t: -t.statistic / critical[t.dof])


def wrong_match_misfits(misfits: Sequence[ObservationTest], offset_m: float, angle_deg: float) -> list[ObservationTest]:
    """The trajectory ``misfits`` that plane links agreeing on a wrong match can explain: those
    whose residual moves a station by at least the distance (``offset_m``) or turns it by the angle
    (``angle_deg``) at which two planes are distinct physical planes ([matching] coplanar_offset_m,
    coplanar_angle_deg). Matching two planes that are not one moves the station by their
    separation; a smaller misfit is the trajectory's model, a millimetre off where the drift model
    fits the run less well (a sample run with static scans, GNSS/INS-like drift: 0.76 mm at 2.4
    sigma, the stations 0.75 mm RMS from the truth). A misfit without its residual counts."""
    def separated(t: ObservationTest) -> bool:
        size = residual_size(t)
        return size is None or size[0] >= offset_m or size[1] >= np.radians(angle_deg)

    return [t for t in misfits if separated(t)]


def residual_size(test: ObservationTest) -> tuple[float, float] | None:
    """How far a pose observation's residual moves [m] and turns [rad] a station; None where its
    residual is unknown."""
    e = test.residual
    if e is None or not np.all(np.isfinite(e)):
        return None
    return float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))


def misfit_text(misfits: Sequence[ObservationTest]) -> str:
    """``misfits`` (:func:`trajectory_misfits`) in a line: how many, the worst five."""
    worst = ", ".join(f"{t.i}-{t.j} ({t.normalised:.0f} sigma{_moved_text(t)})" for t in misfits[:5])
    return f"{len(misfits)} pair(s) of consecutive stations: {worst}"


def _moved_text(test: ObservationTest) -> str:
    """``, 12.3 mm`` (how far its residual moves a station), or nothing where unknown."""
    size = residual_size(test)
    return "" if size is None else f", {1000.0 * size[0]:.1f} mm"


def worst_outliers(tests: ObservationTests, candidates: np.ndarray, alpha: float, budget: int) -> list[int]:
    """Positions in ``tests`` of the observations to reject in one round, worst first, among the
    ``candidates`` (bool, k): those above the critical value that are the worst among all such
    observations touching either of their stations (one per neighbourhood, so
    that an outlier's effect on its neighbours does not reject them too). An observation that
    alone determines some direction (its redundancy there below ``_MIN_DIRECTION_REDUNDANCY``) is
    never rejected: without it the network would be undetermined in that direction (a stretch
    whose planes leave it free, carried by the trajectory alone)."""
    dofs = np.unique(tests.dof[candidates])
    critical = np.full(len(tests), np.inf)
    for dof in dofs.tolist():
        at = tests.dof == dof
        critical[at] = chi2_quantile(1.0 - alpha, dof)
    with np.errstate(invalid="ignore"):
        bad = (candidates & np.isfinite(tests.statistic) & (tests.redundancy > 0.05) & (tests.statistic > critical)
               & ~(tests.min_redundancy < _MIN_DIRECTION_REDUNDANCY))
    bad = np.flatnonzero(bad)
    bad = bad[np.argsort(-(tests.statistic[bad] / critical[bad]), kind="stable")]
    taken: set[int] = set()
    chosen: list[int] = []
    for k in bad.tolist():
        i, j = int(tests.i[k]), int(tests.j[k])
        if i in taken or (j >= 0 and j in taken):
            continue
        chosen.append(k)
        taken.update((i, j))
        if len(chosen) >= budget:
            break
    return chosen


# How far a kind whose errors show in its residuals may be trusted above its a-priori model: its
# weight at most 25x (sigmas a fifth). Below that the plane floors (0.35 mm, 0.14 mrad) would fall under
# what a plane fit's own least squares give (1-3 mm of range noise over a few thousand points:
# 0.02-0.06 mm): no residuals can say a plane is better known than its points make it. A much
# lower cap would keep the sigmas of a kind whose residuals are far below its model (plane offsets:
# a tenth) well above its errors.
MAX_WEIGHT_GAIN = 25.0


def models_rejected(tests: Sequence[ObservationTest], components: dict[str, float], kinds: Sequence[str],
                    alpha: float) -> dict[str, float]:
    """The ``kinds`` whose residuals reject their a-priori model, with their variance factor
    against it: the group's weighted squares under the a-priori weights (its final ones times its
    variance component, ``components``) over its redundancy r, beyond chi-square(1 - alpha, r) / r.
    Kinds with a redundancy under 5 are not tested (as :func:`variance_components`)."""
    sums = {kind: [0.0, 0.0] for kind in kinds}  # redundancy, weighted squares: one pass over the tests
    for t in tests:
        group = sums.get(t.kind.value)
        if group is not None and not t.rejected and np.isfinite(t.vtpv):
            group[0] += t.redundancy
            group[1] += t.vtpv
    out = {}
    for kind, (r, vtpv) in sums.items():
        if r < 5:
            continue
        factor = components.get(kind, 1.0) * vtpv / r
        if factor > chi2_quantile(1.0 - alpha, r) / r:
            out[kind] = factor
    return out


def variance_components(tests: ObservationTests | Sequence[ObservationTest], weights: dict[str, float],
                         alpha: float, may_lower: frozenset[str] = frozenset()) -> dict[str, float]:
    """Förstner's estimate per observation kind: sigma_g^2 = (e^T P e)_g / r_g with the current
    weights; a group's weight is divided by sigma_g^2, never above the a-priori weight, and
    lowered only where its own chi-square test rejects the current model
    (``(e^T P e)_g > chi2(1 - alpha, r_g)``). The kinds in ``may_lower`` (whose errors all show in
    their residuals: the scan planes against the physical planes) take the estimate itself, up or
    down, to at most :data:`MAX_WEIGHT_GAIN` times the a-priori weight.
    Kinds with too little redundancy (< 5) keep their weight: their component cannot be estimated.
    """
    if not isinstance(tests, ObservationTests):
        tests = ObservationTests.from_tests(tests)
    new = dict(weights)
    for kind in weights:
        group = (tests.kind == kind) & ~tests.rejected
        r = float(tests.redundancy[group].sum())
        if r < 5:
            continue
        omega = float(tests.vtpv[group].sum())
        # Only ever inflate the a-priori model: errors shared by all links of a scan (plane-fit
        # systematics) and the trajectory's drift (smooth in time) are invisible in residuals,
        # so a factor below 1 would make the reported sigmas too optimistic. And only where the
        # residuals show the model too optimistic: at a low redundancy the estimate scatters
        # widely (r = 6, four control points: chi-square/6 exceeds 1 in 42% of draws of a right
        # model), so inflating on every estimate above 1 inflates on average. A group inflated too
        # far in an earlier round (by another group's misfit) goes back towards its a-priori weight.
        if kind in may_lower:
            # Their residuals show their whole error, so their component is the estimate itself,
            # not 1 until a test rejects: a group 0.7 of its model, with its r too small for the
            # test to tell, kept sigmas 1.2 times its errors.
            new[kind] = min(MAX_WEIGHT_GAIN, weights[kind] / max(omega / r, 1e-6))
            continue
        if omega > r and omega <= chi2_quantile(1.0 - alpha, r):
            continue
        new[kind] = min(1.0 if kind not in may_lower else max(1.0, weights[kind]), weights[kind] / max(omega / r, 1e-6))
    return new
