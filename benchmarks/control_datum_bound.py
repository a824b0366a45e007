"""What control points alone can give: the datum's own limit on the station positions (issue 15).

For the walks of ``eval_control.py`` (the same seeds, stand-stills and control subsets), the
network is taken as perfect: the stations move rigidly with the transform that the control points
fix (small shift and turn about their centroid, least squares, ``sigma_mm`` per axis), and nothing
else errs. Per station, ``C_k = A_k (sum_i A_i^T A_i / sigma^2)^-1 A_k^T`` with
``A_x = [I, -[x - c]x]``: no estimator of the stations from these control points does better on
average. Station positions: the true walk at the centres of 6 s windows (the default slicing).

Printed per subset size: the RMS 3D of these sigmas per seed and pooled (as ``eval_control.py``
pools: the root mean square of the seeds' RMS), and a Monte-Carlo over the survey noise alone
(``--draws`` draws of the control points' errors, all seeds at once): the pooled station RMS and
the pooled error/sigma per axis (5 / 50 / 95 %) that a perfect network would show, and how often
the pooled RMS stays <= 3 mm.

Usage: python benchmarks/control_datum_bound.py [--seeds 1 2 3 4 5 6] [--sigma-mm 3] [--draws 4000]
    [--out benchmarks/control_datum_bound.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def design(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(n, 3, 6): a point's shift under a small shift and turn (about ``centre``) of the network."""
    return np.array([np.hstack([np.eye(3), -skew(x - centre)]) for x in points])


def geometry(seed: int, window_s: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """The true station positions (k, 3) and stand-still points (8, 3) of ``eval_control``'s run."""
    from eval_accuracy import scenario_config
    from eval_control import N_STAND_STILLS

    from kinreg.simulation.run import simulate_run

    cfg = scenario_config("sample", seed=seed)
    cfg = dataclasses.replace(cfg, walk=dataclasses.replace(cfg.walk, stand_stills=N_STAND_STILLS))
    run = simulate_run(cfg)
    t = run.truth.stamps_s
    centres = np.arange(t[0] + 0.5 * window_s, t[-1] - 0.5 * window_s + 1e-9, window_s)
    _, control = run.control_points(noise=False)
    return run.truth.pose_at(centres).t_xyz, control


def main() -> None:
    from eval_control import spread_subset

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    parser.add_argument("--sigma-mm", type=float, default=3.0)
    parser.add_argument("--draws", type=int, default=4000)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "control_datum_bound.json")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    sigma = args.sigma_mm
    worlds = {seed: geometry(seed) for seed in args.seeds}
    out: dict = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv), "sigma_mm": sigma}
    for n in (3, 4, 6):
        per_seed, errors, sigmas = [], [], []
        for stations, control in worlds.values():
            points = control[spread_subset(control[:, :2], n)]
            centre = points.mean(axis=0)
            A_c, A_s = design(points, centre), design(stations, centre)
            Q = np.linalg.inv(np.einsum("nji,njk->ik", A_c, A_c) / sigma**2)
            C = A_s @ Q @ np.transpose(A_s, (0, 2, 1))  # (k, 3, 3) [mm^2]
            s = np.sqrt(np.diagonal(C, axis1=1, axis2=2))
            per_seed.append(float(np.sqrt(np.mean(np.sum(s**2, axis=1)))))
            # the least-squares shift and turn from the survey errors e: x = Q A^T e / sigma^2
            e = rng.normal(0.0, sigma, (args.draws, n, 3))
            x = np.einsum("ij,njk,dnk->di", Q, np.transpose(A_c, (0, 2, 1)), e) / sigma**2
            errors.append(np.einsum("kij,dj->dki", A_s, x))  # (draws, k, 3) station errors [mm]
            sigmas.append(s)
        rms = np.sqrt(np.mean([np.mean(np.sum(err**2, axis=2), axis=1) for err in errors], axis=0))  # (draws,)
        z = np.concatenate([err / s for err, s in zip(errors, sigmas, strict=True)], axis=1)
        z_pooled = np.sqrt(np.mean(z**2, axis=1))  # (draws, 3)
        pct = (5, 50, 95)
        out[f"n{n}"] = {
            "bound_rms3d_mm_per_seed": per_seed,
            "bound_rms3d_mm_pooled": float(np.sqrt(np.mean(np.square(per_seed)))),
            "pooled_station_rms_mm_percentiles_5_50_95": np.percentile(rms, pct).tolist(),
            "share_of_draws_pooled_rms_le_3mm": float(np.mean(rms <= 3.0)),
            "pooled_error_over_sigma_xyz_percentiles_5_50_95": np.percentile(z_pooled, pct, axis=0).T.tolist(),
        }
        print(f"n{n}: bound RMS 3D per seed {np.round(per_seed, 2).tolist()} pooled "
              f"{out[f'n{n}']['bound_rms3d_mm_pooled']:.2f} mm; Monte-Carlo pooled RMS 5/50/95% "
              f"{np.round(np.percentile(rms, pct), 2).tolist()} mm, <= 3 mm in {100 * np.mean(rms <= 3.0):.0f}% of "
              f"draws; pooled error/sigma x/y/z 5-95%: "
              + " / ".join(f"{a:.2f}-{b:.2f}" for a, _, b in np.percentile(z_pooled, pct, axis=0).T), flush=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
