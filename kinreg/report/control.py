"""The control- and check-point section of ``report.json``, ``report.html`` and ``control_points.csv``.

Control points (``--control``) are observations of the adjustment: per point the corrected
trajectory's reference point at the stand-still minus the surveyed coordinates (dX, dY, dZ,
horizontal, vertical), the normalised residual of its observation and the test decision of the
block's data snooping. Check points (``--check``) never enter the adjustment: the same
differences, for the corrected and for the input trajectory, with their RMS and maximum, and the
USIBD Level of Accuracy class they support.

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
from typing import Any

import numpy as np
from scipy import stats

from kinreg.estimate.control import Assignment
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.drift import DriftRates
from kinreg.estimate.network import Network
from kinreg.geometry import FloatArray
from kinreg.types import BlockResult, Trajectory

# (class, upper edge of the 2-sigma range [mm]); above the last edge: LOA10.
LOA_BANDS_MM = (("LOA50", 1.0), ("LOA40", 5.0), ("LOA30", 15.0), ("LOA20", 50.0))
LOA_SOURCE = "USIBD Level of Accuracy (LOA) Specification Guide v3.0, 2019"

CONTROL_POINTS_HEADER = ("name", "role", "t", "x", "y", "z", "sigma_mm", "dx_mm", "dy_mm", "dz_mm", "horizontal_mm",
                         "vertical_mm", "d3d_mm", "normalised", "decision", "input_d3d_mm")


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
    trajectories, or on the corrected ones (``corrections``, one per run)."""
    out = []
    for still in assignment.stand_stills:
        traj = trajectories[still.run]
        stamp = np.array([still.t_s])
        row = Trajectory(stamp, traj.pose_at(stamp), traj.source)
        if corrections is not None:
            row = corrections[still.run].apply_to_trajectory(row)
        out.append(row.poses.apply(np.asarray(reference_point_m)[None, :])[0])
    return np.array(out).reshape(-1, 3)


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
    """``report.json`` ``control``: one row per control point used, and the points left out."""
    ties = {t.name: (k, t) for k, t in enumerate(network.datum.controls)}
    screened = dict(network.datum.rejected_controls)
    indices = network.control_indices(rates)
    tests = {t.index: t for t in result.tests}
    corrected = positions_at(trajectories, corrections, assignment, reference_point_m)
    original = positions_at(trajectories, None, assignment, reference_point_m)
    rows = _differences(assignment.names, corrected - assignment.xyz)
    for n, row in enumerate(rows):
        if row["name"] in screened:  # rejected before the last pass: not in the network
            row.update({"role": "control", "t": assignment.stand_stills[n].t_s, "station": "",
                        "x": float(assignment.xyz[n, 0]), "y": float(assignment.xyz[n, 1]),
                        "z": float(assignment.xyz[n, 2]), "sigma_mm": float(assignment.sigma_m[n] * 1000.0),
                        "normalised": screened[row["name"]], "decision": "rejected",
                        "input_d3d_mm": float(np.linalg.norm(original[n] - assignment.xyz[n]) * 1000.0)})
            continue
        k, tie = ties[row["name"]]
        test = tests.get(indices[k])
        decision, normalised = "not tested", math.nan
        if test is not None and test.rejected:
            decision = "rejected"
        elif test is not None and np.isfinite(test.statistic):
            normalised = test.normalised
            decision = "accepted" if test.statistic <= stats.chi2.ppf(1.0 - alpha, test.dof) else "suspect"
        row.update({"role": "control", "t": tie.t_s, "station": network.stations[tie.station].name,
                    "x": float(assignment.xyz[n, 0]), "y": float(assignment.xyz[n, 1]),
                    "z": float(assignment.xyz[n, 2]), "sigma_mm": float(assignment.sigma_m[n] * 1000.0),
                    "normalised": normalised, "decision": decision,
                    "input_d3d_mm": float(np.linalg.norm(original[n] - assignment.xyz[n]) * 1000.0)})
    return {"n": len(rows), "rows": rows, "rejected": [r["name"] for r in rows if r["decision"] == "rejected"],
            "summary": _summary([r for r in rows if r["decision"] != "rejected"]),
            "left_out": list(assignment.problems)}


def check_section(assignment: Assignment, trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection],
                  reference_point_m: FloatArray) -> dict[str, Any]:
    """``report.json`` ``check``: per check point the corrected and the input trajectory minus the
    surveyed coordinates, their RMS and maximum, and the LOA class of the corrected differences."""
    corrected = _differences(assignment.names,
                             positions_at(trajectories, corrections, assignment, reference_point_m) - assignment.xyz)
    original = _differences(assignment.names,
                            positions_at(trajectories, None, assignment, reference_point_m) - assignment.xyz)
    for n, (row, before) in enumerate(zip(corrected, original, strict=True)):
        row.update({"role": "check", "t": assignment.stand_stills[n].t_s, "x": float(assignment.xyz[n, 0]),
                    "y": float(assignment.xyz[n, 1]), "z": float(assignment.xyz[n, 2]),
                    "sigma_mm": float(assignment.sigma_m[n] * 1000.0), "normalised": math.nan, "decision": "",
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
    columns = ("name", "dx_mm", "dy_mm", "dz_mm", "horizontal_mm", "vertical_mm", "d3d_mm")

    def table(rows: Sequence[dict[str, Any]], extra: Sequence[str]) -> str:
        head = _tag("tr", "".join(_tag("th", _esc(c)) for c in (*columns, *extra)))
        body = "".join(_tag("tr", "".join(
            _tag("td", _esc(str(r.get(c, "")) if c in ("name", "decision") else _fmt(r.get(c), 2)))
            for c in (*columns, *extra))) for r in rows)
        return _tag("table", head + body)

    control = report.get("control")
    if isinstance(control, dict):
        rejected = control.get("rejected") or []
        text = (f"{control.get('n', 0)} control points; corrected trajectory minus surveyed [mm]; normalised "
                "residual \u221a(T/dof) of its observation and the data-snooping decision"
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
