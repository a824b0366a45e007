"""Absolute accuracy with a static-scan datum and with a virtual reference station (issue 5).

Per scenario (``sample``: the committed run; ``heldout``: another building, sensor and drift,
see accuracy_matrix.py), ``kinreg process`` runs with:

- ``static``: the simulated static scans (E57 with poses) held fixed;
- ``reference``: the simulator's reference planes (two outer walls and the ceiling, 5 cm
  construction accuracy);
- ``reference_wrong``: the same with the south wall's offset deliberately wrong by 5 cm, plus
  the north wall as a second y reference so that the error has something to show against.

Reported: absolute station position errors against the truth (no fit), reported sigmas and
normalised errors, the as-built table, and for the wrong plane the distortion of the network's
inner geometry (after a rigid fit onto the correct-reference result) against its sigmas.

Usage: python benchmarks/datum_modes.py [--scenario sample heldout] [--out benchmarks/results/datum_modes.json]
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))


def stations(out: Path) -> dict[str, np.ndarray]:
    with open(out / "stations.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["t"]]
    return {"t": np.array([float(r["t"]) for r in rows]),
            "xyz": np.array([[float(r[k]) for k in "xyz"] for r in rows]),
            "sigma": np.array([[float(r[k]) for k in ("sx_mm", "sy_mm", "sz_mm")] for r in rows])}


def absolute(out: Path, truth) -> dict:
    st = stations(out)
    e = (st["xyz"] - truth.pose_at(st["t"]).t_xyz) * 1000.0
    z = e / st["sigma"]
    report = json.loads((out / "report.json").read_text())
    return {"position_error_mm": {"rms": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
                                  "max": float(np.linalg.norm(e, axis=1).max()),
                                  "rms_per_axis": np.sqrt(np.mean(e**2, axis=0)).tolist()},
            "reported_sigma_mm_rms_per_axis": np.sqrt(np.mean(st["sigma"] ** 2, axis=0)).tolist(),
            "normalised_error_rms": float(np.sqrt(np.mean(z**2))),
            "sigma0": report["adjustment"]["sigma0"], "datum": report["adjustment"]["datum"],
            "as_built": report.get("reference", {}).get("planes")}


def wrong_reference(data: Path, folder: Path) -> Path:
    """The reference file with the south wall 5 cm off and the north wall added."""
    from kinreg.io.reference_planes import read_reference_planes

    ref = read_reference_planes(data / "reference.toml")
    meta = json.loads((data / "run_meta.json").read_text())
    size_y = meta["config"]["building"]["size_m"][1]
    origin = meta["config"].get("origin_xyz", [0, 0, 0])
    lines = [f"plane_construction_accuracy_m = {ref.accuracy_m}"]
    for p in ref.planes:
        d = p.d_m + (0.05 if p.name == "south_wall" else 0.0)
        lines += ["[[plane]]", f'name = "{p.name}"', f"normal = [{p.normal[0]}, {p.normal[1]}, {p.normal[2]}]",
                  f"d_m = {d}"]
    lines += ["[[plane]]", 'name = "north_wall"', "normal = [0.0, -1.0, 0.0]", f"d_m = {-(size_y + origin[1])}"]
    path = folder / "reference_wrong.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def evaluate(name: str, work: Path, seed: int | None = None, drift_model: str | None = None,
             magnitude: str | None = None) -> dict:
    from accuracy_matrix import scenario_config

    from kinreg.config import KinregConfig
    from kinreg.io.trajectory import read_trajectory
    from kinreg.report.json import rigid_fit
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import simulate_run

    committed = name == "sample" and seed is None and drift_model is None and magnitude is None
    data = REPO / "sample_data" if committed else work / "data"
    if not committed:
        write_run(simulate_run(scenario_config(name, seed, drift_model, magnitude)), data)
    truth = read_trajectory(data / "truth_trajectory.txt")
    traj, cloud = data / "run_trajectory.txt", data / "run_cloud.laz"
    runs = {
        "static": ProcessInputs(traj, cloud, static=data / "static.e57"),
        "reference": ProcessInputs(traj, cloud, reference=data / "reference.toml"),
        "reference_wrong": ProcessInputs(traj, cloud, reference=wrong_reference(data, work)),
    }
    result = {"scenario": name, "seed": seed, "drift_model": drift_model, "magnitude": magnitude}
    for label, inputs in runs.items():
        t0 = time.perf_counter()
        process(inputs, work / label, KinregConfig(), overwrite=True)
        result[label] = absolute(work / label, truth) | {"wall_s": time.perf_counter() - t0}
    right, wrong = stations(work / "reference"), stations(work / "reference_wrong")
    R, t = rigid_fit(wrong["xyz"], right["xyz"])
    distortion = np.linalg.norm(wrong["xyz"] @ R.T + t - right["xyz"], axis=1) * 1000.0
    result["reference_wrong"]["inner_distortion_mm"] = {"rms": float(np.sqrt(np.mean(distortion**2))),
                                                        "max": float(distortion.max())}
    result["reference_wrong"]["shift_mm"] = (np.mean(wrong["xyz"] - right["xyz"], axis=0) * 1000).tolist()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", nargs="+", default=["sample", "heldout"])
    parser.add_argument("--seeds", nargs="*", type=int, default=[None], help="run seeds (default: the scenario's)")
    parser.add_argument("--drift-models", nargs="*", default=[None], help="world, slam, gnss-ins")
    parser.add_argument("--magnitudes", nargs="*", default=[None], help="drift classes of accuracy_matrix.py")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "datum_modes.json")
    args = parser.parse_args()
    results = []
    for name, model, magnitude, seed in itertools.product(args.scenario, args.drift_models, args.magnitudes,
                                                          args.seeds):
        with tempfile.TemporaryDirectory(prefix=f"kinreg-datum-{name}-") as tmp:
            try:
                res = evaluate(name, Path(tmp), seed, model, magnitude)
            except Exception as error:  # a failed run is a row of the table, not the end of the matrix
                res = {"scenario": name, "seed": seed, "drift_model": model, "magnitude": magnitude,
                       "error": f"{type(error).__name__}: {error}"}
        print(json.dumps(res), flush=True)
        results.append(res)
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
                                    "results": results}, indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
