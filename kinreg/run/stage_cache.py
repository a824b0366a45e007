"""The stage cache: each stage's output kept in the output folder under a key of its inputs.

A re-run looks every stage up by its key and re-does only what changed; a killed run leaves
either a complete entry or none, so a restart continues where it stopped and gives the same
result as an uninterrupted run.

Layout: ``<folder>/<stage>/<key>.npz`` (plain numeric and string arrays, ``np.savez``) and
``<key>.json`` (schema version, stage, key, the npz's size and sha256, small metadata). The JSON
sidecar is renamed into place last and is the commit mark: an npz without it is ignored. No
pickle anywhere: the output folder is the user's, and loading it must never run code, so arrays
are loaded with ``allow_pickle=False`` and kinreg's types go through the explicit converters
below (``planes_to_arrays`` / ``planes_from_arrays`` and the same for links, stations and
the slicing windows).

Keys (:meth:`StageCache.key`) are sha256 over a stable serialisation of the parts:

- a config section (a dataclass): ``dataclasses.asdict`` as JSON with sorted keys, enums by value;
- an input file (a :class:`pathlib.Path`): its absolute path, size and ``mtime_ns``. That costs a
  ``stat`` instead of reading gigabytes; the price is that a file replaced by different content
  with the same size and modification time (``cp -p``, ``rsync -t`` of an edited file of equal
  length) is not noticed. Pass ``str(path)`` for a path that is a name, not an input;
- a numpy array: dtype, shape and the raw bytes; a :class:`~kinreg.geometry.Pose`: its arrays;
- plain values (str, int, float including nan/inf, bool, None, lists, tuples, dicts) as JSON.

Every key also covers :data:`CACHE_SCHEMA_VERSION` and the kinreg version, so results of an
older kinreg are not reused. Bump :data:`CACHE_SCHEMA_VERSION` when a stored layout changes, or
when a stage's results change without a change of the kinreg version (development builds).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import logging
import os
import shutil
import zipfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any

import numpy as np

import kinreg
from kinreg.errors import OutputError
from kinreg.geometry import Pose
from kinreg.types import Link, LinkStatus, Plane, PlaneMatch, ScanKind, ScanWindow

log = logging.getLogger(__name__)

# Bump when a stored layout or the meaning of a key part changes (old entries are then ignored).
CACHE_SCHEMA_VERSION = 2

Arrays = dict[str, np.ndarray]


@dataclass(frozen=True)
class CacheEntry:
    """A loaded entry: its arrays and the small JSON metadata stored with them."""

    arrays: Arrays
    meta: dict[str, Any]


class StageCache:
    """Stage outputs in ``folder`` (created on the first store), keyed by their inputs."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    # ------------------------------------------------------------------ keys

    def key(self, stage: str, *parts: Any) -> str:
        """The hex sha256 of ``stage`` and ``parts`` (see the module docstring for how each kind
        of part is serialised). Raises :class:`TypeError` for a part it cannot serialise stably
        and :class:`OutputError` for an input file that does not exist."""
        h = hashlib.sha256()
        _feed(h, ["kinreg-cache", CACHE_SCHEMA_VERSION, kinreg.__version__, stage])
        for part in parts:
            _feed(h, part)
        return h.hexdigest()

    # ------------------------------------------------------------------ entries

    def _paths(self, stage: str, key: str) -> tuple[Path, Path]:
        if not stage or "/" in stage or stage.startswith(".") or not key.isalnum():
            raise ValueError(f"bad stage or key: {stage!r}, {key!r}")
        folder = self.folder / stage
        return folder / f"{key}.npz", folder / f"{key}.json"

    def load(self, stage: str, key: str) -> CacheEntry | None:
        """The entry stored under ``stage``/``key``, or ``None`` when there is none (or it is
        incomplete, of another schema version, or damaged: then it is logged and ignored)."""
        npz_path, json_path = self._paths(stage, key)
        if not json_path.is_file():
            return None
        try:
            sidecar = json.loads(json_path.read_text(encoding="utf-8"))
            if (sidecar.get("schema_version") != CACHE_SCHEMA_VERSION or sidecar.get("stage") != stage
                    or sidecar.get("key") != key):
                return None
            data = npz_path.read_bytes()
            if len(data) != sidecar["npz_size"] or hashlib.sha256(data).hexdigest() != sidecar["npz_sha256"]:
                log.warning("%s: damaged cache entry ignored", npz_path)
                return None
            with np.load(npz_path, allow_pickle=False) as npz:
                arrays = {name: npz[name] for name in npz.files}
        except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as e:
            log.warning("%s: unreadable cache entry ignored (%s)", json_path, e)
            return None
        return CacheEntry(arrays, sidecar.get("meta", {}))

    def store(self, stage: str, key: str, arrays: Mapping[str, np.ndarray],
              meta: Mapping[str, Any] | None = None) -> None:
        """Store ``arrays`` (numeric, bool or fixed-width string; no object arrays) and ``meta``
        (JSON-able) under ``stage``/``key``, atomically: an interruption at any point leaves the
        previous state (no entry, or the old one). Raises :class:`TypeError` for an object array
        or non-JSON meta, :class:`OutputError` when the folder cannot be written."""
        for name, a in arrays.items():
            if np.asarray(a).dtype.hasobject:
                raise TypeError(f"cache array {name!r} has dtype object; convert it to plain arrays first")
        meta_json = json.dumps(dict(meta or {}), sort_keys=True)  # fails before anything is written
        npz_path, json_path = self._paths(stage, key)
        try:
            npz_path.parent.mkdir(parents=True, exist_ok=True)
            with _atomic(npz_path) as tmp, open(tmp, "wb") as f:
                np.savez(f, **{name: np.asarray(a) for name, a in arrays.items()})  # type: ignore[arg-type]
                f.flush()
                os.fsync(f.fileno())
            data = npz_path.read_bytes()
            sidecar = (f'{{"schema_version": {CACHE_SCHEMA_VERSION}, "stage": {json.dumps(stage)}, '
                       f'"key": "{key}", "npz_size": {len(data)}, '
                       f'"npz_sha256": "{hashlib.sha256(data).hexdigest()}", "meta": {meta_json}}}\n')
            with _atomic(json_path) as tmp:
                tmp.write_text(sidecar, encoding="utf-8")
        except OSError as e:
            raise OutputError(f"cannot write the stage cache: {e.strerror or e}", npz_path) from None

    def has(self, stage: str, key: str) -> bool:
        """Whether a committed entry exists (not verified; :meth:`load` verifies)."""
        return self._paths(stage, key)[1].is_file()

    # ------------------------------------------------------------------ large outputs

    def directory(self, stage: str, key: str) -> Path | None:
        """The committed folder of a large output (e.g. the slicing spill) or ``None``."""
        folder = self._paths(stage, key)[0].with_suffix("")
        return folder if folder.is_dir() and (folder / ".complete").is_file() else None

    @contextmanager
    def build_directory(self, stage: str, key: str) -> Iterator[Path]:
        """Yield a temporary folder to fill; on success it is renamed to the entry's folder and
        marked complete, on any exception removed. For outputs too large for one npz."""
        final = self._paths(stage, key)[0].with_suffix("")
        tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            yield tmp
            (tmp / ".complete").write_text("1\n", encoding="utf-8")
            shutil.rmtree(final, ignore_errors=True)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def prune(self, keep: Iterable[tuple[str, str]]) -> int:
        """Delete every committed entry (and large-output folder) whose ``(stage, key)`` is not
        in ``keep``; return how many were deleted. Files that are not cache entries are left."""
        keep = set(keep)
        removed = 0
        if not self.folder.is_dir():
            return 0
        for stage_dir in self.folder.iterdir():
            if not stage_dir.is_dir() or stage_dir.name.startswith("."):
                continue
            for path in stage_dir.iterdir():
                key = path.name.split(".", 1)[0]
                if path.name.startswith(".") or not key.isalnum() or (stage_dir.name, key) in keep:
                    continue
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path, ignore_errors=True)
                elif path.suffix in (".npz", ".json"):
                    path.unlink(missing_ok=True)
                else:
                    continue
                removed += path.suffix != ".npz"  # one per entry: its sidecar (or its folder)
        return removed

    def remove_stale(self) -> None:
        """Delete temporary files left by killed runs (``.*.tmp-<pid>`` of dead processes)."""
        if not self.folder.is_dir():
            return
        for path in [*self.folder.glob(".*.tmp-*"), *self.folder.glob("*/.*.tmp-*")]:
            pid = path.name.rsplit("-", 1)[-1]
            if pid.isdigit() and not process_alive(int(pid)):
                if path.is_dir():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------- key serialisation


def _token(h: Any, tag: bytes, payload: bytes) -> None:
    # Length-prefixed, so that no two different part sequences feed the same bytes.
    h.update(tag + len(payload).to_bytes(8, "little"))
    h.update(payload)


def _plain(x: Any) -> Any:
    """A JSON-able, order-stable form of config values."""
    if isinstance(x, enum.Enum):
        return {"__enum__": type(x).__name__, "value": _plain(x.value)}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {"__dataclass__": type(x).__qualname__,
                **{f.name: _plain(getattr(x, f.name)) for f in dataclasses.fields(x)}}
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, PurePath):
        return {"__path__": str(x)}
    if isinstance(x, np.generic):
        return x.item()
    if x is None or isinstance(x, (str, bool, int, float)):
        return x
    raise TypeError(f"cannot build a cache key from {type(x).__name__}")


def _feed(h: Any, part: Any) -> None:
    if isinstance(part, Path):
        resolved = part.resolve()
        try:
            st = resolved.stat()
        except OSError as e:
            raise OutputError(f"cannot fingerprint the input: {e.strerror or e}", part) from None
        _token(h, b"F", json.dumps([str(resolved), st.st_size, st.st_mtime_ns]).encode())
    elif isinstance(part, np.ndarray):
        if part.dtype.hasobject:
            raise TypeError("cannot build a cache key from an object array")
        a = np.ascontiguousarray(part)
        _token(h, b"A", json.dumps([a.dtype.str, list(a.shape)]).encode())
        _token(h, b"B", a.tobytes())
    elif isinstance(part, Pose):
        _token(h, b"P", b"")
        _feed(h, part.quat_wxyz)
        _feed(h, part.t_xyz)
    elif isinstance(part, bytes):
        _token(h, b"R", part)
    else:
        _token(h, b"J", json.dumps(_plain(part), sort_keys=True, allow_nan=True).encode())


# --------------------------------------------------------------------------- converters


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
    }


def planes_from_arrays(a: Mapping[str, np.ndarray]) -> list[tuple[Plane, ...]]:
    """Inverse of :func:`planes_to_arrays`."""
    hull_at = _offsets(a["hull_counts"])
    flat = [
        Plane(int(a["scan_id"][k]), int(a["plane_id"][k]), a["normal"][k].copy(), float(a["d_m"][k]),
              a["centroid_xyz"][k].copy(), a["basis_uv"][k].copy(), a["cov_uvd"][k].copy(),
              a["hull_xyz"][hull_at[k]:hull_at[k + 1]].copy(), float(a["area_m2"][k]),
              int(a["n_points"][k]), float(a["rms_m"][k]), float(a["t_offset_s"][k]))
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


def stations_to_arrays(stations: Sequence[Any]) -> Arrays:
    """Stations (:class:`kinreg.estimate.network.Station`) as plain arrays; exact round trip with
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


def stations_from_arrays(a: Mapping[str, np.ndarray]) -> list[Any]:
    """Inverse of :func:`stations_to_arrays`."""
    from kinreg.types import Station

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
