"""The control- and check-point section of ``report.json``, ``report.html`` and ``control_points.csv``.

Control points (``--control``) are observations of the adjustment: per point the corrected
trajectory's reference point at the stand-still minus the surveyed coordinates (dX, dY, dZ,
horizontal, vertical), the normalised residual of its observation and the test decision of the
block's data snooping. Check points (``--check``) never enter the adjustment: the same
differences, for the corrected and for the input trajectory, with their RMS and maximum, and the
USIBD Level of Accuracy class they support. A target in a static scan (``kind`` "static target")
is its scan-frame coordinates on the static station's adjusted pose (and, for "input", on the
pose the E57 file gave) minus the surveyed coordinates.

LOA bands (USIBD Level of Accuracy Specification Guide v3.0, 2019), by the 2-sigma (95 %) upper
range: LOA50 0-1 mm, LOA40 1-5 mm, LOA30 5-15 mm, LOA20 15-50 mm, LOA10 above 50 mm. kinreg takes
sigma as the RMS of the check points' 3D differences (conservative: the guide states the band per
measured point), so the class is that of ``2 x RMS 3D``.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kinreg.estimate.control import Assignment, static_station_index
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.drift import DriftRates
from kinreg.estimate.network import Network
from kinreg.estimate.snooping import chi2_quantile
from kinreg.geometry import FloatArray, Pose
from kinreg.types import BlockResult, Station, Trajectory

# (class, upper edge of the 2-sigma range [mm]); above the last edge: LOA10.
LOA_BANDS_MM = (("LOA50", 1.0), ("LOA40", 5.0), ("LOA30", 15.0), ("LOA20", 50.0))
LOA_SOURCE = "USIBD Level of Accuracy (LOA) Specification Guide v3.0, 2019"

# "kind": "stand-still" (the unit stood on the point) or "static target" (a target in the static
# scan named in "scan"); "tied": how a stand-still point was tied ("times given" in the file or
# "stand-still found" in the trajectory), "still_s" its stand-still's duration and "scatter_mm"
# the reference point's RMS scatter over it. Each added at the end so that readers of the
# earlier columns keep working.
CONTROL_POINTS_HEADER = ("name", "role", "t", "x", "y", "z", "sigma_mm", "dx_mm", "dy_mm", "dz_mm", "horizontal_mm",
                         "vertical_mm", "d3d_mm", "normalised", "decision", "input_d3d_mm", "kind", "scan", "tied",
                         "still_s", "scatter_mm")


def loa_class(two_sigma_mm: float) -> str:
    """The USIBD LOA class of a 2-sigma range [mm] (edges belong to the better class).

    >>> loa_class(0.8), loa_class(5.0), loa_class(12.0), loa_class(51.0)
    ('LOA50', 'LOA40', 'LOA30', 'LOA10')
    """
    for name, edge in LOA_BANDS_MM:
        if two_sigma_mm <= edge:
            return name
    return "LOA10"


def positions_at(trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection] | None,
                 assignment: Assignment, reference_point_m: FloatArray) -> FloatArray:
    """The reference point (n, 3) at each assigned point's stand-still time: on the input
    trajectories, or on the corrected ones (``corrections``, one per run). Stand-still points only."""
    out = []
    for still in assignment.stand_stills:
        traj = trajectories[still.run]
        stamp = np.array([still.t_s])
        row = Trajectory(stamp, traj.pose_at(stamp), traj.source)
        if corrections is not None:
            row = corrections[still.run].apply_to_trajectory(row)
        out.append(row.poses.apply(np.asarray(reference_point_m)[None, :])[0])
    return np.array(out).reshape(-1, 3)


def target_positions(stations: Sequence[Station], poses: Pose | None, assignment: Assignment) -> FloatArray:
    """The targets in static scans (n, 3): each target's scan-frame coordinates on its static
    station's adjusted pose (``poses``, all stations), or on its initial pose (``None``)."""
    out = []
    for target in assignment.targets:
        k = static_station_index(stations, target.scan)
        T = stations[k].T_obj_scan if poses is None else poses[k]
        out.append(T.apply(np.asarray(target.scan_xyz)[None, :])[0])
    return np.array(out).reshape(-1, 3)


def _tied(assignment: Assignment) -> list[dict[str, Any]]:
    """How each point was tied, as :class:`_Points` orders them: a stand-still point by the times
    the file gave or by the stand-still found in the trajectory, with its interval, duration and
    scatter; a target in a static scan by its scan."""
    rows: list[dict[str, Any]] = [
        {"tied": "stand-still found" if s.detected else "times given", "still_start": s.t_start_s,
         "still_end": s.t_end_s, "still_s": s.duration_s, "scatter_mm": s.scatter_mm}
        for s in assignment.stand_stills]
    return rows + [{"tied": "static scan"} for _ in assignment.targets]


@dataclass(frozen=True, eq=False)
class _Points:
    """Every point of an assignment, stand-still points then targets: names, surveyed coordinates
    (n, 3), sigma [m], time (nan for targets), how it was observed and the static scan (or "")."""

    names: tuple[str, ...]
    xyz: FloatArray
    sigma_m: FloatArray
    t_s: FloatArray
    kind: tuple[str, ...]
    scan: tuple[str, ...]


def _points(assignment: Assignment) -> _Points:
    targets = assignment.targets
    return _Points(assignment.all_names,
                   np.vstack([assignment.xyz.reshape(-1, 3), np.array([t.xyz for t in targets]).reshape(-1, 3)]),
                   np.concatenate([assignment.sigma_m, [t.sigma_m for t in targets]]),
                   np.array([s.t_s for s in assignment.stand_stills] + [math.nan] * len(targets)),
                   ("stand-still",) * len(assignment.names) + ("static target",) * len(targets),
                   ("",) * len(assignment.names) + tuple(t.scan_name for t in targets))


def _positions(assignment: Assignment, stations: Sequence[Station], result: BlockResult | None,
               trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection] | None,
               reference_point_m: FloatArray) -> FloatArray:
    """Every point's position (n, 3) as :class:`_Points` orders them: corrected (``result`` and
    ``corrections``) or input (both ``None``)."""
    return np.vstack([positions_at(trajectories, corrections, assignment, reference_point_m),
                      target_positions(stations, None if result is None else result.poses, assignment)])


def _differences(names: Sequence[str], d_m: FloatArray) -> list[dict[str, Any]]:
    d = d_m * 1000.0
    return [{"name": n, "dx_mm": float(v[0]), "dy_mm": float(v[1]), "dz_mm": float(v[2]),
             "horizontal_mm": float(np.hypot(v[0], v[1])), "vertical_mm": float(v[2]),
             "d3d_mm": float(np.linalg.norm(v))} for n, v in zip(names, d, strict=True)]


def _summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ("dx_mm", "dy_mm", "dz_mm", "horizontal_mm", "vertical_mm", "d3d_mm"):
        v = np.array([r[key] for r in rows], dtype=np.float64)
        out[key] = {"rms": float(np.sqrt(np.mean(v**2))) if len(v) else math.nan,
                    "max": float(np.max(np.abs(v))) if len(v) else math.nan}
    return out


def control_section(network: Network, result: BlockResult, rates: DriftRates, assignment: Assignment,
                    trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection],
                    reference_point_m: FloatArray, alpha: float) -> dict[str, Any]:
    """``report.json`` ``control``: one row per control point used (stand-still points, then targets
    in static scans), and the points left out."""
    ties = {t.name: (k, t) for k, t in enumerate(network.datum.controls)}
    screened = dict(network.datum.rejected_controls)
    indices = network.control_indices(rates)
    tests = {t.index: t for t in result.tests}
    points = _points(assignment)
    corrected = _positions(assignment, network.stations, result, trajectories, corrections, reference_point_m)
    original = _positions(assignment, network.stations, None, trajectories, None, reference_point_m)
    rows = _differences(points.names, corrected - points.xyz)
    for n, (row, tied) in enumerate(zip(rows, _tied(assignment), strict=True)):
        row.update(tied)
        row.update({"role": "control", "kind": points.kind[n], "scan": points.scan[n],
                    "x": float(points.xyz[n, 0]), "y": float(points.xyz[n, 1]), "z": float(points.xyz[n, 2]),
                    "sigma_mm": float(points.sigma_m[n] * 1000.0),
                    "input_d3d_mm": float(np.linalg.norm(original[n] - points.xyz[n]) * 1000.0)})
        if row["name"] in screened:  # rejected before the last pass: not in the network
            row.update({"t": float(points.t_s[n]), "station": points.scan[n], "normalised": screened[row["name"]],
                        "decision": "rejected"})
            continue
        k, tie = ties[row["name"]]
        test = tests.get(indices[k])
        decision, normalised = "not tested", math.nan
        if test is not None and test.rejected:
            decision = "rejected"
        elif test is not None and np.isfinite(test.statistic):
            normalised = test.normalised
            decision = "accepted" if test.statistic <= chi2_quantile(1.0 - alpha, test.dof) else "suspect"
        row.update({"t": tie.t_s, "station": network.stations[tie.station].name, "normalised": normalised,
                    "decision": decision})
    return {"n": len(rows), "rows": rows, "rejected": [r["name"] for r in rows if r["decision"] == "rejected"],
            "summary": _summary([r for r in rows if r["decision"] != "rejected"]),
            "left_out": list(assignment.problems)}


def check_section(assignment: Assignment, trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection],
                  reference_point_m: FloatArray, stations: Sequence[Station] = (),
                  result: BlockResult | None = None) -> dict[str, Any]:
    """``report.json`` ``check``: per check point the corrected and the input trajectory minus the
    surveyed coordinates, their RMS and maximum, and the LOA class of the corrected differences.
    A target in a static scan is its scan-frame coordinates on the static station's adjusted pose
    (``result``; ``stations`` are the network's) and on its initial one."""
    if assignment.targets and result is None:
        raise ValueError("check targets in static scans need the stations and the block result")
    points = _points(assignment)
    corrected = _differences(points.names, _positions(assignment, stations, result, trajectories, corrections,
                                                      reference_point_m) - points.xyz)
    original = _differences(points.names, _positions(assignment, stations, None, trajectories, None,
                                                     reference_point_m) - points.xyz)
    for n, (row, before, tied) in enumerate(zip(corrected, original, _tied(assignment), strict=True)):
        row.update(tied)
        row.update({"role": "check", "kind": points.kind[n], "scan": points.scan[n], "t": float(points.t_s[n]),
                    "x": float(points.xyz[n, 0]), "y": float(points.xyz[n, 1]), "z": float(points.xyz[n, 2]),
                    "sigma_mm": float(points.sigma_m[n] * 1000.0), "normalised": math.nan, "decision": "",
                    "input_d3d_mm": before["d3d_mm"]})
    summary, summary_input = _summary(corrected), _summary(original)
    two_sigma = 2.0 * summary["d3d_mm"]["rms"]
    return {"n": len(corrected), "rows": corrected, "input_rows": original, "summary": summary,
            "summary_input": summary_input,
            "loa": {"class": loa_class(two_sigma), "two_sigma_mm": two_sigma,
                    "input_class": loa_class(2.0 * summary_input["d3d_mm"]["rms"]),
                    "basis": "2 x RMS of the 3D differences", "bands_mm": dict(LOA_BANDS_MM), "source": LOA_SOURCE},
            "left_out": list(assignment.problems)}


def format_control_points_csv(report: dict[str, Any]) -> str:
    """``control_points.csv``: the control points' rows, then the check points'."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CONTROL_POINTS_HEADER)
    rows = (report.get("control") or {}).get("rows", []) + (report.get("check") or {}).get("rows", [])
    for r in rows:
        writer.writerow([_cell(r.get(c), c) for c in CONTROL_POINTS_HEADER])
    return buf.getvalue()


def _cell(value: Any, column: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, float):
        return f"{value:.6f}" if column in ("t",) else f"{value:.4f}" if column in ("x", "y", "z") else f"{value:.3f}"
    return str(value)


def control_html(report: dict[str, Any]) -> str:
    """The control- and check-point tables of ``report.html`` (empty without either)."""
    from kinreg.report.text import _esc, _fmt, _tag

    parts = []
    columns = ("name", "observed", "dx_mm", "dy_mm", "dz_mm", "horizontal_mm", "vertical_mm", "d3d_mm", "tied")

    def cell(r: dict[str, Any], c: str) -> str:
        if c == "observed":  # a stand-still, or a target in the static scan named
            return _esc(str(r.get("kind", "")) + (f" {r['scan']}" if r.get("scan") else ""))
        if c == "tied":  # how: the file's times or the stand-still found, its duration and scatter
            if "still_s" not in r:
                return _esc(str(r.get("tied", "")))
            return _esc(f"{r.get('tied', '')}: {_fmt(r.get('still_start'), 2)}-{_fmt(r.get('still_end'), 2)} s "
                        f"({_fmt(r.get('still_s'), 1)} s, scatter {_fmt(r.get('scatter_mm'), 1)} mm)")
        return _esc(str(r.get(c, ""))) if c in ("name", "decision") else _fmt(r.get(c), 2)

    def table(rows: Sequence[dict[str, Any]], extra: Sequence[str]) -> str:
        head = _tag("tr", "".join(_tag("th", _esc(c)) for c in (*columns, *extra)))
        body = "".join(_tag("tr", "".join(_tag("td", cell(r, c)) for c in (*columns, *extra))) for r in rows)
        return _tag("table", head + body)

    control = report.get("control")
    if isinstance(control, dict):
        rejected = control.get("rejected") or []
        targets = any(r.get("kind") == "static target" for r in control.get("rows") or [])
        text = (f"{control.get('n', 0)} control points; corrected trajectory "
                + ("(for a static target: the target on its adjusted static scan) " if targets else "")
                + "minus surveyed [mm]; normalised residual \u221a(T/dof) of its observation and the data-snooping "
                "decision"
                + (f"; rejected: {', '.join(rejected)}" if rejected else ""))
        parts.append(_tag("h3", "Control points") + _tag("p", _esc(text))
                     + table(control.get("rows") or [], ("normalised", "decision")))
        parts += [_tag("p", _esc(line)) for line in control.get("left_out") or []]
    check = report.get("check")
    if isinstance(check, dict):
        s, s0, loa = check.get("summary", {}), check.get("summary_input", {}), check.get("loa", {})
        text = (f"{check.get('n', 0)} check points (not in the adjustment): 3D RMS "
                f"{_fmt(s.get('d3d_mm', {}).get('rms'), 1)} mm, max {_fmt(s.get('d3d_mm', {}).get('max'), 1)} mm "
                f"(input trajectory: RMS {_fmt(s0.get('d3d_mm', {}).get('rms'), 1)} mm, max "
                f"{_fmt(s0.get('d3d_mm', {}).get('max'), 1)} mm); supports {loa.get('class', '')} "
                f"(2\u03c3 = {_fmt(loa.get('two_sigma_mm'), 1)} mm; input {loa.get('input_class', '')}; bands: "
                f"{loa.get('source', LOA_SOURCE)})")
        parts.append(_tag("h3", "Check points") + _tag("p", _esc(text)) + table(check.get("rows") or [], ()))
        parts += [_tag("p", _esc(line)) for line in check.get("left_out") or []]
    if not parts:
        return ""
    return _tag("h2", "Control and check points") + _tag("div", "".join(parts), class_="card")
