"""Time of the per-point drift correction (``DriftCorrection.apply_to_points``) on 2 M points of the
sample trajectory with random station corrections.

Usage: python benchmarks/correction_speed.py ref   # keep this code's result as the reference
       python benchmarks/correction_speed.py       # time, and the largest difference from it [mm]

The figures go to ``benchmarks/results/correction_speed.json``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.trajectory import read_trajectory

REPO = Path(__file__).resolve().parents[1]
REFERENCE = Path("/tmp/kinreg_correction_reference.npy")
OUT = REPO / "benchmarks" / "results" / "correction_speed.json"


def main() -> None:
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
    if sys.argv[-1] == "ref":
        np.save(REFERENCE, corrected)
    elif REFERENCE.exists():
        figures["largest_difference_mm"] = float(np.abs(corrected - np.load(REFERENCE)).max() * 1000)
        print(f"largest difference from the reference: {figures['largest_difference_mm']:.4f} mm")
    OUT.write_text(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
