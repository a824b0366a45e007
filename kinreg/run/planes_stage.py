"""The planes stage: each quasi-static scan's planes and its station, on the executor's workers
and through the output folder's stage cache; the static scans' too."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from kinreg.config import KinregConfig, PlanesConfig
from kinreg.estimate.datum import take_out_jumps
from kinreg.estimate.drift import WindowMap, deskewed_points, plane_time_offsets, rms_time_offset
from kinreg.estimate.planes import detect_planes, facing_the_sensor
from kinreg.estimate.reference import to_reference_frame
from kinreg.estimate.slicing import SensorTrack, sensor_track
from kinreg.io.reference_planes import ReferencePlanes
from kinreg.progress import Progress
from kinreg.run.codecs import scan_planes_from_arrays, scan_planes_to_arrays
from kinreg.run.executor import ExecutorContext, in_process, parallel_map
from kinreg.run.output_folder import CachedSlices, RunCache
from kinreg.run.runs import label_run
from kinreg.run.spill import QuasiStaticSequence
from kinreg.types import Plane, ScanKind, Station, Trajectory, TrajectoryJump

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

