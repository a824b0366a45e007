"""Ingest + slicing (+ E57 export) throughput next to the raw lazrs decode of the same file.

Generates a synthetic kinematic run (100 Hz trajectory, time-sorted LAZ 1.4 point format 6 with
gps_time) of N points in a temporary folder, then measures, each in a fresh subprocess so that
peak memory is per measurement:

- ``decode``: raw lazrs (parallel) decode of every chunk, all fields, nothing else: the floor;
- ``decode-selected``: the same, decompressing only the fields kinreg reads (xyz, time, intensity);
- ``slice``: kinreg's streaming ingest + slicing into quasi-static scans (spill to disk);
- ``slice+e57``: the same followed by the E57 sequence export (``kinreg slice``).

Usage: python benchmarks/ingest_speed.py [--points 20e6 5e6] [--out benchmarks/results/ingest_speed.json]
Figures go to the JSON file and are summarised on stdout; benchmarks/RESULTS.md quotes them.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def generate(folder: Path, n_points: int, rate_pts_s: float = 150_000.0) -> tuple[Path, Path]:
    """A cheap run: points scattered around a walking platform, written in 2 M-point chunks."""
    import laspy
    from conftest import make_trajectory

    from kinreg.io.trajectory import write_trajectory_geoslam

    duration = n_points / rate_pts_s
    traj = make_trajectory(duration)
    traj_path = folder / "traj.txt"
    write_trajectory_geoslam(traj_path, traj, overwrite=True)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.array([-100.0, -100.0, -100.0])
    rng = np.random.default_rng(0)
    cloud_path = folder / "cloud.laz"
    block = 2_000_000
    stamps_all = np.linspace(traj.t_start_s, traj.t_end_s, n_points)
    with laspy.open(cloud_path, mode="w", header=header, do_compress=True,
                    laz_backend=laspy.LazBackend.LazrsParallel) as writer:
        for a in range(0, n_points, block):
            t = stamps_all[a: a + block]
            pts = laspy.ScaleAwarePointRecord.zeros(len(t), header=header)
            xyz = traj.pose_at(t).apply(rng.normal(0.0, 5.0, (len(t), 3)))
            pts.x, pts.y, pts.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            pts.gps_time = t
            pts.intensity = rng.integers(0, 65535, len(t), dtype=np.uint16)
            writer.write_points(pts)
    return traj_path, cloud_path


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM). Unlike ru_maxrss it is not inherited from
    the parent across fork + exec."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(mode: str, traj_path: str, cloud_path: str, out_path: str) -> None:
    """Run one measurement in this (fresh) process and print its figures as JSON."""
    t0 = time.perf_counter()
    n = 0
    if mode in ("decode", "decode-selected"):
        import laspy

        from kinreg.io.las import _SELECTION

        selection = _SELECTION if mode == "decode-selected" else laspy.DecompressionSelection.all()
        with laspy.open(cloud_path, laz_backend=laspy.LazBackend.LazrsParallel,
                        decompression_selection=selection) as r:
            for pts in r.chunk_iterator(2_000_000):
                n += len(pts)
    elif mode == "slice":
        from kinreg.config import SlicingConfig
        from kinreg.io.cloud import open_cloud
        from kinreg.io.trajectory import read_trajectory
        from kinreg.run.spill import slice_quasi_static

        traj = read_trajectory(traj_path)
        with open_cloud(cloud_path) as cloud, slice_quasi_static(traj, cloud, SlicingConfig()) as seq:
            n = seq.summary.n_points_read
    elif mode == "slice+e57":
        from kinreg.config import KinregConfig
        from kinreg.run.pipeline import slice_to_e57

        n = slice_to_e57(traj_path, cloud_path, out_path, KinregConfig(), overwrite=True).n_points_read
    wall = time.perf_counter() - t0
    peak_mb = peak_rss_mb()
    print(json.dumps({"mode": mode, "points": n, "wall_s": wall, "points_per_s": n / wall, "peak_rss_mb": peak_mb}))


def measure(mode: str, traj: Path, cloud: Path, folder: Path) -> dict:
    cmd = [sys.executable, __file__, "--child", mode, str(traj), str(cloud), str(folder / "seq.e57")]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True,
                         env={**os.environ, "PYTHONWARNINGS": "ignore"})
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=float, nargs="+", default=[5e6, 20e6])
    parser.add_argument("--modes", nargs="+", default=["decode", "decode-selected", "slice", "slice+e57"])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "ingest_speed.json")
    parser.add_argument("--child", nargs=4, metavar=("MODE", "TRAJ", "CLOUD", "OUT"))
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return
    results = []
    for n in args.points:
        with tempfile.TemporaryDirectory(prefix="kinreg-bench-") as tmp:
            folder = Path(tmp)
            t0 = time.perf_counter()
            traj, cloud = generate(folder, int(n))
            gen_s = time.perf_counter() - t0
            row = {"n_points": int(n), "laz_mb": cloud.stat().st_size / 1e6, "generate_s": gen_s}
            for mode in args.modes:
                row[mode] = measure(mode, traj, cloud, folder)
            if "decode" in row and "slice" in row:
                row["slice_vs_decode"] = row["slice"]["points_per_s"] / row["decode"]["points_per_s"]
            if "decode" in row and "slice+e57" in row:
                row["slice_e57_vs_decode"] = row["slice+e57"]["points_per_s"] / row["decode"]["points_per_s"]
            results.append(row)
            print(json.dumps(row, indent=1), flush=True)
    report = {"date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count(), "command": " ".join(sys.argv),
              "results": results}
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
