"""Seed-scale end-to-end benchmark: ``kinreg process`` on a simulated run of the seed's size.

The seed's project: 26:33 min of handheld scanning, 159,247 trajectory rows (100 Hz), 234.7 M
points (about 147,000 points/s), 231 quasi-static scans. For each size in ``--points`` this
script

1. generates a run with the simulator (:mod:`kinreg.simulation`: the planar building, a 16-beam
   rotating head, a walk at the seed's 0.41 m/s, SLAM drift) at the seed's point rate, so the
   duration follows the size (20 M points: 2:16 min, 17 scans; 235 M points: 26:33 min, 265 scans)
   and the scans have the seed's density at every size. Blocks of the cloud are simulated on
   worker processes (``--gen-workers``) and compressed in order by lazrs; about 0.6 M points/s
   per core, so the seed-scale run takes well under its own 26 minutes to generate;
2. measures, each in a fresh child process run alone (so its peak memory is its own):
   ``decode``: lazrs (parallel) decode of every chunk, all fields: the floor for ingest;
   ``decode-selected``: the same, only the fields kinreg reads; ``roundtrip``: decode, shift X by
   one unit, encode again (parallel lazrs both ways, to a scratch file): the floor for writing
   ``corrected.laz``; decode and round trip run before and again after ``kinreg process``, so the
   floor is measured under the same load as the run; ``process``: ``kinreg process``
   (the console script), with wall time per stage from ``report.json`` (``timings_s``), the peak
   resident memory of the largest process (its ``VmHWM``) and the largest sum of resident memory
   over the process tree (``VmRSS``), both from ``/proc`` sampled every 0.2 s (worker processes
   count); the floor is the mean decode plus the mean round trip, and every stage is given as a
   multiple of it (``x_floor``) besides the whole run;
3. deletes the generated data (``--keep`` keeps it).

Usage::

    .venv/bin/python benchmarks/scale.py --points 20e6 235e6 [--tmp /big/disk] [--workers 2]

Needs about 45 bytes of temporary disk per point at the largest size (LAZ input ~13 B, slicing
spill 36 B, corrected LAZ ~13 B, E57 sequence ~30 B; the spill is freed before the E57 is
written). Figures go to ``--out`` (default ``benchmarks/results/scale.json``) and a Markdown section is
printed for ``benchmarks/RESULTS.md``. Never commit the generated data.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from kinreg.simulation.run import SimulationConfig

REPO = Path(__file__).resolve().parents[1]
# The repository's own venv when there is one (a worktree may have none: the running interpreter's).
KINREG = next((p for p in (REPO / ".venv" / "bin" / "kinreg", Path(sys.executable).with_name("kinreg"))
               if p.exists()), REPO / ".venv" / "bin" / "kinreg")

SEED_POINTS_PER_S = 234.7e6 / (26 * 60 + 33)  # the seed's project: 147,300 points/s
SEED_SPEED_MPS = 655.0 / (26 * 60 + 33)  # 655 m in 26:33 min

# ---------------------------------------------------------------- generation (workers import this)

_RUNS: dict[Any, Any] = {}


def _run_of(config: Any) -> Any:
    from kinreg.simulation.run import simulate_run

    if config not in _RUNS:
        _RUNS.clear()
        _RUNS[config] = simulate_run(config)
    return _RUNS[config]


def simulate_block(task: tuple[Any, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block ``index`` of the run of ``config``: (times, object-frame xyz, intensity)."""
    config, index = task
    blk = _run_of(config).cloud_block(index)
    return blk.stamps_s, blk.xyz_obj, blk.intensity


def seed_like_config(n_points: float, seed: int = 1) -> Any:
    """A simulation of ``n_points`` at the seed's point rate and walking speed."""
    from kinreg.simulation.run import SimulationConfig
    from kinreg.simulation.sensor import SensorConfig
    from kinreg.simulation.walk import WalkConfig

    duration = n_points / SEED_POINTS_PER_S
    sensor = SensorConfig(pulse_rate_hz=SEED_POINTS_PER_S, n_beams=16)
    walk = WalkConfig(speed_mps=SEED_SPEED_MPS, min_speed_mps=0.3)
    probe = SimulationConfig(seed=seed, duration_s=max(duration, 60.0), sensor=sensor, walk=walk, block_s=5.0)
    # The blind cone and misses drop part of the pulses: scale the pulse rate to hit the point rate.
    kept = sum(len(simulate_block((probe, k))[0]) for k in (2, 7)) / (2 * probe.block_s * sensor.pulse_rate_hz)
    return replace(probe, duration_s=duration, sensor=replace(sensor, pulse_rate_hz=SEED_POINTS_PER_S / kept))


def generate(folder: Path, n_points: float, workers: int,
             config: SimulationConfig | None = None) -> tuple[Path, Path, dict[str, Any]]:
    """Write ``run_trajectory.txt`` and ``run_cloud.laz`` of a seed-like run into ``folder``
    (``config``: another simulation than :func:`seed_like_config`'s of ``n_points``)."""
    import laspy

    from kinreg.run.executor import make_executor
    from kinreg.simulation.files import _las_header, write_trajectory_geoslam

    t0 = time.perf_counter()
    config = seed_like_config(n_points) if config is None else config
    run = _run_of(config)
    traj_path, cloud_path = folder / "run_trajectory.txt", folder / "run_cloud.laz"
    write_trajectory_geoslam(traj_path, run.slam)
    n = 0
    with make_executor(workers) as ctx, laspy.open(cloud_path, mode="w", header=_las_header(run), do_compress=True,
                                                   laz_backend=laspy.LazBackend.LazrsParallel) as writer:
        tasks = ((config, k) for k in range(run.n_blocks()))
        for stamps, xyz, intensity in ctx.map(simulate_block, tasks):
            rec = laspy.ScaleAwarePointRecord.zeros(len(stamps), header=writer.header)
            rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            rec.gps_time = stamps
            rec.intensity = intensity
            rec.return_number = np.ones(len(stamps), dtype=np.uint8)
            rec.number_of_returns = np.ones(len(stamps), dtype=np.uint8)
            writer.write_points(rec)
            n += len(stamps)
    info = {"points": n, "duration_s": config.duration_s, "trajectory_rows": len(run.slam),
            "path_length_m": run.slam.path_length_m(), "pulse_rate_hz": config.sensor.pulse_rate_hz,
            "laz_mb": cloud_path.stat().st_size / 1e6, "generate_s": time.perf_counter() - t0}
    return traj_path, cloud_path, info


# ---------------------------------------------------------------- measurements


def _status_kb(pid: int, field: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (from /proc/<pid>/task/*/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def run_measured(cmd: list[str], env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``cmd`` alone; its wall time, the peak RSS of the largest process in its tree (VmHWM)
    and the largest sampled sum of RSS over the tree."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONWARNINGS": "ignore", **(env or {})})
    peak_tree_kb = 0
    peak_hwm_kb: dict[int, int] = {}
    stop = threading.Event()

    def sample() -> None:
        nonlocal peak_tree_kb
        while not stop.is_set():
            pids = _tree(proc.pid)
            peak_tree_kb = max(peak_tree_kb, sum(_status_kb(p, "VmRSS") for p in pids))
            for p in pids:  # VmHWM only grows: the last sample before exit is (nearly) the peak
                peak_hwm_kb[p] = max(peak_hwm_kb.get(p, 0), _status_kb(p, "VmHWM"))
            stop.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out_lines: list[str] = []
    err_lines: list[str] = []
    readers = [threading.Thread(target=lambda s, acc: acc.extend(s), args=(proc.stdout, out_lines)),
               threading.Thread(target=lambda s, acc: acc.extend(s), args=(proc.stderr, err_lines))]
    for r in readers:
        r.start()
    proc.wait()
    wall = time.perf_counter() - t0
    stop.set()
    sampler.join()
    for r in readers:
        r.join()
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd[:3]} failed ({proc.returncode}):\n{''.join(err_lines)[-3000:]}")
    # Not ru_maxrss (wait4, RUSAGE_CHILDREN): Linux carries the parent's RSS at fork into the
    # child's maxrss across exec, so a small child of a big parent would report the parent's size.
    return {"wall_s": wall, "peak_rss_mb": max(peak_hwm_kb.values(), default=0) / 1024,
            "peak_tree_rss_mb": peak_tree_kb / 1024,
            "stdout": "".join(out_lines)}


def decode_child(mode: str, cloud_path: str) -> None:
    """In a fresh process: decode every chunk; print points and seconds as JSON."""
    import laspy

    from kinreg.io.las import _SELECTION

    selection = _SELECTION if mode == "decode-selected" else laspy.DecompressionSelection.all()
    t0 = time.perf_counter()
    n = 0
    with laspy.open(cloud_path, laz_backend=laspy.LazBackend.LazrsParallel, decompression_selection=selection) as r:
        for pts in r.chunk_iterator(2_000_000):
            n += len(pts)
    print(json.dumps({"points": n, "seconds": time.perf_counter() - t0}))


def roundtrip_child(cloud_path: str) -> None:
    """In a fresh process: decode, shift, encode every chunk to a scratch LAZ; print JSON."""
    import laspy

    from kinreg.io.las import _laz_backend

    scratch = Path(cloud_path).with_name("roundtrip-scratch.laz")
    t0 = time.perf_counter()
    n = 0
    try:
        with laspy.open(cloud_path, laz_backend=_laz_backend()) as r, \
                laspy.open(scratch, mode="w", header=r.header, do_compress=True, laz_backend=_laz_backend()) as w:
            for pts in r.chunk_iterator(2_000_000):
                pts.X = pts.X + 1
                w.write_points(pts)
                n += len(pts)
    finally:
        scratch.unlink(missing_ok=True)
    print(json.dumps({"points": n, "seconds": time.perf_counter() - t0}))


def measure_decode(mode: str, cloud: Path) -> dict[str, Any]:
    flag = "--roundtrip-child" if mode == "roundtrip" else "--decode-child"
    res = run_measured([sys.executable, __file__, flag, *([] if mode == "roundtrip" else [mode]), str(cloud)])
    inner = json.loads(res.pop("stdout").strip().splitlines()[-1])
    return {**res, **inner, "points_per_s": inner["points"] / inner["seconds"]}


def measure_process(traj: Path, cloud: Path, out: Path, extra: list[str]) -> dict[str, Any]:
    res = run_measured([str(KINREG), "process", "--trajectory", str(traj), "--cloud", str(cloud), "--out", str(out),
                        "--overwrite", *extra], env={"COLUMNS": "200", "KINREG_DEBUG": "1"})
    res.pop("stdout")
    report = json.loads((out / "report.json").read_text())
    res["timings_s"] = report.get("timings_s", {})
    res["n_stations"] = report["stations"]["n"]
    res["slicing"] = {k: v for k, v in report["slicing"].items() if k != "skipped_windows"}
    res["n_links"] = report["links"]["n_links"]
    res["n_candidate_pairs"] = report["links"]["n_candidate_pairs"]
    res["sigma0"] = report["adjustment"]["sigma0"]
    res["output_mb"] = {p.name: p.stat().st_size / 1e6 for p in out.iterdir() if p.is_file()}
    return res


def _las_points(cloud: Path) -> int:
    import laspy

    with laspy.open(cloud) as r:
        return int(r.header.point_count)


def _duration(traj: Path) -> float:
    from kinreg.io.trajectory import read_trajectory

    return read_trajectory(traj).duration_s


def _floor(row: dict[str, Any]) -> dict[str, Any]:
    """The I/O floor (mean decode + mean round trip, before and after the run) and the run and
    each stage as multiples of it."""
    decode = (row["decode"]["seconds"] + row["decode_after"]["seconds"]) / 2
    roundtrip = (row["roundtrip"]["seconds"] + row["roundtrip_after"]["seconds"]) / 2
    floor = decode + roundtrip
    p = row["process"]
    return {"floor_s": floor, "floor_decode_s": decode, "floor_roundtrip_s": roundtrip,
            "process_x_floor": p["wall_s"] / floor,
            "stage_x_floor": {s: t / floor for s, t in p["timings_s"].items()}}


def markdown(report: dict[str, Any]) -> str:
    rows = report["results"]
    stages = sorted({s for r in rows for s in r["process"]["timings_s"]},
                    key=lambda s: min(list(r["process"]["timings_s"]).index(s) for r in rows
                                      if s in r["process"]["timings_s"]))
    lines = ["### `kinreg process` against the I/O floor (`benchmarks/scale.py`)", "",
             f"Command: `{report['command']}` on {report['cpus']} shared cores "
             f"({report['note']}, {report['date']}).", "",
             "| points | run | scans | links | " + " | ".join(stages) + " | total process | peak RSS (largest process) "
             "| peak RSS (process tree) | decode all fields | slice vs decode | floor (decode + round trip) "
             "| process / floor |",
             "|---" * (len(stages) + 11) + "|"]
    for r in rows:
        p = r["process"]
        lines.append(
            f"| {r['generated']['points'] / 1e6:.1f} M | {r['generated']['duration_s'] / 60:.1f} min "
            f"| {p['n_stations']} | {p['n_links']} | "
            + " | ".join(f"{p['timings_s'].get(s, float('nan')):.1f} s" for s in stages)
            + f" | {p['wall_s']:.0f} s | {p['peak_rss_mb']:.0f} MB | {p['peak_tree_rss_mb']:.0f} MB "
            f"| {r['decode']['seconds']:.1f} s ({r['decode']['points_per_s'] / 1e6:.2f} M/s) "
            f"| {r['slice_vs_decode']:.0%} "
            + (f"| {r['floor_decode_s']:.1f} + {r['floor_roundtrip_s']:.1f} s | {r['process_x_floor']:.2f}x |"
               if "floor_s" in r else "| - | - |"))
        if "floor_s" in r:
            lines.append("| (x floor) | | | | " + " | ".join(f"{r['stage_x_floor'].get(s, float('nan')):.2f}"
                                                           for s in stages)
                         + f" | {r['process_x_floor']:.2f} | | | | | | |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=float, nargs="+", default=[20e6, 235e6])
    parser.add_argument("--tmp", type=Path, default=None, help="where to generate (default: a new temp folder)")
    parser.add_argument("--gen-workers", type=int, default=None, help="processes simulating blocks (default: all)")
    parser.add_argument("--process-args", default="", help="extra arguments for kinreg process, e.g. '--workers 2'")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "scale.json")
    parser.add_argument("--note", default="other jobs running", help="conditions, for the Markdown section")
    parser.add_argument("--keep", action="store_true", help="keep the generated data")
    parser.add_argument("--existing", type=Path, nargs="+", default=None,
                        help="measure runs generated before (folders with run_trajectory.txt and run_cloud.laz; "
                             "kept) instead of generating")
    parser.add_argument("--skip-selected", action="store_true",
                        help="leave out decode-selected (not part of the floor; saves a decode of the file)")
    parser.add_argument("--decode-child", nargs=2, metavar=("MODE", "CLOUD"), help=argparse.SUPPRESS)
    parser.add_argument("--roundtrip-child", metavar="CLOUD", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.decode_child:
        decode_child(*args.decode_child)
        return
    if args.roundtrip_child:
        roundtrip_child(args.roundtrip_child)
        return
    base = args.tmp or Path(tempfile.mkdtemp(prefix="kinreg-scale-"))
    base.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"date": time.strftime("%Y-%m-%d %H:%M"), "cpus": os.cpu_count(),
                              "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "note": args.note,
                              "results": []}
    for n in args.existing or args.points:
        existing = isinstance(n, Path)
        folder = n if existing else Path(tempfile.mkdtemp(prefix=f"run-{n / 1e6:.0f}M-", dir=base))
        try:
            if existing:
                traj, cloud = folder / "run_trajectory.txt", folder / "run_cloud.laz"
                info = {"points": _las_points(cloud), "duration_s": _duration(traj), "generate_s": None,
                        "laz_mb": cloud.stat().st_size / 1e6}
                n = info["points"]
            else:
                print(f"[{time.strftime('%H:%M:%S')}] generating {n / 1e6:.0f} M points in {folder}", flush=True)
                traj, cloud, info = generate(folder, n, args.gen_workers)
            print(f"  {json.dumps(info)}", flush=True)
            row: dict[str, Any] = {"n_points": int(n), "generated": info}
            for mode in ("decode", *(() if args.skip_selected else ("decode-selected",)), "roundtrip"):
                row[mode] = measure_decode(mode, cloud)
                print(f"  {mode}: {json.dumps(row[mode])}", flush=True)
            row["process"] = measure_process(traj, cloud, folder / "out", args.process_args.split())
            print(f"  process: {json.dumps(row['process'])}", flush=True)
            for mode in ("decode", "roundtrip"):
                row[mode + "_after"] = measure_decode(mode, cloud)
                print(f"  {mode} after: {json.dumps(row[mode + '_after'])}", flush=True)
            row.update(_floor(row))
            t_slice = row["process"]["timings_s"].get("slice", math.nan)
            row["slice_vs_decode"] = row["decode"]["seconds"] / t_slice
            if "decode-selected" in row:
                row["slice_vs_decode_selected"] = row["decode-selected"]["seconds"] / t_slice
            report["results"].append(row)
            args.out.write_text(json.dumps(report, indent=1) + "\n")
        except BaseException:
            print(f"failed; the generated data is kept for inspection in {folder}", flush=True)
            raise
        if not args.keep and not existing:
            shutil.rmtree(folder, ignore_errors=True)
        shutil.rmtree(folder / "out", ignore_errors=True)
    if args.tmp is None and not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    print(f"written {args.out}\n")
    print(markdown(report))


if __name__ == "__main__":
    main()
