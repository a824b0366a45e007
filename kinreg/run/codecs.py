"""kinreg's types as plain arrays for the stage cache (no pickle), and back: every round trip exact."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from kinreg.estimate.pairwise import LinkModel
from kinreg.geometry import Pose
from kinreg.run.stage_cache import Arrays
from kinreg.types import Link, LinkStatus, Plane, PlaneMatch, ScanKind, ScanWindow, Station


def _f(a: Any, shape: tuple[int, ...] = ()) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).reshape((-1, *shape))


def _offsets(counts: Sequence[int] | np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(np.asarray(counts, dtype=np.int64))]).astype(np.int64)


def planes_to_arrays(planes: Sequence[tuple[Plane, ...]]) -> Arrays:
    """The planes of every scan (``planes[k]`` for scan k) as plain arrays; exact round trip
    with :func:`planes_from_arrays`."""
    flat = [p for scan in planes for p in scan]
    hull_counts = [len(p.hull_xyz) for p in flat]
    return {
        "scan_plane_counts": np.array([len(scan) for scan in planes], dtype=np.int64),
        "scan_id": np.array([p.scan_id for p in flat], dtype=np.int64),
        "plane_id": np.array([p.plane_id for p in flat], dtype=np.int64),
        "normal": _f([p.normal for p in flat], (3,)),
        "d_m": _f([p.d_m for p in flat]),
        "centroid_xyz": _f([p.centroid_xyz for p in flat], (3,)),
        "basis_uv": _f([p.basis_uv for p in flat], (2, 3)),
        "cov_uvd": _f([p.cov_uvd for p in flat], (3, 3)),
        "hull_counts": np.array(hull_counts, dtype=np.int64),
        "hull_xyz": _f(np.concatenate([p.hull_xyz for p in flat]) if flat else [], (3,)),
        "area_m2": _f([p.area_m2 for p in flat]),
        "n_points": np.array([p.n_points for p in flat], dtype=np.int64),
        "rms_m": _f([p.rms_m for p in flat]),
        "t_offset_s": _f([p.t_offset_s for p in flat]),
        "t_slope_s_per_m": _f([p.t_slope_s_per_m for p in flat], (2,)),
        "sensor_xyz": _f([_nan_if_none(p.sensor_xyz, (3,)) for p in flat], (3,)),
        "sensor_slope": _f([_nan_if_none(p.sensor_slope, (3, 2)) for p in flat], (3, 2)),
    }


def _nan_if_none(a: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    return np.full(shape, np.nan) if a is None else a


def _none_if_nan(a: np.ndarray) -> np.ndarray | None:
    return None if np.all(np.isnan(a)) else a.copy()


def planes_from_arrays(a: Mapping[str, np.ndarray]) -> list[tuple[Plane, ...]]:
    """Inverse of :func:`planes_to_arrays`."""
    hull_at = _offsets(a["hull_counts"])
    flat = [
        Plane(int(a["scan_id"][k]), int(a["plane_id"][k]), a["normal"][k].copy(), float(a["d_m"][k]),
              a["centroid_xyz"][k].copy(), a["basis_uv"][k].copy(), a["cov_uvd"][k].copy(),
              a["hull_xyz"][hull_at[k]:hull_at[k + 1]].copy(), float(a["area_m2"][k]),
              int(a["n_points"][k]), float(a["rms_m"][k]), float(a["t_offset_s"][k]),
              (float(a["t_slope_s_per_m"][k, 0]), float(a["t_slope_s_per_m"][k, 1])),
              _none_if_nan(a["sensor_xyz"][k]), _none_if_nan(a["sensor_slope"][k]))
        for k in range(len(a["scan_id"]))
    ]
    at = _offsets(a["scan_plane_counts"])
    return [tuple(flat[at[s]:at[s + 1]]) for s in range(len(a["scan_plane_counts"]))]


def _matches_to_arrays(prefix: str, groups: Sequence[tuple[PlaneMatch, ...]]) -> Arrays:
    flat = [m for g in groups for m in g]
    return {
        f"{prefix}_counts": np.array([len(g) for g in groups], dtype=np.int64),
        f"{prefix}_planes": np.array([(m.plane_i, m.plane_j) for m in flat], dtype=np.int64).reshape(-1, 2),
        f"{prefix}_values": _f([(m.angle_deg, m.offset_m, m.overlap) for m in flat], (3,)),
    }


def _matches_from_arrays(prefix: str, a: Mapping[str, np.ndarray]) -> list[tuple[PlaneMatch, ...]]:
    planes, values = a[f"{prefix}_planes"], a[f"{prefix}_values"]
    flat = [PlaneMatch(int(planes[k, 0]), int(planes[k, 1]), float(values[k, 0]), float(values[k, 1]),
                       float(values[k, 2])) for k in range(len(planes))]
    at = _offsets(a[f"{prefix}_counts"])
    return [tuple(flat[at[s]:at[s + 1]]) for s in range(len(a[f"{prefix}_counts"]))]


def _poses_to_arrays(prefix: str, poses: Sequence[Pose]) -> Arrays:
    return {f"{prefix}_quat_wxyz": _f([p.quat_wxyz for p in poses], (4,)),
            f"{prefix}_t_xyz": _f([p.t_xyz for p in poses], (3,))}


def _pose_at(prefix: str, a: Mapping[str, np.ndarray], k: int) -> Pose:
    return Pose(a[f"{prefix}_quat_wxyz"][k].copy(), a[f"{prefix}_t_xyz"][k].copy())


def links_to_arrays(links: Sequence[Link]) -> Arrays:
    """Pairwise links as plain arrays; exact round trip with :func:`links_from_arrays`."""
    return {
        "scan_ij": np.array([(x.scan_i, x.scan_j) for x in links], dtype=np.int64).reshape(-1, 2),
        "status": np.array([x.status.value for x in links], dtype=np.str_),
        **_poses_to_arrays("T_i_j", [x.T_i_j for x in links]),
        "cov_xi": _f([x.cov_xi for x in links], (6, 6)),
        **_poses_to_arrays("T_i_j_prior", [x.T_i_j_prior for x in links]),
        **_poses_to_arrays("T_i_j_planes", [x.T_i_j_planes for x in links]),
        "info_planes": _f([x.info_planes for x in links], (6, 6)),
        "rank": np.array([x.rank for x in links], dtype=np.int64),
        "axis_sigma_planes": _f([x.axis_sigma_planes for x in links], (6,)),
        "n_directions": np.array([x.n_directions for x in links], dtype=np.int64),
        "sigma0": _f([x.sigma0 for x in links]),
        "redundancy": np.array([x.redundancy for x in links], dtype=np.int64),
        "global_test_passed": np.array([x.global_test_passed for x in links], dtype=bool),
        **_matches_to_arrays("matches", [x.matches for x in links]),
        **_matches_to_arrays("rejected", [x.rejected for x in links]),
        "max_normalised_residual": _f([x.max_normalised_residual for x in links]),
        "dt_s": _f([x.dt_s for x in links]),
    }


def links_from_arrays(a: Mapping[str, np.ndarray]) -> list[Link]:
    """Inverse of :func:`links_to_arrays`."""
    matches = _matches_from_arrays("matches", a)
    rejected = _matches_from_arrays("rejected", a)
    return [
        Link(int(a["scan_ij"][k, 0]), int(a["scan_ij"][k, 1]), LinkStatus(str(a["status"][k])),
             _pose_at("T_i_j", a, k), a["cov_xi"][k].copy(), _pose_at("T_i_j_prior", a, k),
             _pose_at("T_i_j_planes", a, k), a["info_planes"][k].copy(), int(a["rank"][k]),
             a["axis_sigma_planes"][k].copy(), int(a["n_directions"][k]), float(a["sigma0"][k]),
             int(a["redundancy"][k]), bool(a["global_test_passed"][k]), matches[k], rejected[k],
             float(a["max_normalised_residual"][k]), float(a["dt_s"][k]))
        for k in range(len(a["scan_ij"]))
    ]


def link_model_to_arrays(model: LinkModel) -> Arrays:
    """The model the links were adjusted with (:class:`~kinreg.estimate.pairwise.LinkModel`) as
    plain arrays, beside the links' own."""
    return {"model_tilt_rad": np.array(model.departure_tilt_rad, dtype=np.float64),
            "model_offset_m": np.array(model.departure_offset_m, dtype=np.float64),
            "model_area_edges_m2": np.array(model.area_edges_m2, dtype=np.float64),
            "model_figures": np.array([model.prior_variance_factor, model.sigma0_a_priori, model.sigma0_estimated,
                                       model.n_links], dtype=np.float64)}


def link_model_from_arrays(a: Mapping[str, np.ndarray]) -> LinkModel:
    """Inverse of :func:`link_model_to_arrays` (the a-priori model where the arrays have none)."""
    if "model_figures" not in a:
        return LinkModel()
    factor, s0_prior, s0, n = (float(v) for v in a["model_figures"])
    return LinkModel(tuple(float(v) for v in a["model_tilt_rad"]), tuple(float(v) for v in a["model_offset_m"]),
                     factor, tuple(float(v) for v in a["model_area_edges_m2"]), s0_prior, s0, int(n))


def stations_to_arrays(stations: Sequence[Station]) -> Arrays:
    """Stations (:class:`kinreg.types.Station`) as plain arrays; exact round trip with
    :func:`stations_from_arrays`."""
    return {
        "scan_id": np.array([s.scan_id for s in stations], dtype=np.int64),
        "name": np.array([s.name for s in stations], dtype=np.str_),
        "kind": np.array([s.kind.value for s in stations], dtype=np.str_),
        "times_s": _f([(s.t_s, s.t_start_s, s.t_end_s, s.tau_s) for s in stations], (4,)),
        **_poses_to_arrays("T_obj_scan", [s.T_obj_scan for s in stations]),
        "n_points": np.array([s.n_points for s in stations], dtype=np.int64),
        "run": np.array([s.run for s in stations], dtype=np.int64),
    }


def stations_from_arrays(a: Mapping[str, np.ndarray]) -> list[Station]:
    """Inverse of :func:`stations_to_arrays`."""

    t = a["times_s"]
    runs = a["run"] if "run" in a else np.zeros(len(a["scan_id"]), dtype=np.int64)
    return [
        Station(int(a["scan_id"][k]), str(a["name"][k]), ScanKind(str(a["kind"][k])), float(t[k, 0]),
                float(t[k, 1]), float(t[k, 2]), _pose_at("T_obj_scan", a, k), int(a["n_points"][k]),
                float(t[k, 3]), int(runs[k]))
        for k in range(len(a["scan_id"]))
    ]


def windows_to_arrays(windows: Sequence[ScanWindow], unit_ranges: Sequence[tuple[int, int]],
                      unit_counts: np.ndarray) -> Arrays:
    """The slicing result that indexes a spill folder: the kept windows, each window's range of
    spill units ``[a, b)`` and the point count of every unit. Exact round trip with
    :func:`windows_from_arrays`."""
    return {
        "scan_id": np.array([w.scan_id for w in windows], dtype=np.int64),
        "times_s": _f([(w.t_start_s, w.t_end_s, w.t_s) for w in windows], (3,)),
        **_poses_to_arrays("T_obj_scan", [w.T_obj_scan for w in windows]),
        "unit_ranges": np.array(unit_ranges, dtype=np.int64).reshape(-1, 2),
        "unit_counts": np.asarray(unit_counts, dtype=np.int64),
    }


def windows_from_arrays(a: Mapping[str, np.ndarray]) -> tuple[list[ScanWindow], list[tuple[int, int]], np.ndarray]:
    """Inverse of :func:`windows_to_arrays`: (windows, unit ranges, unit counts)."""
    t = a["times_s"]
    windows = [ScanWindow(int(a["scan_id"][k]), float(t[k, 0]), float(t[k, 1]), float(t[k, 2]),
                          _pose_at("T_obj_scan", a, k)) for k in range(len(a["scan_id"]))]
    ranges = [(int(r[0]), int(r[1])) for r in a["unit_ranges"]]
    return windows, ranges, a["unit_counts"].copy()


def scan_planes_to_arrays(station: Station, planes: tuple[Plane, ...]) -> dict[str, np.ndarray]:
    """One scan's station and planes as plain arrays (one ``planes`` cache entry)."""
    return {**{f"station.{k}": v for k, v in stations_to_arrays([station]).items()},
            **{f"planes.{k}": v for k, v in planes_to_arrays([planes]).items()}}


def scan_planes_from_arrays(arrays: Mapping[str, np.ndarray]) -> tuple[Station, tuple[Plane, ...]]:
    """Inverse of :func:`scan_planes_to_arrays`: (station, planes)."""
    def part(prefix: str) -> dict[str, np.ndarray]:
        return {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}

    return stations_from_arrays(part("station."))[0], planes_from_arrays(part("planes."))[0]
