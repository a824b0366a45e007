"""Networking and block-adjustment speed.

1. Links per second: slice the sample run, detect planes, then time the matching + pairwise
   adjustment over all candidate pairs (``kinreg.estimate.network.link_stations``).
2. ``kinreg.estimate.block.adjust_block`` end to end (Gauss-Newton, selected inverse, tests, variance
   components, data snooping) on synthetic networks of 231 and 20,000 stations: a chain with
   its 4 successors linked (some links rank 5) and loop closures every 50 stations.

Usage: python benchmarks/network_speed.py [--stations 231 20000] [--out benchmarks/results/network_speed.json]

3. ``--block-only``: only (2), each adjustment in a child process of its own (its peak RSS its own),
   the network pickled to ``--cache DIR`` on first use (100,000 stations take minutes to
   simulate), and with ``--trees A B`` alternately with the kinreg of each source tree (e.g. an
   exported ``main`` against this one, ``--repeat`` times): an A/B in the same conditions.

   python benchmarks/network_speed.py --block-only --stations 100000 --cache /tmp/kinreg-bench \
       --trees /tmp/main-tree . --repeat 2 --out benchmarks/results/block_100k.json

4. ``--scan-frames``: the block as the pipeline builds it with ``[block] scan_frames = true``
   (``kinreg.estimate.frames``): per station a scan-frame node (the plane links) and a sensor-pose
   node (the trajectory's links), tied by a ``FRAME`` observation; the first sensor pose is held.
   Made from the same cached network (the trajectory's links moved to the sensor nodes, the ties
   drawn with sigmas of 0.3 mm and 0.1 mrad), so 2 n nodes. The errors and sigmas reported are
   the sensor poses'.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def bench_links() -> dict:
    from kinreg.config import KinregConfig
    from kinreg.estimate.matching import candidate_pairs
    from kinreg.io.cloud import open_cloud
    from kinreg.io.trajectory import read_trajectory
    from kinreg.progress import NullProgress
    from kinreg.run.link_stage import link_stations
    from kinreg.run.planes_stage import detect_all_planes
    from kinreg.run.spill import slice_quasi_static

    cfg = KinregConfig()
    data = REPO / "sample_data"
    traj = read_trajectory(data / "run_trajectory.txt")
    with open_cloud(data / "run_cloud.laz") as cloud:
        seq = slice_quasi_static(traj, cloud, cfg.slicing)
    with seq:
        t0 = time.perf_counter()
        stations, planes = detect_all_planes(seq, cfg.planes, NullProgress(), trajectory=traj)
        t_planes = time.perf_counter() - t0
    n_pairs = len(candidate_pairs(np.array([s.T_obj_scan.t_xyz for s in stations]), cfg.matching))
    t0 = time.perf_counter()
    links, _ = link_stations(stations, planes, cfg.matching, cfg.drift, cfg.pairwise)
    t_links = time.perf_counter() - t0
    return {"scans": len(stations), "points_per_scan": float(np.mean([s.n_points for s in stations])),
            "planes_ms_per_scan": 1000 * t_planes / len(stations), "candidate_pairs": n_pairs,
            "links": len(links), "link_s": t_links, "pairs_per_s": n_pairs / t_links,
            "links_per_s": len(links) / t_links}


def synthetic_network(n: int, seed: int = 0):
    from kinreg.geometry import Pose, rotvec_to_quat
    from kinreg.types import ObservationKind, RelativeObservation

    rng = np.random.default_rng(seed)
    s = np.arange(n)
    # a serpentine walk: lanes of 50 stations, loop closures between neighbouring lanes
    lane, pos = divmod(s, 50)
    x = np.where(lane % 2 == 0, pos, 49 - pos) * 2.0
    truth = Pose(rotvec_to_quat(np.column_stack([0.02 * rng.normal(size=n), 0.02 * rng.normal(size=n),
                                                  np.pi * (lane % 2)])),
                 np.column_stack([x, lane * 4.0, 1.5 + 0.05 * rng.normal(size=n)]))
    cov_t = np.diag(np.square([2e-3] * 3 + [3e-4] * 3))
    cov_p = np.diag(np.square([1e-3] * 3 + [1e-4] * 3))
    obs = []

    def add(i, j, cov, kind, rank=6):
        T = truth[i].inverse().compose(truth[j])
        info = np.linalg.inv(cov)
        if rank == 5:
            info[0, :] = 0
            info[:, 0] = 0
        obs.append(RelativeObservation(kind, i, j, T.compose(Pose.exp(rng.multivariate_normal(np.zeros(6), cov))),
                                       info, rank))

    for i in range(n - 1):
        add(i, i + 1, cov_t, ObservationKind.TRAJECTORY)
        for j in range(i + 1, min(n, i + 5)):
            add(i, j, cov_p, ObservationKind.PLANES, 5 if (i + j) % 7 == 0 else 6)
    for i in range(n):
        if lane[i] % 2 == 0 and pos[i] % 10 == 0:
            j = (lane[i] + 1) * 50 + (49 - pos[i])
            if j < n:
                add(i, int(j), cov_p, ObservationKind.PLANES)
    initial = truth.compose(Pose.exp(np.column_stack([np.linspace(0, 0.05, n)[:, None] * [1, -1, 0.3],
                                                      np.zeros((n, 3))])))
    return truth, initial, obs


def frame_network(truth, initial, obs, seed: int = 1):
    """The network of :func:`synthetic_network` with a scan frame and a sensor pose per station, as
    ``kinreg.estimate.frames.adjust_with_frames`` builds it: nodes 0..n-1 the scan frames (the plane
    links stay there), n..2n-1 the sensor poses (the trajectory's links move there), a ``FRAME`` tie
    ``s_k^-1 x_k = Z`` per station after the other observations. Returns (truth, initial, obs,
    fixed) over the 2 n nodes; the first sensor pose is held (the frames follow by their ties)."""
    from dataclasses import replace

    from kinreg.geometry import Pose
    from kinreg.types import ObservationKind, RelativeObservation

    rng = np.random.default_rng(seed)
    n = len(initial)
    moved = [replace(o, i=o.i + n, j=o.j + n) if o.kind is ObservationKind.TRAJECTORY else o for o in obs]
    cov = np.diag(np.square([3e-4] * 3 + [1e-4] * 3))
    info = np.linalg.inv(cov)
    noise = Pose.exp(rng.multivariate_normal(np.zeros(6), cov, size=n))
    ties = [RelativeObservation(ObservationKind.FRAME, k, n + k, noise[k], info, 6) for k in range(n)]
    both = Pose(np.concatenate([truth.quat_wxyz, truth.quat_wxyz]), np.concatenate([truth.t_xyz, truth.t_xyz]))
    start = Pose(np.concatenate([initial.quat_wxyz, initial.quat_wxyz]), np.concatenate([initial.t_xyz, initial.t_xyz]))
    fixed = np.zeros(2 * n, dtype=bool)
    fixed[n] = True
    return both, start, moved + ties, fixed


def cached_network(n: int, cache: Path | None):
    """:func:`synthetic_network` ``(n)``, pickled into ``cache`` (a folder) on first use."""
    path = None if cache is None else cache / f"network_{n}.pkl"
    if path is not None and path.exists():
        with path.open("rb") as f:
            return pickle.load(f)
    network = synthetic_network(n)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as f:
            pickle.dump(network, f, protocol=5)
    return network


def bench_block(n: int, cache: Path | None = None, scan_frames: bool = False) -> dict:
    from kinreg.config import BlockConfig
    from kinreg.estimate.block import adjust_block
    from kinreg.estimate.sparse import HAVE_CHOLMOD

    truth, initial, obs = cached_network(n, cache)
    fixed = np.zeros(n, dtype=bool)
    fixed[0] = True
    if scan_frames:
        truth, initial, obs, fixed = frame_network(truth, initial, obs)
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    res = adjust_block(initial, obs, fixed, BlockConfig())
    wall = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    sensor = slice(n, 2 * n) if scan_frames else slice(0, n)  # the reported poses: the sensor's
    err = truth[sensor].inverse().compose(res.poses[sensor]).log()[1:]
    sig = np.sqrt(np.diagonal(res.cov_xi[sensor], axis1=1, axis2=2))[1:]
    normalised = np.array([t.normalised for t in res.tests])
    return {"stations": n, "scan_frames": scan_frames, "nodes": len(initial), "observations": len(obs),
            "seconds": wall,
            "cpu_seconds": (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime),
            "peak_rss_gb": cpu1.ru_maxrss / 1e6, "iterations": res.iterations,
            "sigma0": res.sigma0, "redundancy": res.redundancy,
            "rejected": int(sum(t.rejected for t in res.tests)),
            "normalised_residual_rms": float(np.sqrt(np.nanmean(normalised**2))),
            "normalised_error_rms": float(np.sqrt(np.mean((err / sig) ** 2))),
            "station_sigma_last_mm": (1e3 * sig[-1, :3]).tolist(),
            "cholmod": HAVE_CHOLMOD, "load_average": os.getloadavg()}


def bench_block_trees(stations: list[int], cache: Path | None, trees: list[Path], repeat: int,
                      scan_frames: bool = False) -> list[dict]:
    """Each network with the kinreg of each tree, alternating, each run in a child process."""
    out = []
    for n in stations:
        cached_network(n, cache)  # simulated once, outside the timed children
        for round_ in range(repeat):
            for tree in trees:
                env = dict(os.environ, PYTHONPATH=str(tree.resolve()))
                child = [sys.executable, str(Path(__file__).resolve()), "--one-block", str(n)]
                child += [] if cache is None else ["--cache", str(cache.resolve())]
                child += ["--scan-frames"] if scan_frames else []
                res = json.loads(subprocess.run(child, check=True, capture_output=True, text=True, env=env,
                                                cwd=tree).stdout.splitlines()[-1])
                res.update(tree=str(tree), round=round_)
                print(json.dumps(res), flush=True)
                out.append(res)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--stations", type=int, nargs="+", default=[231, 20_000])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "network_speed.json")
    parser.add_argument("--block-only", action="store_true", help="only the block adjustments, in child processes")
    parser.add_argument("--cache", type=Path, help="folder for the pickled synthetic networks")
    parser.add_argument("--trees", type=Path, nargs="+", default=[REPO], help="kinreg source trees to compare")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--scan-frames", action="store_true",
                        help="a scan-frame and a sensor-pose node per station, tied by a FRAME observation")
    parser.add_argument("--one-block", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one_block:
        print(json.dumps(bench_block(args.one_block, args.cache, args.scan_frames)))
        return
    if args.block_only:
        result = {"date": time.strftime("%Y-%m-%d %H:%M"), "command": " ".join(sys.argv), "cpus": os.cpu_count(),
                  "block": bench_block_trees(args.stations, args.cache, args.trees, args.repeat, args.scan_frames)}
    else:
        result = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv), "links": bench_links(),
                  "block": [bench_block(n, args.cache, args.scan_frames) for n in args.stations]}
    print(json.dumps(result, indent=1))
    args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
