"""JSON and text reports of a calibration and of a calibration-field planning.

Units in the reports: millimetres for lever arm and residuals, degrees for the boresight angles,
millidegrees (mdeg) for their standard deviations. Bump :data:`REPORT_SCHEMA_VERSION` whenever a
key is renamed, removed or changes its unit (adding keys does not need a bump).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from kinreg.calibration.assignment import RobustCalibration, moved_sigmas
from kinreg.calibration.model import PARAMETER_NAMES, CalibrationConfig, CalibrationResult
from kinreg.calibration.planning import (
    FITNESS_NAMES,
    SEED_TABLE5,
    SEED_TABLE6,
    EvolutionResult,
    GridResult,
    PlanningConfig,
)
from kinreg.errors import OutputError
from kinreg.io.atomic import atomic_path, check_writable_target

REPORT_SCHEMA_VERSION = 1


def _param_display(values: np.ndarray) -> list[float]:
    """(m, rad) -> (mm, deg)."""
    return [float(v * 1e3) for v in values[:3]] + [float(math.degrees(v)) for v in values[3:]]


def _sigma_display(values: np.ndarray) -> list[float]:
    """(m, rad) -> (mm, mdeg)."""
    return [float(v * 1e3) for v in values[:3]] + [float(math.degrees(v) * 1e3) for v in values[3:]]


def calibration_report(result: CalibrationResult, config: CalibrationConfig | None = None,
                       inputs: dict[str, str] | None = None, robust: RobustCalibration | None = None,
                       problems: list[str] | None = None) -> dict[str, Any]:
    """The calibration result as a JSON-ready dict (schema :data:`REPORT_SCHEMA_VERSION`).

    ``problems`` (from :func:`~kinreg.calibration.assignment.calibration_problems`): a non-empty
    list marks the result ``"accepted": false`` (kept on request); ``robust`` adds the point
    assignment's passes and how far the estimate moved from the starting values.
    """
    x = result.calibration.as_vector()
    est = _param_display(x)
    sig = _sigma_display(result.sigmas)
    units = ["mm"] * 3 + ["deg"] * 3
    params = {name: {"value": v, "unit": u, "sigma": s, "sigma_unit": "mm" if u == "mm" else "mdeg"}
              for name, v, u, s in zip(PARAMETER_NAMES, est, units, sig, strict=True)}
    gt = result.global_test
    return {
        "schema_version": REPORT_SCHEMA_VERSION,
        "kind": "kinreg.calibration",
        "inputs": inputs or {},
        "parameters": params,
        "rotation_convention": "R_bs = Rz(kappa) Ry(phi) Rx(omega); P_b = t_bs + R_bs P_s",
        "correlation": np.round(result.correlation, 6).tolist(),
        "covariance_m_rad": result.covariance.tolist(),
        "sigma0": result.sigma0,
        "redundancy": result.redundancy,
        "global_test": {"statistic": gt.statistic, "lower": gt.lower, "upper": gt.upper,
                        "alpha": gt.alpha, "passed": gt.passed, "scaled": gt.scaled,
                        "sigma0_band": list(config.sigma0_band) if config else None,
                        "note": global_test_note(result)},
        "sigmas_scaled_by_sigma0": bool(config.scale_by_sigma0 if config else False) or gt.scaled,
        "n_points": result.n_points,
        "n_epochs": result.n_epochs,
        "iterations": result.iterations,
        "converged": result.converged,
        "planes": [asdict(s) for s in result.plane_stats],
        "config": asdict(config) if config else None,
        "accepted": not problems,
        "rejection_reasons": list(problems or []),
        "assignment": None if robust is None else {
            "passes": [asdict(p) for p in robust.passes],
            "start_sigma0": robust.start_misfit,
            "start_sigma0_upper_bound": robust.start_misfit_upper,
            "moved_from_start_in_sigmas": moved_sigmas(robust),
            "points_outside_trajectory_time": robust.n_outside_time,
            "planes_without_extent": list(robust.unbounded_planes),
        },
    }


def global_test_note(result: CalibrationResult) -> str:
    """One sentence on the global test: passed, refused, or refused by the chi-square bounds with
    sigma0 in the band that is no failure (the sigmas scaled by sigma0)."""
    gt = result.global_test
    bounds = f"{gt.statistic:.1f} in [{gt.lower:.1f}, {gt.upper:.1f}] at redundancy {result.redundancy}"
    if gt.passed:
        return f"global test passed: {bounds} (alpha {gt.alpha:g})"
    if gt.scaled:
        return (f"sigma0 {result.sigma0:.3f}: outside the chi-square bounds ({bounds.replace(' in ', ' not in ')}, "
                f"alpha {gt.alpha:g}) but an a-priori model {abs(result.sigma0 - 1.0) * 100:.1f} % off, no failed "
                "calibration: the sigmas are scaled by sigma0")
    return (f"global test REJECTED: sigma0 {result.sigma0:.3f}, {bounds.replace(' in ', ' not in ')} "
            f"(alpha {gt.alpha:g})")


def calibration_text(result: CalibrationResult, problems: list[str] | None = None) -> str:
    """A plain-text summary of the calibration (for the report file and logs); ``problems``
    marks it REJECTED at the top."""
    lines = ["kinreg system calibration (lever arm + boresight)", ""]
    if problems:
        lines += ["REJECTED (kept with --accept-rejected): " + "; ".join(problems), ""]
    est = _param_display(result.calibration.as_vector())
    sig = _sigma_display(result.sigmas)
    for name, v, s in zip(PARAMETER_NAMES, est, sig, strict=True):
        if name.startswith("t"):
            lines.append(f"  {name:6s} = {v:12.4f} mm    sigma {s:8.4f} mm")
        else:
            lines.append(f"  {name:6s} = {v:12.6f} deg   sigma {s:8.4f} mdeg")
    lines += ["", "correlation:"]
    header = "        " + " ".join(f"{n:>7s}" for n in PARAMETER_NAMES)
    lines.append(header)
    for name, row in zip(PARAMETER_NAMES, result.correlation, strict=True):
        lines.append(f"  {name:6s}" + " ".join(f"{c:7.3f}" for c in row))
    lines += ["", f"sigma0 = {result.sigma0:.4f} (redundancy {result.redundancy}); {global_test_note(result)}",
              f"{result.n_points} points, {result.n_epochs} tracker epochs, {result.iterations} "
              f"iterations{'' if result.converged else ' (NOT converged)'}", "",
              "residuals per plane (orthogonal distance):",
              f"  {'plane':16s} {'n':>7s} {'mean mm':>9s} {'rms mm':>9s} {'max mm':>9s} {'rms/sigma':>9s}"]
    for ps in result.plane_stats:
        lines.append(f"  {ps.name:16s} {ps.n_points:7d} {ps.mean_mm:9.4f} {ps.rms_mm:9.4f} "
                     f"{ps.max_abs_mm:9.4f} {ps.normalized_rms:9.3f}")
    return "\n".join(lines) + "\n"


def write_report(out_dir: str | Path, stem: str, report: dict[str, Any], text: str,
                 overwrite: bool = False) -> tuple[Path, Path]:
    """Write ``stem.json`` and ``stem.txt`` into ``out_dir`` (created). Raises :class:`OutputError`."""
    d = Path(out_dir)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create output folder: {e}", d) from None
    paths = (d / f"{stem}.json", d / f"{stem}.txt")
    for p in paths:
        check_writable_target(p, overwrite)
    with atomic_path(paths[0], overwrite=overwrite) as tmp:
        tmp.write_text(json.dumps(report, indent=2, allow_nan=True) + "\n", encoding="utf-8")
    with atomic_path(paths[1], overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return paths


def planning_report(result: GridResult, config: PlanningConfig,
                    evolution: list[EvolutionResult] | None = None, top: int = 5) -> dict[str, Any]:
    """Exhaustive (and optional evolutionary) planning result with the seed's Tables 5 and 6."""
    from kinreg.calibration.planning import separate_optimisation

    best = {f: [result.row(i) for i in result.best(f, top)] for f in FITNESS_NAMES}
    seed_rows = {}
    for f, s in SEED_TABLE6.items():
        from kinreg.calibration.planning import grid_index_of

        idx = grid_index_of(result.grid, s["y1_m"], s["z1_m"], s["alpha1_deg"], s["beta1_deg"],
                            s["gamma1_deg"])
        row = result.row(int(np.ravel_multi_index(idx, result.grid.shape)))
        seed_rows[f] = {"seed": s, "this_model": row}
    return {
        "schema_version": REPORT_SCHEMA_VERSION,
        "kind": "kinreg.calibration_planning",
        "config": asdict(config),
        "n_arrangements": int(result.fitness.shape[0]),
        "n_singular": result.n_singular,
        "seconds": result.seconds,
        "best": best,
        "separate_optimisation": {f: separate_optimisation(result, f) for f in FITNESS_NAMES},
        "seed_table6_in_this_model": seed_rows,
        "seed_table5": SEED_TABLE5,
        "evolution": [asdict(e) | {"values_display": _values_display(e.values)} for e in evolution or []],
    }


def _values_display(values: tuple[float, ...]) -> list[float]:
    return [values[0], values[1], *(round(math.degrees(v), 6) for v in values[2:])]


def planning_text(report: dict[str, Any]) -> str:
    """A plain-text table of the planning report: best arrangements next to the seed's."""
    lines = [f"calibration-field planning: {report['n_arrangements']} arrangements in "
             f"{report['seconds']:.2f} s ({report['n_singular']} singular)", "",
             f"  {'fit':4s} {'source':10s} {'y1':>5s} {'z1':>5s} {'alpha1':>6s} {'beta1':>6s} "
             f"{'gamma1':>6s} {'f1 mm':>7s} {'f2 mm':>7s} {'f3 mm':>7s}"]
    for f in FITNESS_NAMES:
        r = report["best"][f][0]
        lines.append(f"  {f:4s} {'kinreg':10s} {r['y1_m']:5.1f} {r['z1_m']:5.1f} {r['alpha1_deg']:6.0f} "
                     f"{r['beta1_deg']:6.0f} {r['gamma1_deg']:6.0f} {r['f1_mm']:7.3f} {r['f2_mm']:7.3f} "
                     f"{r['f3_mm']:7.3f}")
        s = report["seed_table6_in_this_model"][f]
        m = s["this_model"]
        lines.append(f"  {f:4s} {'seed T6':10s} {m['y1_m']:5.1f} {m['z1_m']:5.1f} {m['alpha1_deg']:6.0f} "
                     f"{m['beta1_deg']:6.0f} {m['gamma1_deg']:6.0f} {m['f1_mm']:7.3f} {m['f2_mm']:7.3f} "
                     f"{m['f3_mm']:7.3f}   (seed: {s['seed']['fitness_mm']:.2f} mm)")
    for e in report["evolution"]:
        v = e["values_display"]
        lines.append(f"  DE {e['fitness']}: y1 {v[0]:.1f} z1 {v[1]:.1f} alpha1 {v[2]:.0f} beta1 {v[3]:.0f} "
                     f"gamma1 {v[4]:.0f} -> {e['fitness_mm']:.4f} mm ({e['n_evaluations']} evaluations)")
    return "\n".join(lines) + "\n"
