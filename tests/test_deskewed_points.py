"""A GNSS/INS-like attitude error shears a quasi-static window (issue #14): the points are turned
about where the sensor was when it saw them. Deskewed point by point with the correction
(:func:`kinreg.estimate.drift.deskewed_points`), the window's planes are detected where they are."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from kinreg.config import PlanesConfig, load_config
from kinreg.estimate.drift import MAP_NEIGHBOURS, DriftRates, deskewed_points, window_maps
from kinreg.estimate.planes import detect_planes
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.run.pipeline import ProcessInputs
from kinreg.simulation.drift import DriftConfig as SimDriftConfig
from kinreg.simulation.drift import DriftModel
from kinreg.types import Scan, ScanKind, Station, Trajectory

HEADING_ERROR = 0.025  # rad: 1.4 deg, the held-out GNSS/INS-like run's at its end
SPEED, WINDOW, SPACING = 1.0, 6.0, 6.0  # m/s, s, s
WALLS_Y = (-1.5, 1.5)


def _sensor(t):
    return np.column_stack([SPEED * t, 0 * t, 1.5 + 0 * t])


def _corridor(rng, n=60000):
    """Points of a corridor (walls y = -1.5 and 1.5, floor, ceiling) seen from a walk along x
    through one window centred on t = 0: object frame (the truth), times, the sensor's positions."""
    t = rng.uniform(-WINDOW / 2, WINDOW / 2, n)
    s = _sensor(t)
    surface = rng.integers(0, 4, n)
    x = s[:, 0] + rng.uniform(-5.0, 5.0, n)
    y = rng.uniform(-1.5, 1.5, n)
    z = rng.uniform(0.0, 2.5, n)
    y = np.where(surface == 0, WALLS_Y[0], np.where(surface == 1, WALLS_Y[1], y))
    z = np.where(surface == 2, 0.0, np.where(surface == 3, 2.5, z))
    return np.column_stack([x, y, z]), t, s


def test_the_points_of_a_sheared_window_deskewed_give_its_walls_where_they_are():
    rng = np.random.default_rng(5)
    truth, t, sensor = _corridor(rng)
    D = Pose(rotvec_to_quat(np.array([0.0, 0.0, HEADING_ERROR])), np.zeros(3))
    # GNSS/INS-like: the positions measured apart from the attitude, the attitude turned by D; each
    # point is turned about where the sensor was
    seen = D.apply(truth - sensor) + sensor
    seen += 0.002 * rng.standard_normal(seen.shape)
    stamps = SPACING * np.arange(-1, 2)  # three stations; the window of the middle one
    true_poses = Pose(np.tile([1.0, 0, 0, 0], (3, 1)), _sensor(stamps))
    drifted = D.compose(Pose(true_poses.quat_wxyz, np.zeros((3, 3))))
    drifted = Pose(drifted.quat_wxyz, true_poses.t_xyz)
    T_c = drifted[1]
    scan_xyz = T_c.apply_inverse(seen)
    stations = [Station(k, f"s{k}", ScanKind.QUASI_STATIC, stamps[k], stamps[k] - WINDOW / 2, stamps[k] + WINDOW / 2,
                        drifted[k], 1000) for k in range(3)]
    track_t = np.linspace(-10.0, 10.0, 2001)
    own = Trajectory(track_t, Pose(np.tile(drifted.quat_wxyz[1], (len(track_t), 1)), _sensor(track_t)))
    rates = DriftRates(np.full(3, 3e-4), np.full(3, 1e-5), 1e-3, 1e-4, coupling=1.0)
    result = SimpleNamespace(poses=true_poses, poses_initial=drifted)
    (mapped,) = [m for k, m in window_maps(stations, result, rates, [own], MAP_NEIGHBOURS).items() if k == 1]
    track = (track_t, T_c.apply_inverse(_sensor(track_t)))
    config = PlanesConfig()

    def wall_offsets(xyz):
        scan = Scan(1, "s1", ScanKind.QUASI_STATIC, T_c, xyz, t, None, 0.0, -WINDOW / 2, WINDOW / 2)
        walls = [p for p in detect_planes(scan, config) if abs(p.normal[1]) > 0.9]
        # where each wall crosses the scan's y axis (the frame is the true pose at the centre once
        # deskewed: the map ends in it)
        return sorted(float(p.d_m / p.normal[1]) for p in walls), walls

    before, walls_before = wall_offsets(scan_xyz)
    after, walls_after = wall_offsets(deskewed_points(mapped, scan_xyz, t, track))
    # sheared: walls tilted by about the heading error along the walk
    assert max(np.degrees(np.arccos(min(1.0, abs(p.normal[1])))) for p in walls_before) > 0.5
    assert len(walls_after) == 2
    for p in walls_after:
        assert np.degrees(np.arccos(min(1.0, abs(p.normal[1])))) < 0.02
    assert after == pytest.approx(sorted(WALLS_Y), abs=2e-4)
    # sheared, each wall fell apart into strips some 4 cm apart (here: three each)
    for side in (-1.0, 1.0):
        strips = [w for w in before if np.sign(w) == side]
        assert len(strips) > 1 and max(strips) - min(strips) > 0.03


def _gnss_ins_run(tmp_path: Path, model: DriftModel) -> ProcessInputs:
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import SimulationConfig, simulate_run

    # 1.5 deg of attitude error reached within the 72 s run: the heading error of the held-out
    # GNSS/INS-like run at its end (a wall seen over a 6 s window sheared by centimetres)
    drift = SimDriftConfig(drift_pos_m_at_300s=0.02, drift_rot_deg_at_300s=1.5, model=model, at_s=72.0)
    write_run(simulate_run(SimulationConfig(seed=2, duration_s=72.0, drift=drift)), tmp_path / "data")
    return ProcessInputs(tmp_path / "data" / "run_trajectory.txt", tmp_path / "data" / "run_cloud.laz")


def _station_rms_mm(out: Path, data: Path) -> float:
    from kinreg.io.trajectory import read_trajectory
    from kinreg.report.json import rigid_fit

    rows = np.genfromtxt(out / "stations.csv", delimiter=",", names=True)
    adjusted = np.column_stack([rows["x"], rows["y"], rows["z"]])
    true = read_trajectory(data / "truth_trajectory.txt").pose_at(rows["t"]).t_xyz
    R, t = rigid_fit(adjusted, true)
    return float(np.sqrt(np.mean(np.sum((adjusted @ R.T + t - true) ** 2, axis=1)))) * 1000


def test_a_sheared_run_has_its_points_deskewed_and_its_stations_follow(tmp_path: Path) -> None:
    from kinreg.report.html import _window_text
    from kinreg.run.pipeline import process

    inputs = _gnss_ins_run(tmp_path, DriftModel.GNSS_INS)
    (tmp_path / "off.toml").write_text("[slicing]\ndeskew_sheared = false\n")
    process(inputs, tmp_path / "on", load_config(None))
    process(inputs, tmp_path / "off", load_config(tmp_path / "off.toml"))
    on = json.loads((tmp_path / "on" / "report.json").read_text())["slicing"]
    off = json.loads((tmp_path / "off" / "report.json").read_text())["slicing"]
    assert on["points_deskewed"] and not off["points_deskewed"]
    assert "points deskewed" in _window_text(on) and "points deskewed" not in _window_text(off)
    rms_on, rms_off = (_station_rms_mm(tmp_path / k, tmp_path / "data") for k in ("on", "off"))
    assert rms_on < 0.8 * rms_off


def test_a_rigid_drift_of_the_world_shears_no_window(tmp_path: Path) -> None:
    from kinreg.run.pipeline import process

    inputs = _gnss_ins_run(tmp_path, DriftModel.WORLD)
    process(inputs, tmp_path / "out", load_config(None))
    assert not json.loads((tmp_path / "out" / "report.json").read_text())["slicing"]["points_deskewed"]


def test_the_deskewed_planes_agree_with_the_adjustment_they_end_in(tmp_path: Path, monkeypatch) -> None:
    """Deskewed with the adjustment before the last pass, a GNSS/INS-like run's planes moved by
    several of their sigmas once deskewed with the last pass's own result: they are deskewed and
    adjusted again until they agree (:func:`kinreg.estimate.strategy._deskew_settled`)."""
    import kinreg.estimate.strategy as strategy
    from kinreg.estimate.drift import deskewed_planes
    from kinreg.run.pipeline import process

    inputs = _gnss_ins_run(tmp_path, DriftModel.GNSS_INS)
    (tmp_path / "planes.toml").write_text("[slicing]\ndeskew_sheared = false\n")  # planes deskewed, not points
    moves = {}
    adjust, default = strategy.adjust_with_measured_drift, strategy._DESKEW_ROUNDS

    def both(network, planes, operations, config, trajectories=(), points_deskewed=None):
        for rounds in (0, default):
            monkeypatch.setattr(strategy, "_DESKEW_ROUNDS", rounds)
            out = adjust(network, planes, operations, config, trajectories, points_deskewed)
            again, _ = deskewed_planes(out.network.stations, planes, out.result, out.rates, trajectories)
            moves[rounds] = strategy._largest_move(out.network.planes, again)
        return out

    monkeypatch.setattr(strategy, "adjust_with_measured_drift", both)
    process(inputs, tmp_path / "out", load_config(tmp_path / "planes.toml"))
    unsettled, settled = moves[0], moves[default]
    assert unsettled > 1.0, moves
    assert settled < 0.5 * unsettled and settled < 2.5 * strategy._DESKEW_SETTLED, moves
