"""The large outputs of ``kinreg process``: each run's corrected trajectory and cloud and
``sequence.e57``, each written again only where it is no longer current in the output folder."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinreg.config import KinregConfig
from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose
from kinreg.io.reference_planes import ReferencePlanes
from kinreg.io.trajectory import write_trajectory_geoslam
from kinreg.progress import Progress
from kinreg.report.cloud_views import CloudViews, cloud_views_for_runs
from kinreg.run.context import RunContext
from kinreg.run.corrected_cloud import PointObserver, write_corrected_las
from kinreg.run.estimation import Estimated
from kinreg.run.executor import ExecutorContext
from kinreg.run.output_folder import CachedSlices, RunCache, dataclass_parts
from kinreg.run.runs import RunInputs, adjusted_sequence_scans, run_output_names
from kinreg.run.spill import QuasiStaticSequence
from kinreg.types import Scan, Trajectory


@dataclass(frozen=True, eq=False)
class WrittenOutputs:
    """What writing the large outputs leaves for the report: which outputs were current (kept),
    the corrected trajectories, and the views of the clouds gathered while they were written."""

    plan: LargeOutputs
    corrected: list[Trajectory]
    views: CloudViews


def write_large_outputs(run: RunContext, estimated: Estimated,
                        corrections: Sequence[DriftCorrection]) -> WrittenOutputs:
    """Each run's corrected trajectory and cloud and ``sequence.e57`` into the staging folder:
    ``sequence.e57`` on a worker process (where there are local ones) while this one writes the
    corrected clouds, both single-threaded for much of their time."""
    runs, config, references = run.inputs.runs, estimated.config, run.read.references
    sliced, poses = estimated.sliced, estimated.adjusted.result.poses
    plan = plan_large_outputs(run.folder, runs, sliced, corrections, poses, config, references)
    views = cloud_views_for_runs(config.report, [r.cloud for r in runs], estimated.trajectories, references,
                                 run.inputs.static)
    staging = run.folder.start_outputs()  # every output goes here first
    crs_wkt = views.crs.get("wkt", "")
    sequence_job = start_sequence(staging, sliced, poses, plan, run.executor, crs_wkt)
    corrected = write_corrected_runs(staging, runs, estimated.trajectories, corrections, plan, run.folder, config,
                                     references, run.progress, views, sliced)
    run.clock.lap("corrected cloud")
    write_sequence(staging, sliced, poses, plan, run.folder, run.progress, crs_wkt, sequence_job)
    run.clock.lap("sequence E57")
    return WrittenOutputs(plan, corrected, views)


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
