"""Time of the per-point drift correction (``DriftCorrection.apply_to_points``) on 2 M points of the
sample trajectory with random station corrections; with ``--cloud``, of the whole corrected-cloud
stage on a LAS/LAZ file.

Usage: python benchmarks/correction_speed.py ref   # keep this code's result as the reference
       python benchmarks/correction_speed.py       # time, and the largest difference from it [mm]
       python benchmarks/correction_speed.py --cloud RUN/run_cloud.laz --trajectory RUN/run_trajectory.txt \
           [--repeat 3] [--out FILE]

With ``--cloud``: ``write_corrected_las`` of the file (decode, correct, encode to a scratch LAZ,
with the report's cloud views gathered as ``kinreg process`` does) under 40 random station
corrections with station sigmas, and the I/O floor of the same file (lazrs decode, shift X by one
unit, encode), alternately ``--repeat`` times in this process: the stage's seconds and their
ratio to the floor (the machine is shared; the ratio is what compares across runs). Code without
station sigmas in ``DriftCorrection`` (before the per-point extra bytes) is timed without them.

The figures go to ``benchmarks/results/correction_speed.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import statistics
import time
from pathlib import Path

import numpy as np

from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.trajectory import read_trajectory

REPO = Path(__file__).resolve().parents[1]
REFERENCE = Path("/tmp/kinreg_correction_reference.npy")
OUT = REPO / "benchmarks" / "results" / "correction_speed.json"


def stage_speed(cloud: Path, trajectory: Path, repeat: int, out: Path) -> None:
    """The corrected-cloud stage against the I/O floor on ``cloud`` (see the module)."""
    import laspy

    from kinreg.config import ReportConfig
    from kinreg.io.las import _laz_backend
    from kinreg.report.cloud_views import CloudViews
    from kinreg.run.corrected_cloud import write_corrected_las

    traj = read_trajectory(trajectory)
    rng = np.random.default_rng(0)
    ts = np.linspace(traj.t_start_s + 3, traj.t_end_s - 3, 40)
    initial = traj.pose_at(ts)
    adjusted = Pose(rotvec_to_quat(rng.normal(0, 0.003, (40, 3))), rng.normal(0, 0.05, (40, 3))).compose(initial)
    with_sigmas = "sigma_3d_m" in {f.name for f in dataclasses.fields(DriftCorrection)}
    extra = {"sigma_3d_m": np.linspace(0.0, 0.02, 40)} if with_sigmas else {}
    correction = DriftCorrection.from_stations(ts, initial, adjusted, traj, **extra)
    with laspy.open(cloud) as reader:
        header = reader.header
        lo, hi, n_points = np.asarray(header.mins), np.asarray(header.maxs), int(header.point_count)
    scratch = cloud.with_name("correction-speed-scratch.laz")
    stage, floor, stage_cpu, floor_cpu = [], [], [], []

    def cpu_s() -> float:  # of every thread of this process (lazrs encodes on its own threads)
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    try:
        for _ in range(repeat):
            views = CloudViews(ReportConfig(), lo, hi, traj.t_start_s, traj.t_end_s, n_points_total=n_points)
            start, cpu = time.perf_counter(), cpu_s()
            write_corrected_las(cloud, scratch, correction, overwrite=True, observer=views)
            stage.append(time.perf_counter() - start)
            stage_cpu.append(cpu_s() - cpu)
            start, cpu = time.perf_counter(), cpu_s()
            with laspy.open(cloud, laz_backend=_laz_backend()) as r, \
                    laspy.open(scratch, mode="w", header=r.header, do_compress=True, laz_backend=_laz_backend()) as w:
                for points in r.chunk_iterator(2_000_000):
                    points.X = points.X + 1
                    w.write_points(points)
            floor.append(time.perf_counter() - start)
            floor_cpu.append(cpu_s() - cpu)
            print(f"corrected cloud {stage[-1]:.2f} s ({stage_cpu[-1]:.2f} s CPU), floor (round trip) "
                  f"{floor[-1]:.2f} s ({floor_cpu[-1]:.2f} s CPU), ratio {stage[-1] / floor[-1]:.3f}", flush=True)
    finally:
        scratch.unlink(missing_ok=True)
    ratios = [a / b for a, b in zip(stage, floor, strict=True)]
    figures = {"date": time.strftime("%Y-%m-%d %H:%M"), "cloud": str(cloud), "points": n_points,
               "station_sigmas": with_sigmas, "stage_s": stage, "floor_roundtrip_s": floor, "ratio": ratios,
               "stage_cpu_s": stage_cpu, "floor_roundtrip_cpu_s": floor_cpu,
               "median_stage_s": statistics.median(stage), "median_ratio": statistics.median(ratios),
               "median_stage_cpu_s": statistics.median(stage_cpu)}
    print(f"median: corrected cloud {figures['median_stage_s']:.2f} s ({figures['median_stage_cpu_s']:.2f} s CPU), "
          f"{figures['median_ratio']:.3f} x the round trip")
    out.write_text(json.dumps(figures, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ref", nargs="?", choices=["ref"], help="keep this code's result as the reference")
    parser.add_argument("--cloud", type=Path, help="time the whole corrected-cloud stage on this LAS/LAZ file")
    parser.add_argument("--trajectory", type=Path, help="the cloud's trajectory (with --cloud)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if args.cloud is not None:
        if args.trajectory is None:
            parser.error("--cloud needs --trajectory")
        stage_speed(args.cloud, args.trajectory, args.repeat, args.out)
        return
    traj = read_trajectory(REPO / "sample_data" / "run_trajectory.txt")
    rng = np.random.default_rng(0)
    ts = np.linspace(traj.t_start_s + 3, traj.t_end_s - 3, 40)
    initial = traj.pose_at(ts)
    adjusted = Pose(rotvec_to_quat(rng.normal(0, 0.003, (40, 3))), rng.normal(0, 0.05, (40, 3))).compose(initial)
    correction = DriftCorrection.from_stations(ts, initial, adjusted, traj)
    n = 2_000_000
    t = np.sort(rng.uniform(traj.t_start_s, traj.t_end_s, n))
    xyz = traj.pose_at(t).t_xyz + rng.normal(0, 8, (n, 3))
    start = time.perf_counter()
    corrected = correction.apply_to_points(xyz, t)
    seconds = time.perf_counter() - start
    print(f"apply_to_points: {seconds:.3f} s for {n:,} points")
    figures = {"date": time.strftime("%Y-%m-%d"), "points": n, "seconds": seconds}
    if args.ref == "ref":
        np.save(REFERENCE, corrected)
    elif REFERENCE.exists():
        figures["largest_difference_mm"] = float(np.abs(corrected - np.load(REFERENCE)).max() * 1000)
        print(f"largest difference from the reference: {figures['largest_difference_mm']:.4f} mm")
    args.out.write_text(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
