"""The link stage: every candidate pair of stations linked pairwise, in batches on the executor's
workers; the first links through the output folder's stage cache."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from kinreg.config import DriftConfig, KinregConfig, MatchingConfig, PairwiseConfig, StaticConfig
from kinreg.estimate.drift import DriftRates, with_window_deformation
from kinreg.estimate.network import link_pairs, pair_inputs, station_pairs
from kinreg.estimate.pairwise import MODEL_TOLERANCE, LinkModel, estimate_link_model, pooled_sigma0
from kinreg.geometry import pose_sigmas
from kinreg.progress import NullProgress, Progress
from kinreg.run.codecs import link_model_from_arrays, link_model_to_arrays, links_from_arrays, links_to_arrays
from kinreg.run.executor import ExecutorContext, in_process, parallel_map
from kinreg.run.output_folder import RunCache, content_parts
from kinreg.types import BlockResult, Link, LinkStatus, Plane, Station

log = logging.getLogger(__name__)


def link_stations_cached(stations: list[Station], planes: list[tuple[Plane, ...]], config: KinregConfig,
                         static: StaticConfig | None, progress: Progress, executor: ExecutorContext,
                         run: RunCache) -> tuple[list[Link], LinkModel]:
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
        return links_from_arrays(entry.arrays), link_model_from_arrays(entry.arrays)
    links, model = link_stations(stations, planes, config.matching, config.drift, config.pairwise, progress, static,
                                 executor, loops=loops)
    run.store("link", key, {**links_to_arrays(links), **link_model_to_arrays(model)})
    run.count("link", computed=1)
    return links, model


_PAIRS_PER_TASK = 64
_TILE = 8  # stations: see link_stations


def _link_batch(task: tuple) -> list[Link | None]:
    """A batch of pairs (a top-level function: it runs on worker processes)."""
    pairs, stations, planes, (matching, drift, pairwise, static, model), sigmas = task
    return link_pairs(pairs, stations, planes, matching, drift, pairwise, static, sigmas, model)


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
) -> tuple[list[Link], LinkModel]:
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
    Where the links do not fit the a-priori model of their planes and the trajectory (real
    surfaces are not planes; :data:`~kinreg.estimate.pairwise.MODEL_TOLERANCE`), the model is
    estimated from all of them (:func:`~kinreg.estimate.pairwise.estimate_link_model`) and every
    pair linked again with it, before a link is tested against a model it cannot fit.
    Returns the links in pair order, whatever the number of workers, and the model they were
    adjusted with.
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
    links = _link_todo(todo, pairs, kept, stations, planes, sigmas, (matching, drift, pairwise, static, None),
                       progress, executor)
    model = LinkModel()
    sigma0, n_pooled = pooled_sigma0(links)
    if n_pooled and sigma0 > MODEL_TOLERANCE:
        inputs = pair_inputs(todo, dict(enumerate(stations)), dict(enumerate(planes)), matching, pairwise, static,
                             None if sigmas is None else dict(enumerate(sigmas)))
        model = estimate_link_model([p for p in inputs if p is not None], drift, pairwise)
        if model.estimated:
            links = _link_todo(todo, pairs, kept, stations, planes, sigmas,
                               (matching, drift, pairwise, static, model), progress, executor)
    n_rejected = sum(link.status is LinkStatus.REJECTED for link in links)
    log.info("%d candidate pairs, %d links (%d rejected, %d kept)", len(pairs), len(links), n_rejected, len(kept))
    return links, model


def _link_todo(todo: list[tuple[int, int]], pairs: Sequence[tuple[int, int]], kept: dict[tuple[int, int], Link],
               stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]], sigmas: np.ndarray | None,
               configs: tuple, progress: Progress, executor: ExecutorContext | None) -> list[Link]:
    """The links of the pairs ``todo`` on ``executor`` in batches, with the ``kept`` ones, in the
    order of ``pairs``."""
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
    return [found.get(pair) or kept[pair] for pair in pairs if pair in found or pair in kept]


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

