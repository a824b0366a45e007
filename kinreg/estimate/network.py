"""The network of stations: pairwise links over candidate pairs, and the block's observations.

A *station* is a scan with a pose ``T_obj_scan`` (from the trajectory for quasi-static scans).
Quasi-static stations may come from several runs (trajectory + cloud each) in one frame: the
trajectory ties only consecutive stations of the same run; stations of different runs are tied by
their planes alone, like loop closures.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kinreg.config import DriftConfig, MatchingConfig, PairwiseConfig, StaticConfig
from kinreg.estimate.control import ControlTie, control_observations
from kinreg.estimate.drift import DriftRates, drift_observation, window_bias_covariance
from kinreg.estimate.matching import StationPlanes, candidate_pairs, match_planes
from kinreg.estimate.pairwise import LinkModel, PairInput, adjust_pairs
from kinreg.estimate.plane_nodes import PlaneNodes
from kinreg.geometry import Pose, pose_sigmas
from kinreg.types import (
    BlockResult,
    Link,
    LinkStatus,
    ObservationKind,
    Plane,
    RelativeObservation,
    ScanKind,
    Station,
    Tie,
)


def station_pairs(stations: Sequence[Station], matching: MatchingConfig,
                  static: StaticConfig | None = None, loops: bool = True) -> list[tuple[int, int]]:
    """Candidate pairs: sequence neighbours and nearby stations among the quasi-static stations of
    each run, stations of different runs within ``matching.radius_m`` of each other, and every
    station within ``static.link_radius_m`` of a static one. Without ``loops``, a run's stations
    are paired with their sequence neighbours only (no loop closures within a run)."""
    positions = np.array([s.T_obj_scan.t_xyz for s in stations])
    quasi = np.array([s.kind is ScanKind.QUASI_STATIC for s in stations])
    runs = np.array([s.run for s in stations])
    pairs: set[tuple[int, int]] = set()
    within_run = matching if loops else replace(matching, radius_m=0.0)
    for run in np.unique(runs[quasi]):
        qs = np.flatnonzero(quasi & (runs == run))
        pairs |= {(int(qs[a]), int(qs[b])) for a, b in candidate_pairs(positions[qs], within_run)}
    pairs |= _cross_run_pairs(positions, runs, quasi, matching.radius_m)
    if static is not None and (~quasi).any():
        for k in np.flatnonzero(~quasi):
            near = np.flatnonzero(np.linalg.norm(positions - positions[k], axis=1) <= static.link_radius_m)
            pairs |= {(int(min(k, j)), int(max(k, j))) for j in near if j != k}
    return sorted(pairs)


def _cross_run_pairs(positions: np.ndarray, runs: np.ndarray, quasi: np.ndarray,
                     radius_m: float) -> set[tuple[int, int]]:
    """Pairs of quasi-static stations of different runs whose centres are within ``radius_m``."""
    qs = np.flatnonzero(quasi)
    if len(np.unique(runs[qs])) < 2 or radius_m <= 0:
        return set()
    near = cKDTree(positions[qs]).query_pairs(radius_m)
    return {(int(min(qs[a], qs[b])), int(max(qs[a], qs[b]))) for a, b in near if runs[qs[a]] != runs[qs[b]]}


def link_pairs(
    pairs: Sequence[tuple[int, int]], stations: Mapping[int, Station], planes: Mapping[int, tuple[Plane, ...]],
    matching: MatchingConfig, drift: DriftConfig, pairwise: PairwiseConfig, static: StaticConfig | None,
    sigmas: Mapping[int, np.ndarray] | None = None, model: LinkModel | None = None,
) -> list[Link | None]:
    """Match and adjust candidate pairs ``(i, j)`` of ``stations``; per pair its link, ``None``
    where too few planes match. Each station's planes are formed for matching once
    (:class:`StationPlanes`), not once per pair, and the pairs are adjusted together
    (:func:`adjust_pairs`: numpy's cost per call, not the arithmetic, sets the pace of a pair's
    solve). The planes' covariances are expected to carry the drift inside their windows already
    (:func:`with_window_deformation`, as :func:`link_stations` passes them). A pair's prior is
    the stations' relative pose with ``hypot(sigmas[i], sigmas[j])`` (6,), by default the drift's
    over their time difference. ``model``: the observations' model the links measured
    (:func:`~kinreg.estimate.pairwise.estimate_link_model`), where not the a-priori one."""
    inputs = pair_inputs(pairs, stations, planes, matching, pairwise, static, sigmas)
    links = iter(adjust_pairs([p for p in inputs if p is not None], drift, pairwise, model))
    return [None if p is None else next(links) for p in inputs]


def pair_inputs(
    pairs: Sequence[tuple[int, int]], stations: Mapping[int, Station], planes: Mapping[int, tuple[Plane, ...]],
    matching: MatchingConfig, pairwise: PairwiseConfig, static: StaticConfig | None,
    sigmas: Mapping[int, np.ndarray] | None = None,
) -> list[PairInput | None]:
    """The matches and prior of each pair of :func:`link_pairs`, ready to adjust; ``None`` where
    too few planes match."""
    matchable = {k: StationPlanes(p) for k, p in planes.items()}
    return [_pair_input(i, j, stations[i], stations[j], matchable[i], matchable[j], matching, pairwise, static,
                        None if sigmas is None else np.hypot(sigmas[i], sigmas[j])) for i, j in pairs]


def _pair_input(
    i: int, j: int, si: Station, sj: Station, match_i: StationPlanes, match_j: StationPlanes,
    matching: MatchingConfig, pairwise: PairwiseConfig, static: StaticConfig | None, sigma_prior: np.ndarray | None,
) -> PairInput | None:
    """One pair's matches and prior, ready to adjust; ``None`` where too few planes match."""
    planes_i, planes_j = match_i.planes, match_j.planes
    T_prior = si.T_obj_scan.inverse().compose(sj.T_obj_scan)
    matches = match_planes(match_i, match_j, T_prior, matching)
    sigma = sigma_prior
    if len(matches) < matching.min_matches:
        return None
    if static is not None and ScanKind.STATIC in (si.kind, sj.kind):
        sigma = pose_sigmas(static.prior_sigma_m, np.radians(static.prior_sigma_deg))
    elif si.run != sj.run:
        sigma = pose_sigmas(pairwise.cross_run_prior_sigma_m, np.radians(pairwise.cross_run_prior_sigma_deg))
    return PairInput(i, j, planes_i, planes_j, T_prior, _dt(si, sj), matches, sigma)


def _dt(a: Station, b: Station) -> float:
    """Time between two stations; static stations and stations of two runs are treated as far
    apart in time (no prior information from the trajectory ties them)."""
    if np.isnan(a.t_s) or np.isnan(b.t_s) or a.run != b.run:
        return float("inf")
    return abs(b.t_s - a.t_s)


def block_observations(
    stations: Sequence[Station], links: Sequence[Link], rates: DriftRates, previous: BlockResult | None = None,
    window_bias: bool = True,
) -> list[RelativeObservation]:
    """The block's observations: every usable link's plane-only information, and the trajectory's
    relative pose between consecutive quasi-static stations of the same run, once, weighted by the
    drift rates (plus both scans' window bias: the block's unknowns are scan frames).

    With a coupling ``kappa`` (:class:`DriftRates`), the trajectory's step enters as
    ``(1 - kappa)`` times its step in its own scan frame plus ``kappa`` times its object-frame step
    turned into the adjusted scan frame (the block's own attitude of the first station, an
    unknown): a trajectory whose positions are measured apart from its attitude (GNSS/INS) then
    no longer carries its attitude error into the links. ``previous`` is not used by the links.
    Without ``window_bias`` the scans' window bias is left out of the trajectory's links (the
    block then carries it as the tie of each scan frame to its sensor pose,
    :mod:`kinreg.estimate.frames`)."""
    observations = [
        RelativeObservation(ObservationKind.PLANES, link.scan_i, link.scan_j, link.T_i_j_planes,
                            link.info_planes, link.rank)
        for link in links
        if link.status is LinkStatus.OK and link.rank > 0
    ]
    sequence = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC]
    last: tuple[int, float] | None = None  # the run's previous link: its first station and length
    for a, b in itertools.pairwise(sequence):
        sa, sb = stations[a], stations[b]
        if sa.run != sb.run:
            last = None
            continue  # no trajectory between two runs
        dt = _dt(sa, sb)
        Z = sa.T_obj_scan.inverse().compose(sb.T_obj_scan)
        # With a correlated drift its velocity is an unknown of the link (drift_observation); the
        # link itself then keeps the floors only.
        cov = rates.covariance(0.0 if rates.state_space else dt, sa.T_obj_scan)
        if window_bias:
            cov = (cov + window_bias_covariance(sa, sa.T_obj_scan, rates)
                   + window_bias_covariance(sb, sa.T_obj_scan, rates))
        observations.append(RelativeObservation(ObservationKind.TRAJECTORY, a, b, Z, np.linalg.inv(cov), 6,
                                                dt_s=dt if rates.state_space else 0.0, coupling=rates.coupling,
                                                step_obj=sb.T_obj_scan.t_xyz - sa.T_obj_scan.t_xyz))
        if rates.state_space:
            observations.append(drift_observation(rates, a, dt, last))
            last = (a, dt)
    return observations


@dataclass(frozen=True, eq=False)
class Datum:
    """How the network is held: stations held fixed, datum observations (observed static scans,
    tie planes to reference planes), control points (observations of their stations, formed with
    the drift rates of each pass: :func:`~kinreg.estimate.control.control_observations`), and what
    they are, in words for the report."""

    fixed: NDArray[np.bool_]
    observations: tuple[RelativeObservation, ...]
    description: str
    ties: tuple[Tie, ...] = ()
    controls: tuple[ControlTie, ...] = ()
    # control points rejected by their screening (kinreg.estimate.datum.screen_control_points):
    # name and the normalised residual they had
    rejected_controls: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True, eq=False)
class Network:
    """What the block adjusts, as one object (Open3D's ``PoseGraph``): the stations (nodes, with
    their initial poses), the pairwise links (edges), and the datum."""

    stations: tuple[Station, ...]
    links: tuple[Link, ...]
    datum: Datum
    # per station (n, 6, 6): how a drift velocity inside its window moves the frame its planes fix
    # (kinreg.estimate.frames.window_gain)
    window_gain: NDArray[np.float64] | None = None
    # per station (n, 6, 6, scan axes): the covariance of the drift velocity inside its window that
    # the deskewed planes leave (kinreg.estimate.drift.window_velocity_covariance); None: the rates'
    velocity_cov: NDArray[np.float64] | None = None
    # per station the planes its links were made with: where given, the block adjusts the physical
    # planes as nodes of their own instead of the links (kinreg.estimate.plane_nodes)
    planes: tuple[tuple[Plane, ...], ...] | None = None
    plane_nodes: PlaneNodes | None = None  # ... and which of them are one physical plane
    # the model of the planes and the trajectory the links were adjusted with (where the a-priori
    # one did not fit them, kinreg.estimate.pairwise.estimate_link_model); the block's planes carry it too
    link_model: LinkModel = field(default_factory=LinkModel)

    @property
    def initial_poses(self) -> Pose:
        return Pose.stack([s.T_obj_scan for s in self.stations])

    def observations(self, rates: DriftRates, previous: BlockResult | None = None,
                     window_bias: bool = True) -> list[RelativeObservation]:
        """The block's observations with the trajectory's links weighted by ``rates`` (and coupled
        through a ``previous`` adjustment, :func:`block_observations`), and the datum's; the
        control points' come last, in the order of ``datum.controls``
        (:meth:`control_indices`). ``window_bias``: see :func:`block_observations`."""
        return (block_observations(self.stations, self._linked(), rates, previous, window_bias)
                + list(self.datum.observations)
                + control_observations(self.datum.controls, self.stations, rates, previous, window_bias))

    def control_indices(self, rates: DriftRates) -> range:
        """The positions of the control points' observations in :meth:`observations` with ``rates``
        (whose drift model decides how many observations the trajectory gives)."""
        n = len(block_observations(self.stations, self._linked(), rates))
        first = n + len(self.datum.observations)
        return range(first, first + len(self.datum.controls))

    def _linked(self) -> Sequence[Link]:
        """The links the block observes: none where it adjusts the physical planes instead."""
        return self.links if self.plane_nodes is None else ()

    def with_links(self, links: Sequence[Link], model: LinkModel | None = None) -> Network:
        return replace(self, links=tuple(links), link_model=self.link_model if model is None else model)
