"""Pool the runs of several ``accuracy_matrix.py`` outputs per cell (scenario, drift model, class).

One run's stations share most of their error (it accumulates along the walk), so a run is a few
independent samples at most, and three seeds judge the sigmas' honesty to about +-30 %. This
script gathers the runs of every JSON given (e.g. seeds 1-3 in one file, 4-9 in another), and
prints a Markdown table per cell: the runs, how many failed, the worst and median station RMS
after a rigid fit, the worst max, how many runs miss 2 mm RMS / 6 mm max, the pooled
error/sigma per axis (relative to the datum, see ``accuracy_matrix.py``) with a 90 % bootstrap
interval over the runs, and the worst cloud ratio.

With ``--across-scenes`` a cell is a drift model and class, pooled over the scenes.

Usage: python benchmarks/pool_accuracy.py A.json [B.json ...] [--across-scenes] [--out pooled.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy_matrix import pooled_interval

RMS_TARGET_MM, MAX_TARGET_MM = 2.0, 6.0


def cells(paths: list[Path], across_scenes: bool = False) -> dict[str, dict]:
    """Runs per cell, keyed ``scenario/model/class`` (``model/class`` across scenes); a run given
    twice (same scene, cell and seed) counts once."""
    fields = ("drift_model", "magnitude") if across_scenes else ("scenario", "drift_model", "magnitude")
    out: dict[str, dict] = {}
    for path in paths:
        for r in json.loads(path.read_text())["results"]:
            key = "/".join(str(r.get(k)) for k in fields)
            cell = out.setdefault(key, {"runs": {}, "failed": {}})
            run = (r.get("scenario"), r.get("seed"))
            if "position_error_after_rigid_fit_mm" in r:
                cell["runs"][run] = r
            else:
                cell["failed"][run] = r.get("error", "failed")
    return out


def summary(cell: dict) -> dict:
    runs = [cell["runs"][s] for s in sorted(cell["runs"], key=str)]
    rms = np.array([r["position_error_after_rigid_fit_mm"]["rms"] for r in runs])
    mx = np.array([r["position_error_after_rigid_fit_mm"]["max"] for r in runs])
    ms = [r["normalised_error_ms_per_axis"] for r in runs]
    return {
        "seeds": sorted(cell["runs"], key=str),
        "failed_seeds": sorted(cell["failed"], key=str),
        "rms_mm_worst": float(rms.max()), "rms_mm_median": float(np.median(rms)), "max_mm_worst": float(mx.max()),
        "runs_over_rms_target": int(np.sum(rms > RMS_TARGET_MM)),
        "runs_over_max_target": int(np.sum(mx > MAX_TARGET_MM)),
        "error_over_sigma_pooled": np.sqrt(np.mean(ms, axis=0)).tolist(),
        "error_over_sigma_90": pooled_interval(ms),
        "cloud_worst": max(r["cloud_point_to_plane_rms_mm"]["corrected_over_truth"] for r in runs),
        # plane thickness (rigid motion of the whole cloud left out); runs from before it: none
        "thickness_worst": max((r["cloud_plane_thickness_mm"]["corrected_over_truth"] for r in runs
                                if "cloud_plane_thickness_mm" in r), default=float("nan")),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("inputs", nargs="+", type=Path)
    parser.add_argument("--across-scenes", action="store_true", help="pool each drift model over the scenes")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    table = {key: summary(cell) for key, cell in sorted(cells(args.inputs, args.across_scenes).items()) if cell["runs"]}
    print("| cell | runs (failed) | station RMS worst / median, max worst [mm] | runs > 2 mm RMS / > 6 mm max "
          "| error/sigma x / y / z pooled | 90 % interval x / y / z | cloud worst | thickness worst |")
    print("|---|---|---|---|---|---|---|---|")
    for key, s in table.items():
        es = " / ".join(f"{v:.2f}" for v in s["error_over_sigma_pooled"])
        ci = " / ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in s["error_over_sigma_90"])
        print(f"| {key} | {len(s['seeds'])} ({len(s['failed_seeds'])}) | {s['rms_mm_worst']:.2f} / "
              f"{s['rms_mm_median']:.2f}, {s['max_mm_worst']:.2f} | {s['runs_over_rms_target']} / "
              f"{s['runs_over_max_target']} | {es} | {ci} | {s['cloud_worst']:.3f} | {s['thickness_worst']:.3f} |")
    if args.out is not None:
        args.out.write_text(json.dumps(table, indent=1) + "\n")


if __name__ == "__main__":
    main()
