"""Data snooping and variance components of the block adjustment (kinreg.estimate.block): which
observations one round rejects, which rejections come back, and the variance factor per
observation kind."""

from __future__ import annotations

import numpy as np
from scipy import stats

from kinreg.types import ObservationTest, RelativeObservation


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


def worst_outliers(tests: list[ObservationTest], alpha: float, budget: int) -> list[ObservationTest]:
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


def variance_components(tests: list[ObservationTest], weights: dict[str, float],
                         alpha: float) -> dict[str, float]:
    """Förstner's estimate per observation kind: sigma_g^2 = (e^T P e)_g / r_g with the current
    weights; a group's weight is divided by sigma_g^2, never above the a-priori weight, and
    lowered only where its own chi-square test rejects the current model
    (``(e^T P e)_g > chi2(1 - alpha, r_g)``).
    Kinds with too little redundancy (< 5) keep their weight: their component cannot be estimated.
    """
    new = dict(weights)
    for kind in weights:
        group = [t for t in tests if t.kind.value == kind and not t.rejected]
        r = sum(t.redundancy for t in group)
        if r < 5:
            continue
        omega = sum(t.vtpv for t in group)
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
