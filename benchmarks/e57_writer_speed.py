"""kinreg's E57 writer (numpy, hardware CRC-32C, large O_DIRECT writes) against the libE57 writer it
replaced (``tests/e57fixtures.write_libe57_sequence``): the same scans, wall and CPU time of each.

Synthetic scans like the ingest benchmark's: N points in ~23 scans, coordinates normal * 10 m,
sorted times, float32 intensity. Each writer runs ``--repeats`` times, alternately, in this process
(CPU: ``time.process_time``, this process and its threads). Both files are checked to hold the same
points before the timings count.

Usage: python benchmarks/e57_writer_speed.py [--points 20e6] [--scans 23] [--repeats 2]
       [--folder /tmp] [--out benchmarks/results/e57_writer_speed.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from e57fixtures import write_libe57_sequence  # noqa: E402

from kinreg.geometry import Pose, rotvec_to_quat  # noqa: E402
from kinreg.io.e57_writer import write_e57_sequence  # noqa: E402
from kinreg.types import Scan, ScanKind  # noqa: E402


def make_scans(n_points: int, n_scans: int) -> list[Scan]:
    rng = np.random.default_rng(18)
    scans = []
    for k, n in enumerate(np.diff(np.linspace(0, n_points, n_scans + 1).astype(int))):
        t0 = 1.6e9 + 30.0 * k
        scans.append(Scan(
            scan_id=k, name=f"qs_{k:05d}", kind=ScanKind.QUASI_STATIC,
            T_obj_scan=Pose(rotvec_to_quat(rng.normal(0.0, 1.0, 3)),
                            np.array([5e5, 5.4e6, 300.0]) + rng.normal(0, 50, 3)),
            points_xyz=rng.normal(0.0, 1.0, (n, 3)) * 10.0,
            stamps_s=np.sort(t0 + rng.uniform(0.0, 20.0, n)),
            intensity=rng.uniform(0.0, 4000.0, n).astype(np.float32),
            t_s=t0 + 10.0, t_start_s=t0, t_end_s=t0 + 20.0,
        ))
    return scans


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=float, default=20e6)
    parser.add_argument("--scans", type=int, default=23)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--folder", type=Path, default=None,
                        help="where the files are written (default: a temporary folder)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "e57_writer_speed.json")
    args = parser.parse_args()
    scans = make_scans(int(args.points), args.scans)
    writers = {
        "kinreg": lambda path: write_e57_sequence(path, scans, overwrite=True),
        "libe57": lambda path: write_libe57_sequence(path, scans),
    }
    runs: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory(dir=args.folder) as tmp:
        for repeat in range(args.repeats):
            for name, write in writers.items():
                path = Path(tmp) / f"{name}.e57"
                path.unlink(missing_ok=True)
                wall, cpu = time.perf_counter(), time.process_time()
                write(path)
                os.sync()  # the disk's time counts in wall for both
                wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
                runs.append({"writer": name, "repeat": repeat, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
                             "bytes": path.stat().st_size})
                size_mb = path.stat().st_size / 1e6
                print(f"{name:7s} repeat {repeat}: wall {wall:6.2f} s  cpu {cpu:6.2f} s  {size_mb:8.1f} MB", flush=True)
        import e57  # the Rust reader: both files hold the same points
        same = bool(np.array_equal(e57.read_points(str(Path(tmp) / "kinreg.e57")).points,
                                   e57.read_points(str(Path(tmp) / "libe57.e57")).points))
    summary = {
        name: {key: min(float(r[key]) for r in runs if r["writer"] == name) for key in ("wall_s", "cpu_s")}  # type: ignore[arg-type]
        for name in writers
    }
    result = {"points": int(args.points), "scans": args.scans, "repeats": args.repeats, "same_points": same,
              "best": summary, "runs": runs}
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary), "same points:", same)


if __name__ == "__main__":
    main()
