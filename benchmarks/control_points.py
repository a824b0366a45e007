"""Absolute accuracy with control points as the only datum, check points, a wrong point (issue 15).

Per seed, the committed sample's scene, sensor and drift (``accuracy_matrix.scenario_config``) with a
walk that stands still on 8 points (4 s each, spread over the run); the simulator writes the
surveyed coordinates of the platform origin there (truth + 3 mm per axis, ``control.csv``) and the
true ones (``control_truth.csv``). ``kinreg process`` then runs with

- ``n3``, ``n4``, ``n6``: 3, 4 or 6 of the points as control points (the subset a surveyor would
  take: the one spreading widest, by the smallest singular value of the centred horizontal
  coordinates), the others as check points (``--check`` with their true coordinates, so that the
  check differences are the corrected trajectory's own error);
- ``wrong``: the ``n4`` set with one point moved by +5 cm in x: is it rejected and named?

No static scans, no reference planes: the control points are the datum. Reported per run: the
absolute station position errors against the truth (no fit), the error/sigma per axis (pooled over
seeds in the summary), the check differences (RMS, max) of the corrected and the input trajectory.

Usage: python benchmarks/control_points.py [--seeds 1 2 3 4 5 6] [--out benchmarks/results/control_points.json]

``--scenario static-targets``: targets in static scans as the only datum. The same walk (8
stand-stills, all of them check points with their true coordinates), the scenario's three static
scans written with poses 2 cm and 0.1 deg off (a registration error: the targets, not the E57
poses, must hold the network), and four targets per scan on the walls and ceiling around it
(survey 3 mm, the scan's own measurement 2 mm per axis = ``[control] target_sigma_mm``):

- ``t3x4``: the 12 targets of all three scans;
- ``t1x4``: the 4 targets of the second scan only, the one in a room (the E57 file then holds that
  scan alone; the first scan, in the corridor, sees no plane across the corridor, so alone it
  leaves the translation along it to nothing: build_network warns);
- ``wrong``: ``t3x4`` with one target moved by +5 cm in x: is it rejected and named?

Reported as above, plus the static stations' position errors and error/sigma, and the check
points (stand-stills) before and after. ``--summarise A.json B.json ...`` pools the results of
earlier runs (e.g. seeds run in parallel) and prints the summary.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

N_STAND_STILLS = 8


def spread_subset(xy: np.ndarray, n: int) -> list[int]:
    """The n points (indices) spreading widest: the largest smallest singular value of their
    centred horizontal coordinates (ties broken by the larger largest one)."""
    best, key = None, (-1.0, -1.0)
    for subset in itertools.combinations(range(len(xy)), n):
        s = np.linalg.svd(xy[list(subset)] - xy[list(subset)].mean(axis=0), compute_uv=False)
        if (s[-1], s[0]) > key:
            best, key = list(subset), (float(s[-1]), float(s[0]))
    return best


def station_errors(out: Path, truth) -> dict:
    with open(out / "stations.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["t"]]
    t = np.array([float(r["t"]) for r in rows])
    xyz = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    sigma = np.array([[float(r[k]) for k in ("sx_mm", "sy_mm", "sz_mm")] for r in rows])
    e = (xyz - truth.pose_at(t).t_xyz) * 1000.0
    return {"rms_mm": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), "max_mm": float(np.linalg.norm(e, axis=1).max()),
            "rms_per_axis_mm": np.sqrt(np.mean(e**2, axis=0)).tolist(),
            "sigma_rms_per_axis_mm": np.sqrt(np.mean(sigma**2, axis=0)).tolist(),
            "z": (e / sigma).tolist()}


def _simulated(seed: int, work: Path):
    """The sample scenario's run of ``seed`` with its stand-stills, written to ``work/data``:
    the run, the data folder and the true trajectory."""
    from accuracy_matrix import scenario_config

    from kinreg.io.trajectory import read_trajectory
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import simulate_run

    cfg = scenario_config("sample", seed=seed)
    cfg = dataclasses.replace(cfg, walk=dataclasses.replace(cfg.walk, stand_stills=N_STAND_STILLS))
    run = simulate_run(cfg)
    data = work / "data"
    write_run(run, data)
    return run, data, read_trajectory(data / "truth_trajectory.txt")


def _figures(report: dict, out: Path, truth, moved, row_keys: tuple[str, ...], t0: float) -> dict:
    """What a case's ``report.json`` and ``stations.csv`` say (its ``moved`` point, the datum,
    station errors, rejected points, control rows with ``row_keys``, check points, LOA)."""
    return {
        "moved": moved, "datum": report["adjustment"]["datum"],
        "stations": station_errors(out, truth),
        "rejected_points": report["control"]["rejected"],
        "control_rows": [{k: r[k] for k in row_keys} for r in report["control"]["rows"]],
        "check_mm": {"corrected": report["check"]["summary"]["d3d_mm"],
                     "input": report["check"]["summary_input"]["d3d_mm"],
                     "corrected_horizontal": report["check"]["summary"]["horizontal_mm"],
                     "corrected_vertical": report["check"]["summary"]["vertical_mm"]},
        "loa": report["check"]["loa"]["class"],
        "wall_s": time.perf_counter() - t0,
    }


def evaluate(seed: int, work: Path) -> dict:
    from kinreg.config import KinregConfig
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import control_csv

    run, data, truth = _simulated(seed, work)
    _, true_xyz = run.control_points(noise=False)
    names = [f"CP{k + 1:02d}" for k in range(N_STAND_STILLS)]
    result: dict = {"seed": seed}
    cases = {f"n{n}": spread_subset(true_xyz[:, :2], n) for n in (3, 4, 6)}
    cases["wrong"] = cases["n4"]
    for label, subset in cases.items():
        control_names = [names[k] for k in subset]
        check_names = [n for n in names if n not in control_names]
        moved = {control_names[0]: (0.05, 0.0, 0.0)} if label == "wrong" else None
        control = work / f"control_{label}.csv"
        control.write_text(control_csv(run, names=control_names, moved=moved))
        check = work / f"check_{label}.csv"
        check.write_text(control_csv(run, noise=False, names=check_names))
        t0 = time.perf_counter()
        out = work / label
        process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz", control=control, check=check),
                out, KinregConfig(), overwrite=True)
        report = json.loads((out / "report.json").read_text())
        result[label] = {"control": control_names,
                         **_figures(report, out, truth, moved, ("name", "d3d_mm", "normalised", "decision"), t0)}
        s = result[label]["stations"]
        print(f"seed {seed} {label}: stations RMS {s['rms_mm']:.2f} max {s['max_mm']:.2f} mm, "
              f"check RMS {result[label]['check_mm']['corrected']['rms']:.2f} mm "
              f"(input {result[label]['check_mm']['input']['rms']:.2f}), rejected {result[label]['rejected_points']}",
              flush=True)
    return result


def static_errors(out: Path, scans) -> dict:
    """The static stations' adjusted positions against their true poses (``scans``, file order)."""
    with open(out / "stations.csv") as f:
        rows = [r for r in csv.DictReader(f) if not r["t"]]
    truth = {s.name: s.T_obj_scan.t_xyz for s in scans}
    e = np.array([[float(r[k]) for k in "xyz"] for r in rows]) - np.array([truth[r["station"]] for r in rows])
    sigma = np.array([[float(r[k]) for k in ("sx_mm", "sy_mm", "sz_mm")] for r in rows])
    e = e * 1000.0
    return {"names": [r["station"] for r in rows], "error_mm": e.tolist(), "sigma_mm": sigma.tolist(),
            "rms_mm": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), "z": (e / sigma).tolist()}


TARGET_CASES = ("t3x4", "t1x4", "wrong")


def evaluate_targets(seed: int, work: Path) -> dict:
    from kinreg.config import KinregConfig
    from kinreg.errors import KinregError
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import control_csv, static_targets_csv, write_static_e57

    run, data, truth = _simulated(seed, work)
    misregistered = run.static_scans_misregistered(0.02, 0.1)
    write_static_e57(work / "static_all.e57", misregistered)
    write_static_e57(work / "static_room.e57", misregistered[1:2])
    check = work / "check.csv"
    check.write_text(control_csv(run, noise=False))  # every stand-still: the corrected trajectory's own error
    targets = [t.name for t in run.static_targets()]
    result: dict = {"seed": seed, "targets": targets}
    for label in TARGET_CASES:
        moved = {targets[5]: (0.05, 0.0, 0.0)} if label == "wrong" else None
        control = work / f"targets_{label}.csv"
        control.write_text(static_targets_csv(run, moved=moved, scans=[1] if label == "t1x4" else None))
        static = work / ("static_room.e57" if label == "t1x4" else "static_all.e57")
        t0 = time.perf_counter()
        out = work / label
        try:
            process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz", static=static, control=control,
                                  check=check), out, KinregConfig(), overwrite=True)
        except KinregError as e:  # a failed case is a result too
            result[label] = {"failed": str(e), "wall_s": time.perf_counter() - t0}
            print(f"seed {seed} {label}: failed: {e}", flush=True)
            continue
        report = json.loads((out / "report.json").read_text())
        result[label] = {"static": static_errors(out, run.static_scans),
                         **_figures(report, out, truth, moved,
                                    ("name", "scan", "d3d_mm", "normalised", "decision", "input_d3d_mm"), t0)}
        s, st = result[label]["stations"], result[label]["static"]
        print(f"seed {seed} {label}: stations RMS {s['rms_mm']:.2f} max {s['max_mm']:.2f} mm, static RMS "
              f"{st['rms_mm']:.2f} mm, check RMS {result[label]['check_mm']['corrected']['rms']:.2f} mm "
              f"(input {result[label]['check_mm']['input']['rms']:.2f}), rejected {result[label]['rejected_points']}",
              flush=True)
    return result


def summary(results: list[dict]) -> dict:
    out = {}
    labels = TARGET_CASES if results and "t3x4" in results[0] else ("n3", "n4", "n6", "wrong")
    for label in labels:
        runs = [r[label] for r in results if "failed" not in r[label]]
        failed = [f"seed {r['seed']}: {r[label]['failed']}" for r in results if "failed" in r[label]]
        if not runs:
            out[label] = {"failed": failed}
            continue
        z = np.concatenate([np.array(r["stations"]["z"]) for r in runs])
        check = np.array([r["check_mm"]["corrected"]["rms"] for r in runs])
        out[label] = {
            "station_rms_mm": [r["stations"]["rms_mm"] for r in runs],
            "station_rms_mm_pooled": float(np.sqrt(np.mean([r["stations"]["rms_mm"] ** 2 for r in runs]))),
            "station_max_mm": float(max(r["stations"]["max_mm"] for r in runs)),
            "error_over_sigma_pooled_xyz": np.sqrt(np.mean(z**2, axis=0)).tolist(),
            "check_rms_mm": check.tolist(), "check_rms_mm_pooled": float(np.sqrt(np.mean(check**2))),
            "check_input_rms_mm_pooled": float(np.sqrt(np.mean([r["check_mm"]["input"]["rms"] ** 2 for r in runs]))),
            "rejected": [r["rejected_points"] for r in runs],
            "moved": [list((r["moved"] or {}).keys()) for r in runs],
            "loa": [r["loa"] for r in runs],
        }
        if failed:
            out[label]["failed"] = failed
        if "static" in runs[0]:
            zs = np.concatenate([np.array(r["static"]["z"]) for r in runs])
            out[label].update({
                "static_rms_mm_pooled": float(np.sqrt(np.mean([r["static"]["rms_mm"] ** 2 for r in runs]))),
                "static_error_over_sigma_pooled_xyz": np.sqrt(np.mean(zs**2, axis=0)).tolist()})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "control_points.json")
    parser.add_argument("--scenario", choices=("stand-stills", "static-targets"), default="stand-stills")
    parser.add_argument("--summarise", type=Path, nargs="+", help="pool the results of these files, run nothing")
    args = parser.parse_args()
    if args.summarise:
        pooled = [r for path in args.summarise for r in json.loads(path.read_text())["results"]]
        print(json.dumps(summary(pooled), indent=1))
        return
    results = []
    for seed in args.seeds:
        with tempfile.TemporaryDirectory(prefix=f"kinreg-control-{seed}-") as tmp:
            evaluate_seed = evaluate_targets if args.scenario == "static-targets" else evaluate
            results.append(evaluate_seed(seed, Path(tmp)))
        write(args.out, results)  # after every seed: a long run stopped early keeps what it has
    print(json.dumps(summary(results), indent=1))
    print(f"written {args.out}")


def write(path: Path, results: list[dict]) -> None:
    # The static-target results keep the stations' error/sigma ("z"): --summarise pools them.
    plain = [r if "t3x4" in r else
             {k: ({**v, "stations": {s: x for s, x in v["stations"].items() if s != "z"}} if isinstance(v, dict)
                  else v) for k, v in r.items()} for r in results]
    path.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
                                "seeds_done": [r["seed"] for r in results], "summary": summary(results),
                                "results": plain}, indent=1) + "\n")


if __name__ == "__main__":
    main()
