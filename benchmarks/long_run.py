"""Accuracy and block-stage cost on a long run that revisits the same building many times.

The accuracy matrix (accuracy_matrix.py) runs 90-180 s walks with about 10 links a station. A
surveyor's 30-minute run (the seed's 26:33 min, 655 m) passes every place 20-30 times: with
``[matching] radius_m`` loop closures every station has about a hundred candidate pairs. This
script simulates the seed-scale run of ``scale.py`` at a tenth of its point rate (the same
1,595 s, 266 windows, 23.5 M points: the planes and pairs are those of the 235 M run, thinner),
writes its true trajectory beside it, runs ``kinreg process`` once per configuration and compares
the stations with the truth (``accuracy_matrix.station_errors``).

Usage: python benchmarks/long_run.py --data /work/long23 --config default=  capped=x.toml
           [--out benchmarks/results/long_run.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))


def simulation(rate_divisor: float, drift_model: str | None, seed: int = 1,
               drift_at_end: tuple[float, float] | None = None):
    """The run's simulation; ``drift_at_end``: the position [m] and attitude [deg] errors it reaches
    at its end (else the seed-like run's)."""
    import scale

    cfg = scale.seed_like_config(235e6, seed)
    cfg = replace(cfg, sensor=replace(cfg.sensor, pulse_rate_hz=cfg.sensor.pulse_rate_hz / rate_divisor))
    if drift_model is not None:
        from kinreg.simulation.drift import DriftModel

        cfg = replace(cfg, drift=replace(cfg.drift, model=DriftModel(drift_model)))
    if drift_at_end is not None:
        cfg = replace(cfg, drift=replace(cfg.drift, drift_pos_m_at_300s=drift_at_end[0],
                                         drift_rot_deg_at_300s=drift_at_end[1], at_s=cfg.duration_s))
    return cfg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the run (generated when empty)")
    parser.add_argument("--rate-divisor", type=float, default=10.0)
    parser.add_argument("--drift-model", default=None, help="world, slam or gnss-ins (default: the simulator's)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--drift-at-end", type=float, nargs=2, default=None, metavar=("POS_M", "ROT_DEG"),
                        help="position and attitude errors reached at the run's end (default: the seed-like run's)")
    parser.add_argument("--config", nargs="+", default=["default="],
                        help="label=path of a kinreg config TOML (empty path: the defaults)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "long_run.json")
    args = parser.parse_args()

    import scale
    from accuracy_matrix import station_errors

    from kinreg.config import load_config
    from kinreg.io.trajectory import read_trajectory
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_trajectory_geoslam
    from kinreg.simulation.run import simulate_run

    data = args.data
    data.mkdir(parents=True, exist_ok=True)
    cfg = simulation(args.rate_divisor, args.drift_model, args.seed, args.drift_at_end)
    traj, cloud = data / "run_trajectory.txt", data / "run_cloud.laz"
    generated = None
    if not cloud.exists():
        traj, cloud, generated = scale.generate(data, 0, 2, config=cfg)
    if not (data / "truth_trajectory.txt").exists():
        write_trajectory_geoslam(data / "truth_trajectory.txt", simulate_run(cfg).truth)
    truth, drifted = read_trajectory(data / "truth_trajectory.txt"), read_trajectory(traj)
    results = []
    for item in args.config:
        label, _, path = item.partition("=")
        t0 = time.perf_counter()
        summary = process(ProcessInputs(traj, cloud), data / f"out_{label}", load_config(Path(path) if path else None),
                          overwrite=True)
        wall = time.perf_counter() - t0
        row = {"label": label, "config": path or "defaults", "links": summary.n_links, "sigma0": summary.sigma0,
               "global_test_passed": summary.global_test_passed, "process_wall_s": wall,
               "timings_s": summary.timings_s,
               **station_errors(data / f"out_{label}" / "stations.csv", truth, drifted)}
        row.pop("rigid_fit")  # the fit itself (arrays), not a figure
        results.append(row)
        print(json.dumps({k: row[k] for k in ("label", "links", "sigma0", "timings_s",
                                                "position_error_after_rigid_fit_mm", "normalised_error_rms_per_axis")}),
              flush=True)
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "command": " ".join(sys.argv),
                                    "generated": generated, "drift_model": cfg.drift.model.value, "seed": cfg.seed,
                                    "duration_s": cfg.duration_s, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
