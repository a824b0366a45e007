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
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kinreg.config import KinregConfig
from kinreg.estimate.matching import candidate_pairs
from kinreg.io.atomic import check_writable_target
from kinreg.io.checks import check_inputs, time_filter
from kinreg.io.cloud import open_cloud
from kinreg.progress import NullProgress, Progress
from kinreg.report.tables import format_links_csv, format_planes_csv, links_table, write_text
from kinreg.run.context import RunContext, StageClock
from kinreg.run.estimation import correct_runs, estimate
from kinreg.run.executor import make_executor
from kinreg.run.inputs import ProcessInputs, read_input_trajectory, read_inputs
from kinreg.run.large_outputs import counted, write_large_outputs
from kinreg.run.link_stage import link_stations
from kinreg.run.output_folder import RunCache, open_output_folder
from kinreg.run.planes_stage import detect_all_planes
from kinreg.run.report_outputs import ProcessResults, write_reports
from kinreg.run.spill import QuasiStaticSequence, slice_quasi_static
from kinreg.types import SlicingSummary, Trajectory

__all__ = ["OUTPUT_FILES", "LinkSummary", "ProcessInputs", "ProcessSummary", "link_to_folder", "process",
           "read_and_slice", "slice_to_e57"]


def process(inputs: ProcessInputs, out_dir: str | Path, config: KinregConfig, overwrite: bool = False,
            progress: Progress | None = None, workers: int | None = 1, scheduler: str | None = None,
            resume: bool = False) -> ProcessSummary:
    """``kinreg process``: read, slice, detect planes, link, adjust, correct, report (see the
    module's docstring for ``workers``, ``scheduler``, ``resume`` and ``overwrite``). The outputs
    are written into the folder's staging folder and moved into place together at the end."""
    progress, out, clock = progress or NullProgress(), Path(out_dir), StageClock()
    with prepare_output_folder(out, overwrite, resume, len(inputs.runs)) as folder, contextlib.ExitStack() as stack:
        read = read_inputs(inputs, config)  # every input checked before the long work
        executor = stack.enter_context(make_executor(workers, scheduler))
        run = RunContext(inputs, read, config, folder, stack, progress, executor, clock)
        estimated = estimate(run)  # slice, planes, link, adjust: the rounds of kinreg.estimate.strategy
        corrections = correct_runs(estimated)
        written = write_large_outputs(run, estimated, corrections)  # corrected clouds, sequence.e57
        stack.close()  # the workers and the spill are no longer needed
        report = write_reports(run, ProcessResults(estimated, corrections, written))
        folder.commit_outputs(keep=written.plan.current)  # all at once, report.json last: it marks a finished run
        folder.finish()
    return ProcessSummary.from_report(out, report)


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



OUTPUT_FILES = ("stations.csv", "links.csv", "trajectory_corrected.txt", "corrected.laz", "sequence.e57",
                "report.json", "report.html", "config.toml", "control_points.csv", "planes.csv")


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
        links, _ = link_stations(stations, planes, config.matching, config.drift, config.pairwise, progress,
                                 executor=executor)
        seconds["link"] = time.perf_counter() - t0
    n_candidates = len(candidate_pairs(np.array([s.T_obj_scan.t_xyz for s in stations]), config.matching))
    write_text(out / "planes.csv", format_planes_csv(stations, planes), overwrite=overwrite)
    write_text(out / "links.csv", format_links_csv(links_table(links, None)), overwrite=overwrite)
    by_status: dict[str, int] = {}
    for link in links:
        by_status[link.status.value] = by_status.get(link.status.value, 0) + 1
    return LinkSummary(len(stations), sum(len(p) for p in planes), n_candidates, len(links), by_status, seconds)
