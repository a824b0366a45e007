"""Plane detection speed: milliseconds per scan at typical quasi-static scan sizes.

Scans are ray cast in the synthetic room of ``tests/test_planes.py`` (10 x 8 x 3 m, interior wall
with a door opening, a box, a slanted board; 1 cm range noise; scan frame rotated and shifted)
with 0.3 M and 1 M points, plus a static scan of the simulator's building
(``kinreg.simulation``, corridor and rooms, ranges up to 24 m) with about 1 M points. Each
scan is detected ``--repeat`` times (the first run is a warm-up and is not counted); the minimum
and the median are reported, with the planes found and the accuracy of the well-sampled ones.

BLAS and OpenMP are limited to one thread (``--threads``) to measure the one-core figure the
budget is stated in (231 scans in a few minutes).

Usage: python benchmarks/plane_detection.py [--points 3e5 1e6] [--repeat 5]
       [--out benchmarks/results/plane_detection.json]
"""

from __future__ import annotations

import argparse
import os
import sys

if __name__ == "__main__":
    # Must happen before numpy / open3d are imported.
    _threads = "1"
    if "--threads" in sys.argv:
        _threads = sys.argv[sys.argv.index("--threads") + 1]
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = _threads

import datetime
import json
import statistics
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from test_planes import angle_deg, find_plane, make_room_scan, well_sampled  # noqa: E402

from kinreg.config import PlanesConfig  # noqa: E402
from kinreg.estimate.planes import detect_planes  # noqa: E402
from kinreg.types import Scan  # noqa: E402


def simulator_scan(n_target: int) -> tuple[Scan, list[tuple[np.ndarray, float]]]:
    """A static scan (1 cm range noise) in the simulator's building and its true planes (scan frame)."""
    from kinreg.simulation.scene import BuildingConfig, make_building
    from kinreg.simulation.sensor import StaticConfig, make_static_scans

    scene = make_building(BuildingConfig())
    # The static grid has about (360 / step) * (150 / step) directions; choose the step for n_target.
    step = float(np.sqrt(360.0 * 150.0 / n_target))
    cfg = StaticConfig(n_scans=1, angle_step_deg=step, range_sigma_m=0.01, max_range_m=30.0)
    scan = make_static_scans(scene, cfg, np.random.default_rng(0))[0]
    R, t = scan.T_obj_scan.rotation_matrix, scan.T_obj_scan.t_xyz
    truth = []
    for p in scene.planes():
        n, d = R.T @ p.normal, float(p.d - p.normal @ t)
        truth.append((n, d) if d < 0 else (-n, -d))
    return scan, truth


def measure(scan: Scan, config: PlanesConfig, repeat: int) -> dict:
    detect_planes(scan, config)  # warm-up (imports open3d, fills caches)
    times = []
    planes = ()
    for _ in range(repeat):
        t0 = time.perf_counter()
        planes = detect_planes(scan, config)
        times.append(time.perf_counter() - t0)
    return {
        "n_points": len(scan),
        "ms_min": 1e3 * min(times),
        "ms_median": 1e3 * statistics.median(times),
        "n_planes": len(planes),
        "planes": planes,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, nargs="+", default=[3e5, 1e6])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="BLAS/OpenMP threads (set before import)")
    ap.add_argument("--no-simulator", action="store_true", help="skip the simulator's building scan")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "plane_detection.json")
    args = ap.parse_args()
    config = PlanesConfig()
    rows = []
    for n in args.points:
        room = make_room_scan(n_rays=int(n), seed=1)
        res = measure(room.scan, config, args.repeat)
        errs = []
        for face, pts in well_sampled(room, min_points=20_000):
            nt, dt = room.truth_in_scan(face)
            p = find_plane(res["planes"], nt, dt, near_xyz=pts.mean(axis=0))
            errs.append((angle_deg(p.normal, nt) * 1e3, abs(p.d_m - dt) * 1e3) if p else (np.inf, np.inf))
        rows.append({"scene": "room", **{k: v for k, v in res.items() if k != "planes"},
                     "n_well_sampled": len(errs),
                     "max_angle_mdeg": max(e[0] for e in errs) if errs else None,
                     "max_offset_mm": max(e[1] for e in errs) if errs else None})
    if not args.no_simulator:
        scan, truth = simulator_scan(int(max(args.points)))
        res = measure(scan, config, args.repeat)
        # Every detected plane should be a true plane (angle < 0.5 deg, offset < 2 cm).
        errs = []
        for p in res["planes"]:
            best = min(truth, key=lambda nd: angle_deg(p.normal, nd[0]) + 1e3 * abs(p.d_m - nd[1]))
            errs.append((angle_deg(p.normal, best[0]) * 1e3, abs(p.d_m - best[1]) * 1e3, p.n_points))
        big = [e for e in errs if e[2] >= 20_000]
        rows.append({"scene": "simulator_building_static", **{k: v for k, v in res.items() if k != "planes"},
                     "n_well_sampled": len(big),
                     "max_angle_mdeg": max(e[0] for e in big) if big else None,
                     "max_offset_mm": max(e[1] for e in big) if big else None,
                     "n_unmatched": sum(e[0] > 500 or e[1] > 20 for e in errs)})

    out = {
        "benchmark": "planes",
        "date": datetime.date.today().isoformat(),
        "threads": args.threads,
        "repeat": args.repeat,
        "config": {k: getattr(config, k) for k in config.__dataclass_fields__},
        "results": rows,
    }
    args.out.write_text(json.dumps(out, indent=2))
    print(f"detect_planes, {args.threads} thread(s), {args.repeat} runs after a warm-up:")
    for r in rows:
        print(f"  {r['scene']:27s} {r['n_points']:>9,d} points: {r['ms_min']:7.0f} ms min, "
              f"{r['ms_median']:7.0f} ms median, {r['n_planes']:2d} planes; well-sampled "
              f"{r['n_well_sampled']}: max {r['max_angle_mdeg']:.1f} mdeg, {r['max_offset_mm']:.3f} mm")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
