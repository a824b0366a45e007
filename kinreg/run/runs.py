"""Several kinematic runs in one project: how their stations are numbered and named, what their
outputs are called, and how they are reported.

A project may hold several runs (a trajectory and the cloud it georeferenced, each), delivered in
one frame, as the SLAM runs of one project are (a few centimetres, tenths of a degree apart). Each
run is read and sliced on its own; its quasi-static stations join one network, numbered after the
stations of the runs before it. The trajectory ties only consecutive stations of the same run;
stations of two runs are linked through identical planes where they are close
(``[matching] radius_m``), with a loose prior (``[pairwise] cross_run_prior_sigma_*``), like loop
closures (:mod:`kinreg.estimate.network`).

Names, with one run exactly as without this module: stations ``qs_00012`` and outputs
``corrected.laz``, ``trajectory_corrected.txt``. With several runs, run k (1-based) names its
stations ``rk_qs_00012`` (the number is the window's within its run, as ``kinreg slice`` numbers
it) and its outputs ``corrected_rk.laz`` and ``trajectory_corrected_rk.txt``; ``stations.csv``,
``links.csv``, ``sequence.e57`` and the reports hold all runs.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from kinreg.config import SlicingConfig, WindowMode
from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose
from kinreg.types import Plane, Scan, ScanKind, SlicingSummary, Trajectory

if TYPE_CHECKING:
    from kinreg.run.spill import QuasiStaticSequence
    from kinreg.types import BlockResult, Station, TrajectoryJump

# A per-run output of an earlier run in the output folder (or its temporary file).
_RUN_OUTPUT = re.compile(r"\.?(?:trajectory_)?corrected_r(\d+)\.")


class SlicedRun(Protocol):
    """What the report needs of a run's slices (:class:`kinreg.run.output_folder.CachedSlices`,
    which imports this module): the cloud's point count and the number of windows."""

    n_points_input: int

    def __len__(self) -> int: ...


@dataclass(frozen=True)
class RunInputs:
    """One kinematic run: a trajectory and the cloud georeferenced with it."""

    trajectory: Path
    cloud: Path


def run_station_name(name: str, run_index: int, n_runs: int) -> str:
    """The name of a quasi-static station of run ``run_index`` (0-based) of ``n_runs``: as sliced
    with one run, prefixed by its run with several.

    >>> run_station_name("qs_00012", 0, 1), run_station_name("qs_00012", 1, 2)
    ('qs_00012', 'r2_qs_00012')
    """
    return name if n_runs == 1 else f"r{run_index + 1}_{name}"


def run_output_names(run_index: int, n_runs: int) -> tuple[str, str]:
    """(corrected cloud, corrected trajectory) file names of run ``run_index`` (0-based).

    >>> run_output_names(0, 1), run_output_names(1, 3)
    (('corrected.laz', 'trajectory_corrected.txt'), ('corrected_r2.laz', 'trajectory_corrected_r2.txt'))
    """
    if n_runs == 1:
        return "corrected.laz", "trajectory_corrected.txt"
    return f"corrected_r{run_index + 1}.laz", f"trajectory_corrected_r{run_index + 1}.txt"


def output_files(out_dir: Path, fixed: tuple[str, ...], n_runs: int) -> tuple[str, ...]:
    """Every output name kinreg may have in ``out_dir``: the ``fixed`` ones, the per-run ones of
    ``n_runs`` runs, and those of an earlier run with more runs found in the folder (so that they
    are replaced or removed, never mixed with this run's)."""
    highest = n_runs if n_runs > 1 else 0
    if out_dir.is_dir():
        for path in out_dir.iterdir():
            m = _RUN_OUTPUT.match(path.name)
            if m:
                highest = max(highest, int(m.group(1)))
    per_run = tuple(name for k in range(highest) for name in run_output_names(k, max(highest, 2)))
    return fixed + tuple(name for name in per_run if name not in fixed)


def label_run(stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]], run_index: int, first_id: int,
              n_runs: int) -> tuple[list[Station], list[tuple[Plane, ...]]]:
    """A run's quasi-static stations and their planes (as sliced: ids ``0..n-1``) numbered after
    the ``first_id`` stations of the runs before it, named by :func:`run_station_name` and marked
    with their run. With one run they come back unchanged."""
    if n_runs == 1 and first_id == 0:
        return list(stations), list(planes)
    labelled: list[Station] = []
    moved: list[tuple[Plane, ...]] = []
    for k, (station, found) in enumerate(zip(stations, planes, strict=True)):
        scan_id = first_id + k
        labelled.append(replace(station, scan_id=scan_id, name=run_station_name(station.name, run_index, n_runs),
                                run=run_index))
        moved.append(tuple(replace(p, scan_id=scan_id) for p in found))
    return labelled, moved


def run_correction(stations: Sequence[Station], result: BlockResult, run_index: int, trajectory: Trajectory,
                   jumps: Sequence[TrajectoryJump] = (), coupling: float = 0.0) -> DriftCorrection:
    """The drift correction of one run, from its own quasi-static stations only (runs overlap in
    space and may overlap in time; each has its own drift); ``coupling``: the drift's measured one
    (:class:`~kinreg.estimate.correction.DriftCorrection`). The stations' 3D position sigmas
    (the root of the trace of ``result.cov_position``) go with it, for the points' sigmas."""
    own = np.array([s.kind is ScanKind.QUASI_STATIC and s.run == run_index for s in stations])
    times = np.array([s.t_s for s in stations])
    sigma_3d_m = np.sqrt(np.maximum(np.trace(result.cov_position[own], axis1=1, axis2=2), 0.0))
    return DriftCorrection.from_stations(times[own], result.poses_initial[own], result.poses[own], trajectory,
                                         jumps, coupling, sigma_3d_m)


def adjusted_sequence_scans(sequences: Sequence[QuasiStaticSequence], poses: Pose) -> Iterator[Scan]:
    """The quasi-static scans of every run's sequence (their points read one scan at a time) in
    station order, with their adjusted ``poses``, numbered and named as their stations
    (:func:`label_run`). The sequences pickle as their small index: a worker process can write them."""
    first = 0
    for k, sequence in enumerate(sequences):
        for scan in sequence.iter_scans():
            scan_id = first + scan.scan_id
            yield replace(scan, scan_id=scan_id, name=run_station_name(scan.name, k, len(sequences)),
                          T_obj_scan=poses[scan_id])
        first += len(sequence)


# --------------------------------------------------------------------------- report.json


def inputs_report(runs: Sequence[RunInputs], trajectories: Sequence[Trajectory], sliced: Sequence[SlicedRun],
                  static: Path | None = None, reference: Path | None = None) -> dict[str, Any]:
    """``report.json`` ``inputs``: ``runs`` lists every run (its files, counts and output names).
    The keys of schema 1 keep their meaning: ``trajectory`` and ``cloud`` are the run's files
    (``null`` with several runs: see ``runs``), the counts are totals over the runs."""
    n_runs = len(runs)
    listed = []
    for k, (run, trajectory, slices) in enumerate(zip(runs, trajectories, sliced, strict=True)):
        cloud_name, trajectory_name = run_output_names(k, n_runs)
        listed.append({"trajectory": str(run.trajectory), "cloud": str(run.cloud), "n_points": slices.n_points_input,
                       "n_trajectory_rows": len(trajectory), "duration_s": trajectory.duration_s,
                       "path_length_m": trajectory.path_length_m(), "n_scans": len(slices),
                       "station_prefix": run_station_name("", k, n_runs),
                       "corrected_cloud": cloud_name, "corrected_trajectory": trajectory_name})
    totals = ("n_points", "n_trajectory_rows", "duration_s", "path_length_m")
    return {
        "trajectory": listed[0]["trajectory"] if n_runs == 1 else None,
        "cloud": listed[0]["cloud"] if n_runs == 1 else None,
        **{key: sum(r[key] for r in listed) for key in totals},
        "runs": listed,
        "static": None if static is None else str(static),
        "reference": None if reference is None else str(reference),
    }


def slicing_report(summaries: Sequence[SlicingSummary], config: SlicingConfig | None = None,
                   smear_m: np.ndarray | None = None, first_window_s: float | None = None,
                   points_deskewed: bool = False) -> dict[str, Any]:
    """``report.json`` ``slicing``: totals over the runs; with several runs each skipped window
    names its run (1-based); the window length used (``first_window_s``: the one the run was
    sliced with first, where the drift made it slice again), the smear of each station's
    window by the measured drift (:func:`~kinreg.estimate.slicing.window_smear_m`), and whether
    the planes were detected on points deskewed by a first adjustment (``points_deskewed``)."""
    several = len(summaries) > 1
    smear = np.zeros(0) if smear_m is None else np.asarray(smear_m) * 1000.0
    finite = smear[np.isfinite(smear)]
    windows = {} if config is None else {
        "window_s": config.window_s if config.mode is WindowMode.DURATION else None,
        "window_s_first": first_window_s,
        "points_deskewed": points_deskewed,
        "smear_mm": {"median": float(np.median(finite)) if len(finite) else None,
                     "max": float(finite.max()) if len(finite) else None,
                     "per_station": [None if not np.isfinite(v) else float(v) for v in smear]},
    }
    return {
        **windows,
        "n_scans": sum(s.n_scans for s in summaries),
        "n_points_in_scans": sum(s.n_points_in_scans for s in summaries),
        "n_points_outside_trajectory": sum(s.n_points_outside_trajectory for s in summaries),
        "skipped_windows": [{**dataclasses.asdict(w), **({"run": k + 1} if several else {})}
                            for k, s in enumerate(summaries) for w in s.skipped],
    }


def trajectory_plot(trajectories: Sequence[Trajectory], corrected: Sequence[Trajectory],
                    max_points: int = 2000) -> dict[str, list[float]]:
    """``report.json`` ``trajectory_plot``: plan positions before and after along time since the
    earliest start; the runs one after the other, separated by a gap (``null``)."""
    t0 = min(t.t_start_s for t in trajectories)
    plot: dict[str, list[float]] = {key: [] for key in ("t", "x_before", "y_before", "x_after", "y_after")}
    for trajectory, after in zip(trajectories, corrected, strict=True):
        step = max(1, len(trajectory) // max(1, max_points // len(trajectories)))
        part = {
            "t": (trajectory.stamps_s[::step] - t0).tolist(),
            "x_before": trajectory.poses.t_xyz[::step, 0].tolist(),
            "y_before": trajectory.poses.t_xyz[::step, 1].tolist(),
            "x_after": after.poses.t_xyz[::step, 0].tolist(),
            "y_after": after.poses.t_xyz[::step, 1].tolist(),
        }
        for key, values in part.items():
            if plot[key]:
                plot[key].append(math.nan)  # breaks the lines between two runs
            plot[key] += values
    return plot
