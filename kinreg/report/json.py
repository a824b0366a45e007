"""``report.json``: the accuracy report of ``kinreg process``, assembled in one place."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kinreg._version import __version__
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.drift import DriftRates
from kinreg.estimate.network import Network
from kinreg.estimate.reference import as_built
from kinreg.estimate.snooping import residual_size
from kinreg.geometry import FloatArray, Pose, matrix_to_quat, quat_to_rotvec
from kinreg.report.tables import links_per_station, stations_table, write_text
from kinreg.survey import ReferencePlanes
from kinreg.types import BlockResult, LinkStatus, ObservationTest, Plane, ScanKind, TrajectoryJump

REPORT_SCHEMA_VERSION = 1


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
    network: Network,
    planes: Sequence[tuple[Plane, ...]],
    n_candidate_pairs: int,
    result: BlockResult,
    drift_rates: DriftRates | None,
    slicing: dict[str, Any],
    corrections: Sequence[DriftCorrection],
    jumps: Sequence[Sequence[TrajectoryJump]],
    references: ReferencePlanes | None,
    stage_cache: dict[str, dict[str, int]],
    alpha: float,
    timings_s: dict[str, float],
    trajectory_plot: dict[str, list[float]],
    misfits: Sequence[ObservationTest],
    cloud_views: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The content of ``report.json``: ``jumps`` and ``corrections`` one per run, ``timings_s``
    the stage timings (the dictionary itself: a stage timed after this call still shows);
    ``misfits`` the trajectory's links beyond their model
    (:func:`~kinreg.estimate.snooping.trajectory_misfits`, found with the adjustment)."""
    stations, links, datum = network.stations, network.links, network.datum.description
    shift_m, rotation_rad = (np.concatenate(parts) for parts in zip(*(c.magnitude() for c in corrections), strict=True))
    correction_mm, correction_mdeg = shift_m * 1000.0, np.degrees(rotation_rad) * 1000.0
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
        "kinreg_version": __version__,
        "inputs": inputs,
        "config_toml": config_toml,
        "slicing": slicing,
        "adjustment": {
            "status": _status(result),
            "failure": result.failure,
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
                "coupling": drift_rates.coupling,
                "regime": drift_rates.regime,
                "correlation_s": list(drift_rates.correlation_s),
            },
            "n_observations": len(result.tests),
            "rejected_observations": rejected,
            "normalised_residuals": tests_by_kind,
            # the trajectory's links beyond their model (never rejected: a wrong match or a jump)
            "trajectory_misfits": [{"stations": [int(t.i), int(t.j)], "normalised": float(t.normalised),
                                    **_residual_figures(t)} for t in misfits],
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
            # the model of the planes and the trajectory the links were adjusted with
            "model": network.link_model.as_dict(),
        },
        "timings_s": timings_s,
        "trajectory_plot": trajectory_plot,
        "trajectory_jumps": [
            {"t": j.t_s, "row": j.index, "step_m": j.step_m, "step_deg": j.step_deg,
             "translation_m": j.translation_m.tolist(), "significance": j.significance,
             **({"run": k + 1} if len(jumps) > 1 else {})} for k, run_jumps in enumerate(jumps) for j in run_jumps],
        **({} if references is None else {"reference": {
            "accuracy_m": references.accuracy_m, "n_ties": len(network.datum.ties),
            "planes": as_built(network.datum.ties, result.poses, planes, references)}}),
        "stage_cache": stage_cache,
        **(cloud_views or {}),  # "cloud" and "crs" (kinreg.report.cloud_views)
    }


def _status(result: BlockResult) -> str:
    """``failed`` (no result), ``rejected`` (global test failed: the sigmas are scaled by sigma0), ``passed``."""
    return "failed" if result.failed else ("passed" if result.global_test_passed else "rejected")


def build_failure_report(*, inputs: dict[str, Any], config_toml: str, result: BlockResult, datum: str,
                         alpha: float, network: Network | None = None,
                         planes: Sequence[tuple[Plane, ...]] | None = None) -> dict[str, Any]:
    """``report.json`` of a run whose block adjustment failed: what went in and why it failed,
    and with the ``network`` what a user needs to see why: its links (each with its status) and
    the stations at the trajectory's poses (not adjusted: none of them is a result)."""
    report: dict[str, Any] = {
        "schema_version": REPORT_SCHEMA_VERSION,
        "kinreg_version": __version__,
        "inputs": inputs,
        "config_toml": config_toml,
        "adjustment": {"status": _status(result), "failure": result.failure, "datum": datum,
                       "sigma0": result.sigma0, "redundancy": result.redundancy, "alpha": alpha,
                       "global_test_passed": False, "iterations": result.iterations,
                       "n_observations": len(result.tests)},
    }
    if network is not None:
        links = network.links
        n_links = links_per_station(len(network.stations), links)
        report["stations"] = {"n": len(network.stations), "poses": "the trajectory's (not adjusted)", "rows": [
            {"station": s.name, "kind": s.kind.value, "x": float(s.T_obj_scan.t_xyz[0]),
             "y": float(s.T_obj_scan.t_xyz[1]), "z": float(s.T_obj_scan.t_xyz[2]),
             "n_planes": len(planes[k]) if planes is not None else None, "n_links": int(n_links[k])}
            for k, s in enumerate(network.stations)]}
        report["links"] = {
            "n_links": len(links),
            "by_status": {st.value: sum(link.status is st for link in links) for st in LinkStatus},
            "sigma0": _stats(np.array([link.sigma0 for link in links if np.isfinite(link.sigma0)])),
            "pairs": [[link.scan_i, link.scan_j, link.status.value] for link in links],
            "model": network.link_model.as_dict(),
        }
    return report


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


def write_report_json(path: Path, report: dict[str, Any]) -> None:
    write_text(path, json.dumps(_clean(report), indent=1, default=_json_default) + "\n")


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


def _residual_figures(test: ObservationTest) -> dict[str, float | None]:
    """How far a pose observation's residual moves [mm] and turns [mdeg] a station (None where
    unknown)."""
    size = residual_size(test)
    if size is None:
        return {"moved_mm": None, "turned_mdeg": None}
    return {"moved_mm": 1000.0 * size[0], "turned_mdeg": 1000.0 * float(np.degrees(size[1]))}
