"""The planes stage's work on the scans of a real run, one source tree against another.

Slices a run (trajectory + LAS/LAZ) once with the default configuration and keeps its scans and
sensor tracks in ``--cache`` (pickles, about 45 MB a million points; reused on the next call).
Then one worker process per source tree (``--tree label=path``, e.g. ``main=/work/main`` and
``new=.``) runs ``detect_planes`` and ``plane_time_offsets`` on every scan, the workers taking
turns scan by scan so that the load of a shared machine falls on both alike; each scan's CPU
seconds (``time.process_time``, one BLAS thread) are the minimum over ``--repeat`` rounds. With
two trees the planes (every field, times and sensor moments included) are compared to the bit.

Usage::

    python benchmarks/bench_planes_ab.py --run /path/to/run_folder --cache /tmp/planes_cache \\
        --tree main=/work/main --tree new=. [--repeat 2]

(``run_folder`` holds ``run_trajectory.txt`` and ``run_cloud.laz``, as ``bench_scale.py --keep``
leaves them.)
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
import os
import pickle
import sys
import time
from pathlib import Path
from typing import Any


def _slice_once(run: Path, cache: Path) -> list[Path]:
    files = sorted(cache.glob("scan_*.pkl"))
    if files:
        return files
    from kinreg.config import load_config
    from kinreg.estimate.slicing import sensor_track
    from kinreg.progress import NullProgress
    from kinreg.run.pipeline import read_and_slice

    config = load_config()
    cache.mkdir(parents=True, exist_ok=True)
    trajectory, _, sequence = read_and_slice(run / "run_trajectory.txt", run / "run_cloud.laz", config,
                                             NullProgress())
    with sequence:
        for i in range(len(sequence)):
            track = sensor_track(trajectory, sequence.windows[i])
            with open(cache / f"scan_{i:04d}.pkl", "wb") as f:
                pickle.dump((sequence.read_scan(i), track, config.planes), f, protocol=5)
    return sorted(cache.glob("scan_*.pkl"))


def _worker(tree: str, files: list[str], repeat: int, turn: Any, next_turn: Any, results: Any, label: str) -> None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    sys.path.insert(0, tree)
    from kinreg.estimate.drift import plane_time_offsets
    from kinreg.estimate.planes import detect_planes

    best: dict[str, tuple[float, float]] = {}
    planes: dict[str, Any] = {}
    for _ in range(repeat):
        for name in files:
            with open(name, "rb") as f:
                scan, track, config = pickle.load(f)
            turn.wait()
            turn.clear()
            a = time.process_time()
            found = detect_planes(scan, config)
            b = time.process_time()
            times = plane_time_offsets(scan.points_xyz, scan.stamps_s, scan.t_s, found, config.refit_distance_m,
                                       track)
            c = time.process_time()
            next_turn.set()
            planes[name] = times.applied(found)
            old = best.get(name, (float("inf"), float("inf")))
            best[name] = (min(old[0], b - a), min(old[1], c - b))
    results.put((label, best, pickle.dumps(planes)))


def _same(a: Any, b: Any) -> bool:
    import numpy as np

    if len(a) != len(b):
        return False
    for p, q in zip(a, b, strict=True):
        for field in dataclasses.fields(p):
            u, v = getattr(p, field.name), getattr(q, field.name)
            if isinstance(u, np.ndarray | float | tuple):
                if not np.array_equal(np.asarray(u, dtype=float), np.asarray(v, dtype=float), equal_nan=True):
                    return False
            elif u != v:
                return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--cache", type=Path, required=True)
    parser.add_argument("--tree", action="append", required=True, help="label=path of a source tree (at most two)")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    files = [str(f) for f in _slice_once(args.run, args.cache)]
    trees = [t.split("=", 1) for t in args.tree][:2]
    ctx = mp.get_context("spawn")
    turns = [ctx.Event() for _ in trees]
    results = ctx.Queue()
    workers = [ctx.Process(target=_worker, args=(str(Path(path).resolve()), files, args.repeat, turns[k],
                                                 turns[(k + 1) % len(trees)], results, label))
               for k, (label, path) in enumerate(trees)]
    for w in workers:
        w.start()
    turns[0].set()
    got = {}
    for _ in workers:
        label, best, planes = results.get()
        got[label] = (best, pickle.loads(planes))
    for w in workers:
        w.join()
    print(f"{len(files)} scans, CPU s (min of {args.repeat} rounds, one core):")
    for label, (best, _) in got.items():
        detect = sum(v[0] for v in best.values())
        times = sum(v[1] for v in best.values())
        print(f"  {label:>8}: detect_planes {detect:7.2f}  plane_time_offsets {times:6.2f}  sum {detect + times:7.2f}")
    if len(got) == 2:
        (_, (_, a)), (_, (_, b)) = got.items()
        differ = [Path(f).name for f in files if not _same(a[f], b[f])]
        print("  planes the same to the bit" if not differ else f"  planes differ in {len(differ)} scans: {differ}")


if __name__ == "__main__":
    main()
