"""What the report's views of the cloud (sections, plane-thickness map; issue #16) cost next to
``kinreg process``.

Runs ``kinreg process`` on each given run twice, in fresh subprocesses, with ``[report]
cloud_views`` on and off, and records: the wall time of each, the views' own seconds (``gather``:
inside the streaming write of corrected.laz; ``figures``: PNGs and cloud.json), their share of the
process time without them, the size of report.html, and the key figures (thickness ratio, section
heights). Optionally copies the section PNGs of one run into ``benchmarks/results/``.

Usage:
    python benchmarks/report_views.py --run sample_data/run_trajectory.txt sample_data/run_cloud.laz \\
        --run /tmp/big/run_trajectory.txt /tmp/big/run_cloud.laz --keep-pngs 1 \\
        --out benchmarks/results/report_views.json

The views' own seconds are CPU seconds of the thread that gathers them (``gather``) and draws
the figures (``figures``): corrected.laz is decoded and encoded on other threads at the same
time, whose work would count in the wall time inside the views' calls. They are compared with
the run's time (stage timings: ``views_share_of_process``) and with its CPU seconds
(``views_share_of_process_cpu``: ``getrusage`` of the reaped children, i.e. the kinreg process
with all its threads but not its worker processes, which it does not reap: an upper bound of the
views' share of all the run's CPU), which the load of a shared machine skews less.

Make a bigger run with ``python sample_data/simulate.py --out /tmp/big ...`` (its command line is
stored in the JSON when ``--label`` names it). The wall times are noisy on a shared machine; the
views' own seconds are measured inside the run and are the figure to quote.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_process(trajectory: str, cloud: str, out: Path, views: bool) -> dict:
    config = out.parent / f"{out.name}.toml"
    config.write_text(f"[report]\ncloud_views = {'true' if views else 'false'}\n")
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{REPO / 'cli'}"}
    start = time.perf_counter()
    cpu_start = _children_cpu_s()
    done = subprocess.run([sys.executable, "-m", "kinreg_cli", "process", "-t", trajectory, "-c", cloud, "--out",
                           str(out), "--config", str(config), "--overwrite"], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"kinreg process failed:\n{done.stderr[-3000:]}")
    wall = time.perf_counter() - start
    cpu = _children_cpu_s() - cpu_start  # the process with its threads (not its unreaped workers), user + system
    report = json.loads((out / "report.json").read_text())
    views = out / "figures" / "cloud.json"
    seconds = json.loads(views.read_text())["seconds"] if views.exists() else None
    return {"wall_s": wall, "cpu_s": cpu, "timings_s": report["timings_s"], "cloud": report.get("cloud"),
            "seconds": seconds,
            "crs": report.get("crs"), "report_html_bytes": (out / "report.html").stat().st_size,
            "n_points": report["inputs"].get("n_points")}


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", nargs=2, action="append", metavar=("TRAJECTORY", "CLOUD"), required=True)
    parser.add_argument("--label", action="append", default=[], help="a name per --run (e.g. the simulate command)")
    parser.add_argument("--keep-pngs", type=int, default=None, help="copy the section PNGs of this run (0-based)")
    parser.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "report_views.json"))
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (trajectory, cloud) in enumerate(args.run):
            label = args.label[k] if k < len(args.label) else f"{trajectory} {cloud}"
            without = run_process(trajectory, cloud, Path(tmp) / f"off{k}", views=False)
            with_views = run_process(trajectory, cloud, Path(tmp) / f"on{k}", views=True)
            seconds = with_views["seconds"]
            own = seconds["gather"] + seconds["figures"]
            process_s = sum(without["timings_s"].values())
            entry = {
                "run": label,
                "n_points": with_views["n_points"],
                "process_s_without_views": process_s,
                "process_s_with_views": sum(with_views["timings_s"].values()),
                "wall_s_without_views": without["wall_s"],
                "wall_s_with_views": with_views["wall_s"],
                "views_s": seconds,
                "views_share_of_process": own / process_s,
                # like with like: the views' CPU seconds against the CPU seconds of the run without
                # them (the kinreg process's threads; its workers are not counted: an upper bound)
                "cpu_s_without_views": without["cpu_s"],
                "cpu_s_with_views": with_views["cpu_s"],
                "views_share_of_process_cpu": own / without["cpu_s"],
                "html_bytes_without_views": without["report_html_bytes"],
                "html_bytes_with_views": with_views["report_html_bytes"],
                "sections": [{key: s[key] for key in ("z_m", "pixel_m", "width_px", "height_px", "n_points_before")}
                             for s in with_views["cloud"]["sections"]],
                "heights": with_views["cloud"]["heights"],
                "thickness": {key: value for key, value in with_views["cloud"]["thickness"].items()
                              if key != "images"},
                "crs": with_views["crs"],
            }
            results.append(entry)
            print(f"{label}: {entry['n_points']:,} points, process {process_s:.1f} s ({without['cpu_s']:.1f} CPU s), "
                  f"views {own:.2f} CPU s ({100 * entry['views_share_of_process']:.1f} % of the process time, "
                  f"{100 * entry['views_share_of_process_cpu']:.1f} % of its CPU), thickness ratio "
                  f"{entry['thickness']['median_ratio_after_before']:.3f}", flush=True)
            if args.keep_pngs == k:
                for name in ("section_1_before.png", "section_1_after.png"):
                    shutil.copy(Path(tmp) / f"on{k}" / "figures" / name,
                                REPO / "benchmarks" / "results" / f"report_{name}")
    Path(args.out).write_text(json.dumps({"command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
                                          "cpu_count": os.cpu_count(), "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
