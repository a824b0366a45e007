"""The stages of ``kinreg process`` with their side effects: on the executor's workers, through
the output folder's stage cache (:mod:`kinreg.run.output_folder`), with progress."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kinreg.config import (
    BlockConfig,
    DriftConfig,
    InputConfig,
    KinregConfig,
    MatchingConfig,
    PairwiseConfig,
    PlanesConfig,
    StaticConfig,
)
from kinreg.errors import AdjustmentFailedError, ConfigError
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.datum import adjust_network, screen_control_points, take_out_jumps
from kinreg.estimate.drift import (
    DriftRates,
    WindowMap,
    coupling_by_fit,
    deskewed_planes,
    deskewed_points,
    estimate_drift_rates,
    fits_better,
    plane_time_offsets,
    regime_coupling,
    rms_time_offset,
    window_velocity_covariance,
    with_window_bias,
    with_window_deformation,
)
from kinreg.estimate.network import Network, link_pairs, station_pairs
from kinreg.estimate.plane_nodes import plane_clusters
from kinreg.estimate.planes import detect_planes, facing_the_sensor
from kinreg.estimate.reference import to_reference_frame
from kinreg.estimate.slicing import SensorTrack, sensor_track
from kinreg.estimate.snooping import misfit_text, trajectory_misfits, wrong_match_misfits
from kinreg.geometry import FloatArray, Pose, pose_sigmas
from kinreg.io.checks import check_inputs
from kinreg.io.reference_planes import ReferencePlanes
from kinreg.io.trajectory import parse_column_mapping, read_trajectory, write_trajectory_geoslam
from kinreg.progress import NullProgress, Progress
from kinreg.run.codecs import links_from_arrays, links_to_arrays, scan_planes_from_arrays, scan_planes_to_arrays
from kinreg.run.corrected_cloud import PointObserver, write_corrected_las
from kinreg.run.executor import ExecutorContext, in_process, parallel_map
from kinreg.run.output_folder import CachedSlices, RunCache, content_parts, dataclass_parts
from kinreg.run.runs import RunInputs, adjusted_sequence_scans, label_run, run_output_names
from kinreg.run.spill import QuasiStaticSequence
from kinreg.types import (
    BlockResult,
    Link,
    LinkStatus,
    ObservationKind,
    ObservationTest,
    Plane,
    Scan,
    ScanKind,
    Station,
    Trajectory,
    TrajectoryJump,
)

log = logging.getLogger(__name__)


# A planes task: the sequence's small index, the scan's number, the settings, the sensor's track,
# the map that takes the drift inside the window out of its points (or None).
PlanesTask = tuple[QuasiStaticSequence, int, PlanesConfig, SensorTrack | None, WindowMap | None]


def scan_planes(task: PlanesTask) -> tuple[Station, tuple[Plane, ...]]:
    """One scan's planes and its station (a top-level function: it runs on worker processes).
    The task carries the sequence's small index (windows, spill paths), the sensor's track
    through the window (:func:`~kinreg.estimate.slicing.sensor_track`, or None) and a map that
    deskews the scan's points before its planes are detected
    (:func:`~kinreg.estimate.drift.deskewed_points`, or None), never the points."""
    sequence, i, config, track, mapped = task
    scan = sequence.read_scan(i)
    if mapped is not None and track is not None and scan.stamps_s is not None:
        scan = replace(scan, points_xyz=deskewed_points(mapped, scan.points_xyz, scan.stamps_s - scan.t_s, track))
    found = detect_planes(scan, config)
    tau = float("nan")
    if scan.stamps_s is not None:
        times = plane_time_offsets(scan.points_xyz, scan.stamps_s, scan.t_s, found, config.refit_distance_m, track)
        found = facing_the_sensor(times.applied(found), config.refit_distance_m)
        tau = rms_time_offset(times.offsets)
    station = Station(scan.scan_id, scan.name, scan.kind, scan.t_s, scan.t_start_s, scan.t_end_s,
                      scan.T_obj_scan, len(scan), tau)
    return station, found


def _tasks(sequence: QuasiStaticSequence, indices: Iterable[int], config: PlanesConfig,
           trajectory: Trajectory | None, maps: Mapping[int, WindowMap]) -> Iterator[PlanesTask]:
    for i in indices:
        yield (sequence, i, config, None if trajectory is None else sensor_track(trajectory, sequence.windows[i]),
               maps.get(i))


def detect_all_planes(sequence: QuasiStaticSequence, config: PlanesConfig, progress: Progress,
                      executor: ExecutorContext | None = None,
                      trajectory: Trajectory | None = None) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """Planes of every quasi-static scan, and the stations they belong to (on ``executor``; in this
    process without one). The result does not depend on the number of workers. With the
    ``trajectory`` the run was sliced with, each plane also knows where the sensor was while it
    saw it (:attr:`~kinreg.types.Plane.sensor_xyz`)."""
    progress.start("planes", total=len(sequence), unit="scans")
    results = parallel_map(scan_planes, _tasks(sequence, range(len(sequence)), config, trajectory, {}),
                           executor or in_process(), progress)
    progress.finish()
    return [r[0] for r in results], [r[1] for r in results]


def detect_planes_cached(slices: CachedSlices, config: PlanesConfig, progress: Progress,
                         executor: ExecutorContext, run: RunCache,
                         trajectory: Trajectory | None = None,
                         maps: Mapping[int, WindowMap] | None = None) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """:func:`detect_all_planes` through the stage cache: each scan is looked up under (slice
    key, scan index, ``[planes]``, its deskew map); the others are detected and stored as each
    finishes, so that an interrupted run keeps the scans it finished. The points are read only when
    a scan is missing. ``maps``: per scan index, the map that deskews its points
    (:func:`~kinreg.estimate.drift.deskewed_points`)."""
    maps = maps or {}
    keys = [run.key("planes", slices.key, i, config, *(maps[i].key_parts() if i in maps else ()))
            for i in range(len(slices))]
    results: list[tuple[Station, tuple[Plane, ...]] | None] = []
    for key in keys:
        entry = run.load("planes", key)
        results.append(None if entry is None else scan_planes_from_arrays(entry.arrays))
    missing = [i for i, r in enumerate(results) if r is None]
    run.count("planes", reused=len(keys) - len(missing), computed=len(missing))
    if len(missing) < len(keys):
        log.info("planes: %d of %d scans re-used from the stage cache", len(keys) - len(missing), len(keys))
    sequence = slices.sequence() if missing else None  # points are read only for scans not in the cache

    def keep(index: int, result: tuple[Station, tuple[Plane, ...]]) -> None:
        run.store("planes", keys[missing[index]], scan_planes_to_arrays(*result))
        results[missing[index]] = result

    progress.start("planes", total=len(keys), unit="scans")
    progress.advance(len(keys) - len(missing))
    if sequence is not None:
        parallel_map(scan_planes, _tasks(sequence, missing, config, trajectory, maps), executor, progress,
                     on_result=keep)
    progress.finish()
    done = [r for r in results if r is not None]
    return [r[0] for r in done], [r[1] for r in done]


def static_scan_name(name: str, k: int) -> str:
    """The station name of the static E57 file's scan ``k`` (its ``name``; else by its position)."""
    return name or f"static_{k:03d}"


def static_scan_names(path: Path) -> list[str]:
    """The station names of a static E57 file's scans, in file order (headers only: cheap)."""
    from kinreg.io.e57 import list_e57_scans

    return [static_scan_name(h.name, k) for k, h in enumerate(list_e57_scans(path))]


def detect_static_planes(path: Path | None, first_id: int, config: PlanesConfig, progress: Progress,
                         run: RunCache | None = None) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """Planes of every static scan of a registered E57 (poses in the object frame required);
    none without ``path``. With ``run``, each scan is looked up in (and stored into) its stage cache."""
    if path is None:
        return [], []
    from kinreg.io.e57 import list_e57_scans, read_e57_scan

    headers = list_e57_scans(path)
    stations: list[Station] = []
    planes: list[tuple[Plane, ...]] = []
    progress.start("static planes", total=len(headers), unit="scans")
    for k in range(len(headers)):
        key = run.key("static-planes", path, k, first_id, config) if run is not None else ""
        entry = run.load("static-planes", key) if run is not None else None
        if entry is not None:
            station, found = scan_planes_from_arrays(entry.arrays)
        else:
            scan = replace(read_e57_scan(path, k, require_pose=True), scan_id=first_id + k)
            found = tuple(replace(p, scan_id=scan.scan_id) for p in detect_planes(scan, config))
            nan = float("nan")
            station = Station(scan.scan_id, static_scan_name(scan.name, k), ScanKind.STATIC, nan, nan, nan,
                              scan.T_obj_scan, len(scan))
        if run is not None:
            if entry is None:
                run.store("static-planes", key, scan_planes_to_arrays(station, found))
            run.count("static planes", reused=int(entry is not None), computed=int(entry is None))
        stations.append(station)
        planes.append(found)
        progress.advance(1)
    progress.finish()
    return stations, planes


def link_stations_cached(stations: list[Station], planes: list[tuple[Plane, ...]], config: KinregConfig,
                         static: StaticConfig | None, progress: Progress, executor: ExecutorContext,
                         run: RunCache) -> list[Link]:
    """:func:`~kinreg.estimate.network.link_stations` through the stage cache, keyed by the stations and
    planes themselves (so also by anything that moved them, e.g. ``[initial_transform]``) and
    ``[matching]``, ``[drift]``, ``[pairwise]``, ``[static]``."""
    # Coarse to fine: the first links are the sequence neighbours' (and the static scans' and other
    # runs'); loop closures within a run wait for the relinking from the adjusted poses, once the
    # drift is measured and taken out. Matched on the drifted trajectory, a loop closure across a
    # drift larger than the prior's found parallel planes 0.2 m off on a 0.5 m / 2 deg run and
    # moved its stations by as much.
    loops = config.block.max_relink_rounds == 0
    key = run.key("link", *content_parts(stations, planes), config.matching, config.drift, config.pairwise, static,
                  loops)
    entry = run.load("link", key)
    if entry is not None:
        run.count("link", reused=1)
        log.info("link: the pairwise links are re-used from the stage cache")
        return links_from_arrays(entry.arrays)
    links = link_stations(stations, planes, config.matching, config.drift, config.pairwise, progress, static,
                          executor, loops=loops)
    run.store("link", key, links_to_arrays(links))
    run.count("link", computed=1)
    return links


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


def adjust_with_measured_drift(
    network: Network,
    planes: list[tuple[Plane, ...]],
    static: StaticConfig | None,
    config: KinregConfig,
    progress: Progress,
    executor: ExecutorContext | None = None,
    trajectories: Sequence[Trajectory] = (),
    points_deskewed: FloatArray | None = None,
    start_coupling: float | None = None,
) -> AdjustedNetwork:
    """The block adjustment of ``network`` with the drift it measures: the first adjustment measures
    the drift rates and the coupling (:func:`~kinreg.estimate.drift.estimate_drift_rates`); the pairs
    are then linked again from the adjusted poses (on ``executor``) and the network adjusted again,
    until the linked pairs no longer change (``[block] max_relink_rounds``); a last pass forms the
    trajectory's links with the final rates and coupling, so that the planes' window deformation
    and the stretches carried by the trajectory alone get honest sigmas. ``points_deskewed``: the
    planes were detected on points an earlier adjustment deskewed (:func:`~kinreg.estimate.drift.deskewed_points`),
    and this (n, 6, 6) is the drift velocity's covariance that deskew left
    (:func:`~kinreg.estimate.drift.window_velocity_covariance`): their parameters are not deskewed again.

    The first adjustment is made again with the coupling its network fits significantly better
    than the prior's (:func:`_coupling_by_fit`; where none, the coupling is read off it as before),
    or with ``start_coupling``; the last pass's network is asked the same, and where it fits a
    coupling of another regime significantly better than the one the rounds settled on
    (:data:`_COUPLING_DISAGREES`), the rounds start again from that one, once;
    ``coupling_disagrees`` says that they settled apart from it again."""
    given = (network, planes, static, config, progress, executor, trajectories, points_deskewed)
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
        links = link_stations(network.stations, deskewed if sheared else planes, config.matching, config.drift,
                              config.pairwise, progress, static, executor, rates, adjusted=result,
                              previous=() if faster or sheared else network.links, velocity_cov=velocity_cov)
        linked_with = rates if faster else linked_with
        used_planes = deskewed if sheared else planes
        same = _linked_pairs(links) == _linked_pairs(network.links)
        log.info("linked again from the adjusted poses: %d links (were %d)", len(links), len(network.links))
        network = replace(network.with_links(links), velocity_cov=velocity_cov)
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
        network, result, rates = _deskew_settled(network, planes, result, rates, prior_rates, config, progress,
                                                 trajectories)
    fitted = _coupling_by_fit(network, rates, config.block, progress, result, rates.coupling)
    disagrees = None
    if fitted is not None and abs(fitted - rates.coupling) > _COUPLING_DISAGREES:
        if start_coupling is None:
            log.warning("the adjusted network fits a coupling of %.2f (%s) better than the %.2f its rounds "
                        "settled on: adjusted again from %.2f", fitted, replace(rates, coupling=fitted).regime,
                        rates.coupling, fitted)
            return adjust_with_measured_drift(*given, start_coupling=fitted)
        disagrees = (rates.coupling, fitted)
    misfits, wrong = _warn_trajectory_misfits(result, config.block.alpha, config.matching)
    if not config.block.scan_frames:  # else the block carries the window bias (kinreg.estimate.frames)
        result = with_window_bias(result, network.stations, rates)
    return AdjustedNetwork(network, result, rates, tuple(misfits), tuple(wrong), disagrees)


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
                             config: KinregConfig, progress: Progress) -> tuple[float, float]:
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
                    prior: DriftRates, config: KinregConfig, progress: Progress,
                    trajectories: Sequence[Trajectory]) -> tuple[Network, BlockResult, DriftRates]:
    """The network's deskewed planes and its adjustment made to agree. The planes of the last pass
    were deskewed with the adjustment before it, and the last pass (plane nodes instead of links)
    moves the stations' corrections: deskewed with its own result, the planes of a GNSS/INS-like
    run (sample building, medium class, seed 1) moved by up to 3.5 of their sigmas, and the tilt
    errors of its large walls were 2.1 times their sigmas (0.7 once they agree). Deskewed again
    and adjusted again until no plane moves by more than :data:`_DESKEW_SETTLED` of its sigma
    (each round moves them about half as far as the last); the links are not formed again (a
    deskew keeps the planes' matches). Each adjustment again is made with the drift's spreads and
    floors that the one before measured (:func:`~kinreg.estimate.drift.with_measured_spread`);
    returns the rates the last was made with."""
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
        raise AdjustmentFailedError(checked_reason(result), result)
    return result


def checked_reason(result: BlockResult, report_in: Path | None = None) -> str:
    """The line a failed adjustment ends the run with; ``report_in``: the folder where a report
    marked failed was written (``[block] on_failure = "report"``)."""
    head = (f"the block adjustment failed: {result.failure} (sigma0 {result.sigma0:.3g}, redundancy "
            f"{result.redundancy:.0f})")
    if report_in is not None:
        return (f"{head}; report.json in {report_in} is marked failed, nothing else was written. Check the links "
                "in a `kinreg link` run")
    return (f"{head}; nothing was written. Check the links in a `kinreg link` run, or set [block] on_failure = "
            '"report" to keep a report marked failed')


# Pairs per task on an executor: a pair takes milliseconds, so single pairs would drown in overhead.
_PAIRS_PER_TASK = 64
_TILE = 8  # stations: see link_stations


def _link_batch(task: tuple) -> list[Link | None]:
    """A batch of pairs (a top-level function: it runs on worker processes)."""
    pairs, stations, planes, (matching, drift, pairwise, static), sigmas = task
    return link_pairs(pairs, stations, planes, matching, drift, pairwise, static, sigmas)


def link_stations(
    stations: Sequence[Station],
    planes: Sequence[tuple[Plane, ...]],
    matching: MatchingConfig,
    drift: DriftConfig,
    pairwise: PairwiseConfig,
    progress: Progress | None = None,
    static: StaticConfig | None = None,
    executor: ExecutorContext | None = None,
    rates: DriftRates | None = None,
    adjusted: BlockResult | None = None,
    previous: Sequence[Link] = (),
    loops: bool = True,
    velocity_cov: np.ndarray | None = None,
) -> list[Link]:
    """Pairwise links over all candidate pairs (see :func:`station_pairs`), on ``executor`` in
    batches (in this process without one). ``planes[k]`` are the planes of ``stations[k]``. Pairs
    with fewer than ``matching.min_matches`` plane matches are not linked. A pair with a static
    station has no trajectory between them: its prior comes from ``static.prior_sigma_*``; nor has
    a pair of two runs: its prior comes from ``pairwise.cross_run_prior_sigma_*``.
    ``rates`` are the drift rates for the planes' window deformation (default: the prior's).
    With an ``adjusted`` network the pairs are found, matched and given their prior from its
    poses (the prior's sigmas: twice the stations' adjusted sigmas combined, with the drift's
    floors), so that loop closures across an accumulated drift come within the gates.
    A ``previous`` link of a pair whose prior the adjustment moved by less than a tenth of the
    matching gates is kept as it is (matching it again would find the same planes).
    Returns the links in pair order, whatever the number of workers.
    """
    progress = progress or NullProgress()
    rates = rates or DriftRates.from_config(drift)
    sigmas = None
    initial = stations
    if adjusted is not None:
        stations = [replace(s, T_obj_scan=adjusted.poses[k]) for k, s in enumerate(stations)]
        # the drift's floors of the scanner's specification: the prior of a pair covers the matching's
        # own errors, not only the trajectory's floor that an adjustment measured
        prior = DriftRates.from_config(drift)
        floor = pose_sigmas(prior.pos_floor_m, prior.rot_floor_rad)
        own = np.sqrt(np.maximum(np.diagonal(adjusted.cov_xi, axis1=1, axis2=2), 0.0))
        sigmas = 2.0 * np.hypot(own, floor / np.sqrt(2.0))
    pairs = station_pairs(stations, matching, static, loops)
    kept = _unmoved_links(previous, pairs, initial, stations, matching) if adjusted is not None else {}
    todo = [pair for pair in pairs if pair not in kept]
    # Once per station, not once per pair: matching does not look at the covariances.
    planes = [with_window_deformation(p, s.T_obj_scan, rates, None if velocity_cov is None else velocity_cov[k])
              for k, (s, p) in enumerate(zip(stations, planes, strict=True))]
    configs = (matching, drift, pairwise, static)
    # Each task carries the stations and planes of its own pairs: pairs taken tile by tile of the
    # station indices (sequence neighbours and loop closures fall in few tiles) ship a station to
    # fewer tasks (at seed scale 25 stations a task instead of 65, 2.5x fewer bytes to pickle).
    tiled = sorted(todo, key=lambda pair: (pair[0] // _TILE, pair[1] // _TILE, pair))
    batches = [tiled[k:k + _PAIRS_PER_TASK] for k in range(0, len(tiled), _PAIRS_PER_TASK)]
    progress.start("link", total=len(batches), unit="batches")

    def task(batch: list[tuple[int, int]]) -> tuple:
        # Each task gets only the stations and planes of its own pairs.
        used = {k for pair in batch for k in pair}
        return (batch, {k: stations[k] for k in used}, {k: planes[k] for k in used}, configs,
                None if sigmas is None else {k: sigmas[k] for k in used})

    results = parallel_map(_link_batch, (task(b) for b in batches), executor or in_process(), progress)
    progress.finish()
    found = {(link.scan_i, link.scan_j): link for batch in results for link in batch if link is not None}
    links = [found.get(pair) or kept[pair] for pair in pairs if pair in found or pair in kept]
    n_rejected = sum(link.status is LinkStatus.REJECTED for link in links)
    log.info("%d candidate pairs, %d links (%d rejected, %d kept)", len(pairs), len(links), n_rejected, len(kept))
    return links


def _unmoved_links(previous: Sequence[Link], pairs: Sequence[tuple[int, int]], initial: Sequence[Station],
                   adjusted: Sequence[Station], matching: MatchingConfig) -> dict[tuple[int, int], Link]:
    """The ``previous`` links of ``pairs`` whose prior (the stations' relative pose) moved from
    ``initial`` to ``adjusted`` by less than a tenth of the matching gates."""
    old = {(link.scan_i, link.scan_j): link for link in previous}
    kept = {}
    for i, j in pairs:
        link = old.get((i, j))
        if link is None:
            continue
        before = initial[i].T_obj_scan.inverse().compose(initial[j].T_obj_scan)
        after = adjusted[i].T_obj_scan.inverse().compose(adjusted[j].T_obj_scan)
        moved = before.inverse().compose(after).log()
        if (np.linalg.norm(moved[:3]) < 0.1 * matching.max_offset_m
                and np.degrees(np.linalg.norm(moved[3:])) < 0.1 * matching.max_angle_deg):
            kept[(i, j)] = link
    return kept


def read_input_trajectory(path: str | Path, config: InputConfig) -> Trajectory:
    """The trajectory named in the inputs, read with the configured format and column mapping."""
    fmt = None if config.trajectory_format == "auto" else config.trajectory_format
    columns = parse_column_mapping(config.trajectory_columns) if config.trajectory_columns else None
    return read_trajectory(path, fmt, columns)


def read_run_trajectories(runs: Sequence[RunInputs], config: InputConfig,
                          static: Path | None = None) -> list[Trajectory]:
    """Each run's trajectory, after the inputs are checked against each other before the long work
    (:func:`~kinreg.io.checks.check_inputs`: time bases, static scans); a run whose cloud cannot
    be written corrected is refused first."""
    for r in runs:
        if r.cloud.suffix.lower() not in (".las", ".laz"):
            raise ConfigError("writing the corrected cloud from an E57 input is not supported yet", r.cloud)
    trajectories = [read_input_trajectory(r.trajectory, config) for r in runs]
    check_inputs([r.cloud for r in runs], trajectories, static, config)
    return trajectories


@dataclass(frozen=True, eq=False)
class KinematicStations:
    """The quasi-static stations of every run with their planes, in the frame of the reference
    planes (``[initial_transform]``), labelled by run, jumps taken out; the trajectories moved
    likewise, and each run's trajectory jumps."""

    stations: list[Station]
    planes: list[tuple[Plane, ...]]
    trajectories: list[Trajectory]
    jumps: list[list[TrajectoryJump]]


def detect_run_planes(sliced: Sequence[CachedSlices], trajectories: Sequence[Trajectory],
                      references: ReferencePlanes | None, config: KinregConfig, progress: Progress,
                      executor: ExecutorContext, run: RunCache,
                      maps: Mapping[int, WindowMap] | None = None) -> KinematicStations:
    """Planes and stations of every run (:func:`detect_planes_cached`), each run numbered after the
    previous one, moved into the reference frame and with its trajectory jumps taken out.
    ``maps``: per station (numbered as the result's), the map that deskews its scan's points."""
    stations: list[Station] = []
    planes: list[tuple[Plane, ...]] = []
    moved, jumps = list(trajectories), []
    for k, slices in enumerate(sliced):
        first = len(stations)
        run_maps = {i - first: m for i, m in (maps or {}).items() if first <= i < first + len(slices)}
        run_stations, run_planes = detect_planes_cached(slices, config.planes, progress, executor, run, trajectories[k],
                                                        run_maps)
        run_stations, moved[k] = to_reference_frame(run_stations, moved[k], references)  # [initial_transform]
        run_stations, run_planes = label_run(run_stations, run_planes, k, len(stations), len(sliced))
        run_stations, run_planes, run_jumps = take_out_jumps(run_stations, run_planes, moved[k], config.jumps)
        stations, planes = stations + run_stations, planes + run_planes
        jumps.append(run_jumps)
    return KinematicStations(stations, planes, moved, jumps)


@dataclass(frozen=True)
class LargeOutputs:
    """The keys of the large outputs (each corrected cloud, ``sequence.e57``) by what they are made
    of, and which of them are still current in the folder (kept, not written again)."""

    keys: dict[str, str]
    current: frozenset[str]


def plan_large_outputs(run: RunCache, runs: Sequence[RunInputs], sliced: Sequence[CachedSlices],
                       corrections: Sequence[DriftCorrection], poses: Pose, config: KinregConfig,
                       references: ReferencePlanes | None) -> LargeOutputs:
    """Key the large outputs and find which of them in the folder are still current (all but
    those are written again; the folder's others are replaced when the run commits its outputs)."""
    T_obj_cloud = None if references is None else references.T_ref_traj
    keys = {}
    for k, (r, correction) in enumerate(zip(runs, corrections, strict=True)):
        cloud_name = run_output_names(k, len(runs))[0]
        keys[cloud_name] = run.key("output", cloud_name, r.cloud, config.input.chunk_points, T_obj_cloud,
                                   config.input.cloud_time_offset_s, *dataclass_parts(correction))
    n_scans = sum(len(slices) for slices in sliced)
    keys["sequence.e57"] = run.key("output", "sequence.e57", *(slices.key for slices in sliced),
                                   poses[np.arange(n_scans)])
    current = frozenset(name for name, key in keys.items() if run.output_is_current(name, key))
    return LargeOutputs(keys, current)


def write_corrected_runs(out: Path, runs: Sequence[RunInputs], trajectories: Sequence[Trajectory],
                         corrections: Sequence[DriftCorrection], plan: LargeOutputs, run: RunCache,
                         config: KinregConfig, references: ReferencePlanes | None,
                         progress: Progress, views: PointObserver | None = None,
                         sliced: Sequence[CachedSlices] = ()) -> list[Trajectory]:
    """Each run's corrected trajectory and (unless still current) corrected cloud; returns the
    corrected trajectories. A run's cloud is read from the decoded copy its spill (of ``sliced``)
    kept, where there is one, else decoded again."""
    T_obj_cloud = None if references is None else references.T_ref_traj
    corrected = [c.apply_to_trajectory(t) for c, t in zip(corrections, trajectories, strict=True)]
    names = [run_output_names(k, len(runs)) for k in range(len(runs))]
    for (_, trajectory_name), trajectory in zip(names, corrected, strict=True):
        write_trajectory_geoslam(out / trajectory_name, trajectory, overwrite=True)
    for k, ((cloud_name, _), r, correction) in enumerate(zip(names, runs, corrections, strict=True)):
        if cloud_name not in plan.current:
            write_corrected_las(r.cloud, out / cloud_name, correction, config.input.chunk_points,
                                overwrite=True, progress=progress, T_obj_cloud=T_obj_cloud,
                                time_offset_s=config.input.cloud_time_offset_s, observer=views,
                                records=sliced[k].records() if k < len(sliced) else None)
            run.record_output(cloud_name, plan.keys[cloud_name])
        run.count("corrected cloud", reused=int(cloud_name in plan.current),
                  computed=int(cloud_name not in plan.current))
    return corrected


def counted(scans: Iterator[Scan], progress: Progress, stage: str, total: int) -> Iterator[Scan]:
    """``scans`` passed through, with progress per scan."""
    progress.start(stage, total=total, unit="scans")
    for scan in scans:
        yield scan
        progress.advance(1)
    progress.finish()


def start_sequence(out: Path, sliced: Sequence[CachedSlices], poses: Pose, plan: LargeOutputs,
                   executor: ExecutorContext, crs_wkt: str = "") -> Future[None] | None:
    """Start writing ``sequence.e57`` on one of the local worker processes, so that it overlaps
    the corrected cloud written in this process (the worker reads the scans from the spill), and
    return its future; ``None`` when it is still current or the executor has no local processes
    (a Dask worker may not see the output folder): then :func:`write_sequence` writes it."""
    if "sequence.e57" in plan.current or executor.kind != "processes":
        return None
    n_scans = sum(len(slices) for slices in sliced)
    sequences = [slices.sequence() for slices in sliced]
    return executor.executor.submit(write_sequence_file, out / "sequence.e57", sequences, poses[np.arange(n_scans)],
                                    crs_wkt)


def write_sequence_file(path: Path, sequences: Sequence[QuasiStaticSequence], poses: Pose, crs_wkt: str = "",
                        progress: Progress | None = None) -> None:
    """``sequence.e57`` of the runs' open sequences with the adjusted ``poses`` (a top-level
    function: it runs on a worker process)."""
    from kinreg.io.e57_writer import write_e57_sequence

    n_scans = sum(len(sequence) for sequence in sequences)
    scans = adjusted_sequence_scans(sequences, poses)
    write_e57_sequence(path, counted(scans, progress, "write E57", n_scans) if progress is not None else scans,
                       overwrite=True, coordinate_metadata=crs_wkt)


def write_sequence(out: Path, sliced: Sequence[CachedSlices], poses: Pose, plan: LargeOutputs, run: RunCache,
                   progress: Progress, crs_wkt: str = "", started: Future[None] | None = None) -> None:
    """``sequence.e57``: the quasi-static scans of every run with their adjusted poses (unless still
    current); with ``started`` (:func:`start_sequence`), waits for the worker writing it."""
    done = "sequence.e57" in plan.current
    if not done:
        n_scans = sum(len(slices) for slices in sliced)
        if started is not None:
            progress.start("write E57", total=n_scans, unit="scans")
            started.result()  # raises the worker's error
            progress.advance(n_scans)
            progress.finish()
        else:
            write_sequence_file(out / "sequence.e57", [slices.sequence() for slices in sliced],
                                poses[np.arange(n_scans)], crs_wkt, progress)
        run.record_output("sequence.e57", plan.keys["sequence.e57"])
    run.count("sequence E57", reused=int(done), computed=int(not done))
