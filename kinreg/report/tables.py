"""Reports of a processed run: ``stations.csv``, ``links.csv``, ``report.json`` (METHOD.md section 6).

``report.json`` follows :data:`REPORT_SCHEMA_VERSION`; bump it when a key is renamed or removed
or its meaning changes (adding keys does not need a bump). Units: mm and mdeg in the report.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import kinreg
from kinreg.estimate.network import Station
from kinreg.geometry import FloatArray, Pose, matrix_to_quat, quat_to_rotvec
from kinreg.io.atomic import atomic_path
from kinreg.types import BlockResult, Link, LinkStatus, ObservationKind, Plane, ScanKind

REPORT_SCHEMA_VERSION = 1

# METHOD.md section 6: fixed names and order, other tools read them.
STATIONS_HEADER = ["station", "t", "t_start", "t_end", "x", "y", "z", "qw", "qx", "qy", "qz",
                   "sx_mm", "sy_mm", "sz_mm", "s3d_mm", "n_points", "n_planes", "n_links"]
LINKS_HEADER = ["scan_i", "scan_j", "status", "dt_s", "n_matches", "n_rejected_matches", "n_directions", "rank",
                "tx", "ty", "tz", "qw", "qx", "qy", "qz", "stx_mm", "sty_mm", "stz_mm", "srx_mdeg", "sry_mdeg",
                "srz_mdeg", "sigma0", "redundancy", "global_test", "max_normalised_residual", "block_statistic",
                "block_normalised", "block_rejected"]


def rigid_fit(source: FloatArray, target: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least-squares rotation R and translation t with ``target ~ R source + t`` (Kabsch).

    >>> R, t = rigid_fit(np.eye(3), np.eye(3) + 1.0)
    >>> np.allclose(R, np.eye(3)) and np.allclose(t, 1.0)
    True
    """
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    H = (source - cs).T @ (target - ct)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, ct - R @ cs


def _stats(values: FloatArray) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"rms": math.nan, "mean": math.nan, "max": math.nan}
    return {"rms": float(np.sqrt(np.mean(v**2))), "mean": float(np.mean(v)), "max": float(np.max(v))}


def _fmt(value: float, digits: int) -> str:
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def stations_table(stations: Sequence[Station], result: BlockResult, planes: Sequence[tuple[Plane, ...]],
                   links: Sequence[Link]) -> list[dict[str, Any]]:
    """One row per station with the columns of ``stations.csv`` (plus orientation sigmas)."""
    n_links = np.zeros(len(stations), dtype=int)
    for link in links:
        if link.status is LinkStatus.OK:
            n_links[link.scan_i] += 1
            n_links[link.scan_j] += 1
    sigma = result.sigma_position_m * 1000.0
    sigma_rot = np.degrees(np.sqrt(np.maximum(np.diagonal(result.cov_xi[:, 3:, 3:], axis1=1, axis2=2), 0))) * 1000
    rows = []
    for k, s in enumerate(stations):
        pose = result.poses[k]
        rows.append({
            "station": s.name, "t": s.t_s, "t_start": s.t_start_s, "t_end": s.t_end_s,
            "x": pose.t_xyz[0], "y": pose.t_xyz[1], "z": pose.t_xyz[2],
            "qw": pose.quat_wxyz[0], "qx": pose.quat_wxyz[1], "qy": pose.quat_wxyz[2], "qz": pose.quat_wxyz[3],
            "sx_mm": sigma[k, 0], "sy_mm": sigma[k, 1], "sz_mm": sigma[k, 2],
            "s3d_mm": float(np.linalg.norm(sigma[k])), "n_points": s.n_points, "n_planes": len(planes[k]),
            "n_links": int(n_links[k]), "srx_mdeg": sigma_rot[k, 0], "sry_mdeg": sigma_rot[k, 1],
            "srz_mdeg": sigma_rot[k, 2], "kind": s.kind.value, "fixed": bool(result.fixed[k]),
        })  # fmt: skip
    return rows


def format_stations_csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(STATIONS_HEADER)
    for r in rows:
        writer.writerow([
            r["station"], _fmt(r["t"], 6), _fmt(r["t_start"], 6), _fmt(r["t_end"], 6),
            f"{r['x']:.6f}", f"{r['y']:.6f}", f"{r['z']:.6f}",
            f"{r['qw']:.9f}", f"{r['qx']:.9f}", f"{r['qy']:.9f}", f"{r['qz']:.9f}",
            f"{r['sx_mm']:.3f}", f"{r['sy_mm']:.3f}", f"{r['sz_mm']:.3f}", f"{r['s3d_mm']:.3f}",
            r["n_points"], r["n_planes"], r["n_links"],
        ])  # fmt: skip
    return buf.getvalue()


def links_table(links: Sequence[Link], result: BlockResult | None) -> list[dict[str, Any]]:
    """One row per pairwise link with its figures (and its test in the block adjustment)."""
    block_tests = {}
    if result is not None:
        for t in result.tests:
            if t.kind is ObservationKind.PLANES:
                block_tests[(t.i, t.j)] = t
    rows = []
    for link in links:
        sig = np.sqrt(np.maximum(np.diag(link.cov_xi), 0.0))
        test = block_tests.get((link.scan_i, link.scan_j))
        rows.append({
            "scan_i": link.scan_i, "scan_j": link.scan_j, "status": link.status.value, "dt_s": link.dt_s,
            "n_matches": len(link.matches), "n_rejected_matches": len(link.rejected),
            "n_directions": link.n_directions, "rank": link.rank,
            "tx": link.T_i_j.t_xyz[0], "ty": link.T_i_j.t_xyz[1], "tz": link.T_i_j.t_xyz[2],
            "qw": link.T_i_j.quat_wxyz[0], "qx": link.T_i_j.quat_wxyz[1], "qy": link.T_i_j.quat_wxyz[2],
            "qz": link.T_i_j.quat_wxyz[3],
            "stx_mm": sig[0] * 1e3, "sty_mm": sig[1] * 1e3, "stz_mm": sig[2] * 1e3,
            "srx_mdeg": math.degrees(sig[3]) * 1e3, "sry_mdeg": math.degrees(sig[4]) * 1e3,
            "srz_mdeg": math.degrees(sig[5]) * 1e3,
            "sigma0": link.sigma0, "redundancy": link.redundancy,
            "global_test": "passed" if link.global_test_passed else "failed",
            "max_normalised_residual": link.max_normalised_residual,
            "block_statistic": test.statistic if test else math.nan,
            "block_normalised": test.normalised if test else math.nan,
            "block_rejected": bool(test.rejected) if test else False,
        })  # fmt: skip
    return rows


def format_links_csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(LINKS_HEADER)
    for r in rows:
        writer.writerow([_fmt(r[k], 9) if isinstance(r[k], float) else r[k] for k in LINKS_HEADER])
    return buf.getvalue()


PLANES_HEADER = ["station", "plane", "nx", "ny", "nz", "d_m", "cx", "cy", "cz", "area_m2", "n_points", "rms_mm",
                 "s_tilt_u_mdeg", "s_tilt_v_mdeg", "s_d_mm"]


def format_planes_csv(stations: Sequence[Station], planes: Sequence[tuple[Plane, ...]]) -> str:
    """One row per detected plane, in its scan's frame (normal towards the scanner)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(PLANES_HEADER)
    for station, found in zip(stations, planes, strict=True):
        for p in found:
            s = np.sqrt(np.maximum(np.diag(p.cov_uvd), 0.0))
            writer.writerow([station.name, p.plane_id, *(f"{v:.9f}" for v in p.normal), f"{p.d_m:.6f}",
                             *(f"{v:.6f}" for v in p.centroid_xyz), f"{p.area_m2:.3f}", p.n_points,
                             f"{p.rms_m * 1e3:.3f}", f"{math.degrees(s[0]) * 1e3:.3f}",
                             f"{math.degrees(s[1]) * 1e3:.3f}", f"{s[2] * 1e3:.4f}"])
    return buf.getvalue()


def before_after(initial: Pose, adjusted: Pose, use: np.ndarray) -> dict[str, Any]:
    """Rigid transformation of the initial station positions onto the adjusted ones and the
    residual gaps (METHOD.md step 10: the seed's 'gaps before vs after')."""
    src, dst = initial.t_xyz[use], adjusted.t_xyz[use]
    if len(src) < 3:
        return {"type": "rigid", "gaps_mm": _stats(np.zeros(0))}
    R, t = rigid_fit(src, dst)
    gaps = np.linalg.norm(dst - (src @ R.T + t), axis=1) * 1000.0
    return {
        "type": "rigid",
        "rotation_mdeg": float(np.degrees(np.linalg.norm(quat_to_rotvec(matrix_to_quat(R)))) * 1e3),
        "translation_mm": (t * 1000.0).tolist(),
        "gaps_mm": _stats(gaps),
        "gap_per_station_mm": gaps.tolist(),
    }


def before_after_runs(initial: Pose, adjusted: Pose, use: np.ndarray, runs: np.ndarray) -> dict[str, Any]:
    """:func:`before_after` with one rigid transformation per run (``runs``: each station's run).
    Several runs of one project start in frames centimetres apart, which one common transformation
    would count as gaps. With one run exactly :func:`before_after`; with several, ``runs`` lists
    each run's transformation and gaps, and ``gap_per_station_mm`` holds every used station's gap."""
    labels = np.unique(runs[use])
    if len(labels) <= 1:
        return before_after(initial, adjusted, use)
    gaps = np.full(len(runs), np.nan)
    per_run = []
    for label in labels:
        own = use & (runs == label)
        part = before_after(initial, adjusted, own)
        if "gap_per_station_mm" in part:
            gaps[own] = part.pop("gap_per_station_mm")
        per_run.append(part)
    return {"type": "rigid per run", "gaps_mm": _stats(gaps[use]), "gap_per_station_mm": gaps[use].tolist(),
            "runs": per_run}


def build_report(
    *,
    inputs: dict[str, Any],
    config_toml: str,
    stations: Sequence[Station],
    planes: Sequence[tuple[Plane, ...]],
    links: Sequence[Link],
    n_candidate_pairs: int,
    result: BlockResult,
    slicing: dict[str, Any],
    correction_mm: FloatArray,
    correction_mdeg: FloatArray,
    datum: str,
    alpha: float,
    timings_s: dict[str, float],
    trajectory_plot: dict[str, list[float]],
    drift_rates: Any = None,
) -> dict[str, Any]:
    """The content of ``report.json``."""
    rows = stations_table(stations, result, planes, links)
    free = ~result.fixed
    quasi = np.array([s.kind is ScanKind.QUASI_STATIC for s in stations])
    s3d = np.array([r["s3d_mm"] for r in rows])
    srot = np.array([max(r["srx_mdeg"], r["sry_mdeg"], r["srz_mdeg"]) for r in rows])
    status_counts = {s.value: sum(link.status is s for link in links) for s in LinkStatus}
    rejected = [
        {"kind": t.kind.value, "i": t.i, "j": t.j} for t in result.tests if t.rejected
    ]
    tests_by_kind: dict[str, list[float]] = {}
    for t in result.tests:
        if not t.rejected and np.isfinite(t.normalised):
            tests_by_kind.setdefault(t.kind.value, []).append(t.normalised)
    return {
        "schema_version": REPORT_SCHEMA_VERSION,
        "kinreg_version": kinreg.__version__,
        "inputs": inputs,
        "config_toml": config_toml,
        "slicing": slicing,
        "adjustment": {
            "datum": datum,
            "sigma0": result.sigma0,
            "redundancy": result.redundancy,
            "alpha": alpha,
            "global_test_passed": result.global_test_passed,
            "variance_factor_applied": result.variance_factor,
            "variance_components": result.variance_components,
            "iterations": result.iterations,
            "drift_rates": None if drift_rates is None else {
                "estimated": drift_rates.estimated,
                "pos_mm_per_s": (np.asarray(drift_rates.pos_m_per_s) * 1000).tolist(),
                "rot_mdeg_per_s": (np.degrees(drift_rates.rot_rad_per_s) * 1000).tolist(),
            },
            "n_observations": len(result.tests),
            "rejected_observations": rejected,
            "normalised_residuals": tests_by_kind,
        },
        "stations": {
            "n": len(stations),
            "n_fixed": int(np.count_nonzero(result.fixed)),
            "position_sigma_mm": _stats(s3d[free]),
            "orientation_sigma_mdeg": _stats(srot[free]),
            "correction_mm": _stats(correction_mm),
            "correction_mdeg": _stats(correction_mdeg),
            "rows": rows,
        },
        "before_after": before_after_runs(result.poses_initial, result.poses, quasi,
                                          np.array([s.run for s in stations])),
        "links": {
            "n_candidate_pairs": n_candidate_pairs,
            "n_links": len(links),
            "by_status": status_counts,
            "per_scan": len(links) / max(len(stations), 1),
            "sigma0": _stats(np.array([link.sigma0 for link in links if link.status is LinkStatus.OK])),
            "n_matches": int(sum(len(link.matches) for link in links)),
            "n_rejected_matches": int(sum(len(link.rejected) for link in links)),
            "rank_histogram": {str(r): sum(link.rank == r for link in links) for r in range(7)},
            "pairs": [[link.scan_i, link.scan_j, link.status.value] for link in links],
        },
        "timings_s": timings_s,
        "trajectory_plot": trajectory_plot,
    }


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _clean(value: Any) -> Any:
    """NaN and inf are not JSON: write them as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        return _clean(value.item())
    return value


def write_text(path: Path, text: str, overwrite: bool = True) -> None:
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_report_json(path: Path, report: dict[str, Any]) -> None:
    write_text(path, json.dumps(_clean(report), indent=1, default=_json_default) + "\n")
