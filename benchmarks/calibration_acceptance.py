"""Which calibrations the acceptance refuses: clean and cluttered runs, and wrong ones.

Run: ``.venv/bin/python benchmarks/calibration_acceptance.py [--clean 40] [--room 20] [--alpha 0.001]
[--out benchmarks/results/calibration_acceptance.json]``

1. ``--clean`` plate-only runs of the seed's field (default :class:`SimulationConfig`, tracker
   sigmas of the seed) and ``--room`` runs amid the room's surfaces with each plate's extent
   (:func:`room_scenario`), all through :func:`calibrate_robust` as ``kinreg calibrate`` runs them:
   sigma0, the chi-square test at ``--alpha``, whether the sigmas were scaled by sigma0, the
   acceptance's refusals and their reasons, the error over the (scaled) sigma.
2. Wrong runs that must be refused: starting values 10 cm and 3 deg off with the one-gate
   assignment (infinite planes, a 5 cm gate) that lets the estimate converge on the room's points.
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

from kinreg.calibration import CalibrationConfig, SimulationConfig, SystemCalibration, simulate_calibration
from kinreg.calibration.assignment import (
    AssignmentConfig,
    RobustCalibration,
    calibrate_robust,
    calibration_problems,
    start_misfit,
)
from kinreg.calibration.model import assign_points_to_planes, estimate_calibration
from kinreg.calibration.simulate import room_scenario
from kinreg.errors import KinregError


def _row(kind: str, seed: int, rob: RobustCalibration, truth: SystemCalibration, cfg: CalibrationConfig,
         planes, seconds: float) -> dict:
    res = rob.result
    z = (res.calibration.as_vector() - truth.as_vector()) / res.sigmas
    return {"kind": kind, "seed": seed, "sigma0": res.sigma0, "redundancy": res.redundancy,
            "chi2_passed": res.global_test.passed, "scaled": res.global_test.scaled,
            "problems": calibration_problems(rob, planes, cfg), "max_abs_z": float(np.max(np.abs(z))),
            "z": z.tolist(), "seconds": seconds}


def good_runs(clean: int, room: int, alpha: float) -> list[dict]:
    cfg = CalibrationConfig(alpha=alpha)
    rows = []
    for kind, n in (("clean", clean), ("room", room)):
        for seed in range(n):
            if kind == "clean":
                sim = simulate_calibration(SimulationConfig(), seed=seed)
                start = SystemCalibration(sim.truth.lever_arm_m + np.array([0.02, -0.01, 0.015]),
                                          sim.truth.boresight_rad + np.radians([0.5, -0.3, 0.4]))
            else:
                sim_cfg, start = room_scenario(seed)
                sim = simulate_calibration(sim_cfg, seed=seed)
            t0 = time.perf_counter()
            try:
                rob = calibrate_robust(sim.points_s, sim.stamps_s, sim.trajectory, sim.planes, start, cfg,
                                       AssignmentConfig(alpha=alpha))
            except KinregError as e:
                rows.append({"kind": kind, "seed": seed, "error": str(e)})
                continue
            rows.append(_row(kind, seed, rob, sim.truth, cfg, sim.planes, time.perf_counter() - t0))
            r = rows[-1]
            print(f"{kind} {seed}: sigma0 {r['sigma0']:.3f} (r {r['redundancy']}) chi2 "
                  f"{'passed' if r['chi2_passed'] else 'refused'}{' scaled' if r['scaled'] else ''}, |z|max "
                  f"{r['max_abs_z']:.2f}" + (f", REFUSED: {r['problems']}" if r["problems"] else ""), flush=True)
    return rows


def wrong_runs(n: int, alpha: float) -> list[dict]:
    cfg = CalibrationConfig(alpha=alpha)
    rows = []
    for seed in range(n):
        sim_cfg, start = room_scenario(seed, start_lever_m=0.1, start_angle_deg=3.0)
        sim = simulate_calibration(sim_cfg, seed=seed)
        idx = assign_points_to_planes(sim.points_s, sim.stamps_s, sim.trajectory, sim.planes, start, 0.05)
        try:
            res = estimate_calibration(sim.points_s, sim.stamps_s, idx, sim.trajectory, sim.planes, start, cfg)
        except KinregError as e:
            rows.append({"kind": "wrong start, one gate", "seed": seed, "error": str(e)})
            continue
        misfit, upper = start_misfit(sim.points_s, sim.stamps_s, idx, sim.trajectory, sim.planes, start, cfg)
        rob = RobustCalibration(res, idx, (), misfit, upper, start)
        rows.append(_row("wrong start, one gate", seed, rob, sim.truth, cfg, sim.planes, math.nan))
        r = rows[-1]
        print(f"wrong {seed}: sigma0 {r['sigma0']:.2f} |z|max {r['max_abs_z']:.0f}, refused: {bool(r['problems'])}",
              flush=True)
    return rows


def summary(rows: list[dict]) -> dict:
    out = {}
    for kind in sorted({r["kind"] for r in rows}):
        mine = [r for r in rows if r["kind"] == kind and "error" not in r]
        s0 = np.array([r["sigma0"] for r in mine])
        in_band = (s0 >= 0.9) & (s0 <= 1.1)
        out[kind] = {
            "runs": sum(r["kind"] == kind for r in rows), "without_estimate": sum(r["kind"] == kind and "error" in r
                                                                                  for r in rows),
            "sigma0_min": float(s0.min()), "sigma0_max": float(s0.max()),
            "chi2_refused": int(sum(not r["chi2_passed"] for r in mine)),
            "scaled_by_sigma0": int(sum(r["scaled"] for r in mine)),
            "refused": int(sum(bool(r["problems"]) for r in mine)),
            "refused_with_sigma0_in_band": int(sum(bool(r["problems"]) and b for r, b in zip(mine, in_band,
                                                                                              strict=True))),
            "accepted_with_error_over_5_sigma": int(sum(not r["problems"] and r["max_abs_z"] > 5.0 for r in mine)),
            "share_all_six_within_3_sigma": float(np.mean([r["max_abs_z"] < 3.0 for r in mine])),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clean", type=int, default=40)
    ap.add_argument("--room", type=int, default=20)
    ap.add_argument("--wrong", type=int, default=5)
    ap.add_argument("--alpha", type=float, default=0.001)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "calibration_acceptance.json"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = good_runs(args.clean, args.room, args.alpha) + wrong_runs(args.wrong, args.alpha)
    report = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "alpha": args.alpha,
              "summary": summary(rows), "runs": rows, "seconds_total": time.perf_counter() - t0}
    with open(args.out, "w") as fh:
        json.dump(report, fh, indent=1)
    print(json.dumps(report["summary"], indent=1))
    print("wrote", args.out, f"({report['seconds_total']:.0f} s)")


if __name__ == "__main__":
    main()
