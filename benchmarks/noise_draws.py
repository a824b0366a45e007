"""Station errors over draws of the point noise alone: the same walk, the same drift, the same
building, ``--draws`` realisations of the sensor's noise (the simulator's per-block streams drawn
again). A matrix seed draws walk, drift and noise at once, and the error relative to the datum
is dominated by a few degrees of freedom of the network (its tilt and turn about the datum
station), so a run is only a few samples of the sigmas' honesty. Here each station is seen
``--draws`` times: the mean of its errors over the draws is what the run's drift and the method
leave in it (a bias no noise draw takes away: a model error where it exceeds the sigma), their
spread is what the noise makes of it, and both are compared with the reported sigmas.

Usage: python benchmarks/noise_draws.py --scenario heldout --drift-model gnss-ins
           --magnitude medium --seed 5 --draws 8 [--config F] [--out benchmarks/results/noise_draws.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))


def one_draw(scenario: str, drift_model: str, magnitude: str, seed: int, draw: int, config: Path | None) -> dict:
    """The stations' errors relative to the datum [mm] and their sigmas [mm] for noise draw ``draw``."""
    from accuracy_matrix import errors_relative_to_datum, read_stations, scenario_config

    import kinreg.simulation.run as simulation
    from kinreg.config import load_config
    from kinreg.io.trajectory import read_trajectory
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run

    streams = simulation._rng

    def redrawn(s: int, stream: int) -> np.random.Generator:  # the point noise's streams are 1000 + block
        return np.random.default_rng([s, stream, 777 + draw]) if stream >= 1000 else streams(s, stream)

    simulation._rng = redrawn
    try:
        with tempfile.TemporaryDirectory() as tmp:
            data, out = Path(tmp) / "data", Path(tmp) / "out"
            write_run(simulation.simulate_run(scenario_config(scenario, seed, drift_model, magnitude)), data)
            process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz"), out, load_config(config),
                    overwrite=True)
            st = read_stations(out / "stations.csv")
            error = errors_relative_to_datum(st, read_trajectory(data / "truth_trajectory.txt"),
                                             read_trajectory(data / "run_trajectory.txt"))
    finally:
        simulation._rng = streams
    sigma = np.column_stack([st["sx_mm"], st["sy_mm"], st["sz_mm"]])
    return {"draw": draw, "t": st["t"].tolist(), "error_mm": error.tolist(), "sigma_mm": sigma.tolist()}


def summary(draws: list[dict]) -> dict:
    """Per axis, over the stations every draw has (free ones): the pooled error/sigma RMS, and the
    RMS over the stations of the spread over the draws, of the mean over the draws (the bias) and
    of the sigma, in mm and over the sigma."""
    times = [np.round(d["t"], 3) for d in draws]
    common = sorted(set(times[0]).intersection(*map(set, times[1:])))
    rows = [[list(t).index(c) for c in common] for t in times]
    error = np.array([np.asarray(d["error_mm"])[r] for d, r in zip(draws, rows, strict=True)])
    sigma = np.array([np.asarray(d["sigma_mm"])[r] for d, r in zip(draws, rows, strict=True)])
    free = sigma[0].max(axis=1) > 0
    error, sigma = error[:, free], sigma[:, free]
    spread, bias, s = error.std(axis=0, ddof=1), error.mean(axis=0), sigma.mean(axis=0)

    def rms(a: np.ndarray) -> list[float]:
        return np.sqrt(np.mean(a**2, axis=0)).round(3).tolist()

    return {"draws": len(draws), "stations": int(free.sum()),
            "error_over_sigma_rms": np.sqrt(np.mean((error / sigma) ** 2, axis=(0, 1))).round(3).tolist(),
            "spread_over_sigma_rms": rms(spread / s), "bias_over_sigma_rms": rms(bias / s),
            "sigma_rms_mm": rms(s), "spread_rms_mm": rms(spread), "bias_rms_mm": rms(bias)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="heldout")
    parser.add_argument("--drift-model", default="gnss-ins")
    parser.add_argument("--magnitude", default="medium")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--config", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "noise_draws.json")
    args = parser.parse_args()
    draws = []
    for k in range(args.draws):
        draws.append(one_draw(args.scenario, args.drift_model, args.magnitude, args.seed, k, args.config))
        print(f"draw {k}: {len(draws[-1]['t'])} stations", flush=True)
    result = summary(draws)
    print(json.dumps(result), flush=True)
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "command": " ".join(sys.argv),
                                    "summary": result, "draws": draws}) + "\n")


if __name__ == "__main__":
    main()
