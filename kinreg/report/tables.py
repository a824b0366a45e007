"""Reports of a processed run: ``stations.csv``, ``links.csv``, ``report.json`` (METHOD.md section 6).

``report.json`` follows :data:`REPORT_SCHEMA_VERSION`; bump it when a key is renamed or removed
or its meaning changes (adding keys does not need a bump). Units: mm and mdeg in the report.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from kinreg.estimate.plane_nodes import PlaneNodes
from kinreg.io.atomic import atomic_path
from kinreg.types import (
    SCAN_PLANE_RANK,
    BlockResult,
    Link,
    LinkStatus,
    ObservationKind,
    ObservationTest,
    Plane,
    Station,
)

# METHOD.md section 6: fixed names and order, other tools read them.
STATIONS_HEADER = ["station", "t", "t_start", "t_end", "x", "y", "z", "qw", "qx", "qy", "qz",
                   "sx_mm", "sy_mm", "sz_mm", "s3d_mm", "n_points", "n_planes", "n_links"]
LINKS_HEADER = ["scan_i", "scan_j", "status", "dt_s", "n_matches", "n_rejected_matches", "n_directions", "rank",
                "tx", "ty", "tz", "qw", "qx", "qy", "qz", "stx_mm", "sty_mm", "stz_mm", "srx_mdeg", "sry_mdeg",
                "srz_mdeg", "sigma0", "redundancy", "global_test", "max_normalised_residual", "block_statistic",
                "block_normalised", "block_rejected"]


def _fmt(value: float, digits: int) -> str:
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def links_per_station(n_stations: int, links: Sequence[Link]) -> np.ndarray:
    """How many ``ok`` links each station has."""
    n_links = np.zeros(n_stations, dtype=int)
    for link in links:
        if link.status is LinkStatus.OK:
            n_links[link.scan_i] += 1
            n_links[link.scan_j] += 1
    return n_links


def stations_table(stations: Sequence[Station], result: BlockResult, planes: Sequence[tuple[Plane, ...]],
                   links: Sequence[Link]) -> list[dict[str, Any]]:
    """One row per station with the columns of ``stations.csv`` (plus orientation sigmas)."""
    n_links = links_per_station(len(stations), links)
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


def links_table(links: Sequence[Link], result: BlockResult | None,
                plane_nodes: PlaneNodes | None = None) -> list[dict[str, Any]]:
    """One row per pairwise link with its figures (and its test in the block adjustment). Where the
    block adjusted the physical planes (``plane_nodes``) instead of the links, a link's block figures
    are those of its worst matched scan plane (its statistic is not given: no observation was the
    link's own), and it counts as rejected where one of its planes was."""
    block_tests = {}
    if result is not None:
        for t in result.tests:
            if t.kind is ObservationKind.PLANES:
                block_tests[(t.i, t.j)] = t
    by_plane = _plane_tests(result, plane_nodes) if result is not None and plane_nodes is not None else {}
    rows = []
    for link in links:
        sig = np.sqrt(np.maximum(np.diag(link.cov_xi), 0.0))
        test = block_tests.get((link.scan_i, link.scan_j))
        if by_plane:
            seen = [by_plane[key] for m in link.matches for key in ((link.scan_i, m.plane_i), (link.scan_j, m.plane_j))
                    if key in by_plane]
            worst = max(seen, key=lambda t: t.normalised if np.isfinite(t.normalised) else -1.0, default=None)
            test = None if worst is None else replace(worst, statistic=math.nan,
                                                      rejected=any(t.rejected for t in seen))
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


def _plane_tests(result: BlockResult, nodes: PlaneNodes) -> dict[tuple[int, int], ObservationTest]:
    """The block's test of each scan plane ``(station, plane_id)`` against its physical plane."""
    out = {}
    taken = [0] * len(nodes)  # the observations of a physical plane come in its members' order
    for t in result.tests:
        if SCAN_PLANE_RANK.get(t.kind) == 2 and 0 <= t.j < len(nodes) and taken[t.j] < len(nodes.clusters[t.j]):
            k, pid = nodes.clusters[t.j][taken[t.j]]
            taken[t.j] += 1
            if k == t.i:
                out[(k, pid)] = t
    return out


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


def write_text(path: Path, text: str, overwrite: bool = True) -> None:
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")


