"""The estimation strategy: how the quasi-static scans become an adjusted network.

One pass slices the runs, detects the planes, links the sequence neighbours and adjusts the
network with the drift it measures: the pairs are linked again from the adjusted poses until the
linked pairs and the drift's coupling settle (:func:`adjust_with_measured_drift`). The passes:

1. the first, with the configured windows;
2. where the measured drift smears the planes of those windows, one with shorter windows
   (:func:`_with_shorter_windows`);
3. where the attitude error shears the windows, one on points deskewed with the adjustment
   (:func:`_with_deskewed_points`);

and the decision whether the chosen network is a result (:func:`_failure`).

The strategy never sees where it runs: it is handed the operations it needs
(:class:`Operations`: slice, detect and link; link again; a pass adjusted) the way Open3D's
multiway registration takes its pairwise step. :mod:`kinreg.run.estimation` builds them on the
stage cache, the executor and the spill.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Generic, Protocol, TypeVar

import numpy as np

from kinreg.config import BlockConfig, DriftConfig, KinregConfig, MatchingConfig, PlanesConfig, SlicingConfig
from kinreg.errors import AdjustmentFailedError
from kinreg.estimate.datum import adjust_network, screen_control_points
from kinreg.estimate.drift import (
    MAP_NEIGHBOURS,
    MIXED_COUPLING,
    DriftRates,
    WindowMap,
    coupling_by_fit,
    deskewed_planes,
    estimate_drift_rates,
    fits_better,
    regime_coupling,
    window_maps,
    window_velocity_covariance,
    with_window_bias,
)
from kinreg.estimate.network import Network
from kinreg.estimate.pairwise import LinkModel
from kinreg.estimate.plane_nodes import plane_clusters
from kinreg.estimate.slicing import shorter_window_s, window_smear_m
from kinreg.estimate.snooping import misfit_text, models_rejected, trajectory_misfits, wrong_match_misfits
from kinreg.progress import Progress
from kinreg.types import BlockResult, Link, LinkStatus, ObservationKind, ObservationTest, Plane, Station, Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StrategyConfig:
    """The configuration sections the strategy reads."""

    slicing: SlicingConfig
    planes: PlanesConfig
    matching: MatchingConfig
    drift: DriftConfig
    block: BlockConfig

    @classmethod
    def from_config(cls, config: KinregConfig) -> StrategyConfig:
        return cls(config.slicing, config.planes, config.matching, config.drift, config.block)


class SlicedNetwork(Protocol):
    """What one slicing gives the strategy: every station (kinematic, then static) with its
    planes, the runs' trajectories in the stations' frame, and the network of the first links."""

    @property
    def stations(self) -> Sequence[Station]: ...

    @property
    def planes(self) -> list[tuple[Plane, ...]]: ...

    @property
    def trajectories(self) -> Sequence[Trajectory]: ...

    @property
    def network(self) -> Network: ...


S = TypeVar("S", bound=SlicedNetwork)

# link_again(stations, planes, rates, adjusted, previous, velocity_cov): every candidate pair linked
# again from the poses of ``adjusted``, the planes' window deformation by ``rates``; a ``previous``
# link whose prior hardly moved is kept (kinreg.run.link_stage.link_stations); with the model of the
# planes and the trajectory they were adjusted with (kinreg.estimate.pairwise.LinkModel).
LinkAgain = Callable[[Sequence[Station], Sequence[tuple[Plane, ...]], DriftRates, BlockResult, Sequence[Link],
                      np.ndarray | None], tuple[list[Link], LinkModel]]


@dataclass(frozen=True)
class Operations(Generic[S]):
    """The operations the strategy is handed; where and how they run is the caller's.

    ``sliced_network(window_s, deskew_maps)``: the runs sliced into windows of ``window_s``
    seconds, each scan's points deskewed by its map in ``deskew_maps`` (by station index; none
    for the others), their planes detected, the sequence neighbours linked and the network built.
    ``link_again``: see :data:`LinkAgain`. ``pass_adjusted()``: called once a pass's network is
    adjusted. ``progress``: what the adjustments report to."""

    sliced_network: Callable[[float, Mapping[int, WindowMap]], S]
    link_again: LinkAgain
    pass_adjusted: Callable[[], None]
    progress: Progress


@dataclass(frozen=True, eq=False)
class AdjustedNetwork:
    network: Network  # the links the result rests on (linked again when the drift was faster)
    result: BlockResult
    rates: DriftRates
    # the trajectory's links beyond their model (kinreg.estimate.snooping.trajectory_misfits), worst first
    misfits: tuple[ObservationTest, ...] = ()
    # those of them a wrong plane match can explain (kinreg.estimate.snooping.wrong_match_misfits):
    # such a network is no result
    wrong_matches: tuple[ObservationTest, ...] = ()
    # (settled on, fitted best) where the adjusted network fits a coupling of another regime better
    # than the one its rounds settled on, even when started from that one: such a network is no result
    coupling_disagrees: tuple[float, float] | None = None


@dataclass(frozen=True, eq=False)
class Estimate(Generic[S]):
    """One pass: the slicing's network and its adjustment."""

    sliced: S
    adjusted: AdjustedNetwork
    window_s: float  # the windows it was sliced with
    smear_m: np.ndarray  # per station, by the measured drift over half its window
    first_window_s: float | None = None  # the windows of the first slicing, where they were too long
    points_deskewed: bool = False  # planes detected on points an earlier adjustment deskewed
    # why the network is no result (kinreg.errors.AdjustmentFailedError with adjusted.result marked
    # failed); empty: it is one
    failure: str = ""


def estimate_quasi_static(operations: Operations[S], config: StrategyConfig) -> Estimate[S]:
    """The first pass, then the shorter windows' and the deskewed points' where the drift calls
    for them, and the decision whether the chosen network is a result (``failure``). Raises
    :class:`~kinreg.errors.AdjustmentFailedError` where an adjustment of a pass fails: the pass
    is the one :attr:`Operations.sliced_network` gave last."""
    first = _estimate(operations, config, config.slicing.window_s)
    chosen = _with_shorter_windows(operations, config, first)
    chosen = _with_deskewed_points(operations, config, chosen)
    return replace(chosen, failure=_failure(chosen.adjusted))


def _estimate(operations: Operations[S], config: StrategyConfig, window_s: float,
              deskew_from: Estimate[S] | None = None) -> Estimate[S]:
    """One pass with windows of ``window_s``. ``deskew_from``: an estimate with the same windows
    whose adjustment deskews the scans' points before their planes are detected
    (:func:`_with_deskewed_points`)."""
    maps: dict[int, WindowMap] = {}
    left = None
    if deskew_from is not None:
        first = deskew_from.adjusted
        maps = window_maps(first.network.stations, first.result, first.rates, deskew_from.sliced.trajectories,
                           MAP_NEIGHBOURS)
        left = window_velocity_covariance(first.network.stations, first.result, first.rates)
    sliced = operations.sliced_network(window_s, maps)
    adjusted = adjust_with_measured_drift(sliced.network, sliced.planes, operations, config, sliced.trajectories,
                                          left)
    operations.pass_adjusted()
    return Estimate(sliced, adjusted, window_s, window_smear_m(sliced.stations, sliced.planes, adjusted.rates))


# The scan planes' offsets, which a window's smear moves first (:func:`_with_shorter_windows`).
_OFFSET_KINDS = tuple(k.value for k in (ObservationKind.PLANE_OFFSET, ObservationKind.PLANE_OFFSET_FLOOR,
                                        ObservationKind.PLANE_OFFSET_FLOOR_LEVEL))


def _with_shorter_windows(operations: Operations[S], config: StrategyConfig, est: Estimate[S]) -> Estimate[S]:
    """Where the drift measured by ``est`` smears the planes of its windows
    (:func:`~kinreg.estimate.slicing.shorter_window_s`; whether their offsets show it:
    :func:`~kinreg.estimate.snooping.models_rejected`): the network sliced again with shorter
    windows, or with ``est``'s windows again where the shorter windows' network shows a
    trajectory misfit of a wrong match that ``est``'s does not. Else ``est``."""
    window_s = config.slicing.window_s
    window = shorter_window_s(window_s, est.smear_m, est.sliced.planes, config.slicing)
    if window is None:
        return est
    showing: dict[str, float] = {}
    if shorter_window_s(window_s, est.smear_m, est.sliced.planes, config.slicing, False) is None:
        # below the noise: worth shorter windows only where the planes' offsets show the smear
        result = est.adjusted.result
        showing = models_rejected(result.tests, result.variance_components, _OFFSET_KINDS, config.block.alpha)
        if not showing:
            return est
    shown = "".join(f", {kind} {factor:.1f}x its model" for kind, factor in showing.items())
    log.warning("the drift smears the planes by %.1f mm over half a window (median%s): sliced again with %.1f s "
                "windows instead of %.1f s", 1000 * float(np.nanmedian(est.smear_m)), shown, window, window_s)
    again = _estimate(operations, config, window)
    # Shorter windows hold fewer planes each, and their links can agree on a wrong match that no
    # test finds; then the trajectory's own links disagree with the network. Where the longer
    # windows' network had no such misfit, it is the better result (a held-out run, world drift
    # 0.26 m: 3 s windows ended 63 mm RMS off with the global test passed, 7 sigma between the
    # trajectory and the network; its 6 s windows were within 5 mm).
    if again.adjusted.wrong_matches and not est.adjusted.wrong_matches:
        log.warning("with %.1f s windows the trajectory disagrees with the adjusted network between %s "
                    "(a wrong plane match the tests did not find): kept the %.1f s windows",
                    window, misfit_text(again.adjusted.wrong_matches), window_s)
        # the first slicing's spill made way for the second's: sliced again, the rest from the cache
        return _estimate(operations, config, window_s)
    return replace(again, first_window_s=window_s)


def _with_deskewed_points(operations: Operations[S], config: StrategyConfig, est: Estimate[S]) -> Estimate[S]:
    """Where the attitude error turns the trajectory's steps (a coupled drift: GNSS/INS-like,
    ``rates.coupling`` at least :data:`~kinreg.estimate.drift.MIXED_COUPLING`'s upper end) and
    shears the windows by more than the range noise (a third of the planes' band), ``est``'s planes
    were chosen from sheared points: the band around a sheared wall takes in points of other
    surfaces and leaves out the wall's own at the window's ends, and deskewing the plane's
    parameters keeps that choice (held-out building, GNSS/INS-like drift: planes 7-9 mm off after
    the deskew, 0.01-0.1 mm when the points themselves are deskewed with the true drift). Then
    the points are deskewed with ``est``'s adjustment and the planes detected, linked and adjusted
    again; that network is kept unless the trajectory disagrees with it as a wrong plane match
    would where it did not with ``est``'s. ``[slicing] deskew_sheared = false``: ``est`` stands."""
    adjusted = est.adjusted
    if not config.slicing.deskew_sheared or adjusted.rates.coupling < MIXED_COUPLING[1]:
        return est
    _, shift = deskewed_planes(adjusted.network.stations, est.sliced.planes, adjusted.result, adjusted.rates,
                               est.sliced.trajectories)
    if shift <= config.planes.refit_distance_m / 3.0:
        return est
    log.warning("the attitude error shears the windows (a plane by up to %.1f mm): their points deskewed "
                "with the adjusted drift and their planes detected again", 1000 * shift)
    again = _estimate(operations, config, est.window_s, deskew_from=est)
    if again.adjusted.wrong_matches and not adjusted.wrong_matches:
        log.warning("with the deskewed points the trajectory disagrees with the adjusted network between %s: "
                    "kept the planes of the sheared points", misfit_text(again.adjusted.wrong_matches))
        return est
    return replace(again, first_window_s=est.first_window_s, points_deskewed=True)


def _failure(adjusted: AdjustedNetwork) -> str:
    """Why ``adjusted`` is no result, or ``""``."""
    # The trajectory's own links are never rejected: beyond their model, by as much as two distinct
    # planes lie apart, they show plane links that agree on a wrong match no test found (or a jump
    # the detector missed). The global test can pass all the same, and the stations be 30-60 mm
    # RMS off (held-out runs, world drift 0.26 m). A smaller misfit stays a warning in the report.
    if adjusted.wrong_matches:
        return (f"the trajectory disagrees with the adjusted network between {misfit_text(adjusted.wrong_matches)}, "
                "beyond its model: plane links that agree on a wrong match, or a jump in the trajectory")
    # The drift model's coupling is the run's own where the adjusted network fits it best; a network
    # that settles on another one, started from either, can pass its global test 36 mm off.
    if adjusted.coupling_disagrees is not None:
        settled, fitted = adjusted.coupling_disagrees
        return (f"the adjusted network fits a drift coupling of {fitted:.2f} better than the {settled:.2f} it "
                "settled on, started from either: the trajectory's error model is not settled")
    return ""


def adjust_with_measured_drift(network: Network, planes: list[tuple[Plane, ...]], operations: Operations,
                               config: StrategyConfig, trajectories: Sequence[Trajectory] = (),
                               points_deskewed: np.ndarray | None = None) -> AdjustedNetwork:
    """The block adjustment of ``network`` with the drift it measures (:func:`_settled_rounds`).
    The last network is asked which coupling of the drift it fits best (:func:`_coupling_by_fit`);
    where that is of another regime than the one the rounds settled on (:data:`_COUPLING_DISAGREES`),
    the rounds start again from it, once; ``coupling_disagrees`` says that they settled apart from
    it again. ``points_deskewed``: see :func:`_settled_rounds`. Raises
    :class:`~kinreg.errors.AdjustmentFailedError` where an adjustment fails."""
    start_coupling: float | None = None
    while True:
        last, result, rates = _settled_rounds(network, planes, operations, config, trajectories,
                                                  points_deskewed, start_coupling)
        fitted = _coupling_by_fit(last, rates, config.block, operations.progress, result, rates.coupling)
        disagrees = None
        if fitted is not None and abs(fitted - rates.coupling) > _COUPLING_DISAGREES:
            disagrees = (rates.coupling, fitted)
        if disagrees is None or start_coupling is not None:
            break
        log.warning("the adjusted network fits a coupling of %.2f (%s) better than the %.2f its rounds "
                    "settled on: adjusted again from %.2f", fitted, replace(rates, coupling=fitted).regime,
                    rates.coupling, fitted)
        start_coupling = fitted
    misfits, wrong = _warn_trajectory_misfits(result, config.block.alpha, config.matching)
    if not config.block.scan_frames:  # else the block carries the window bias (kinreg.estimate.frames)
        result = with_window_bias(result, last.stations, rates)
    return AdjustedNetwork(last, result, rates, tuple(misfits), tuple(wrong), disagrees)


def _settled_rounds(network: Network, planes: list[tuple[Plane, ...]], operations: Operations,
                    config: StrategyConfig, trajectories: Sequence[Trajectory], points_deskewed: np.ndarray | None,
                    start_coupling: float | None) -> tuple[Network, BlockResult, DriftRates]:
    """The first adjustment measures the drift rates and the coupling
    (:func:`~kinreg.estimate.drift.estimate_drift_rates`); the pairs are then linked again from
    the adjusted poses (:attr:`Operations.link_again`) and the network adjusted again, until the
    linked pairs no longer change (``[block] max_relink_rounds``); a last pass forms the
    trajectory's links with the final rates and coupling, so that the planes' window deformation
    and the stretches carried by the trajectory alone get honest sigmas. ``points_deskewed``: the
    planes were detected on points an earlier adjustment deskewed (:func:`~kinreg.estimate.drift.deskewed_points`),
    and this (n, 6, 6) is the drift velocity's covariance that deskew left
    (:func:`~kinreg.estimate.drift.window_velocity_covariance`): their parameters are not deskewed again.

    The first adjustment is made again with the coupling its network fits significantly better
    than the prior's (:func:`_coupling_by_fit`; where none, the coupling is read off it as before),
    or with ``start_coupling``. Returns the last network, its adjustment and the rates it was made with."""
    progress = operations.progress
    prior_rates = DriftRates.from_config(config.drift)
    if points_deskewed is not None:
        network = replace(network, velocity_cov=points_deskewed)
    result = _checked(adjust_network(network, prior_rates, config.block, progress))
    coupling = (_coupling_by_fit(network, prior_rates, config.block, progress, result, prior_rates.coupling)
                if start_coupling is None else start_coupling)
    if coupling is not None:
        log.info("the first network adjusted again with a coupling of %.2f (%s): the one %s", coupling,
                 replace(prior_rates, coupling=coupling).regime,
                 "it fits best" if start_coupling is None else "the last network fitted best")
        result = _checked(adjust_network(network, replace(prior_rates, coupling=coupling), config.block, progress,
                                         previous=result))
    rates = estimate_drift_rates(network.stations, result, prior_rates, config.drift.measured_rate_floor,
                                 config.drift.measure_correlation, network.links, coupling=coupling)
    # The correlation of the drift is measured on the first adjustment, whose links are
    # independent (an adjustment that already carries a smooth drift through the stretches no
    # plane fixes would find it smooth there because it made it so), and once more on the first
    # round's deskewed planes (:func:`_correlation_of_deskewed`).
    correlation = rates.correlation_s
    linked_with = prior_rates
    tried: list[tuple[float, float]] = []  # (coupling deskewed and adjusted with, coupling it measured)
    rounds = config.block.max_relink_rounds + _COUPLING_ROUNDS if config.block.max_relink_rounds else 0
    used_planes = planes  # those of the last links
    for round_ in range(rounds):
        # Matched again from the adjusted poses: pairs that the trajectory's drift kept apart or
        # out of the gates (loop closures) are linked now, and the planes' window deformation
        # follows the measured rates. Until the set of linked pairs no longer changes. Links whose
        # prior hardly moved are kept, unless the drift is faster than they were made with.
        faster = bool(np.any(rates.pos_m_per_s > 1.2 * linked_with.pos_m_per_s)
                      or np.any(rates.rot_rad_per_s > 1.2 * linked_with.rot_rad_per_s))
        # Where the attitude error is coupled (GNSS/INS-like) it shears every window: its planes are
        # moved back with the adjusted attitudes, and every pair is linked again with them.
        # (Where no plane moves by more than its offset's floor sigma, nothing is gained.)
        if points_deskewed is None:
            deskewed, shift = deskewed_planes(network.stations, planes, result, rates, trajectories)
            sheared = shift > config.planes.min_sigma_d_m
            velocity_cov = window_velocity_covariance(network.stations, result, rates) if sheared else None
        else:
            deskewed, sheared, velocity_cov = planes, False, points_deskewed
        links, model = operations.link_again(network.stations, deskewed if sheared else planes, rates, result,
                                             () if faster or sheared else network.links, velocity_cov)
        linked_with = rates if faster else linked_with
        used_planes = deskewed if sheared else planes
        same = _linked_pairs(links) == _linked_pairs(network.links)
        log.info("linked again from the adjusted poses: %d links (were %d)", len(links), len(network.links))
        network = replace(network.with_links(links, model), velocity_cov=velocity_cov)
        if round_ == 0 and (sheared or points_deskewed is not None) and config.drift.measure_correlation:
            correlation = _correlation_of_deskewed(network, result, rates, prior_rates, config, progress)
            rates = replace(rates, correlation_s=correlation)
        result = _checked(adjust_network(network, rates, config.block, progress, previous=result))
        used = rates
        rates = replace(estimate_drift_rates(network.stations, result, prior_rates, config.drift.measured_rate_floor,
                                             measure_correlation=False, links=network.links),
                        correlation_s=correlation)
        tried.append((used.coupling, rates.coupling))
        rates = replace(rates, coupling=_settled_coupling(tried))
        settled = abs(rates.coupling - used.coupling) < _COUPLING_TOLERANCE
        if settled and (same or round_ + 1 >= config.block.max_relink_rounds):
            break
    # Control points tested against their own sigmas, then the last pass: the trajectory's links
    # coupled with the measured coupling and rates.
    network = screen_control_points(network, rates, config.block, progress, previous=result)
    if config.block.plane_nodes and config.block.scan_frames:
        # The links' matches say which planes are one; a link the block rejected says nothing.
        rejected = {(t.i, t.j) for t in result.tests if t.kind is ObservationKind.PLANES and t.rejected}
        usable = [link for link in network.links if (link.scan_i, link.scan_j) not in rejected]
        network = replace(network, planes=tuple(used_planes), plane_nodes=plane_clusters(
            usable, (config.planes.min_sigma_angle_rad, config.planes.min_sigma_d_m)))
    result = _checked(adjust_network(network, rates, config.block, progress, previous=result))
    if used_planes is not planes and network.plane_nodes is not None:
        network, result, rates = _deskew_settled(network, planes, result, rates, config, progress,
                                                 trajectories)
    return network, result, rates


# A network's least-squares cost is taken at these couplings (kinreg.estimate.drift.coupling_by_fit).
_COUPLINGS_TRIED = (0.0, 0.5, 1.0)
# The adjusted network fits another coupling better than the one its rounds settled on where the
# two lie further apart than this (the width of a regime, kinreg.estimate.drift.MIXED_COUPLING).
# Healthy runs of the sample building agree (costs at the regime ends 15-60 times apart); a run that
# settled on 0.32 from a first coupling read off wrong attitudes fitted 0.83 (cost 642 at 1, 810 at
# 0.32) and was 36 mm off.
_COUPLING_DISAGREES = 0.25


def _coupling_by_fit(network: Network, rates: DriftRates, config: BlockConfig, progress: Progress,
                     result: BlockResult, against: float) -> float | None:
    """The coupling of the trajectory's attitude error into its steps that ``network`` fits best
    with ``rates`` (:func:`~kinreg.estimate.drift.coupling_by_fit`; a coupling that names a regime
    is that regime's), where it fits it significantly better than the coupling ``against``
    (:func:`~kinreg.estimate.drift.fits_better`); else None. The fit is the least-squares cost with
    the a-priori weights (no variance components, no data snooping) at :data:`_COUPLINGS_TRIED`:
    the coupling an unknown of the adjustment in effect, tested as one. For the first network it
    is not read off the first adjustment's attitudes (:func:`~kinreg.estimate.drift.coupling_from_links`):
    that adjustment is made with the prior's coupling, and where the prior is the wrong regime its
    attitudes are wrong where few planes fix them, and lean the coupling read off them towards the
    prior (a GNSS/INS-like run of the sample building, seed 3: 0.16 at a sigma of 0.03, from
    attitudes 93 mm off; the relinked rounds never left it and ended 36 mm off, their global test
    passed)."""
    plain = replace(config, variance_components=False, data_snooping=False)
    # Per coupling tried: the fit's cost and redundancy (not the fit: its tests and covariances
    # are hundreds of MB at city scale).
    fits: dict[float, tuple[float, float]] = {}

    def cost(kappa: float) -> float:
        if kappa not in fits:
            fit = adjust_network(network, replace(rates, coupling=kappa), plain, progress, previous=result)
            fits[kappa] = (fit.sigma0**2 * fit.redundancy if not fit.failed else np.inf, fit.redundancy)
        return fits[kappa][0]

    best = regime_coupling(coupling_by_fit(_COUPLINGS_TRIED, [cost(k) for k in _COUPLINGS_TRIED]))
    redundancy = fits[_COUPLINGS_TRIED[0]][1]  # the same observations at every coupling
    if best == against or not fits_better(cost(best), cost(against), redundancy, config.alpha):
        return None
    return best


def _correlation_of_deskewed(network: Network, result: BlockResult, rates: DriftRates, prior: DriftRates,
                             config: StrategyConfig, progress: Progress) -> tuple[float, float]:
    """The drift velocity's correlation times, measured again once the planes are deskewed (the
    first relink round), on an adjustment whose trajectory links are independent (as the first
    one's: a smooth drift carried through stretches no plane fixes would read as smooth because
    the adjustment made it so). The first adjustment's planes carry the drift inside their windows:
    under GNSS/INS-like drift they are sheared by the attitude error, the stations' corrections
    err by millimetres from one station to the next, and a position drift whose velocity keeps
    its direction for minutes read as decorrelated within 0-18 s."""
    independent = _checked(adjust_network(network, replace(rates, correlation_s=(0.0, 0.0)), config.block,
                                          progress, previous=result))
    measured = estimate_drift_rates(network.stations, independent, prior, config.drift.measured_rate_floor,
                                    measure_correlation=True, links=network.links)
    log.info("drift velocity correlation on the deskewed planes: %.0f s (position), %.0f s (rotation); "
             "on the first adjustment %.0f s, %.0f s", *measured.correlation_s, *rates.correlation_s)
    return measured.correlation_s


# The planes' deskew is settled when deskewing them with the last adjustment moves none by more than
# this share of its own sigma; until it is, at most this many adjustments more.
_DESKEW_SETTLED = 0.2
_DESKEW_ROUNDS = 4


def _deskew_settled(network: Network, planes: Sequence[tuple[Plane, ...]], result: BlockResult, rates: DriftRates,
                    config: StrategyConfig, progress: Progress,
                    trajectories: Sequence[Trajectory]) -> tuple[Network, BlockResult, DriftRates]:
    """The network's deskewed planes and its adjustment made to agree. The planes of the last pass
    were deskewed with the adjustment before it, and the last pass (plane nodes instead of links)
    moves the stations' corrections: deskewed with its own result, the planes of a GNSS/INS-like
    run (sample building, medium class, seed 1) moved by up to 3.5 of their sigmas, and the tilt
    errors of its large walls were 2.1 times their sigmas (0.7 once they agree). Deskewed again
    and adjusted again until no plane moves by more than :data:`_DESKEW_SETTLED` of its sigma
    (each round moves them about half as far as the last); the links are not formed again (a
    deskew keeps the planes' matches). Returns the rates the last was made with."""
    for _ in range(_DESKEW_ROUNDS):
        deskewed, _shift = deskewed_planes(network.stations, planes, result, rates, trajectories)
        moved = _largest_move(network.planes or (), deskewed)
        if moved <= _DESKEW_SETTLED:
            break
        log.info("planes deskewed again with the last adjustment (moved by up to %.2f sigma)", moved)
        network = replace(network, planes=tuple(deskewed),
                          velocity_cov=window_velocity_covariance(network.stations, result, rates))
        result = _checked(adjust_network(network, rates, config.block, progress, previous=result))
    return network, result, rates


def _largest_move(before: Sequence[tuple[Plane, ...]], after: Sequence[tuple[Plane, ...]]) -> float:
    """The largest change of a plane from ``before`` to ``after`` (the same planes), in its sigmas:
    its turn towards either tangent and its offset at its centroid."""
    largest = 0.0
    for old, new in zip(before, after, strict=True):
        for a, b in zip(old, new, strict=True):
            change = np.append(a.basis_uv @ (b.normal - a.normal), b.normal @ a.centroid_xyz - b.d_m)
            largest = max(largest, float(np.max(np.abs(change) / np.sqrt(np.diagonal(a.cov_uvd)))))
    return largest


# The coupling is settled when the next round would deskew with one this close to the last; until it
# is, up to this many rounds more than [block] max_relink_rounds.
_COUPLING_TOLERANCE = 0.05
_COUPLING_ROUNDS = 2


def _settled_coupling(tried: Sequence[tuple[float, float]]) -> float:
    """The coupling to deskew and adjust with next: the one that would measure itself. Planes
    deskewed with a coupling lean towards it, so the coupling measured after a round lies between
    the one used and the run's own, and repeating rounds creeps up on it; from the last two rounds
    the secant finds where the measured and the used coupling agree (within [0, 1])."""
    found = tried[-1][1]
    if len(tried) < 2:
        return regime_coupling(found)
    (u0, f0), (u1, f1) = tried[-2], tried[-1]
    g0, g1 = f0 - u0, f1 - u1
    if abs(u1 - u0) < 1e-6 or abs(g1 - g0) < 1e-6:
        return regime_coupling(found)
    return regime_coupling(float(np.clip(u1 - g1 * (u1 - u0) / (g1 - g0), 0.0, 1.0)))



def _warn_trajectory_misfits(result: BlockResult, alpha: float,
                             matching: MatchingConfig) -> tuple[list[ObservationTest], list[ObservationTest]]:
    """Say where the trajectory's own links disagree with the adjusted network beyond their model
    (:func:`~kinreg.estimate.snooping.trajectory_misfits`); returns them and those as large as a
    wrong plane match makes them (:func:`~kinreg.estimate.snooping.wrong_match_misfits`)."""
    misfits = trajectory_misfits(result.tests, alpha)
    wrong = wrong_match_misfits(misfits, matching.coplanar_offset_m, matching.coplanar_angle_deg)
    if wrong:
        log.warning("the trajectory disagrees with the adjusted network between %s. Check the links there "
                    "(a wrong plane match or a jump)", misfit_text(wrong))
    elif misfits:
        log.warning("the trajectory disagrees with the adjusted network between %s, by less than a wrong plane "
                    "match would: the drift model fits the run less well there, and those stations may be less "
                    "accurate than their sigmas say", misfit_text(misfits))
    return misfits, wrong


def _linked_pairs(links: Sequence[Link]) -> set[tuple[int, int]]:
    return {(link.scan_i, link.scan_j) for link in links if link.status is LinkStatus.OK}


def _checked(result: BlockResult) -> BlockResult:
    """``result``, unless the adjustment failed: then :class:`AdjustmentFailedError`."""
    if result.failed:
        raise AdjustmentFailedError(adjustment_failure(result), result)
    return result


def adjustment_failure(result: BlockResult) -> str:
    """What a failed adjustment says: its failure, sigma0 and redundancy."""
    return (f"the block adjustment failed: {result.failure} (sigma0 {result.sigma0:.3g}, redundancy "
            f"{result.redundancy:.0f})")
