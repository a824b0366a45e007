"""The pipelines, readable top to bottom: each line names one stage.

``process`` runs per-scan and per-pair work on ``workers`` local processes (``None``: every core;
1: in this process) or on the Dask cluster at ``scheduler``; results do not depend on either.
Each stage keeps its results in the output folder's stage cache (:mod:`kinreg.run.output_folder`).
A folder that holds results or a cache is refused, unless ``resume`` (re-use the cache: only
stages whose inputs changed are done again, and the outputs are rewritten) or ``overwrite``
(start afresh). A run killed at any point and resumed gives the same outputs as one that ran
through. One run writes into a folder at a time, and its outputs appear there together at its
end (the writer lock and the staged outputs of :mod:`kinreg.run.output_folder`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import shutil
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from kinreg.config import (
    KinregConfig,
    OnFailure,
    StaticConfig,
    format_toml,
)
from kinreg.errors import AdjustmentFailedError, ConfigError
from kinreg.estimate.control import Assignment, assign_points, tie_points
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.datum import build_network
from kinreg.estimate.drift import (
    MAP_NEIGHBOURS,
    MIXED_COUPLING,
    DriftRates,
    deskewed_planes,
    window_maps,
    window_velocity_covariance,
)
from kinreg.estimate.matching import candidate_pairs
from kinreg.estimate.network import Network, station_pairs
from kinreg.estimate.reference import to_reference_frame
from kinreg.estimate.slicing import shorter_window_s, window_smear_m
from kinreg.estimate.snooping import misfit_text, models_rejected
from kinreg.io.atomic import check_writable_target
from kinreg.io.checks import check_inputs, time_filter
from kinreg.io.cloud import open_cloud
from kinreg.io.control import read_control_points
from kinreg.io.reference_planes import ReferencePlanes, read_reference_planes
from kinreg.progress import NullProgress, Progress
from kinreg.report.cloud_views import FIGURES_DIR, cloud_views_for_runs
from kinreg.report.control import check_section, control_section, format_control_points_csv
from kinreg.report.html import render_html
from kinreg.report.json import build_failure_report, build_report, write_report_json
from kinreg.report.tables import (
    format_links_csv,
    format_planes_csv,
    format_stations_csv,
    links_table,
    stations_table,
    write_text,
)
from kinreg.run.executor import ExecutorContext, make_executor
from kinreg.run.output_folder import (
    CachedSlices,
    RunCache,
    open_output_folder,
    sliced_run,
)
from kinreg.run.runs import (
    RunInputs,
    inputs_report,
    run_correction,
    slicing_report,
    trajectory_plot,
)
from kinreg.run.spill import QuasiStaticSequence, slice_quasi_static
from kinreg.run.stages import (
    AdjustedNetwork,
    KinematicStations,
    adjust_with_measured_drift,
    checked_reason,
    counted,
    detect_all_planes,
    detect_run_planes,
    detect_static_planes,
    link_stations,
    link_stations_cached,
    plan_large_outputs,
    read_input_trajectory,
    read_run_trajectories,
    start_sequence,
    static_scan_names,
    write_corrected_runs,
    write_sequence,
)
from kinreg.types import (
    BlockResult,
    ObservationKind,
    Plane,
    SlicingSummary,
    Station,
    Trajectory,
)

log = logging.getLogger(__name__)




def read_and_slice(
    trajectory_path: str | Path, cloud_path: str | Path, config: KinregConfig, progress: Progress
) -> tuple[Trajectory, int, QuasiStaticSequence]:
    """The input trajectory, the cloud's point count, and the cloud sliced into quasi-static scans."""
    trajectory = read_input_trajectory(trajectory_path, config.input)
    check_inputs([cloud_path], [trajectory], None, config.input)
    with open_cloud(cloud_path, times=time_filter(config.input)) as cloud:
        sequence = slice_quasi_static(trajectory, cloud, config.slicing, config.input.chunk_points,
                                      progress=progress)
        return trajectory, cloud.info.n_points, sequence




def slice_to_e57(
    trajectory_path: str | Path,
    cloud_path: str | Path,
    out_path: str | Path,
    config: KinregConfig,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> SlicingSummary:
    """``kinreg slice``: read, slice into quasi-static scans, export one E57 sequence."""
    from kinreg.io.e57_writer import write_e57_sequence

    progress = progress or NullProgress()
    check_writable_target(Path(out_path), overwrite)  # fail before the long work, not after
    _, _, sequence = read_and_slice(trajectory_path, cloud_path, config, progress)
    with sequence:
        scans = counted(sequence.iter_scans(), progress, "export E57", len(sequence))
        write_e57_sequence(out_path, scans, overwrite=overwrite)
    return sequence.summary


@dataclass(frozen=True)
class ProcessInputs:
    """What ``kinreg process`` reads: one or several runs (``trajectory`` and ``cloud`` are the
    first, ``more_runs`` the others, in order; see :mod:`kinreg.run.runs`), static scans, reference planes."""

    trajectory: Path
    cloud: Path
    static: Path | None = None
    reference: Path | None = None
    more_runs: tuple[RunInputs, ...] = ()
    control: Path | None = None  # control points (CSV): observations of the adjustment
    check: Path | None = None  # check points (CSV): only compared

    @property
    def runs(self) -> tuple[RunInputs, ...]:
        return (RunInputs(Path(self.trajectory), Path(self.cloud)), *self.more_runs)

    @classmethod
    def from_runs(cls, trajectories: Sequence[str | Path], clouds: Sequence[str | Path],
                  static: Path | None = None, reference: Path | None = None, control: Path | None = None,
                  check: Path | None = None) -> ProcessInputs:
        """Runs paired in order: ``trajectories[k]`` with ``clouds[k]``. Raises :class:`ConfigError`
        when the counts differ, none is given, or a file is given twice."""
        if len(trajectories) != len(clouds):
            raise ConfigError(f"{len(trajectories)} trajectories (--trajectory) but {len(clouds)} clouds (--cloud): "
                              "give one cloud per trajectory, paired in order")
        if not trajectories:
            raise ConfigError("no run given: give a trajectory (--trajectory) and its cloud (--cloud)")
        runs = [RunInputs(Path(t), Path(c)) for t, c in zip(trajectories, clouds, strict=True)]
        for paths in ([r.trajectory for r in runs], [r.cloud for r in runs]):
            seen = [path.resolve() for path in paths]
            twice = next((path for k, path in enumerate(paths) if seen[k] in seen[:k]), None)
            if twice is not None:
                raise ConfigError("given for two runs", twice)
        return cls(runs[0].trajectory, runs[0].cloud, static, reference, tuple(runs[1:]), control, check)


@dataclass(frozen=True)
class ProcessSummary:
    """The headline figures of a processed run (the full report is in ``report.json``)."""

    out_dir: Path
    n_stations: int
    n_links: int
    sigma0: float
    global_test_passed: bool
    position_sigma_rms_mm: float
    position_sigma_max_mm: float
    gaps_mean_mm: float
    gaps_max_mm: float
    n_rejected: int
    timings_s: dict[str, float]
    # per stage: {"reused": n, "computed": m} items (scans, files) of this run
    stage_cache: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    n_runs: int = 1
    control_rejected: tuple[str, ...] | None = None  # None: no control points given
    check_rms_mm: float | None = None  # 3D RMS of the check differences; None: no check points
    check_loa: str = ""

    @classmethod
    def from_report(cls, out_dir: Path, report: dict[str, Any]) -> ProcessSummary:
        """The headline figures of ``report`` (:func:`~kinreg.report.json.build_report`)."""
        stations, adjustment = report["stations"], report["adjustment"]
        return cls(
            out_dir=out_dir,
            n_stations=stations["n"],
            n_links=report["links"]["n_links"],
            sigma0=adjustment["sigma0"],
            global_test_passed=adjustment["global_test_passed"],
            position_sigma_rms_mm=stations["position_sigma_mm"]["rms"],
            position_sigma_max_mm=stations["position_sigma_mm"]["max"],
            gaps_mean_mm=report["before_after"]["gaps_mm"]["mean"],
            gaps_max_mm=report["before_after"]["gaps_mm"]["max"],
            n_rejected=len(adjustment["rejected_observations"]),
            timings_s=report["timings_s"],
            stage_cache=report["stage_cache"],
            n_runs=len(report["inputs"]["runs"]),
            control_rejected=tuple(report["control"]["rejected"]) if "control" in report else None,
            check_rms_mm=report["check"]["summary"]["d3d_mm"]["rms"] if "check" in report else None,
            check_loa=report["check"]["loa"]["class"] if "check" in report else "",
        )


class StageClock:
    """Seconds per stage, each from the end of the previous one."""

    def __init__(self) -> None:
        self.timings_s: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        """The time since the last lap, added to ``stage`` (a stage done twice counts twice)."""
        now = time.perf_counter()
        self.timings_s[stage] = self.timings_s.get(stage, 0.0) + now - self._last
        self._last = now


OUTPUT_FILES = ("stations.csv", "links.csv", "trajectory_corrected.txt", "corrected.laz", "sequence.e57",
                "report.json", "report.html", "config.toml", "control_points.csv")


@contextlib.contextmanager
def prepare_output_folder(out_dir: Path, overwrite: bool, resume: bool = False, n_runs: int = 1) -> Iterator[RunCache]:
    """Create the output folder, hold its writer lock while the block runs, and open its stage
    cache. A folder that another kinreg writes into, or that already holds kinreg results (any of
    :data:`OUTPUT_FILES`) or a stage cache, is refused unless ``resume`` (re-use the cache) or
    ``overwrite`` (start afresh: the cache is cleared); see
    :func:`kinreg.run.output_folder.open_output_folder`."""
    with open_output_folder(out_dir, OUTPUT_FILES, n_runs, overwrite=overwrite, resume=resume) as run:
        check_writable_target(out_dir / "stations.csv", overwrite=True)
        yield run


def process(inputs: ProcessInputs, out_dir: str | Path, config: KinregConfig, overwrite: bool = False,
            progress: Progress | None = None, workers: int | None = 1, scheduler: str | None = None,
            resume: bool = False) -> ProcessSummary:
    """``kinreg process``: read, slice, detect planes, link, adjust, correct, report (see the
    module's docstring for ``workers``, ``scheduler``, ``resume`` and ``overwrite``). The outputs
    are written into the folder's staging folder and moved into place together at the end."""
    progress, out, clock, runs = progress or NullProgress(), Path(out_dir), StageClock(), inputs.runs
    with prepare_output_folder(out, overwrite, resume, len(runs)) as folder, contextlib.ExitStack() as stack:
        references = read_reference_planes(inputs.reference) if inputs.reference is not None else None
        static = config.static if inputs.static is not None else None
        trajectories = read_run_trajectories(runs, config.input, inputs.static)
        control, check = read_points(inputs, trajectories, references, config)  # before the long work
        executor = stack.enter_context(make_executor(workers, scheduler))
        est, config = estimate_quasi_static(stack, folder, inputs, trajectories, references, config, progress,
                                            executor, clock, control)
        sliced, kinematic, stations, planes, adjusted = (est.sliced, est.kinematic, est.stations, est.planes,
                                                         est.adjusted)
        corrections = [run_correction(stations, adjusted.result, k, kinematic.trajectories[k], kinematic.jumps[k],
                                      adjusted.rates.coupling) for k in range(len(runs))]
        plan = plan_large_outputs(folder, runs, sliced, corrections, adjusted.result.poses, config, references)
        views = cloud_views_for_runs(config.report, [r.cloud for r in runs], kinematic.trajectories, references,
                                     inputs.static)
        staging = folder.start_outputs()  # every output goes here first
        # sequence.e57 on a worker process (where there are local ones) while this one writes the
        # corrected clouds: both are single-threaded for much of their time.
        sequence_job = start_sequence(staging, sliced, adjusted.result.poses, plan, executor,
                                      views.crs.get("wkt", ""))
        corrected = write_corrected_runs(staging, runs, kinematic.trajectories, corrections, plan, folder, config,
                                         references, progress, views, sliced)
        clock.lap("corrected cloud")
        write_sequence(staging, sliced, adjusted.result.poses, plan, folder, progress, views.crs.get("wkt", ""),
                       sequence_job)
        clock.lap("sequence E57")
        stack.close()  # the workers and the spill are no longer needed
        report = build_report(
            inputs=inputs_report(runs, kinematic.trajectories, sliced, inputs.static, inputs.reference),
            config_toml=format_toml(config), network=adjusted.network, planes=planes,
            n_candidate_pairs=len(station_pairs(stations, config.matching, static)), result=adjusted.result,
            drift_rates=adjusted.rates, slicing=slicing_report([slices.summary for slices in sliced], config.slicing,
                                                               est.smear_m, est.first_window_s,
                                                               est.points_deskewed),
            corrections=corrections, jumps=kinematic.jumps, references=references, stage_cache=folder.summary(),
            alpha=config.block.alpha, timings_s=clock.timings_s,
            trajectory_plot=trajectory_plot(kinematic.trajectories, corrected),
            misfits=adjusted.misfits,
            cloud_views=views.finish(out))  # "cloud" and "crs"; the PNGs go straight into out/figures
        report.update(points_report(adjusted.network, adjusted.result, adjusted.rates, control, check,
                                    kinematic.trajectories,
                                    corrections, config))
        report["inputs"].update({k: str(p) for k, p in (("control", inputs.control), ("check", inputs.check)) if p})
        write_tables(staging, report, adjusted.network, adjusted.result, planes, figures_dir=out)
        clock.lap("reports")
        write_report_json(staging / "report.json", report)
        folder.commit_outputs(keep=plan.current)  # all at once, report.json last: it marks a finished run
        folder.finish()
    return ProcessSummary.from_report(out, report)


@dataclass(frozen=True, eq=False)
class EstimatedNetwork:
    """Slice, planes, links and the adjusted network of every run, for one window length."""

    sliced: list[CachedSlices]
    kinematic: KinematicStations
    stations: list[Station]
    planes: list[tuple[Plane, ...]]
    adjusted: AdjustedNetwork
    smear_m: np.ndarray  # per station, by the measured drift over half its window
    first_window_s: float | None = None  # the windows of the first slicing, where they were too long
    points_deskewed: bool = False  # planes detected on points an earlier adjustment deskewed


def estimate_quasi_static(stack: contextlib.ExitStack, folder: RunCache, inputs: ProcessInputs,
                          trajectories: list[Trajectory], references: ReferencePlanes | None, config: KinregConfig,
                          progress: Progress, executor: ExecutorContext, clock: StageClock,
                          control: Assignment | None = None) -> tuple[EstimatedNetwork, KinregConfig]:
    """:func:`estimate_network`; where the measured drift smears the planes of its windows
    (:func:`~kinreg.estimate.slicing.shorter_window_s`), once more with shorter windows
    (:func:`_with_shorter_windows`). Returns the result and the configuration it was made with;
    raises :class:`AdjustmentFailedError` (after :func:`fail_adjustment`) where the trajectory
    disagrees with that result's network as a wrong plane match would
    (:func:`~kinreg.estimate.snooping.wrong_match_misfits`)."""
    est = estimate_network(stack, folder, inputs, trajectories, references, config, progress, executor, clock,
                           control)
    chosen = _with_shorter_windows(stack, folder, inputs, trajectories, references, config, progress, executor,
                                   clock, control, est)
    if chosen is not None:
        est, config = chosen
    est = _with_deskewed_points(stack, folder, inputs, trajectories, references, config, progress, executor, clock,
                                control, est)
    # The trajectory's own links are never rejected: beyond their model, by as much as two distinct
    # planes lie apart, they show plane links that agree on a wrong match no test found (or a jump
    # the detector missed). The global test can pass all the same, and the stations be 30-60 mm
    # RMS off (held-out runs, world drift 0.26 m). A smaller misfit stays a warning in the report.
    failure = ""
    if est.adjusted.wrong_matches:
        failure = (f"the trajectory disagrees with the adjusted network between "
                   f"{misfit_text(est.adjusted.wrong_matches)}, beyond its model: plane links that agree on a wrong "
                   "match, or a jump in the trajectory")
    # The drift model's coupling is the run's own where the adjusted network fits it best; a network
    # that settles on another one, started from either, can pass its global test 36 mm off.
    elif est.adjusted.coupling_disagrees is not None:
        settled, fitted = est.adjusted.coupling_disagrees
        failure = (f"the adjusted network fits a drift coupling of {fitted:.2f} better than the {settled:.2f} it "
                   "settled on, started from either: the trajectory's error model is not settled")
    if failure:
        failed = dataclasses.replace(est.adjusted.result, failure=failure)
        fail_adjustment(AdjustmentFailedError(checked_reason(failed), failed), est.adjusted.network, config, folder,
                        inputs_report(inputs.runs, est.kinematic.trajectories, est.sliced, inputs.static,
                                      inputs.reference))
    return est, config


# The scan planes' offsets, which a window's smear moves first (:func:`_with_shorter_windows`).
_OFFSET_KINDS = tuple(k.value for k in (ObservationKind.PLANE_OFFSET, ObservationKind.PLANE_OFFSET_FLOOR,
                                        ObservationKind.PLANE_OFFSET_FLOOR_LEVEL))


def _with_shorter_windows(stack: contextlib.ExitStack, folder: RunCache, inputs: ProcessInputs,
                          trajectories: list[Trajectory], references: ReferencePlanes | None, config: KinregConfig,
                          progress: Progress, executor: ExecutorContext, clock: StageClock, control: Assignment | None,
                          est: EstimatedNetwork) -> tuple[EstimatedNetwork, KinregConfig] | None:
    """Where the drift measured by ``est`` smears the planes of its windows
    (:func:`~kinreg.estimate.slicing.shorter_window_s`; whether their offsets show it:
    :func:`~kinreg.estimate.snooping.models_rejected`): the network sliced again with shorter
    windows and its configuration, or ``est``'s again where the shorter windows' network shows a
    trajectory misfit of a wrong match that ``est``'s does not. ``None``: ``est`` stands."""
    window = shorter_window_s(config.slicing.window_s, est.smear_m, est.planes, config.slicing)
    if window is None:
        return None
    showing: dict[str, float] = {}
    if shorter_window_s(config.slicing.window_s, est.smear_m, est.planes, config.slicing, False) is None:
        # below the noise: worth shorter windows only where the planes' offsets show the smear
        result = est.adjusted.result
        showing = models_rejected(result.tests, result.variance_components, _OFFSET_KINDS, config.block.alpha)
        if not showing:
            return None
    shown = "".join(f", {kind} {factor:.1f}x its model" for kind, factor in showing.items())
    log.warning("the drift smears the planes by %.1f mm over half a window (median%s): sliced again with %.1f s "
                "windows instead of %.1f s", 1000 * float(np.nanmedian(est.smear_m)), shown, window,
                config.slicing.window_s)
    again = estimate_network(stack, folder, inputs, trajectories, references, with_window(config, window), progress,
                             executor, clock, control, decoded=[slices.records() for slices in est.sliced])
    # Shorter windows hold fewer planes each, and their links can agree on a wrong match that no
    # test finds; then the trajectory's own links disagree with the network. Where the longer
    # windows' network had no such misfit, it is the better result (a held-out run, world drift
    # 0.26 m: 3 s windows ended 63 mm RMS off with the global test passed, 7 sigma between the
    # trajectory and the network; its 6 s windows were within 5 mm).
    if again.adjusted.wrong_matches and not est.adjusted.wrong_matches:
        log.warning("with %.1f s windows the trajectory disagrees with the adjusted network between %s "
                    "(a wrong plane match the tests did not find): kept the %.1f s windows",
                    window, misfit_text(again.adjusted.wrong_matches), config.slicing.window_s)
        # the first slicing's spill made way for the second's: sliced again, the rest from the cache
        return estimate_network(stack, folder, inputs, trajectories, references, config, progress, executor, clock,
                                control, decoded=[slices.records() for slices in again.sliced]), config
    return dataclasses.replace(again, first_window_s=config.slicing.window_s), with_window(config, window)


def _with_deskewed_points(stack: contextlib.ExitStack, folder: RunCache, inputs: ProcessInputs,
                          trajectories: list[Trajectory], references: ReferencePlanes | None, config: KinregConfig,
                          progress: Progress, executor: ExecutorContext, clock: StageClock,
                          control: Assignment | None, est: EstimatedNetwork) -> EstimatedNetwork:
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
    _, shift = deskewed_planes(adjusted.network.stations, est.planes, adjusted.result, adjusted.rates,
                               est.kinematic.trajectories)
    if shift <= config.planes.refit_distance_m / 3.0:
        return est
    log.warning("the attitude error shears the windows (a plane by up to %.1f mm): their points deskewed "
                "with the adjusted drift and their planes detected again", 1000 * shift)
    again = estimate_network(stack, folder, inputs, trajectories, references, config, progress, executor, clock,
                             control, decoded=[slices.records() for slices in est.sliced], deskew_from=est)
    if again.adjusted.wrong_matches and not adjusted.wrong_matches:
        log.warning("with the deskewed points the trajectory disagrees with the adjusted network between %s: "
                    "kept the planes of the sheared points", misfit_text(again.adjusted.wrong_matches))
        return est
    return dataclasses.replace(again, first_window_s=est.first_window_s, points_deskewed=True)


def estimate_network(stack: contextlib.ExitStack, folder: RunCache, inputs: ProcessInputs,
                     trajectories: list[Trajectory], references: ReferencePlanes | None, config: KinregConfig,
                     progress: Progress, executor: ExecutorContext, clock: StageClock,
                     control: Assignment | None = None, decoded: Sequence[Path | None] = (),
                     deskew_from: EstimatedNetwork | None = None) -> EstimatedNetwork:
    """Slice every run (its spill kept open on ``stack``), detect planes (and the static scans'),
    link and adjust: the stages of :func:`process` before the outputs, each through the stage cache.
    ``decoded``: each run's cloud as an earlier slicing decoded it, where it kept it.
    ``deskew_from``: an estimate with the same windows whose adjustment deskews the scans' points
    before their planes are detected (:func:`_with_deskewed_points`)."""
    maps, left = {}, None
    if deskew_from is not None:
        first = deskew_from.adjusted
        maps = window_maps(first.network.stations, first.result, first.rates, deskew_from.kinematic.trajectories,
                           MAP_NEIGHBOURS)
        left = window_velocity_covariance(first.network.stations, first.result, first.rates)
    runs, static = inputs.runs, config.static if inputs.static is not None else None
    sliced = [stack.enter_context(sliced_run(folder, r.trajectory, r.cloud, trajectories[k], config, progress, k,
                                             decoded[k] if k < len(decoded) else None))
              for k, r in enumerate(runs)]
    clock.lap("slice")
    kinematic = detect_run_planes(sliced, trajectories, references, config, progress, executor, folder, maps)
    static_stations, static_planes = detect_static_planes(inputs.static, len(kinematic.stations), config.planes,
                                                          progress, folder)  # none without --static
    stations, planes = kinematic.stations + static_stations, kinematic.planes + static_planes
    clock.lap("planes")
    links = link_stations_cached(stations, planes, config, static, progress, executor, folder)
    clock.lap("link")
    controls = () if control is None else tie_points(control, stations, kinematic.trajectories, config.control)
    network = build_network(stations, planes, links, references, static, config, controls)
    adjusted = adjust_or_fail(network, planes, static, config, progress, executor, folder,
                              inputs_report(runs, kinematic.trajectories, sliced, inputs.static, inputs.reference),
                              kinematic.trajectories, left)
    folder.count("block", computed=1)
    clock.lap("block")
    return EstimatedNetwork(sliced, kinematic, stations, planes, adjusted,
                            window_smear_m(stations, planes, adjusted.rates))


def with_window(config: KinregConfig, window_s: float) -> KinregConfig:
    """``config`` with quasi-static windows of ``window_s`` seconds."""
    return dataclasses.replace(config, slicing=dataclasses.replace(config.slicing, window_s=window_s))


def adjust_or_fail(network: Network, planes: list[tuple[Plane, ...]], static: StaticConfig | None,
                   config: KinregConfig, progress: Progress, executor: ExecutorContext, folder: RunCache,
                   report_inputs: dict[str, Any], trajectories: Sequence[Trajectory] = (),
                   points_deskewed: np.ndarray | None = None) -> AdjustedNetwork:
    """:func:`~kinreg.run.stages.adjust_with_measured_drift`; when the adjustment fails, the
    folder's outputs (of an earlier run too) are removed, and with ``[block] on_failure =
    "report"`` a ``report.json`` and ``report.html`` marked failed take their place."""
    try:
        return adjust_with_measured_drift(network, planes, static, config, progress, executor, trajectories,
                                          points_deskewed)
    except AdjustmentFailedError as e:
        fail_adjustment(e, network, config, folder, report_inputs)


def fail_adjustment(e: AdjustmentFailedError, network: Network, config: KinregConfig, folder: RunCache,
                    report_inputs: dict[str, Any]) -> NoReturn:
    """Raise ``e``, the folder's outputs (of an earlier run too) removed, and with ``[block]
    on_failure = "report"`` a ``report.json`` and ``report.html`` marked failed in their place."""
    if config.block.on_failure is OnFailure.REPORT:
        staging = folder.start_outputs()
        report = build_failure_report(inputs=report_inputs, config_toml=format_toml(config), result=e.result,
                                      datum=network.datum.description, alpha=config.block.alpha)
        write_text(staging / "report.html", render_html(report))
        write_report_json(staging / "report.json", report)
    folder.commit_outputs()
    shutil.rmtree(folder.out_dir / FIGURES_DIR, ignore_errors=True)  # the report's images of an earlier run
    if config.block.on_failure is not OnFailure.REPORT:
        raise e
    raise AdjustmentFailedError(checked_reason(e.result, report_in=folder.out_dir), e.result) from None


def write_tables(out: Path, report: dict[str, Any], network: Network, result: BlockResult,
                 planes: Sequence[tuple[Plane, ...]], figures_dir: Path | None = None) -> None:
    """``stations.csv``, ``links.csv``, ``config.toml`` and ``report.html`` (``report.json`` is
    written last); the report's images are read from ``figures_dir`` (default ``out``)."""
    rows = stations_table(network.stations, result, planes, network.links)
    write_text(out / "stations.csv", format_stations_csv(rows))
    write_text(out / "links.csv", format_links_csv(links_table(network.links, result, network.plane_nodes)))
    write_text(out / "config.toml", report["config_toml"])
    write_text(out / "report.html", render_html(report, base_dir=figures_dir or out))
    # always written (only its header without --control/--check): every name in OUTPUT_FILES is
    # in every finished run's folder, so that no file of an earlier run is left there
    write_text(out / "control_points.csv", format_control_points_csv(report))


def read_points(inputs: ProcessInputs, trajectories: Sequence[Trajectory], references: ReferencePlanes | None,
                config: KinregConfig) -> tuple[Assignment | None, Assignment | None]:
    """The control and check points (``--control``, ``--check``), each with its stand-still on the
    trajectories (moved into the reference frame, as the stations will be), or its static scan
    (``--static``); ``None`` where not given. Raises :class:`~kinreg.errors.InputError` for a bad
    file or one whose points tie to nothing."""
    moved = [to_reference_frame([], t, references)[1] for t in trajectories]
    found = []
    scans = static_scan_names(inputs.static) if inputs.static is not None else None
    for path, what in ((inputs.control, "control"), (inputs.check, "check")):
        found.append(None if path is None else assign_points(read_control_points(path), moved, config.control, what,
                                                             scans))
    if found[0] is not None and found[1] is not None and set(found[0].all_names) & set(found[1].all_names):
        both = ", ".join(sorted(set(found[0].all_names) & set(found[1].all_names))[:5])
        raise ConfigError(f"point(s) {both} are both control and check points: a check point must stay out of the "
                          "adjustment", inputs.check)
    return found[0], found[1]


def points_report(network: Network, result: BlockResult, rates: DriftRates, control: Assignment | None,
                  check: Assignment | None,
                  trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection],
                  config: KinregConfig) -> dict[str, Any]:
    """``report.json``'s ``control`` and ``check`` sections (only those given)."""
    reference = np.asarray(config.control.reference_point_m)
    out: dict[str, Any] = {}
    if control is not None:
        out["control"] = control_section(network, result, rates, control, trajectories, corrections, reference,
                                         config.block.alpha)
    if check is not None:
        out["check"] = check_section(check, trajectories, corrections, reference, network.stations, result)
    return out


@dataclass(frozen=True)
class LinkSummary:
    n_scans: int
    n_planes: int
    n_candidate_pairs: int
    n_links: int
    by_status: dict[str, int]
    seconds: dict[str, float]


def link_to_folder(
    trajectory_path: str | Path,
    cloud_path: str | Path,
    out_dir: str | Path,
    config: KinregConfig,
    overwrite: bool = False,
    progress: Progress | None = None,
    workers: int | None = 1,
    scheduler: str | None = None,
) -> LinkSummary:
    """``kinreg link``: slice, detect planes, link the scans pairwise; write ``planes.csv`` (one row
    per plane and scan) and ``links.csv`` into ``out_dir``. No block adjustment."""
    progress = progress or NullProgress()
    out = Path(out_dir)
    check_writable_target(out / "links.csv", overwrite)
    check_writable_target(out / "planes.csv", overwrite)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    trajectory, _, sequence = read_and_slice(trajectory_path, cloud_path, config, progress)
    seconds["slice"] = time.perf_counter() - t0
    with sequence, make_executor(workers, scheduler) as executor:
        t0 = time.perf_counter()
        stations, planes = detect_all_planes(sequence, config.planes, progress, executor, trajectory)
        seconds["planes"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        links = link_stations(stations, planes, config.matching, config.drift, config.pairwise, progress,
                              executor=executor)
        seconds["link"] = time.perf_counter() - t0
    n_candidates = len(candidate_pairs(np.array([s.T_obj_scan.t_xyz for s in stations]), config.matching))
    write_text(out / "planes.csv", format_planes_csv(stations, planes), overwrite=overwrite)
    write_text(out / "links.csv", format_links_csv(links_table(links, None)), overwrite=overwrite)
    by_status: dict[str, int] = {}
    for link in links:
        by_status[link.status.value] = by_status.get(link.status.value, 0) + 1
    return LinkSummary(len(stations), sum(len(p) for p in planes), n_candidates, len(links), by_status, seconds)
