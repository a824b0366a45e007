"""The pipelines, readable top to bottom: each line names one stage."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kinreg.block import adjust_block, loose_parts
from kinreg.cache import links_from_arrays, links_to_arrays
from kinreg.config import (
    Disconnected,
    DiscontinuityConfig,
    InputConfig,
    KinregConfig,
    PlanesConfig,
    StaticConfig,
    StaticDatum,
    format_toml,
)
from kinreg.correction import write_corrected_las
from kinreg.discontinuity import TrajectoryJump, detect_jumps, jump_arrays, jump_removal
from kinreg.errors import ConfigError, EstimationError
from kinreg.executor import ExecutorContext, in_process, make_executor, parallel_map
from kinreg.geometry import Pose
from kinreg.io.atomic import check_writable_target
from kinreg.io.checks import check_inputs, time_filter
from kinreg.io.cloud import open_cloud
from kinreg.io.reference_planes import ReferencePlanes, read_reference_planes
from kinreg.io.trajectory import parse_column_mapping, read_trajectory, write_trajectory_geoslam
from kinreg.matching import candidate_pairs
from kinreg.network import (
    DriftRates,
    Station,
    block_observations,
    estimate_drift_rates,
    link_stations,
    plane_time_offsets,
    rms_time_offset,
    station_pairs,
    with_window_bias,
)
from kinreg.planes import detect_planes
from kinreg.progress import NullProgress, Progress
from kinreg.reference import Tie, as_built, associate, tie_observations, to_reference_frame
from kinreg.report import (
    build_report,
    format_links_csv,
    format_planes_csv,
    format_stations_csv,
    links_table,
    stations_table,
    write_report_json,
    write_text,
)
from kinreg.report_html import render_html
from kinreg.resume import (
    CachedSlices,
    RunCache,
    content_parts,
    dataclass_parts,
    open_run_cache,
    remove_outputs,
    scan_planes_from_arrays,
    scan_planes_to_arrays,
    sliced_run,
)
from kinreg.runs import (
    RunInputs,
    adjusted_scans,
    inputs_report,
    label_run,
    output_files,
    run_correction,
    run_output_names,
    slicing_report,
    trajectory_plot,
)
from kinreg.slicing import QuasiStaticSequence, SlicingSummary, slice_quasi_static
from kinreg.types import (
    BlockResult,
    Link,
    ObservationKind,
    Plane,
    RelativeObservation,
    Scan,
    ScanKind,
    Trajectory,
)

log = logging.getLogger(__name__)


def read_input_trajectory(path: str | Path, config: InputConfig) -> Trajectory:
    """The trajectory named in the inputs, read with the configured format and column mapping."""
    fmt = None if config.trajectory_format == "auto" else config.trajectory_format
    columns = parse_column_mapping(config.trajectory_columns) if config.trajectory_columns else None
    return read_trajectory(path, fmt, columns)


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


def _counted(scans: Iterator[Scan], progress: Progress, stage: str, total: int) -> Iterator[Scan]:
    progress.start(stage, total=total, unit="scans")
    for scan in scans:
        yield scan
        progress.advance(1)
    progress.finish()


def slice_to_e57(
    trajectory_path: str | Path,
    cloud_path: str | Path,
    out_path: str | Path,
    config: KinregConfig,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> SlicingSummary:
    """``kinreg slice``: read, slice into quasi-static scans, export one E57 sequence."""
    from kinreg.io.e57 import write_e57_sequence

    progress = progress or NullProgress()
    check_writable_target(Path(out_path), overwrite)  # fail before the long work, not after
    _, _, sequence = read_and_slice(trajectory_path, cloud_path, config, progress)
    with sequence:
        scans = _counted(sequence.iter_scans(), progress, "export E57", len(sequence))
        write_e57_sequence(out_path, scans, overwrite=overwrite)
    return sequence.summary


@dataclass(frozen=True)
class ProcessInputs:
    """What ``kinreg process`` reads: one or several runs (``trajectory`` and ``cloud`` are the
    first, ``more_runs`` the others, in order; see :mod:`kinreg.runs`), static scans, reference planes."""

    trajectory: Path
    cloud: Path
    static: Path | None = None
    reference: Path | None = None
    more_runs: tuple[RunInputs, ...] = ()

    @property
    def runs(self) -> tuple[RunInputs, ...]:
        return (RunInputs(Path(self.trajectory), Path(self.cloud)), *self.more_runs)

    @classmethod
    def from_runs(cls, trajectories: Sequence[str | Path], clouds: Sequence[str | Path],
                  static: Path | None = None, reference: Path | None = None) -> ProcessInputs:
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
        return cls(runs[0].trajectory, runs[0].cloud, static, reference, tuple(runs[1:]))


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


OUTPUT_FILES = ("stations.csv", "links.csv", "trajectory_corrected.txt", "corrected.laz", "sequence.e57",
                "report.json", "report.html", "config.toml")


def prepare_output_folder(out_dir: Path, overwrite: bool, resume: bool = False,
                          outputs: tuple[str, ...] = OUTPUT_FILES) -> RunCache:
    """Create the output folder and open its stage cache. A folder that already holds kinreg
    results (any of ``outputs``) or a stage cache is refused unless ``resume`` (re-use the cache)
    or ``overwrite`` (start afresh: the cache is cleared); see :func:`kinreg.resume.open_run_cache`."""
    run = open_run_cache(out_dir, outputs, overwrite=overwrite, resume=resume)
    check_writable_target(out_dir / "stations.csv", overwrite=True)
    return run


def scan_planes(task: tuple[QuasiStaticSequence, int, PlanesConfig]) -> tuple[Station, tuple[Plane, ...]]:
    """One scan's planes and its station (a top-level function: it runs on worker processes).
    The task carries the sequence's small index (windows, spill paths), never the points."""
    sequence, i, config = task
    scan = sequence.read_scan(i)
    found = detect_planes(scan, config)
    tau = float("nan")
    if scan.stamps_s is not None:
        offsets = plane_time_offsets(scan.points_xyz, scan.stamps_s, scan.t_s, found, config.refit_distance_m)
        found = tuple(dataclasses.replace(p, t_offset_s=float(t)) if np.isfinite(t) else p
                      for p, t in zip(found, offsets, strict=True))
        tau = rms_time_offset(offsets)
    station = Station(scan.scan_id, scan.name, scan.kind, scan.t_s, scan.t_start_s, scan.t_end_s,
                      scan.T_obj_scan, len(scan), tau)
    return station, found


def detect_all_planes(sequence: QuasiStaticSequence, config: PlanesConfig, progress: Progress,
                      executor: ExecutorContext | None = None) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """Planes of every quasi-static scan, and the stations they belong to (on ``executor``; in this
    process without one). The result does not depend on the number of workers."""
    progress.start("planes", total=len(sequence), unit="scans")
    tasks = ((sequence, i, config) for i in range(len(sequence)))
    results = parallel_map(scan_planes, tasks, executor or in_process(), progress)
    progress.finish()
    return [r[0] for r in results], [r[1] for r in results]


def detect_planes_cached(slices: CachedSlices, config: PlanesConfig, progress: Progress,
                         executor: ExecutorContext, run: RunCache) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """:func:`detect_all_planes` through the stage cache: each scan is looked up under (slice
    key, scan index, ``[planes]``); the others are detected and stored as each finishes, so that
    an interrupted run keeps the scans it finished. The points are read only when a scan is missing."""
    keys = [run.key("planes", slices.key, i, config) for i in range(len(slices))]
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
        parallel_map(scan_planes, ((sequence, i, config) for i in missing), executor, progress, on_result=keep)
    progress.finish()
    done = [r for r in results if r is not None]
    return [r[0] for r in done], [r[1] for r in done]


def detect_static_planes(path: Path, first_id: int, config: PlanesConfig, progress: Progress,
                         run: RunCache | None = None) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """Planes of every static scan of a registered E57 (poses in the object frame required).
    With ``run``, each scan is looked up in (and stored into) its stage cache."""
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
            station = Station(scan.scan_id, scan.name or f"static_{k:03d}", ScanKind.STATIC, nan, nan, nan,
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
    """:func:`~kinreg.network.link_stations` through the stage cache, keyed by the stations and
    planes themselves (so also by anything that moved them, e.g. ``[initial_transform]``) and
    ``[matching]``, ``[drift]``, ``[pairwise]``, ``[static]``."""
    key = run.key("link", *content_parts(stations, planes), config.matching, config.drift, config.pairwise, static)
    entry = run.load("link", key)
    if entry is not None:
        run.count("link", reused=1)
        log.info("link: the pairwise links are re-used from the stage cache")
        return links_from_arrays(entry.arrays)
    links = link_stations(stations, planes, config.matching, config.drift, config.pairwise, progress, static,
                          executor)
    run.store("link", key, links_to_arrays(links))
    run.count("link", computed=1)
    return links


@dataclass(frozen=True, eq=False)
class AdjustedNetwork:
    result: BlockResult
    rates: DriftRates
    datum: str
    ties: tuple[Tie, ...]
    links: tuple[Link, ...]  # the links the result rests on (linked again when the drift was faster)


def adjust_network(
    stations: list[Station],
    planes: list[tuple[Plane, ...]],
    links: list[Link],
    references: ReferencePlanes | None,
    static: StaticConfig | None,
    config: KinregConfig,
    progress: Progress,
    executor: ExecutorContext | None = None,
) -> AdjustedNetwork:
    """The block adjustment with its datum: static scans (fixed or observed), reference planes
    (tie planes), or else the first station. The first adjustment also measures the drift; where
    it is faster than the prior, the pairs are linked again (on ``executor``) and the network is
    adjusted again with the measured rates, so that the planes' window deformation and the
    stretches carried by the trajectory alone get honest sigmas."""
    poses_initial = Pose.stack([s.T_obj_scan for s in stations])
    is_static = np.array([s.kind is ScanKind.STATIC for s in stations])
    fixed = np.zeros(len(stations), dtype=bool)
    datum_obs: list[RelativeObservation] = []
    ties: list[Tie] = []
    datum = []
    if static is not None and is_static.any():
        if static.datum is StaticDatum.FIXED:
            fixed |= is_static
            datum.append("static scans fixed")
        else:
            sigma = np.array([static.sigma_mm / 1000.0] * 3 + [np.radians(static.sigma_mdeg / 1000.0)] * 3)
            datum_obs += [RelativeObservation(ObservationKind.STATION, int(k), -1, stations[k].T_obj_scan,
                                              np.diag(1.0 / sigma**2), 6) for k in np.flatnonzero(is_static)]
            datum.append("static scans observed")
    if references is not None:
        ties = associate([s.name for s in stations], poses_initial, planes, references, config.reference)
        if not ties:
            raise ConfigError("no detected plane could be tied to a reference plane (is the trajectory in the "
                              "building's frame? give [initial_transform] or [[link]] entries otherwise)",
                              references.source)
        datum_obs += tie_observations(ties, poses_initial, planes, references, config.reference)
        datum.append(f"reference planes ({len(ties)} tie planes)")
    if not datum:
        fixed[0] = True
        datum.append("first station")
    if references is not None and not fixed.any() and static is None:
        _check_reference_datum(ties, references)
    parts = loose_parts(block_observations(stations, links, DriftRates.from_config(config.drift)) + datum_obs,
                        fixed, len(stations))
    if parts:
        names = ", ".join(f"{stations[p[0]].name}..{stations[p[-1]].name}" for p in parts[:5])
        if config.block.disconnected is Disconnected.STOP:
            raise EstimationError(
                f"the network falls apart: {len(parts)} part(s) are not linked to the datum ({names}); set "
                '[block] disconnected = "fix_each" to adjust each part in its own datum')
        log.warning("%d part(s) not linked to the datum (%s): each adjusted with its first station fixed",
                    len(parts), names)
        for p in parts:
            fixed[p[0]] = True
        datum.append(f"{len(parts)} disconnected part(s) each on its first station")
    prior_rates = DriftRates.from_config(config.drift)
    result = adjust_block(poses_initial, block_observations(stations, links, prior_rates) + datum_obs, fixed,
                          config.block, progress)
    rates = estimate_drift_rates(stations, result, prior_rates, config.drift.measured_rate_floor)
    if np.any(rates.pos_m_per_s > 1.2 * prior_rates.pos_m_per_s) or np.any(
            rates.rot_rad_per_s > 1.2 * prior_rates.rot_rad_per_s):
        # The planes of a scan are deformed by the drift inside its window: faster than the prior,
        # by more than their covariances say, so the pairs are linked again with the measured rates.
        log.info("drift faster than the prior: linking again with the measured rates")
        links = link_stations(stations, planes, config.matching, config.drift, config.pairwise, progress,
                              static, executor, rates)
    if rates.estimated:
        # Second pass: the trajectory's links (and the scans' window bias) with the measured rates.
        result = adjust_block(poses_initial, block_observations(stations, links, rates) + datum_obs, fixed,
                              config.block, progress)
    return AdjustedNetwork(with_window_bias(result, stations, rates), rates, "; ".join(datum), tuple(ties),
                           tuple(links))


def take_out_jumps(
    stations: list[Station], planes: list[tuple[Plane, ...]], trajectory: Trajectory, config: DiscontinuityConfig,
) -> tuple[list[Station], list[tuple[Plane, ...]], list[TrajectoryJump]]:
    """Find jumps in the trajectory (:func:`~kinreg.discontinuity.detect_jumps`) and take them out
    of the quasi-static stations' initial poses, so that the trajectory links and the pairwise
    priors no longer carry them. A scan's points are in its own frame whatever the trajectory
    did, except where its window contains a jump: those points were georeferenced on both sides
    of the step, so that scan keeps only its trajectory links (its planes are dropped). The
    corrected cloud and trajectory take the jumps out by time (:class:`DriftCorrection`)."""
    if not config.detect:
        return stations, planes, []
    jumps = detect_jumps(trajectory, config)
    if not jumps:
        return stations, planes, []
    intervals, steps = jump_arrays(jumps)
    times = np.array([s.t_s for s in stations])
    quasi = np.flatnonzero([s.kind is ScanKind.QUASI_STATIC for s in stations])
    removal = jump_removal(intervals, steps, times[quasi])
    stations, planes = list(stations), list(planes)
    for n, k in enumerate(quasi):
        s = stations[k]
        stations[k] = dataclasses.replace(s, T_obj_scan=removal[n].compose(s.T_obj_scan))
        inside = [j.t_s for j in jumps if s.t_start_s < j.t_s and j.t_before_s < s.t_end_s]
        if inside:
            log.warning("scan %s contains the trajectory jump at %.2f s: not linked by planes", s.name, inside[0])
            planes[k] = ()
    for j in jumps:
        log.warning("the trajectory jumps by %.3f m and %.2f deg at %.3f s (row %d): taken out "
                    "(set [jumps] detect = false to keep it)", j.step_m, j.step_deg, j.t_s, j.index)
    return stations, planes, jumps


def _axis_name(v: np.ndarray) -> str:
    k = int(np.argmax(np.abs(v)))
    return "xyz"[k] if abs(v[k]) > 0.99 else "(" + ", ".join(f"{c:.2f}" for c in v) + ")"


def _check_reference_datum(ties: list[Tie], references: ReferencePlanes) -> None:
    """The tied reference planes must fix all six datum directions: normals spanning three
    directions fix the translations (and then the rotations too)."""
    normals = references.normals[sorted({t.reference for t in ties})]
    _, sing, Vt = np.linalg.svd(normals)
    free = [Vt[k] for k in range(3) if k >= len(sing) or sing[k] < 0.1]
    if free:
        directions = " and ".join(f"translation along {_axis_name(v)}" for v in free)
        if len(free) == 2:
            directions += f", rotation about {_axis_name(normals[0])}"
        raise ConfigError(f"the tied reference planes do not fix the datum: {directions} stay free; add reference "
                          "planes in that direction, [[link]] entries, or static scans", references.source)


def process(
    inputs: ProcessInputs,
    out_dir: str | Path,
    config: KinregConfig,
    overwrite: bool = False,
    progress: Progress | None = None,
    workers: int | None = 1,
    scheduler: str | None = None,
    resume: bool = False,
) -> ProcessSummary:
    """``kinreg process``: read, slice, detect planes, link, adjust, correct, report.

    Per-scan and per-pair work runs on ``workers`` local processes (``None``: every core; 1: in
    this process) or on the Dask cluster at ``scheduler``; results do not depend on either.

    Each stage keeps its results in the output folder's stage cache (:mod:`kinreg.resume`). A
    folder that holds results or a cache is refused, unless ``resume`` (re-use the cache: only
    stages whose inputs changed are done again, and the outputs are rewritten) or ``overwrite``
    (start afresh). A run killed at any point and resumed gives the same outputs as one that ran
    through.
    """
    from kinreg.io.e57 import write_e57_sequence

    progress = progress or NullProgress()
    out = Path(out_dir)
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[stage] = now - clock
        clock = now

    runs = inputs.runs  # each run is read and sliced on its own (kinreg.runs)
    outputs = output_files(out, OUTPUT_FILES, len(runs))
    run = prepare_output_folder(out, overwrite, resume, outputs)
    references = read_reference_planes(inputs.reference) if inputs.reference is not None else None
    trajectories = [read_input_trajectory(r.trajectory, config.input) for r in runs]
    for r in runs:
        if r.cloud.suffix.lower() not in (".las", ".laz"):
            raise ConfigError("writing the corrected cloud from an E57 input is not supported yet", r.cloud)
    check_inputs([r.cloud for r in runs], trajectories, inputs.static, config.input)
    with contextlib.ExitStack() as stack:
        sliced = [stack.enter_context(sliced_run(run, r.trajectory, r.cloud, trajectories[k], config, progress, k))
                  for k, r in enumerate(runs)]
        executor = stack.enter_context(make_executor(workers, scheduler))
        lap("slice")
        stations: list[Station] = []
        planes: list[tuple[Plane, ...]] = []
        jumps: list[list[TrajectoryJump]] = []  # one list per run
        for k, slices in enumerate(sliced):
            run_stations, run_planes = detect_planes_cached(slices, config.planes, progress, executor, run)
            run_stations, trajectories[k] = to_reference_frame(run_stations, trajectories[k],
                                                               references)  # [initial_transform]
            run_stations, run_planes = label_run(run_stations, run_planes, k, len(stations), len(runs))
            run_stations, run_planes, run_jumps = take_out_jumps(run_stations, run_planes, trajectories[k],
                                                                 config.jumps)
            stations, planes = stations + run_stations, planes + run_planes
            jumps.append(run_jumps)
        if inputs.static is not None:
            static_stations, static_planes = detect_static_planes(inputs.static, len(stations), config.planes,
                                                                  progress, run)
            stations, planes = stations + static_stations, planes + static_planes
        lap("planes")
        static = config.static if inputs.static is not None else None
        links = link_stations_cached(stations, planes, config, static, progress, executor, run)
        n_candidates = len(station_pairs(stations, config.matching, static))
        lap("link")
        network = adjust_network(stations, planes, links, references, static, config, progress, executor)
        links = list(network.links)
        result, rates = network.result, network.rates
        run.count("block", computed=1)
        lap("block")
        # One correction per run, from the run's own stations (each run has its own drift).
        corrections = [run_correction(stations, result, k, trajectories[k], jumps[k]) for k in range(len(runs))]
        corrected_trajectories = [c.apply_to_trajectory(t) for c, t in zip(corrections, trajectories, strict=True)]
        names = [run_output_names(k, len(runs)) for k in range(len(runs))]
        # The large outputs are keyed by what they are made of; one still in the folder is kept.
        T_obj_cloud = None if references is None else references.T_ref_traj
        keys = {cloud_name: run.key("output", cloud_name, r.cloud, config.input.chunk_points, T_obj_cloud,
                                    config.input.cloud_time_offset_s,
                                    *dataclass_parts(correction))
                for (cloud_name, _), r, correction in zip(names, runs, corrections, strict=True)}
        n_scans = sum(len(slices) for slices in sliced)
        keys["sequence.e57"] = run.key("output", "sequence.e57", *(slices.key for slices in sliced),
                                       result.poses[np.arange(n_scans)])
        current = {name for name, key in keys.items() if run.output_is_current(name, key)}
        remove_outputs(out, tuple(name for name in outputs if name not in current))
        for (_, trajectory_name), corrected_trajectory in zip(names, corrected_trajectories, strict=True):
            write_trajectory_geoslam(out / trajectory_name, corrected_trajectory, overwrite=True)
        for (cloud_name, _), r, correction in zip(names, runs, corrections, strict=True):
            if cloud_name not in current:
                write_corrected_las(r.cloud, out / cloud_name, correction, config.input.chunk_points,
                                    overwrite=True, progress=progress, T_obj_cloud=T_obj_cloud,
                                    time_offset_s=config.input.cloud_time_offset_s)
                run.record_output(cloud_name, keys[cloud_name])
            run.count("corrected cloud", reused=int(cloud_name in current), computed=int(cloud_name not in current))
        lap("corrected cloud")
        if "sequence.e57" not in current:
            scans = _counted(adjusted_scans(sliced, result.poses), progress, "write E57", n_scans)
            write_e57_sequence(out / "sequence.e57", scans, overwrite=True)
            run.record_output("sequence.e57", keys["sequence.e57"])
        run.count("sequence E57", reused=int("sequence.e57" in current), computed=int("sequence.e57" not in current))
        lap("sequence E57")

    shift = np.concatenate([c.magnitude()[0] for c in corrections])
    rot = np.concatenate([c.magnitude()[1] for c in corrections])
    config_toml = format_toml(config)
    report = build_report(
        inputs=inputs_report(runs, trajectories, sliced),
        config_toml=config_toml,
        stations=stations, planes=planes, links=links, n_candidate_pairs=n_candidates, result=result,
        slicing=slicing_report([slices.summary for slices in sliced]),
        correction_mm=shift * 1000.0, correction_mdeg=np.degrees(rot) * 1000.0,
        datum=network.datum, alpha=config.block.alpha, timings_s=timings, drift_rates=rates,
        trajectory_plot=trajectory_plot(trajectories, corrected_trajectories),
    )
    report["inputs"]["static"] = None if inputs.static is None else str(inputs.static)
    report["inputs"]["reference"] = None if inputs.reference is None else str(inputs.reference)
    report["trajectory_jumps"] = [
        {"t": j.t_s, "row": j.index, "step_m": j.step_m, "step_deg": j.step_deg,
         "translation_m": j.translation_m.tolist(), "significance": j.significance,
         **({"run": k + 1} if len(runs) > 1 else {})} for k, run_jumps in enumerate(jumps) for j in run_jumps]
    if references is not None:
        report["reference"] = {"accuracy_m": references.accuracy_m, "n_ties": len(network.ties),
                               "planes": as_built(network.ties, result.poses, planes, references)}
    report["stage_cache"] = run.summary()
    rows = stations_table(stations, result, planes, links)
    write_text(out / "stations.csv", format_stations_csv(rows))
    write_text(out / "links.csv", format_links_csv(links_table(links, result)))
    write_text(out / "config.toml", config_toml)
    write_text(out / "report.html", render_html(report))
    lap("reports")
    report["timings_s"] = timings
    write_report_json(out / "report.json", report)  # last: it marks a finished run
    run.finish()
    return ProcessSummary(
        out_dir=out,
        n_stations=len(stations),
        n_links=len(links),
        sigma0=result.sigma0,
        global_test_passed=result.global_test_passed,
        position_sigma_rms_mm=report["stations"]["position_sigma_mm"]["rms"],
        position_sigma_max_mm=report["stations"]["position_sigma_mm"]["max"],
        gaps_mean_mm=report["before_after"]["gaps_mm"]["mean"],
        gaps_max_mm=report["before_after"]["gaps_mm"]["max"],
        n_rejected=len(report["adjustment"]["rejected_observations"]),
        timings_s=timings,
        stage_cache=run.summary(),
        n_runs=len(runs),
    )


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
    _, _, sequence = read_and_slice(trajectory_path, cloud_path, config, progress)
    seconds["slice"] = time.perf_counter() - t0
    with sequence, make_executor(workers, scheduler) as executor:
        t0 = time.perf_counter()
        stations, planes = detect_all_planes(sequence, config.planes, progress, executor)
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
