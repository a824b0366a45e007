"""``kinreg calibrate`` and ``kinreg plan-calibration``: thin front ends of kinreg.calibration.

Registered by the main app as ``app.command("calibrate")(calibrate)`` and
``app.command("plan-calibration")(plan_calibration)``.
"""

from __future__ import annotations

import enum
import math
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from kinreg.errors import CloudError, ConfigError, EstimationError, InputError

console = Console()


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        raise ConfigError(f"{what} must be {n} comma-separated numbers, got '{text}'") from None
    if len(vals) != n:
        raise ConfigError(f"{what} must be {n} comma-separated numbers, got '{text}'")
    return vals


def _read_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from kinreg.io.cloud import open_cloud

    xyz, t = [], []
    with open_cloud(path, require_time=True) as reader:
        n_scans = reader.info.n_scans
        for chunk in reader.iter_chunks():
            xyz.append(chunk.xyz)
            if chunk.stamps_s is None:  # not reached: require_time=True
                raise CloudError("the points have no time stamps", path)
            t.append(chunk.stamps_s)
    if not xyz:
        what = "holds no scans" if n_scans == 0 else "holds no points"
        raise CloudError(f"{what}: nothing to calibrate with", path)
    return np.concatenate(xyz), np.concatenate(t)


def _read_plane_index(path: Path, n: int, n_planes: int) -> np.ndarray:
    try:
        idx = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, dtype=np.int64, ndmin=1)
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read plane indices: {e}", path) from None
    idx = np.asarray(idx, dtype=np.int64).ravel()
    if len(idx) != n:
        raise InputError(f"{len(idx)} plane indices for {n} points", path)
    bad = (idx < -1) | (idx >= n_planes)
    if np.any(bad):
        raise InputError(f"{int(bad.sum())} plane indices outside -1..{n_planes - 1} (the planes file has "
                         f"{n_planes} planes), e.g. {int(idx[bad][0])} at point {int(np.flatnonzero(bad)[0])}",
                         path)
    return idx


def _warn(message: str) -> None:
    # Plain print to stderr like the error line: a warning must not be wrapped or lost in a table.
    print(f"kinreg: warning: {message}", file=sys.stderr)


def calibrate(
    cloud: Annotated[Path, typer.Option("--cloud", help="Scanner points in the scanner frame with "
                                        "times (LAS/LAZ/E57).")],
    trajectory: Annotated[Path, typer.Option("--trajectory", help="Tracker poses T_l_b (any "
                                             "trajectory format kinreg reads).")],
    planes: Annotated[Path, typer.Option("--planes", help="Reference planes (TOML) in the object frame, "
                                         "each plate with its extent (centre + size or polygon).")],
    lever_arm: Annotated[str, typer.Option(help="Approximate lever arm tx,ty,tz in metres.")],
    boresight_deg: Annotated[str, typer.Option(help="Approximate omega,phi,kappa in degrees.")],
    out: Annotated[Path, typer.Option("--out", help="Folder for calibration.json/.txt.")],
    plane_index: Annotated[Path | None, typer.Option(help="Plane index per point (.npy or text, "
                                                      "-1 = none); else points are gated.")] = None,
    gate_mm: Annotated[float, typer.Option(help="Starting gate: the widest distance from a plate "
                                           "(as found in the data inside the plane's extent) "
                                           "accepted in the first pass; later passes gate with "
                                           "the estimate's propagated uncertainty.")] = 50.0,
    sigma_d_mm: Annotated[float, typer.Option(help="Scanner range sigma.")] = 0.5,
    sigma_angle_mdeg: Annotated[float, typer.Option(help="Scanner angle sigma (phi and theta).")] = 4.0,
    tracker_sigma_t_um: Annotated[float, typer.Option(help="Tracker translation sigma per axis.")] = 7.8,
    tracker_sigma_rot_mdeg: Annotated[float, typer.Option(help="Tracker rotation sigma per axis.")] = 2.0,
    observe_planes: Annotated[bool, typer.Option(help="Plane parameters as observations "
                                                 "(offset sigma = plane_construction_accuracy_m).")] = False,
    plane_sigma_normal_mdeg: Annotated[float, typer.Option(help="Tilt sigma of plane normals "
                                                           "with --observe-planes.")] = 10.0,
    trajectory_format: Annotated[str | None, typer.Option(help="Trajectory format (guessed).")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace existing report files.")] = False,
    alpha: Annotated[float, typer.Option(help="Significance level of the global test and "
                                         "family-wise level of the data snooping: a correct "
                                         "calibration is refused with this probability.")] = 0.05,
    accept_rejected: Annotated[bool, typer.Option(help="Keep a calibration that fails the "
                                                  "acceptance checks (marked REJECTED in the "
                                                  "report) instead of exit 1.")] = False,
) -> None:
    """Estimate lever arm and boresight from scans of reference planes (Gauss-Helmert model).

    Refuses (exit 1) a result with too few points on a plane, a failed global test, no
    convergence, or an estimate that stayed at starting values the data contradict, unless
    --accept-rejected.
    """
    from kinreg.calibration import (
        CalibrationConfig,
        ScannerSigmas,
        SystemCalibration,
        TrackerSigmas,
        calibration_report,
        calibration_text,
        estimate_calibration,
        write_report,
    )
    from kinreg.calibration.assignment import (
        AssignmentConfig,
        RobustCalibration,
        calibrate_robust,
        calibration_problems,
        check_time_overlap,
        start_misfit,
    )
    from kinreg.calibration.report import global_test_note
    from kinreg.errors import CalibrationRejectedError
    from kinreg.io.reference_planes import read_reference_planes
    from kinreg.io.trajectory import read_trajectory

    approx = SystemCalibration(np.array(_floats(lever_arm, 3, "--lever-arm")),
                               np.radians(_floats(boresight_deg, 3, "--boresight-deg")))
    ref = read_reference_planes(planes)
    traj = read_trajectory(trajectory, trajectory_format)
    points, stamps = _read_points(cloud)
    cfg = CalibrationConfig(
        scanner=ScannerSigmas(sigma_d_mm * 1e-3, math.radians(sigma_angle_mdeg * 1e-3),
                              math.radians(sigma_angle_mdeg * 1e-3)),
        tracker=TrackerSigmas(tracker_sigma_t_um * 1e-6, math.radians(tracker_sigma_rot_mdeg * 1e-3)),
        plane_sigma_d_m=ref.accuracy_m if observe_planes else None,
        plane_sigma_normal_rad=math.radians(plane_sigma_normal_mdeg * 1e-3) if observe_planes else None,
        alpha=alpha,
    )
    if not 0.0 < alpha < 1.0:
        raise ConfigError(f"--alpha must lie between 0 and 1, got {alpha}")
    n_outside = check_time_overlap(stamps, traj, str(cloud))
    if n_outside:
        _warn(f"{cloud}: {n_outside} of {len(stamps)} points lie outside the trajectory's time range "
              f"[{traj.t_start_s:.3f}, {traj.t_end_s:.3f}] s ({trajectory}) and are left out")
    try:
        if plane_index is not None:
            idx = _read_plane_index(plane_index, len(points), len(ref))
            result = estimate_calibration(points, stamps, idx, traj, ref, approx, cfg)
            misfit, upper = start_misfit(points, stamps, np.where(traj.covers(stamps), idx, -1), traj, ref,
                                         approx, cfg)
            robust = RobustCalibration(result, idx, (), misfit, upper, approx)
        else:
            unbounded = [p.name for p in ref.planes if p.extent is None]
            if unbounded:
                _warn(f"{planes}: plane(s) {', '.join(unbounded)} have no extent: room surfaces near their "
                      "infinite planes can be taken for them (give each plate's extent)")
            robust = calibrate_robust(points, stamps, traj, ref, approx, cfg,
                                      AssignmentConfig(gate_m=gate_mm * 1e-3, alpha=alpha))
            result = robust.result
    except EstimationError as e:
        # The adjustment does not know the file; the one error line must name it.
        if e.path is None:
            raise type(e)(e.reason, cloud) from None
        raise
    problems = calibration_problems(robust, ref, cfg)
    if problems and not accept_rejected:
        raise CalibrationRejectedError("calibration rejected: " + "; ".join(problems)
                                  + " (--accept-rejected keeps it)", cloud)
    report = calibration_report(result, cfg, {"cloud": str(cloud), "trajectory": str(trajectory),
                                              "planes": str(planes)}, robust=robust, problems=problems)
    write_report(out, "calibration", report, calibration_text(result, problems), overwrite=overwrite)

    table = Table(title="system calibration")
    for col in ("parameter", "value", "sigma"):
        table.add_column(col, justify="right")
    for name, p in report["parameters"].items():
        table.add_row(name, f"{p['value']:.4f} {p['unit']}", f"{p['sigma']:.4f} {p['sigma_unit']}")
    console.print(table)
    console.print(f"{global_test_note(result)}; report in {out}")
    if problems:
        _warn(f"{cloud}: calibration REJECTED but kept (--accept-rejected): " + "; ".join(problems))


class PlanMethod(str, enum.Enum):
    EXHAUSTIVE = "exhaustive"
    EVOLUTION = "evolution"
    BOTH = "both"


def plan_calibration(
    arrangement: Annotated[Path | None, typer.Option(help="Evaluate this arrangement (TOML) "
                                                     "instead of optimising the Table 2 family.")] = None,
    method: Annotated[PlanMethod, typer.Option(help="Optimiser over the Table 3 grid.")] = PlanMethod.BOTH,
    plane_size_m: Annotated[float, typer.Option(help="Side of the square reference planes.")] = 0.3,
    zenith_step_deg: Annotated[float, typer.Option(help="Zenith resolution of the profile.")] = 0.036,
    sigma_d_mm: Annotated[float, typer.Option(help="Scanner range sigma.")] = 0.5,
    sigma_angle_mdeg: Annotated[float, typer.Option(help="Scanner angle sigma.")] = 4.0,
    tracker_sigma_t_um: Annotated[float, typer.Option(help="Tracker translation sigma per axis.")] = 7.8,
    tracker_sigma_rot_mdeg: Annotated[float, typer.Option(help="Tracker rotation sigma per axis.")] = 2.0,
    no_tracker: Annotated[bool, typer.Option(help="Leave the tracker errors out.")] = False,
    lever_arm: Annotated[str, typer.Option(help="Nominal lever arm tx,ty,tz in metres.")] = "0,0,0",
    distance_m: Annotated[float, typer.Option(help="Object distance d in f2, f3.")] = 10.0,
    profiles: Annotated[int, typer.Option(help="Profiles, each with its own tracker pose.")] = 1,
    top: Annotated[int, typer.Option(help="Best arrangements listed per fitness.")] = 3,
    seed: Annotated[int, typer.Option(help="Seed of the evolutionary optimiser.")] = 0,
    out: Annotated[Path | None, typer.Option(help="Folder for planning.json/.txt.")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace existing report files.")] = False,
) -> None:
    """Theoretical sigmas of lever arm and boresight for a plane arrangement; optimise Table 3."""
    from kinreg.calibration import (
        PlanningConfig,
        ScannerSigmas,
        TrackerSigmas,
        evaluate_arrangement,
        exhaustive_search,
        optimise_evolution,
        planning_report,
        planning_text,
        read_arrangement,
        write_report,
    )
    from kinreg.calibration.model import PARAMETER_NAMES
    from kinreg.calibration.planning import Table2Tables, Table3Grid

    la = _floats(lever_arm, 3, "--lever-arm")
    cfg = PlanningConfig(
        scanner=ScannerSigmas(sigma_d_mm * 1e-3, math.radians(sigma_angle_mdeg * 1e-3),
                              math.radians(sigma_angle_mdeg * 1e-3)),
        tracker=None if no_tracker else TrackerSigmas(tracker_sigma_t_um * 1e-6,
                                                      math.radians(tracker_sigma_rot_mdeg * 1e-3)),
        zenith_step_deg=zenith_step_deg, plane_size_m=plane_size_m,
        lever_arm_m=(la[0], la[1], la[2]), object_distance_m=distance_m, n_profiles=profiles)
    if arrangement is not None:
        q = evaluate_arrangement(read_arrangement(arrangement, plane_size_m), cfg)
        table = Table(title=f"arrangement {arrangement.name}")
        table.add_column("parameter")
        table.add_column("sigma", justify="right")
        for name, s in zip(PARAMETER_NAMES, q.sigmas, strict=True):
            table.add_row(name, f"{s * 1e3:.4f} mm" if name.startswith("t")
                          else f"{math.degrees(s) * 1e3:.4f} mdeg")
        console.print(table)
        console.print(f"f1 {q.f1_mm:.4f} mm, f2 {q.f2_mm:.4f} mm, f3 {q.f3_mm:.4f} mm; "
                      f"points per plane {q.points_per_plane}")
        return
    grid = Table3Grid()
    tables = Table2Tables(grid, cfg)
    result = exhaustive_search(cfg, grid, tables)
    evo = []
    if method in (PlanMethod.EVOLUTION, PlanMethod.BOTH):
        evo = [optimise_evolution(f, cfg, grid, tables, seed=seed) for f in ("f1", "f2", "f3")]
    report = planning_report(result, cfg, evo, top=top)
    text = planning_text(report)
    if out is not None:
        write_report(out, "planning", report, text, overwrite=overwrite)

    table = Table(title=f"best of {report['n_arrangements']} arrangements "
                  f"({report['seconds']:.1f} s exhaustive)")
    for col in ("fitness", "y1 m", "z1 m", "alpha1", "beta1", "gamma1", "f1 mm", "f2 mm", "f3 mm"):
        table.add_column(col, justify="right")
    for f in ("f1", "f2", "f3"):
        if method is PlanMethod.EVOLUTION:
            break
        for r in report["best"][f]:
            table.add_row(f, f"{r['y1_m']:.1f}", f"{r['z1_m']:.1f}", f"{r['alpha1_deg']:.0f}",
                          f"{r['beta1_deg']:.0f}", f"{r['gamma1_deg']:.0f}", f"{r['f1_mm']:.3f}",
                          f"{r['f2_mm']:.3f}", f"{r['f3_mm']:.3f}")
    for e in report["evolution"]:
        v = e["values_display"]
        table.add_row(f"DE {e['fitness']}", f"{v[0]:.1f}", f"{v[1]:.1f}", f"{v[2]:.0f}", f"{v[3]:.0f}",
                      f"{v[4]:.0f}", "", "", f"{e['fitness_mm']:.3f} ({e['fitness']})")
    console.print(table)
    for f, s in report["seed_table6_in_this_model"].items():
        m = s["this_model"]
        console.print(f"seed Table 6 best for {f} ({s['seed']['fitness_mm']:.2f} mm in the seed) "
                      f"scores {m[f + '_mm']:.3f} mm here")
