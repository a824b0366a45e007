"""The estimation of ``kinreg process`` on the machinery of :mod:`kinreg.run`: the operations the
strategy (:mod:`kinreg.estimate.strategy`) is handed, built on the stage cache, the executor and
the spill; a failed estimation's outputs and report; the drift correction of each run."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kinreg.config import KinregConfig
from kinreg.errors import AdjustmentFailedError
from kinreg.estimate.control import tie_points
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.datum import build_network
from kinreg.estimate.drift import DriftRates, WindowMap
from kinreg.estimate.network import Network
from kinreg.estimate.pairwise import LinkModel
from kinreg.estimate.strategy import (
    AdjustedNetwork,
    Estimate,
    Operations,
    StrategyConfig,
    estimate_quasi_static,
)
from kinreg.run.context import RunContext
from kinreg.run.failed_run import fail_adjustment
from kinreg.run.link_stage import link_stations, link_stations_cached
from kinreg.run.output_folder import CachedSlices, sliced_run
from kinreg.run.planes_stage import KinematicStations, detect_run_planes, detect_static_planes
from kinreg.run.runs import inputs_report, run_correction
from kinreg.types import BlockResult, Link, Plane, Station, Trajectory


@dataclass(frozen=True, eq=False)
class RunSlicing:
    """One slicing of every run (the strategy's :class:`~kinreg.estimate.strategy.SlicedNetwork`):
    its scans (their spills open on the run's stack), stations and planes (kinematic, then static),
    and the network of its first links; ``config`` has the windows it was sliced with."""

    config: KinregConfig
    sliced: list[CachedSlices]
    kinematic: KinematicStations
    stations: list[Station]
    planes: list[tuple[Plane, ...]]
    network: Network

    @property
    def trajectories(self) -> list[Trajectory]:
        return self.kinematic.trajectories


@dataclass(frozen=True, eq=False)
class Estimated:
    """The chosen estimate and the configuration it was made with (its windows)."""

    estimate: Estimate[RunSlicing]

    @property
    def config(self) -> KinregConfig:
        return self.estimate.sliced.config

    @property
    def sliced(self) -> list[CachedSlices]:
        return self.estimate.sliced.sliced

    @property
    def kinematic(self) -> KinematicStations:
        return self.estimate.sliced.kinematic

    @property
    def trajectories(self) -> list[Trajectory]:
        return self.estimate.sliced.trajectories

    @property
    def stations(self) -> list[Station]:
        return self.estimate.sliced.stations

    @property
    def planes(self) -> list[tuple[Plane, ...]]:
        return self.estimate.sliced.planes

    @property
    def adjusted(self) -> AdjustedNetwork:
        return self.estimate.adjusted


def estimate(run: RunContext) -> Estimated:
    """Slice, detect planes, link and adjust, in the rounds of
    :func:`~kinreg.estimate.strategy.estimate_quasi_static`. Raises
    :class:`~kinreg.errors.AdjustmentFailedError` (after :func:`fail_adjustment`: the folder's
    outputs removed, a report marked failed where ``[block] on_failure = "report"``) where an
    adjustment fails or the chosen network is no result."""
    on_run = _RunOperations(run)
    operations = Operations(on_run.sliced_network, on_run.link_again, on_run.pass_adjusted, run.progress)
    try:
        chosen = estimate_quasi_static(operations, StrategyConfig.from_config(run.config))
    except AdjustmentFailedError as e:
        last = on_run.last
        assert last is not None  # an adjustment fails only once a slicing is there
        fail_adjustment(e.result, last.network, last.config, run.folder, _report_inputs(run, last), last.planes)
    if chosen.failure:
        failed = dataclasses.replace(chosen.adjusted.result, failure=chosen.failure)
        fail_adjustment(failed, chosen.adjusted.network, chosen.sliced.config, run.folder,
                        _report_inputs(run, chosen.sliced), chosen.sliced.planes)
    return Estimated(chosen)


def correct_runs(estimated: Estimated) -> list[DriftCorrection]:
    """Each run's drift correction, from its own stations' adjusted poses."""
    adjusted, kinematic = estimated.adjusted, estimated.kinematic
    return [run_correction(estimated.stations, adjusted.result, k, trajectory, kinematic.jumps[k],
                           adjusted.rates.coupling) for k, trajectory in enumerate(kinematic.trajectories)]


class _RunOperations:
    """The strategy's operations on one run's machinery; remembers the last slicing, whose
    decoded points the next one reads and whose network a failed adjustment reports."""

    def __init__(self, run: RunContext) -> None:
        self.run = run
        self.last: RunSlicing | None = None
        self.static = run.config.static if run.inputs.static is not None else None

    def sliced_network(self, window_s: float, deskew_maps: Mapping[int, WindowMap]) -> RunSlicing:
        """Slice every run (its spill kept open on the run's stack), detect planes (and the static
        scans'), link the first pairs and build the network, each through the stage cache."""
        run, given = self.run, self.run.config
        config = given if window_s == given.slicing.window_s else with_window(given, window_s)
        decoded = [] if self.last is None else [slices.records() for slices in self.last.sliced]
        trajectories, references, control = run.read.trajectories, run.read.references, run.read.control
        sliced = [run.stack.enter_context(sliced_run(run.folder, r.trajectory, r.cloud, trajectories[k], config,
                                                     run.progress, k, decoded[k] if k < len(decoded) else None))
                  for k, r in enumerate(run.inputs.runs)]
        run.clock.lap("slice")
        kinematic = detect_run_planes(sliced, trajectories, references, config, run.progress, run.executor,
                                      run.folder, deskew_maps)
        static_stations, static_planes = detect_static_planes(run.inputs.static, len(kinematic.stations),
                                                              config.planes, run.progress, run.folder)
        stations, planes = kinematic.stations + static_stations, kinematic.planes + static_planes
        run.clock.lap("planes")
        links, model = link_stations_cached(stations, planes, config, self.static, run.progress, run.executor,
                                            run.folder)
        run.clock.lap("link")
        controls = () if control is None else tie_points(control, stations, kinematic.trajectories, config.control)
        network = dataclasses.replace(build_network(stations, planes, links, references, self.static, config, controls),
                          link_model=model)
        self.last = RunSlicing(config, sliced, kinematic, stations, planes, network)
        return self.last

    def link_again(self, stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]], rates: DriftRates,
                   adjusted: BlockResult, previous: Sequence[Link],
                   velocity_cov: np.ndarray | None) -> tuple[list[Link], LinkModel]:
        """Every candidate pair linked again from the ``adjusted`` poses, on the executor."""
        config = self.run.config
        return link_stations(stations, planes, config.matching, config.drift, config.pairwise, self.run.progress,
                             self.static, self.run.executor, rates, adjusted=adjusted, previous=previous,
                             velocity_cov=velocity_cov)

    def pass_adjusted(self) -> None:
        self.run.folder.count("block", computed=1)
        self.run.clock.lap("block")


def _report_inputs(run: RunContext, slicing: RunSlicing) -> dict[str, Any]:
    return inputs_report(run.inputs.runs, slicing.trajectories, slicing.sliced, run.inputs.static,
                         run.inputs.reference)


def with_window(config: KinregConfig, window_s: float) -> KinregConfig:
    """``config`` with quasi-static windows of ``window_s`` seconds."""
    return dataclasses.replace(config, slicing=dataclasses.replace(config.slicing, window_s=window_s))

