"""Calibration benchmark: Monte-Carlo check of the reported sigmas, Table 3 planning timing.

Run: ``.venv/bin/python benchmarks/calibration.py [--reps 200] [--out benchmarks/results/calibration.json]``

1. 200 seeded simulations (default :class:`SimulationConfig`: Table 2 field at y1 = 3 m,
   z1 = 2.5 m, 45 deg, 0.5 m planes, 40 profiles, 0.2 deg zenith step, moving and turning
   platform, seed-000 sigmas): share of repetitions with all six parameters within 3 reported
   sigmas, per parameter, and empirical RMS error / mean reported sigma. Once with fixed planes,
   once with plane parameters as observations (0.3 mm, 0.3 mrad).
2. Exhaustive planning over the full Table 3 grid (448,875 arrangements, zenith step 0.036 deg),
   best arrangements for f1, f2, f3; the seed's two-step optimisation (Table 5); variants.
3. Cost of one arrangement with full ray casting (no table decomposition), extrapolated.
4. Differential evolution (scipy, integer variables) for f1, f2, f3 with three seeds each.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from kinreg.calibration import (
    CalibrationConfig,
    PlanningConfig,
    SimulationConfig,
    SystemCalibration,
    Table3Grid,
    estimate_calibration,
    evaluate_arrangement,
    exhaustive_search,
    optimise_evolution,
    simulate_calibration,
    table2_arrangement,
)
from kinreg.calibration.model import PARAMETER_NAMES, TrackerSigmas
from kinreg.calibration.planning import (
    FITNESS_NAMES,
    SEED_TABLE6,
    Table2Tables,
    grid_index_of,
    separate_optimisation,
)
from kinreg.errors import EstimationError


def monte_carlo(reps: int, planes_observed: bool) -> dict:
    s = 3e-4 if planes_observed else 0.0
    sim_cfg = SimulationConfig(plane_sigma_d_m=s, plane_sigma_normal_rad=s)
    est_cfg = (CalibrationConfig(plane_sigma_d_m=s, plane_sigma_normal_rad=s) if planes_observed
               else CalibrationConfig())
    err, sig, s0, passed = [], [], [], []
    t0 = time.perf_counter()
    for seed in range(reps):
        sim = simulate_calibration(sim_cfg, seed=seed)
        approx = SystemCalibration(sim.truth.lever_arm_m + np.array([0.02, -0.01, 0.015]),
                                   sim.truth.boresight_rad + np.radians([0.5, -0.3, 0.4]))
        res = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory,
                                   sim.planes, approx, est_cfg)
        err.append(res.calibration.as_vector() - sim.truth.as_vector())
        sig.append(res.sigmas)
        s0.append(res.sigma0)
        passed.append(res.global_test.passed)
    seconds = time.perf_counter() - t0
    err, sig = np.array(err), np.array(sig)
    inside = np.abs(err) < 3 * sig
    ratio = np.sqrt(np.mean(err**2, axis=0)) / np.mean(sig, axis=0)
    return {
        "reps": reps, "planes_observed": planes_observed, "seconds": seconds,
        "n_points_last": len(sim.points_s),
        "coverage_all_six_3sigma": float(np.mean(np.all(inside, axis=1))),
        "coverage_per_parameter_3sigma": dict(zip(PARAMETER_NAMES, inside.mean(0).tolist(), strict=True)),
        "empirical_over_reported_sigma": dict(zip(PARAMETER_NAMES, ratio.tolist(), strict=True)),
        "mean_reported_sigma_mm_mdeg": dict(zip(
            PARAMETER_NAMES, [*(sig.mean(0)[:3] * 1e3), *np.degrees(sig.mean(0)[3:]) * 1e3], strict=True)),
        "mean_bias_over_sigma": dict(zip(PARAMETER_NAMES, (err.mean(0) / sig.mean(0)).tolist(), strict=True)),
        "sigma0_mean": float(np.mean(s0)), "global_test_pass_rate": float(np.mean(passed)),
    }


def planning(cfg: PlanningConfig, label: str, top: int = 3) -> dict:
    grid = Table3Grid()
    t0 = time.perf_counter()
    tables = Table2Tables(grid, cfg)
    t_tables = time.perf_counter() - t0
    res = exhaustive_search(cfg, grid, tables)
    total = time.perf_counter() - t0
    out = {"label": label, "config": {"plane_size_m": cfg.plane_size_m, "tracker": cfg.tracker is not None,
                                      "zenith_step_deg": cfg.zenith_step_deg},
           "n_arrangements": grid.size, "n_singular": res.n_singular, "seconds_tables": t_tables,
           "seconds_total": total, "n_ray_casts": tables.n_ray_casts,
           "best": {f: [res.row(i) for i in res.best(f, top)] for f in FITNESS_NAMES},
           "separate": {f: separate_optimisation(res, f) for f in FITNESS_NAMES}, "seed_arrangements": {}}
    for f, s in SEED_TABLE6.items():
        idx = grid_index_of(grid, s["y1_m"], s["z1_m"], s["alpha1_deg"], s["beta1_deg"], s["gamma1_deg"])
        out["seed_arrangements"][f] = res.row(int(np.ravel_multi_index(idx, grid.shape)))
    return out, res, tables


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "calibration.json"))
    args = ap.parse_args()
    report: dict = {"date": time.strftime("%Y-%m-%d"), "machine": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count()}

    report["monte_carlo"] = [monte_carlo(args.reps, False), monte_carlo(args.reps, True)]
    for mc in report["monte_carlo"]:
        print(json.dumps(mc, indent=1))

    cfg = PlanningConfig()
    main_run, res, tables = planning(cfg, "default: 0.3 m planes, tracker errors")
    report["planning"] = [main_run]
    print(json.dumps({k: main_run[k] for k in ("seconds_tables", "seconds_total", "n_singular")}))
    for f in FITNESS_NAMES:
        print(f, main_run["best"][f][0])
    for label, variant in (("no tracker errors", PlanningConfig(tracker=None)),
                           ("0.2 m planes", PlanningConfig(plane_size_m=0.2)),
                           ("0.5 m planes", PlanningConfig(plane_size_m=0.5)),
                           ("1.0 m planes", PlanningConfig(plane_size_m=1.0)),
                           ("tracker rot 0.0018 deg (0.002 gon)",
                            PlanningConfig(tracker=TrackerSigmas(sigma_rot_rad=math.radians(0.0018))))):
        run, _, _ = planning(variant, label, top=1)
        report["planning"].append(run)
        print(label, {f: run["best"][f][0] for f in FITNESS_NAMES})

    # Full ray casting per arrangement (with occlusion), no table decomposition.
    rng = np.random.default_rng(0)
    grid = Table3Grid()
    sample = np.stack([rng.integers(0, n, 200) for n in grid.shape], axis=-1)
    t0 = time.perf_counter()
    n_ok = 0
    for ix in sample:
        try:
            evaluate_arrangement(table2_arrangement(*grid.values(ix), size_m=cfg.plane_size_m), cfg)
            n_ok += 1
        except EstimationError:
            pass
    per = (time.perf_counter() - t0) / len(sample)
    report["full_ray_casting"] = {"seconds_per_arrangement": per,
                                  "extrapolated_full_grid_hours_one_core": per * grid.size / 3600}
    print(report["full_ray_casting"])

    evo = []
    for f in FITNESS_NAMES:
        for seed in range(3):
            e = optimise_evolution(f, cfg, grid, tables, seed=seed)
            best = res.fitness[res.best(f)[0], FITNESS_NAMES.index(f)]
            evo.append({"fitness": f, "seed": seed, "index": e.index,
                        "values": [e.values[0], e.values[1], *np.degrees(e.values[2:]).round(6).tolist()],
                        "fitness_mm": e.fitness_mm, "exhaustive_best_mm": float(best),
                        "found_optimum": bool(abs(e.fitness_mm - best) < 1e-12),
                        "n_evaluations": e.n_evaluations, "generations": e.n_generations,
                        "seconds": e.seconds})
            print(evo[-1])
    report["evolution"] = evo
    with open(args.out, "w") as fh:
        json.dump(report, fh, indent=1)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
