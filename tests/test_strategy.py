"""The estimation strategy (:mod:`kinreg.estimate.strategy`) on operations that are plain
in-memory functions: a room of planes seen from six stations whose poses drifted, no files."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
from planefixtures import pose, scan_planes

import kinreg.estimate.strategy as strategy
from kinreg.config import load_config
from kinreg.errors import AdjustmentFailedError
from kinreg.estimate.datum import build_network
from kinreg.estimate.network import Network, link_pairs, station_pairs
from kinreg.estimate.pairwise import LinkModel
from kinreg.progress import NullProgress
from kinreg.types import Link, ObservationKind, Plane, ScanKind, Station, Trajectory


@dataclass(frozen=True, eq=False)
class Sliced:
    stations: list[Station]
    planes: list[tuple[Plane, ...]]
    trajectories: list[Trajectory]
    network: Network


def _links(stations, planes, config, loops: bool) -> list[Link]:
    pairs = station_pairs(stations, config.matching, None, loops)
    found = link_pairs(pairs, dict(enumerate(stations)), dict(enumerate(planes)), config.matching, config.drift,
                       config.pairwise, None)
    return [link for link in found if link is not None]


def _room(config) -> Sliced:
    """Six stations 3 s apart through the room of :mod:`planefixtures`, their poses drifted by
    millimetres and tenths of a degree; the sequence neighbours linked."""
    rng = np.random.default_rng(1)
    stations, planes = [], []
    for k in range(6):
        t = 100.0 + 3.0 * k
        y = 3.0 + 0.3 * np.sin(k)
        drifted = pose([0, 0, 0.051 * k], [2.0 + 1.504 * k, y + 0.002 * k, 1.5])
        stations.append(Station(k, f"qs_{k:05d}", ScanKind.QUASI_STATIC, t, t - 1.5, t + 1.5, drifted, 100_000, 0.0))
        planes.append(scan_planes(pose([0, 0, 0.05 * k], [2.0 + 1.5 * k, y, 1.5]), k, rng))
    links = _links(stations, planes, config, loops=False)
    return Sliced(stations, planes, [], build_network(stations, planes, links, None, None, config, ()))


class Recorder:
    """The operations, recording what the strategy asks of them. ``relinked``: the link sets the
    relinking rounds are given, one per round (the last one repeated); default: linked again."""

    def __init__(self, config, relinked: list[list[Link]] | None = None) -> None:
        self.config, self.relinked = config, relinked
        self.sliced = _room(config)
        self.calls: list[tuple[Any, ...]] = []

    def operations(self) -> strategy.Operations:
        return strategy.Operations(self.sliced_network, self.link_again, self.pass_adjusted, NullProgress())

    def sliced_network(self, window_s, deskew_maps) -> Sliced:
        self.calls.append(("slice", window_s, len(deskew_maps)))
        return self.sliced

    def link_again(self, stations, planes, rates, adjusted, previous, velocity_cov) -> tuple[list[Link], LinkModel]:
        n = sum(call[0] == "link" for call in self.calls)
        self.calls.append(("link",))
        if self.relinked is not None:
            return self.relinked[min(n, len(self.relinked) - 1)], LinkModel()
        moved = [replace(s, T_obj_scan=adjusted.poses[k]) for k, s in enumerate(stations)]
        return _links(moved, planes, self.config, loops=True), LinkModel()

    def pass_adjusted(self) -> None:
        self.calls.append(("adjusted",))

    def count(self, what: str) -> int:
        return sum(call[0] == what for call in self.calls)


def _config(**block: Any):
    config = load_config(None)
    return replace(config, block=replace(config.block, **block))


def test_a_pass_slices_links_again_until_the_linked_pairs_settle_and_is_a_result():
    config = _config()
    ops = Recorder(config)
    est = strategy.estimate_quasi_static(ops.operations(), strategy.StrategyConfig.from_config(config))
    assert ops.calls[0] == ("slice", config.slicing.window_s, 0) and ops.count("slice") == 1
    assert ops.calls[-1] == ("adjusted",) and ops.count("adjusted") == 1
    assert ops.count("link") >= 1
    # the loop closures come in with the relinking: more links than the sequence neighbours'
    assert len(est.adjusted.network.links) > len(ops.sliced.network.links)
    assert est.failure == "" and not est.adjusted.result.failed
    assert est.window_s == config.slicing.window_s and est.first_window_s is None and not est.points_deskewed
    assert est.smear_m.shape == (6,)


def test_the_rounds_stop_once_a_round_links_the_pairs_the_one_before_did():
    config = _config(max_relink_rounds=6)
    room = _room(config)
    full = _links(room.stations, room.planes, config, loops=True)
    # the first round links one pair fewer, the second all, the third the same again
    ops = Recorder(config, relinked=[full[:-1], full, full])
    est = strategy.estimate_quasi_static(ops.operations(), strategy.StrategyConfig.from_config(config))
    assert ops.count("link") == 3
    assert len(est.adjusted.network.links) == len(full)


def test_no_relinking_rounds_without_max_relink_rounds():
    config = _config(max_relink_rounds=0)
    ops = Recorder(config)
    strategy.estimate_quasi_static(ops.operations(), strategy.StrategyConfig.from_config(config))
    assert ops.count("link") == 0


def test_the_rounds_start_again_once_from_the_coupling_the_last_network_fits(monkeypatch, caplog):
    asked: list[float] = []

    def fitted(network, rates, config, progress, result, against):
        asked.append(rates.coupling)
        return 1.0 if len(asked) == 2 else None  # only the first last network fits another coupling

    monkeypatch.setattr(strategy, "_coupling_by_fit", fitted)
    config = _config()
    ops = Recorder(config)
    est = strategy.estimate_quasi_static(ops.operations(), strategy.StrategyConfig.from_config(config))
    # the first network, the last, and the last again after the rounds started from 1.0 (the
    # first network of that start is adjusted with it, not asked)
    assert len(asked) == 3
    assert "adjusted again from 1.00" in caplog.text
    assert ops.count("slice") == 1 and ops.count("adjusted") == 1  # not sliced again
    assert est.adjusted.coupling_disagrees is None and est.failure == ""


def test_a_network_that_settles_apart_from_the_coupling_it_fits_twice_is_no_result(monkeypatch):
    def other_regime(network, rates, config, progress, result, against):
        return 1.0 if rates.coupling < 0.5 else 0.0

    monkeypatch.setattr(strategy, "_coupling_by_fit", other_regime)
    config = _config()
    est = strategy.estimate_quasi_static(Recorder(config).operations(), strategy.StrategyConfig.from_config(config))
    assert est.adjusted.coupling_disagrees is not None
    assert est.failure.startswith("the adjusted network fits a drift coupling of")
    assert "started from either" in est.failure


def test_a_trajectory_that_disagrees_as_a_wrong_match_would_is_no_result(monkeypatch):
    def wrong(tests, alpha):
        return [dataclasses.replace(t, residual=np.array([0.0, 0.2, 0.0, 0.0, 0.0, 0.0])) for t in tests
                if t.kind is ObservationKind.TRAJECTORY and (t.i, t.j) == (2, 3)]

    monkeypatch.setattr(strategy, "trajectory_misfits", wrong)
    config = _config()
    est = strategy.estimate_quasi_static(Recorder(config).operations(), strategy.StrategyConfig.from_config(config))
    assert [(t.i, t.j) for t in est.adjusted.wrong_matches] == [(2, 3)]
    assert est.failure.startswith("the trajectory disagrees with the adjusted network between")


def test_a_failed_adjustment_raises_with_its_result(monkeypatch):
    real = strategy.adjust_network

    def fails(*args, **kwargs):
        return replace(real(*args, **kwargs), failure="no convergence")

    monkeypatch.setattr(strategy, "adjust_network", fails)
    config = _config()
    with pytest.raises(AdjustmentFailedError, match="the block adjustment failed: no convergence") as raised:
        strategy.estimate_quasi_static(Recorder(config).operations(), strategy.StrategyConfig.from_config(config))
    assert raised.value.result.failure == "no convergence"


def test_shorter_windows_are_kept_unless_their_network_shows_a_wrong_match(monkeypatch):
    config = _config()
    window_s = config.slicing.window_s
    monkeypatch.setattr(strategy, "shorter_window_s", lambda window, *args: 3.0 if window == window_s else None)
    ops = Recorder(config)
    est = strategy.estimate_quasi_static(ops.operations(), strategy.StrategyConfig.from_config(config))
    assert [call[1] for call in ops.calls if call[0] == "slice"] == [window_s, 3.0]
    assert est.window_s == 3.0 and est.first_window_s == window_s

    # The shorter windows' network shows a wrong match the first did not: the first windows again.
    adjust = strategy.adjust_with_measured_drift

    def wrong_with_short_windows(network, planes, operations, config, trajectories=(), points_deskewed=None):
        short = [call[1] for call in ops.calls if call[0] == "slice"][-1] == 3.0
        adjusted = adjust(network, planes, operations, config, trajectories, points_deskewed)
        return replace(adjusted, wrong_matches=adjusted.result.tests[:1]) if short else adjusted

    monkeypatch.setattr(strategy, "adjust_with_measured_drift", wrong_with_short_windows)
    ops = Recorder(config)
    est = strategy.estimate_quasi_static(ops.operations(), strategy.StrategyConfig.from_config(config))
    assert [call[1] for call in ops.calls if call[0] == "slice"] == [window_s, 3.0, window_s]
    assert est.window_s == window_s and est.first_window_s is None and est.failure == ""


def test_the_strategy_never_sees_where_it_runs():
    """No import of ``kinreg.run``, ``kinreg.report`` or ``kinreg.io`` (also inside a function)."""
    import ast
    from pathlib import Path

    tree = ast.parse(Path(strategy.__file__).read_text(encoding="utf-8"))
    imported = [node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module]
    imported += [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
    assert imported and not [name for name in imported
                             if name.split(".")[:2] in (["kinreg", "run"], ["kinreg", "report"], ["kinreg", "io"])]
