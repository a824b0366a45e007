"""Robustness: wrong plane correspondences and gross trajectory errors (issue 8).

Runs ``kinreg process`` on a simulated run (the committed sample, or the held-out scenario of
accuracy_matrix.py) with:

- ``clean``: as it is (the reference figures);
- ``wrong_matches``: 10 % wrong plane correspondences injected into the matching (each pair
  gets, for about every tenth true match, one extra match between planes that are not the same);
- ``jumps``: the trajectory and the cloud with gross errors: at two instants the exported
  trajectory jumps by 0.5 m (a SLAM failure: everything after the jump is georeferenced with the
  jumped trajectory until the next jump, which returns it), written as new files.

Reported: what was rejected (wrong matches found by the pairwise data snooping, observations
rejected by the block), and the station accuracy against the truth after a rigid fit, next to the
issue's targets (RMS <= 3 mm, max <= 10 mm).

Usage: python benchmarks/robustness.py [--scenario sample] [--out benchmarks/results/robustness.json]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

JUMP_M = 0.5


def errors_after_rigid_fit(xyz: np.ndarray, truth: np.ndarray) -> dict:
    """RMS and max [mm] of the position errors after a rigid fit onto the truth."""
    from kinreg.report.json import rigid_fit

    R, t = rigid_fit(xyz, truth)
    err = np.linalg.norm(xyz @ R.T + t - truth, axis=1) * 1000.0
    return {"rms_mm": float(np.sqrt(np.mean(err**2))), "max_mm": float(err.max())}


def station_errors(out: Path, truth_path: Path) -> dict:
    from kinreg.io.trajectory import read_trajectory

    with open(out / "stations.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["t"]]
    t = np.array([float(r["t"]) for r in rows])
    adj = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    return errors_after_rigid_fit(adj, read_trajectory(truth_path).pose_at(t).t_xyz)


def trajectory_errors(out: Path, truth_path: Path) -> dict:
    """Corrected trajectory (every row) against the truth after a rigid fit: the jumps' rows too."""
    from kinreg.io.trajectory import read_trajectory

    corrected = read_trajectory(out / "trajectory_corrected.txt")
    truth = read_trajectory(truth_path).pose_at(corrected.stamps_s).t_xyz
    return errors_after_rigid_fit(corrected.poses.t_xyz, truth)


def with_jumps(data: Path, folder: Path, jump_times: tuple[float, float]) -> tuple[Path, Path]:
    """Trajectory and cloud with a 0.5 m jump (x) between the two times, as a SLAM failure leaves them."""
    import laspy

    from kinreg.io.trajectory import read_trajectory, write_trajectory_geoslam
    from kinreg.types import Trajectory

    traj = read_trajectory(data / "run_trajectory.txt")
    t0, t1 = traj.t_start_s + jump_times[0], traj.t_start_s + jump_times[1]

    def offset(stamps: np.ndarray) -> np.ndarray:
        return np.where((stamps >= t0) & (stamps < t1), JUMP_M, 0.0)

    poses = traj.poses
    moved = poses.t_xyz.copy()
    moved[:, 0] += offset(traj.stamps_s)
    traj_path = folder / "jump_trajectory.txt"
    write_trajectory_geoslam(traj_path, Trajectory(traj.stamps_s, type(poses)(poses.quat_wxyz, moved)),
                             overwrite=True)
    las = laspy.read(data / "run_cloud.laz")
    las.x = np.asarray(las.x) + offset(np.asarray(las.gps_time))
    cloud_path = folder / "jump_cloud.laz"
    las.write(cloud_path)
    return traj_path, cloud_path


def run(name: str, work: Path, inject: bool = False, jumps: bool = False, seed: int = 0) -> dict:
    from accuracy_matrix import scenario_config

    import kinreg.estimate.network as network
    from kinreg.config import KinregConfig
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import simulate_run
    from kinreg.types import PlaneMatch

    data = REPO / "sample_data" if name == "sample" else work / "data"
    if name != "sample" and not (data / "run_cloud.laz").exists():
        write_run(simulate_run(scenario_config(name)), data)
    traj, cloud = data / "run_trajectory.txt", data / "run_cloud.laz"
    if jumps:
        traj, cloud = with_jumps(data, work, (70.0, 150.0))

    injected: set[tuple[int, int, int, int]] = set()
    original = network.match_planes
    rng = np.random.default_rng(seed)
    counter = {"pair": 0}

    def match_with_errors(planes_i, planes_j, T_i_j, config):
        matches = original(planes_i, planes_j, T_i_j, config)
        counter["pair"] += 1
        if not inject or len(matches) < 3:
            return matches
        extra = []
        true_pairs = {(m.plane_i, m.plane_j) for m in matches}
        for _ in range(len(matches)):
            if rng.random() < 0.1:
                a = planes_i[rng.integers(len(planes_i))].plane_id
                b = planes_j[rng.integers(len(planes_j))].plane_id
                if (a, b) not in true_pairs and a != b:
                    extra.append(PlaneMatch(a, b, 0.0, 0.0, 1.0))
                    injected.add((planes_i[0].scan_id, planes_j[0].scan_id, a, b))
        return (*matches, *extra)

    network.match_planes = match_with_errors
    try:
        t0 = time.perf_counter()
        process(ProcessInputs(traj, cloud), work / "out", KinregConfig(), overwrite=True)
        wall = time.perf_counter() - t0
    finally:
        network.match_planes = original

    report = json.loads((work / "out" / "report.json").read_text())
    with open(work / "out" / "links.csv") as f:
        links = list(csv.DictReader(f))
    return {
        "errors_after_rigid_fit": station_errors(work / "out", data / "truth_trajectory.txt"),
        "corrected_trajectory_errors_after_rigid_fit": trajectory_errors(work / "out", data / "truth_trajectory.txt"),
        "trajectory_jumps_found": [{k: j[k] for k in ("t", "step_m", "step_deg")}
                                   for j in report.get("trajectory_jumps", [])],
        "injected_wrong_matches": len(injected),
        "rejected_matches_pairwise": int(sum(int(r["n_rejected_matches"]) for r in links)),
        "links_rejected": int(sum(r["status"] == "rejected" for r in links)),
        "block_rejected": report["adjustment"]["rejected_observations"],
        "sigma0": report["adjustment"]["sigma0"],
        "wall_s": wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="sample")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "robustness.json")
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory(prefix="kinreg-robust-") as tmp:
        for label, kwargs in (("clean", {}), ("wrong_matches", {"inject": True}), ("jumps", {"jumps": True}),
                              ("wrong_matches_and_jumps", {"inject": True, "jumps": True})):
            folder = Path(tmp) / label
            folder.mkdir()
            results[label] = run(args.scenario, folder, **kwargs)
            print(label, json.dumps(results[label]), flush=True)
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
                                    "scenario": args.scenario, "results": results}, indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
