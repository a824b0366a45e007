"""Data snooping and variance components of the block adjustment (kinreg.estimate.block): which
observations one round rejects, which rejections come back, and the variance factor per
observation kind."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy import stats

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
        cov = [None if self.cov_adjusted is None or rejected else self.cov_adjusted[k]
               for k, rejected in enumerate(self.rejected.tolist())]
        rows = zip(self.index.tolist(), [kinds[k] for k in self.kind.tolist()], self.i.tolist(), self.j.tolist(),
                   self.statistic.tolist(), self.dof.tolist(), self.redundancy.tolist(), self.normalised.tolist(),
                   self.rejected.tolist(), self.vtpv.tolist(), self.min_redundancy.tolist(), cov, strict=True)
        return [ObservationTest(index, kind, i, j, statistic, dof, redundancy, normalised, rejected, vtpv,
                                min_redundancy=least, cov_adjusted=c)
                for index, kind, i, j, statistic, dof, redundancy, normalised, rejected, vtpv, least, c in rows]


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
        critical[at] = stats.chi2.ppf(1.0 - alpha, dof)
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


def variance_components(tests: ObservationTests | Sequence[ObservationTest], weights: dict[str, float],
                         alpha: float) -> dict[str, float]:
    """Förstner's estimate per observation kind: sigma_g^2 = (e^T P e)_g / r_g with the current
    weights; a group's weight is divided by sigma_g^2, never above the a-priori weight, and
    lowered only where its own chi-square test rejects the current model
    (``(e^T P e)_g > chi2(1 - alpha, r_g)``).
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
        if omega > r and omega <= stats.chi2.ppf(1.0 - alpha, r):
            continue
        new[kind] = min(1.0, weights[kind] / max(omega / r, 1e-6))
    return new
