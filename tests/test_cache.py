"""The stage cache: exact round trips of kinreg's types, keys that follow inputs and config,
atomic stores."""

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest
from planefixtures import pose, scan_planes

from kinreg.config import DriftConfig, MatchingConfig, PairwiseConfig, PlanesConfig, SlicingConfig, WindowMode
from kinreg.estimate.matching import match_planes
from kinreg.estimate.pairwise import adjust_pair
from kinreg.geometry import Pose
from kinreg.run.codecs import (
    links_from_arrays,
    links_to_arrays,
    planes_from_arrays,
    planes_to_arrays,
    stations_from_arrays,
    stations_to_arrays,
    windows_from_arrays,
    windows_to_arrays,
)
from kinreg.run.stage_cache import StageCache
from kinreg.types import Link, LinkStatus, Plane, PlaneMatch, ScanKind, ScanWindow, Station


def same(a, b) -> bool:
    """Exact equality of two values built from kinreg's types (nan equals nan)."""
    if isinstance(a, Pose):
        return isinstance(b, Pose) and same(a.quat_wxyz, b.quat_wxyz) and same(a.t_xyz, b.t_xyz)
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.shape == b.shape and a.dtype == b.dtype
                and np.array_equal(a, b, equal_nan=True))
    if isinstance(a, float):
        return type(b) is float and (a == b or (np.isnan(a) and np.isnan(b)))
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(same(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a))
    return type(a) is type(b) and a == b


def make_planes_and_links() -> tuple[list[tuple[Plane, ...]], list[Link]]:
    rng = np.random.default_rng(3)
    T = [pose(rng.normal(0, [0.05, 0.05, 0.3]), [4.0 + 1.5 * k, 3.0, 1.4] + rng.normal(0, 0.2, 3)) for k in range(3)]
    planes = [scan_planes(T[k], k, rng) for k in range(3)] + [()]  # a scan without planes
    links = []
    for i, j in ((0, 1), (1, 2), (0, 2)):
        T_prior = T[i].inverse().compose(T[j])
        matches = match_planes(planes[i], planes[j], T_prior, MatchingConfig())
        links.append(adjust_pair(i, j, planes[i], planes[j], T_prior, 6.0 * (j - i), matches, DriftConfig(),
                                 PairwiseConfig()))
    links.append(adjust_pair(0, 3, planes[0], (), T[0], float("inf"), (), DriftConfig(), PairwiseConfig()))
    # edge values a real run can produce: inf sigmas, nan, rejected matches, every status
    links[1] = dataclasses.replace(links[1], status=LinkStatus.REJECTED, max_normalised_residual=float("nan"),
                                   rejected=(PlaneMatch(1, 2, 0.25, -0.003, 1.0),))
    links[2] = dataclasses.replace(links[2], axis_sigma_planes=np.array([np.inf, 1e-3, 2e-3, np.inf, 1e-5, -0.0]))
    return planes, links


def test_planes_round_trip_exactly():
    planes, _ = make_planes_and_links()
    assert sum(len(p) for p in planes) > 10
    # where the sensor saw a plane from: known for some planes (a kinematic scan), not for others
    planes[1] = tuple(dataclasses.replace(p, sensor_xyz=np.array([0.1 * k, -0.3, 1e-17]),
                                          sensor_slope=np.arange(6.0).reshape(3, 2) * k)
                      if k % 2 else p for k, p in enumerate(planes[1]))
    back = planes_from_arrays(planes_to_arrays(planes))
    assert same(back, planes)
    assert planes_from_arrays(planes_to_arrays([])) == []


def test_links_round_trip_exactly():
    _, links = make_planes_and_links()
    assert {x.status for x in links} == set(LinkStatus)
    assert any(len(x.matches) for x in links)
    back = links_from_arrays(links_to_arrays(links))
    assert same(back, links)
    assert back[0].T_i_j.shape == () and isinstance(back[0].matches, tuple)
    assert links_from_arrays(links_to_arrays([])) == []


def test_stations_round_trip_exactly():
    stations = [
        Station(0, "qs_00000", ScanKind.QUASI_STATIC, 1623220971.123456789, 1623220968.0, 1623220974.0,
                pose([0.01, -0.02, 0.3], [500000.123456, 5400000.987654, 1.3]), 123456, 0.8125),
        Station(1, "static Ä 1", ScanKind.STATIC, float("nan"), float("nan"), float("nan"),
                Pose.identity(), 7, float("nan")),
    ]
    back = stations_from_arrays(stations_to_arrays(stations))
    assert same(back, stations)


def test_windows_round_trip_exactly():
    windows = [ScanWindow(0, 1623220971.15523, 1623220977.15523, 1623220974.16, pose([0.1, 0, 0], [1.0, 2.0, 3.0])),
               ScanWindow(1, 1623220983.15523, 1623220989.15523, 1623220986.15, Pose.identity())]
    ranges, counts = [(0, 1), (2, 3)], np.array([5000, 12, 7000])
    back = windows_from_arrays(windows_to_arrays(windows, ranges, counts))
    assert same(back[0], windows) and back[1] == ranges and same(back[2], counts)


def test_round_trip_through_the_cache_files(tmp_path: Path):
    planes, links = make_planes_and_links()
    cache = StageCache(tmp_path / "cache")
    key = cache.key("link", PlanesConfig(), MatchingConfig())
    assert cache.load("link", key) is None
    cache.store("link", key, links_to_arrays(links), meta={"n_candidates": 3})
    entry = cache.load("link", key)
    assert entry is not None and entry.meta == {"n_candidates": 3}
    assert same(links_from_arrays(entry.arrays), links)
    cache.store("planes", key, planes_to_arrays(planes))
    assert same(planes_from_arrays(cache.load("planes", key).arrays), planes)


def test_key_follows_config_and_inputs(tmp_path: Path):
    cache = StageCache(tmp_path / "cache")
    cloud = tmp_path / "cloud.laz"
    cloud.write_bytes(b"x" * 100)
    base = cache.key("planes", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(), 7)
    assert base == cache.key("planes", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(), 7)
    assert len(base) == 64
    others = [
        cache.key("slice", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(), 7),
        cache.key("planes", cloud, PlanesConfig(seed=1), np.arange(3.0), Pose.identity(), 7),
        cache.key("planes", cloud, PlanesConfig(), np.arange(3.0).astype(np.float32), Pose.identity(), 7),
        cache.key("planes", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(2)[1:], 7),
        cache.key("planes", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(), 8),
        cache.key("planes", str(cloud), PlanesConfig(), np.arange(3.0), Pose.identity(), 7),
    ]
    assert len(set(others) | {base}) == len(others) + 1
    # enums and nested values serialise stably
    assert cache.key("s", SlicingConfig(mode=WindowMode.PATH)) != cache.key("s", SlicingConfig())
    assert cache.key("s", {"b": 1, "a": float("nan")}) == cache.key("s", {"a": float("nan"), "b": 1})
    # the input file: a change of size or of modification time changes the key
    cloud.write_bytes(b"x" * 101)
    changed_size = cache.key("planes", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(), 7)
    st = cloud.stat()
    os.utime(cloud, ns=(st.st_atime_ns, st.st_mtime_ns + 1000))
    changed_time = cache.key("planes", cloud, PlanesConfig(), np.arange(3.0), Pose.identity(), 7)
    assert len({base, changed_size, changed_time}) == 3
    with pytest.raises(TypeError):
        cache.key("planes", object())


def test_a_store_interrupted_by_an_exception_leaves_no_entry(tmp_path: Path, monkeypatch):
    cache = StageCache(tmp_path / "cache")
    arrays = {"x": np.arange(10.0)}

    def failing_write_text(self, *args, **kwargs):
        raise KeyboardInterrupt  # the run is killed between the npz and its sidecar

    monkeypatch.setattr(Path, "write_text", failing_write_text)
    with pytest.raises(KeyboardInterrupt):
        cache.store("planes", "abc", arrays)
    monkeypatch.undo()
    assert cache.load("planes", "abc") is None
    assert not [p for p in (tmp_path / "cache" / "planes").iterdir() if ".tmp-" in p.name]

    with pytest.raises(TypeError):
        cache.store("planes", "abc", {"x": np.array([object()])})
    with pytest.raises(TypeError):
        cache.store("planes", "abc", arrays, meta={"x": object()})
    assert cache.load("planes", "abc") is None


def test_a_damaged_or_foreign_entry_is_ignored(tmp_path: Path):
    cache = StageCache(tmp_path / "cache")
    cache.store("planes", "abc", {"x": np.arange(10.0)})
    assert cache.load("planes", "abc") is not None
    npz = tmp_path / "cache" / "planes" / "abc.npz"
    npz.write_bytes(npz.read_bytes()[:-5])  # truncated
    assert cache.load("planes", "abc") is None
    cache.store("planes", "abc", {"x": np.arange(10.0)})
    sidecar = tmp_path / "cache" / "planes" / "abc.json"
    data = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps({**data, "schema_version": 999}))
    assert cache.load("planes", "abc") is None


def test_pickled_arrays_are_never_loaded(tmp_path: Path):
    """An entry whose npz holds an object array (a pickle) is refused, not unpickled."""
    import hashlib

    cache = StageCache(tmp_path / "cache")
    cache.store("planes", "abc", {"x": np.arange(3.0)})
    npz = tmp_path / "cache" / "planes" / "abc.npz"
    with open(npz, "wb") as f:
        np.savez(f, x=np.array([{"evil": 1}], dtype=object))
    data = npz.read_bytes()
    sidecar = tmp_path / "cache" / "planes" / "abc.json"
    meta = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps({**meta, "npz_size": len(data), "npz_sha256": hashlib.sha256(data).hexdigest()}))
    assert cache.load("planes", "abc") is None


def test_prune_keeps_what_a_run_used_and_nothing_else(tmp_path: Path):
    cache = StageCache(tmp_path / "cache")
    for stage, key in (("planes", "a1"), ("planes", "b2"), ("link", "c3")):
        cache.store(stage, key, {"x": np.arange(3.0)})
    (tmp_path / "cache" / "planes" / "notes.txt").write_text("not an entry")
    assert cache.prune({("planes", "a1"), ("link", "zz")}) == 2
    assert cache.load("planes", "a1") is not None
    assert cache.load("planes", "b2") is None and cache.load("link", "c3") is None
    assert sorted(p.name for p in (tmp_path / "cache" / "planes").iterdir()) == ["a1.json", "a1.npz", "notes.txt"]
