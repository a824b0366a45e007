"""Kinematic vs static (issue #16, item 3) against the truth: the static-deviation RMS of the
corrected cloud next to the same figure for the cloud georeferenced with the TRUE trajectory.

The simulator's input cloud is georeferenced with the drifted trajectory: ``p = T_slam(t) x``. The
same points with the true trajectory are ``T_true(t) T_slam(t)^-1 p``; their deviations from the
static cloud's local planes are what a perfect correction would give (noise and georeferencing
of the sensor only). Done when the corrected cloud's RMS is within 10 % of it.

Usage:
    kinreg process -t RUN/run_trajectory.txt -c RUN/run_cloud.laz --static RUN/static.e57 --out OUT
    python benchmarks/static_deviation.py --run RUN --out-dir OUT [--json benchmarks/results/static_deviation.json]

``--json`` keeps one entry per run folder (later calls add to it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import laspy
import numpy as np

from kinreg.geometry import interpolate_poses
from kinreg.io.trajectory import read_trajectory
from kinreg.report.deviations import Deviations, static_planes_from_e57


def cloud_chunks(path: Path, stride: int):
    with laspy.open(path) as reader:
        for points in reader.chunk_iterator(1_000_000):
            xyz = np.column_stack([points.x, points.y, points.z]).astype(np.float64)[::stride]
            yield xyz, np.asarray(points.gps_time, dtype=np.float64)[::stride]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", required=True, help="simulated run folder (run_*, truth_trajectory.txt, static.e57)")
    parser.add_argument("--out-dir", required=True, help="kinreg process output folder of that run with --static")
    parser.add_argument("--json", default=str(Path(__file__).parent / "results" / "static_deviation.json"))
    parser.add_argument("--stride", type=int, default=4)
    args = parser.parse_args()
    run, out = Path(args.run), Path(args.out_dir)
    report = json.loads((out / "report.json").read_text())
    kinreg_figures = report["cloud"].get("static_deviations") or {}
    noise_mm = kinreg_figures.get("noise_mm") or report["cloud"]["thickness"]["median_after_mm"]
    bounds = laspy.open(run / "run_cloud.laz").header
    planes = static_planes_from_e57(run / "static.e57", np.asarray(bounds.mins) - 1.0)
    slam = read_trajectory(run / "run_trajectory.txt")
    truth = read_trajectory(run / "truth_trajectory.txt")
    deviations = Deviations(planes, stride=1)
    for xyz, t in cloud_chunks(run / "run_cloud.laz", args.stride):
        deviations.add("before", xyz)
        T_slam = interpolate_poses(slam.stamps_s, slam.poses, t)
        T_true = interpolate_poses(truth.stamps_s, truth.poses, t)
        deviations.add("after", T_true.apply(T_slam.inverse().apply(xyz)))  # "after": with the true trajectory
    for xyz, _ in cloud_chunks(out / "corrected.laz", args.stride):
        deviations.hist.setdefault("kinreg", np.zeros_like(deviations.hist["after"]))
        deviations.sums.setdefault("kinreg", np.zeros(3))
        deviations.add("kinreg", xyz)
    truth_figures = deviations.figures(noise_mm)
    n, s, s2 = deviations.sums["kinreg"]
    kinreg_rms = float(np.sqrt(s2 / n))
    result = {
        "run": str(run), "out_dir": str(out), "stride": args.stride, "noise_mm": noise_mm,
        "rms_mm": {"input": truth_figures["before"]["rms_mm"], "true_trajectory": truth_figures["after"]["rms_mm"],
                   "kinreg_corrected": kinreg_rms},
        "mean_mm": {"input": truth_figures["before"]["mean_mm"], "true_trajectory": truth_figures["after"]["mean_mm"],
                    "kinreg_corrected": s / n},
        "kinreg_over_truth": kinreg_rms / truth_figures["after"]["rms_mm"],
        "report_static_deviations": {k: v for k, v in kinreg_figures.items() if k not in ("before", "after")} | {
            w: {k: v for k, v in (kinreg_figures.get(w) or {}).items() if k != "histogram"}
            for w in ("before", "after")},
    }
    print(json.dumps(result, indent=1))
    if args.json:  # one entry per run, kept across calls
        path = Path(args.json)
        runs = json.loads(path.read_text()) if path.exists() else {}
        runs[str(run)] = result
        path.write_text(json.dumps(runs, indent=1) + "\n")


if __name__ == "__main__":
    main()
