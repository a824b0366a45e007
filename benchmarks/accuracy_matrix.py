"""Accuracy of ``kinreg process`` against the simulator's ground truth.

For each scenario: simulate a run (or use the committed sample), run the whole pipeline, then
compare with the truth:

- station positions: adjusted vs true (trajectory at the station time), after a rigid fit
  (RMS, max), absolute (``position_error_in_datum_mm``: the datum's own error included) and
  relative to the datum (``position_error_relative_to_datum_mm``): the truth moved rigidly so
  that the datum station's true pose falls on the trajectory pose it is held at;
- honesty: normalised errors (error relative to the datum / reported sigma, per axis): the
  sigmas are relative to the datum, which carries the run's drift at its own time, so that
  drift is no error of the adjustment; their RMS should be 0.8-1.25. The absolute ones are kept
  beside (``normalised_error_rms_per_axis_absolute``);
- the corrected cloud: RMS of point-to-true-plane distances, next to what the true trajectory
  gives (the range noise alone) and what the drifted input gives.

Scenarios: ``sample`` (the committed sample_data run), ``heldout`` (another building layout,
a 16-beam sensor, other drift and seeds: not used for any development decision), or both.

Usage: python benchmarks/accuracy_matrix.py [--scenario sample heldout] [--seeds 1 2 3 ...]
       [--real-world] [--out benchmarks/results/accuracy_matrix.json]

With ``--seeds`` every scenario is repeated with those run seeds and the figures are pooled.
``--real-world`` turns on every effect of real scans the simulator has
(:meth:`kinreg.simulation.realism.RealWorldConfig.all_on`: wavy surfaces, heavy-tailed range
noise and mixed pixels, 0.1 s sweeps every 0.5 s, centimetre jitter of the trajectory, clutter),
``--real-world jitter sweeps`` only those named (``realism.EFFECTS``);
the cloud figures then count the points on the building's planes only (not the clutter's).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


# Drift classes of the matrix: position / attitude error reached after the given time, and the
# run's duration (None: the scenario's).
MAGNITUDES = {
    "small": (0.04, 0.25, 300.0, None),  # the sample's drift (post-processed SLAM)
    "medium": (0.07, 0.4, 180.0, None),  # the held-out handheld case of issue #14
    "large": (0.5, 2.0, 90.0, 90.0),  # SLAM without loop closure: 0.5 m / 2 deg over a 90 s run
}


def scenario_config(name: str, seed: int | None = None, drift_model: str | None = None,
                    magnitude: str | None = None, real_world: bool | list[str] = False):
    """The scenario's simulation configuration; ``seed`` replaces its run seed (walk, drift,
    noise; the building stays) for repeated realisations; ``drift_model`` and ``magnitude``
    (a key of :data:`MAGNITUDES`) replace its drift; ``real_world`` turns on every real-world
    effect of the simulator (``True``) or those named."""
    import dataclasses

    from kinreg.simulation.drift import DriftModel
    from kinreg.simulation.realism import RealWorldConfig

    cfg = _scenario_config(name)
    if real_world:
        world = RealWorldConfig.all_on() if real_world is True else RealWorldConfig.only(*real_world)
        cfg = dataclasses.replace(cfg, real_world=world)
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=seed)
    drift = cfg.drift
    if drift_model is not None:
        drift = dataclasses.replace(drift, model=DriftModel(drift_model))
    if magnitude is not None:
        pos, rot, at, duration = MAGNITUDES[magnitude]
        drift = dataclasses.replace(drift, drift_pos_m_at_300s=pos, drift_rot_deg_at_300s=rot, at_s=at)
        if duration is not None:
            cfg = dataclasses.replace(cfg, duration_s=duration)
    return dataclasses.replace(cfg, drift=drift)


def _scenario_config(name: str):
    from kinreg.simulation.drift import DriftConfig
    from kinreg.simulation.run import SimulationConfig, config_from_dict
    from kinreg.simulation.scene import BuildingConfig, BuildingLayout
    from kinreg.simulation.sensor import SensorConfig

    if name == "sample":
        meta = json.loads((REPO / "sample_data" / "run_meta.json").read_text())
        return config_from_dict(meta["config"])
    if name == "tilted":  # a 16-beam head tilted 45 deg, carried with a strong step sway, 180 s
        from kinreg.simulation.walk import WalkConfig

        return SimulationConfig(
            seed=5, duration_s=180.0,
            building=BuildingConfig(size_m=(24.0, 12.0, 3.0), n_rooms=3, seed=3),
            sensor=SensorConfig(pulse_rate_hz=20_000.0, n_beams=16, line_rate_hz=10.0, head_rate_hz=0.0,
                                head_tilt_deg=45.0, range_sigma_m=0.01),
            walk=WalkConfig(sway_m=0.05, sway_deg=3.0),
        )
    if name == "heldout":
        return SimulationConfig(
            seed=42,
            duration_s=300.0,
            building=BuildingConfig(size_m=(30.0, 16.0, 3.2), n_rooms=4, layout=BuildingLayout.CENTRAL_CORRIDOR,
                                    seed=7),
            sensor=SensorConfig(pulse_rate_hz=16_000.0, n_beams=16, line_rate_hz=10.0, head_rate_hz=0.0,
                                range_sigma_m=0.01),
            drift=DriftConfig(drift_pos_m_at_300s=0.06, drift_rot_deg_at_300s=0.35),
        )
    raise SystemExit(f"unknown scenario {name}")


def read_stations(path: Path) -> dict[str, np.ndarray]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    cols = {k: np.array([float(r[k]) if r[k] else np.nan for r in rows]) for k in
            ("t", "x", "y", "z", "sx_mm", "sy_mm", "sz_mm", "s3d_mm")}
    return cols


def cloud_fit(run, xyz_iter) -> tuple[float, float]:
    """Two figures of a cloud (points with their simulated patch ids, same order): the RMS distance
    of the points to their true plane, and the planes' thickness: the RMS distance of each
    physical plane's points to the plane fitted to them (the smallest eigenvalue of their scatter);
    points on no patch (the clutter of a real-world run) are left out of both.
    The first also counts where the whole network sits (its datum's error, a tilt about the datum
    station); the second only how well the passes over each plane agree, which a rigid motion of
    the whole cloud leaves unchanged (and the linear part of a bend across one plane with it): the
    crispness issue #14 asks for."""
    planes = run.scene.patches
    normals = np.array([p.normal for p in planes])
    d = np.array([p.d for p in planes])
    plane_of = run.scene.plane_of_patch()
    n_planes = int(plane_of.max()) + 1
    moments = np.zeros((10, n_planes))  # count, sums of x, y, z, of xx, xy, xz, yy, yz, zz
    sq, n = 0.0, 0
    origin = run.origin
    for block, xyz in xyz_iter:
        on_patch = block.patch_id >= 0
        pid = block.patch_id[on_patch]
        local = xyz[on_patch] - origin
        r = np.einsum("ij,ij->i", local, normals[pid]) - d[pid]
        sq += float(np.sum(r**2))
        n += len(r)
        plane = plane_of[pid]
        x, y, z = local[:, 0], local[:, 1], local[:, 2]
        for k, w in enumerate((None, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z)):
            moments[k] += np.bincount(plane, weights=w, minlength=n_planes)
    count = moments[0]
    used = count >= 10
    sq_fit = 0.0
    for k in np.flatnonzero(used):
        c = count[k]
        mean = moments[1:4, k] / c
        xx, xy, xz, yy, yz, zz = moments[4:, k] / c
        scatter = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]) - np.outer(mean, mean)
        sq_fit += c * max(float(np.linalg.eigvalsh(scatter)[0]), 0.0)
    return float(np.sqrt(sq / n)), float(np.sqrt(sq_fit / count[used].sum()))


def errors_relative_to_datum(st: dict[str, np.ndarray], truth, drifted) -> np.ndarray:
    """Per station (n, 3) [mm]: the adjusted position (``st``, :func:`read_stations`) against the
    truth moved rigidly so that the datum station's true pose falls on the pose it was held at, the
    trajectory's (where the datum is one held station, zero sigmas; else against the truth itself)."""
    adj = np.column_stack([st["x"], st["y"], st["z"]])
    true_xyz = truth.pose_at(st["t"]).t_xyz
    held = np.flatnonzero(np.column_stack([st["sx_mm"], st["sy_mm"], st["sz_mm"]]).max(axis=1) == 0)
    if len(held) == 1:
        t_datum = st["t"][held]
        true_xyz = drifted.pose_at(t_datum).compose(truth.pose_at(t_datum).inverse()).apply(true_xyz)
    return (adj - true_xyz) * 1000


def station_errors(stations_csv: Path, truth, drifted) -> dict:
    """The adjusted stations of ``stations_csv`` against the ``truth`` trajectory (``drifted``: the
    run's own): errors after a rigid fit, in the datum, relative to the datum station, and
    normalised by the reported sigmas."""
    from kinreg.report.json import rigid_fit

    st = read_stations(stations_csv)
    true_xyz = truth.pose_at(st["t"]).t_xyz
    adj = np.column_stack([st["x"], st["y"], st["z"]])
    initial_xyz = drifted.pose_at(st["t"]).t_xyz
    R, t = rigid_fit(adj, true_xyz)
    err_fit = np.linalg.norm(adj @ R.T + t - true_xyz, axis=1) * 1000
    err_datum = (adj - true_xyz) * 1000
    R0, t0_ = rigid_fit(initial_xyz, true_xyz)
    err_initial_fit = np.linalg.norm(initial_xyz @ R0.T + t0_ - true_xyz, axis=1) * 1000
    sig = np.column_stack([st["sx_mm"], st["sy_mm"], st["sz_mm"]])
    free = sig.max(axis=1) > 0
    # The sigmas are relative to the datum: the first station holds its sensor pose at the
    # trajectory's value, which carries the run's drift at that moment. The error they describe
    # is the adjusted position's against the truth moved rigidly so that the datum station's true
    # pose falls on the pose it was held at (where the datum is one held station; else absolute).
    err_relative = errors_relative_to_datum(st, truth, drifted)
    z = err_relative[free] / sig[free]
    # How much of the height error is one tilt of the network about the datum station (two numbers
    # per run): where it is most of it, a run is about two samples of the z sigmas' honesty, not
    # one per station, and nine runs judge them to about +-25 %.
    lever = (adj - adj[~free][:1])[free][:, :2] if np.any(~free) else adj[free][:, :2] - adj[free][:, :2].mean(axis=0)
    tilt, *_ = np.linalg.lstsq(lever, err_relative[free, 2], rcond=None)
    ms_z = float(np.mean(err_relative[free, 2] ** 2))
    z_absolute = err_datum[free] / sig[free]
    return {
        "stations": len(adj),
        "rigid_fit": (R, t),  # adjusted stations onto the truth (not written to the JSON)
        "position_error_after_rigid_fit_mm": {"rms": float(np.sqrt(np.mean(err_fit**2))), "max": float(err_fit.max())},
        "position_error_input_after_rigid_fit_mm": {"rms": float(np.sqrt(np.mean(err_initial_fit**2))),
                                                    "max": float(err_initial_fit.max())},
        "position_error_in_datum_mm": {"rms": float(np.sqrt(np.mean(np.sum(err_datum**2, axis=1)))),
                                       "max": float(np.linalg.norm(err_datum, axis=1).max())},
        "reported_sigma_3d_mm": {"rms": float(np.sqrt(np.mean(st["s3d_mm"][free] ** 2))),
                                 "max": float(st["s3d_mm"].max())},
        "position_error_relative_to_datum_mm": {"rms": float(np.sqrt(np.mean(np.sum(err_relative**2, axis=1)))),
                                                "max": float(np.linalg.norm(err_relative, axis=1).max())},
        "normalised_error_rms": float(np.sqrt(np.mean(z**2))),
        "normalised_error_rms_per_axis_absolute": np.sqrt(np.mean(z_absolute**2, axis=0)).tolist(),
        "normalised_error_rms_per_axis": np.sqrt(np.mean(z**2, axis=0)).tolist(),
        "normalised_error_ms_per_axis": np.mean(z**2, axis=0).tolist(),
        "network_rotation_mdeg": float(np.degrees(np.linalg.norm(_rotvec(R))) * 1000),
        "z_error_tilt_share": float(np.mean((lever @ tilt) ** 2) / ms_z) if ms_z > 0 else 0.0,
        "share_within_3_sigma": float(np.mean(np.abs(z) < 3)),
    }


def evaluate(name: str, workdir: Path, seed: int | None = None, config_path: Path | None = None,
             drift_model: str | None = None, magnitude: str | None = None,
             real_world: bool | list[str] = False) -> dict:
    import laspy

    from kinreg.config import load_config
    from kinreg.io.trajectory import read_trajectory
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import simulate_run

    cfg = scenario_config(name, seed, drift_model, magnitude, real_world)
    if name == "sample" and seed is None and drift_model is None and magnitude is None and not real_world:
        data = REPO / "sample_data"
    else:
        data = workdir / "data"
        write_run(simulate_run(cfg), data)
    run = simulate_run(cfg)
    t0 = time.perf_counter()
    summary = process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz"), workdir / "out",
                      load_config(config_path), overwrite=True)
    wall = time.perf_counter() - t0

    truth = read_trajectory(data / "truth_trajectory.txt")
    stations = station_errors(workdir / "out" / "stations.csv", truth, read_trajectory(data / "run_trajectory.txt"))

    # corrected cloud vs true planes, next to the true-trajectory cloud and the drifted input
    with laspy.open(workdir / "out" / "corrected.laz") as r:
        points = next(r.chunk_iterator(10**9))
        corrected_xyz = np.column_stack([points.x, points.y, points.z])
    R_fit, t_fit = stations.pop("rigid_fit")

    def corrected(rigid: bool = False):
        # rigid: moved by the stations' rigid fit onto the truth (their datum's error taken out)
        first = 0
        for block in run.iter_cloud_blocks():
            xyz = corrected_xyz[first:first + len(block)]
            yield block, (xyz @ R_fit.T + t_fit if rigid else xyz)
            first += len(block)

    def with_truth():
        for block in run.iter_cloud_blocks():
            poses = truth.pose_at(block.stamps_s)
            yield block, poses.apply(block.xyz_sensor)

    def drifted():
        for block in run.iter_cloud_blocks():
            yield block, block.xyz_obj

    report = json.loads((workdir / "out" / "report.json").read_text())
    adjustment = report["adjustment"]
    drift = adjustment["drift_rates"]
    (rms_corrected, thick_corrected), (rms_rigid, _), (rms_truth, thick_truth), (rms_input, thick_input) = (
        cloud_fit(run, cloud) for cloud in (corrected(), corrected(rigid=True), with_truth(), drifted()))
    return {
        "scenario": name,
        "seed": cfg.seed,
        "stations": stations["stations"],
        "links": summary.n_links,
        "sigma0": summary.sigma0,
        "drift_rates": drift,
        "variance_components": adjustment.get("variance_components"),
        "global_test_passed": summary.global_test_passed,
        **{k: v for k, v in stations.items() if k != "stations"},
        "drift_model": cfg.drift.model.value, "magnitude": magnitude, "real_world": real_world,
        "link_model": (report.get("links") or {}).get("model"),
        "cloud_point_to_plane_rms_mm": {"corrected": rms_corrected * 1000, "true_trajectory": rms_truth * 1000,
                                        "input": rms_input * 1000,
                                        "corrected_over_truth": rms_corrected / rms_truth,
                                        "corrected_after_rigid_fit": rms_rigid * 1000,
                                        "corrected_after_rigid_fit_over_truth": rms_rigid / rms_truth},
        "cloud_plane_thickness_mm": {"corrected": thick_corrected * 1000, "true_trajectory": thick_truth * 1000,
                                     "input": thick_input * 1000,
                                     "corrected_over_truth": thick_corrected / thick_truth},
        "gaps_mm": {"mean": summary.gaps_mean_mm, "max": summary.gaps_max_mm},
        "rejected_observations": summary.n_rejected,
        "trajectory_misfits": len(adjustment.get("trajectory_misfits") or []),
        "window_s": (report.get("slicing") or {}).get("window_s"),
        "process_wall_s": wall,
        "timings_s": summary.timings_s,
    }


def _rotvec(R: np.ndarray) -> np.ndarray:
    from kinreg.geometry import matrix_to_quat, quat_to_rotvec

    return quat_to_rotvec(matrix_to_quat(R))


def pooled_interval(mean_squares: list[list[float]], level: float = 0.9, draws: int = 2000) -> list[list[float]]:
    """A bootstrap interval per axis of the pooled RMS of normalised errors, over the runs: a
    run's stations share most of their error, so the run (not the station) is the sample; with
    3 runs the interval is wide, and a pooled figure of 0.7 or 1.3 may still be a right model."""
    ms = np.asarray(mean_squares, dtype=float)
    rng = np.random.default_rng(0)
    picks = rng.integers(0, len(ms), size=(draws, len(ms)))
    rms = np.sqrt(ms[picks].mean(axis=1))  # (draws, 3)
    lo, hi = np.quantile(rms, [(1 - level) / 2, (1 + level) / 2], axis=0)
    return np.column_stack([lo, hi]).tolist()


def pooled(results: list[dict]) -> dict:
    """Figures over repeated realisations of one scenario: one run's stations share most of their
    error (it accumulates along the walk), so a single run is a few independent samples at most;
    the honesty of the sigmas is judged on the pool."""
    z2 = [r["normalised_error_rms"] ** 2 for r in results]
    return {
        "runs": len(results),
        "normalised_error_rms_pooled": float(np.sqrt(np.mean(z2))),
        "normalised_error_rms_per_run": [r["normalised_error_rms"] for r in results],
        "normalised_error_rms_pooled_per_axis": np.sqrt(np.mean([r["normalised_error_ms_per_axis"] for r in results],
                                                                axis=0)).tolist(),
        "normalised_error_rms_pooled_per_axis_90": pooled_interval([r["normalised_error_ms_per_axis"]
                                                                    for r in results]),
        "cloud_corrected_over_truth_worst_run": max(r["cloud_point_to_plane_rms_mm"]["corrected_over_truth"]
                                                    for r in results),
        "cloud_thickness_corrected_over_truth_worst_run": max(
            (r["cloud_plane_thickness_mm"]["corrected_over_truth"] for r in results if "cloud_plane_thickness_mm" in r),
            default=None),
        "position_error_after_rigid_fit_mm_rms_worst_run": max(r["position_error_after_rigid_fit_mm"]["rms"]
                                                               for r in results),
        "position_error_after_rigid_fit_mm_max_worst_run": max(r["position_error_after_rigid_fit_mm"]["max"]
                                                               for r in results),
        "share_within_3_sigma": float(np.mean([r["share_within_3_sigma"] for r in results])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", nargs="+", default=["sample", "heldout"])
    parser.add_argument("--seeds", nargs="*", type=int, default=None,
                        help="repeat each scenario with these run seeds (walk, drift, noise) and pool the figures")
    parser.add_argument("--config", type=Path, default=None, help="kinreg configuration (default: the defaults)")
    parser.add_argument("--drift-models", nargs="*", default=[None],
                        help="world, slam, gnss-ins (default: the scenario's)")
    parser.add_argument("--magnitudes", nargs="*", default=[None], help=f"drift classes: {', '.join(MAGNITUDES)}")
    parser.add_argument("--real-world", nargs="*", default=None,
                        help="real-world effects of the simulator on: all without a name, else those named "
                             "(waviness, noise, sweeps, jitter, clutter)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "accuracy_matrix.json")
    args = parser.parse_args()
    results, pools = [], {}
    real_world = False if args.real_world is None else (args.real_world or True)
    cells = [(n, m, g) for n in args.scenario for m in args.drift_models for g in args.magnitudes]
    for name, model, magnitude in cells:
        runs = []
        key = "/".join(str(x) for x in (name, model, magnitude) if x is not None)
        for seed in args.seeds or [None]:
            with tempfile.TemporaryDirectory(prefix=f"kinreg-eval-{name}-") as tmp:
                try:
                    res = evaluate(name, Path(tmp), seed, args.config, model, magnitude, real_world)
                except Exception as e:  # a failed run is a result of the matrix too
                    res = {"scenario": name, "seed": seed, "drift_model": model, "magnitude": magnitude,
                           "error": f"{type(e).__name__}: {e}"}
            print(json.dumps(res), flush=True)
            runs.append(res)
        results += runs
        good = [r for r in runs if "error" not in r]
        if args.seeds and good:
            pools[key] = {**pooled(good), "failed_runs": len(runs) - len(good)}
            print(json.dumps({key: pools[key]}, indent=1), flush=True)
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
                                    "results": results, "pooled": pools}, indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()

