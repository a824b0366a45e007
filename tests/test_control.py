"""Control and check points (issue 15): the CSV reader, stand-still detection and assignment, the
control observation in the block, bad files through the command line, and one simulated run."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from clirunner import run_cli
from conftest import write_synthetic_run

from kinreg.config import BlockConfig, ControlConfig, KinregConfig
from kinreg.errors import InputError
from kinreg.estimate.block import adjust_block
from kinreg.estimate.control import (
    Assignment,
    ControlTie,
    assign_points,
    control_observations,
    find_stand_stills,
    first_station_rotation,
    free_rotations,
)
from kinreg.estimate.drift import DriftRates
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.control import parse_control_points, read_control_points
from kinreg.report.control import loa_class
from kinreg.types import ScanKind, Station, Trajectory

GOOD = "name,x,y,z,sigma_mm\nA,1.0,2.0,3.0,3\nB,4.0,5.0,6.0,2.5\n"


def test_reader_reads_points_in_any_column_order(tmp_path):
    path = tmp_path / "cp.csv"
    path.write_text("# surveyed 2026\nsigma_mm,z,y,x,name,t_start,t_end\n3,3.0,2.0,1.0,A,10,12\n")
    points = read_control_points(path)
    assert points.names == ("A",)
    p = points.points[0]
    assert np.allclose(p.xyz, [1, 2, 3]) and p.sigma_m == pytest.approx(0.003)
    assert p.has_times and (p.t_start_s, p.t_end_s) == (10.0, 12.0)
    assert not parse_control_points(GOOD, "x.csv").points[1].has_times


@pytest.mark.parametrize(("text", "reason"), [
    ("name,x,y,sigma_mm\nA,1,2,3\n", "missing column(s) z"),
    ("name,x,y,z,sigma_mm\nA,1,nan,3,3\n", "y is not a finite number"),
    ("name,x,y,z,sigma_mm\nA,1,b,3,3\n", "y is not a number"),
    ("name,x,y,z,sigma_mm\nA,1,2,3,3\nA,1,2,3,3\n", "point A is given twice"),
    ("name,x,y,z,sigma_mm\nA,1,2,3,0\n", "sigma_mm must be positive"),
    ("name,x,y,z,sigma_mm,t_start\nA,1,2,3,3,5\n", "t_start without t_end"),
    ("name,x,y,z,sigma_mm,t_start,t_end\nA,1,2,3,3,5,4\n", "is not after t_start"),
    ("name,x,y,z,sigma_mm\nA,1,2,3\n", "4 values for 5 columns"),
    ("name,x,y,z,sigma_mm\n", "no points"),
    ("", "empty"),
    # targets in static scans (station, sx, sy, sz)
    ("name,x,y,z,sigma_mm,station,sx,sy\nT1,1,2,3,3,s,1,2\n", "without sz"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,s,1,2,\n", "line 2: target T1 in static scan s: sz missing"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,s,1,nan,3\n", "line 2: point T1: sy is not a finite number"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,,1,2,3\n", "sx,sy,sz given without a station"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz,t_start,t_end\nT1,1,2,3,3,s,1,2,3,5,6\n", "leave t_start,t_end empty"),
])
def test_reader_names_the_file_and_the_problem(tmp_path, text, reason):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_control_points(path)
    assert reason in str(info.value) and str(path) in str(info.value)


def _still_trajectory(t0: float = 100.0) -> tuple[Trajectory, list[tuple[float, float]]]:
    """A walk at 1 m/s along x with two 4 s stand-stills (at x = 5 and x = 15), 100 Hz."""
    t = t0 + np.arange(0, 40.0, 0.01)
    rate = np.ones_like(t)
    stills = [(t0 + 8.0, t0 + 12.0), (t0 + 24.0, t0 + 28.0)]
    for a, b in stills:
        rate[(t >= a) & (t <= b)] = 0.0
    x = np.concatenate([[0.0], np.cumsum(rate[1:] * 0.01)])
    xyz = np.column_stack([x, 0.1 * np.sin(0.3 * x), np.full_like(x, 1.3)])
    yaw = 0.02 * x
    q = rotvec_to_quat(np.column_stack([np.zeros_like(x), np.zeros_like(x), yaw]))
    return Trajectory(t, Pose(q, xyz)), stills


def test_stand_stills_are_found_and_points_assigned_one_to_one():
    traj, stills = _still_trajectory()
    found = find_stand_stills(traj, ControlConfig())
    assert len(found) == 2
    for s, (a, b) in zip(found, stills, strict=True):
        assert a - 0.2 <= s.t_start_s and s.t_end_s <= b + 0.2 and abs(s.t_s - 0.5 * (a + b)) < 0.05
    x1, x2 = (traj.pose_at(np.array([s.t_s])).t_xyz[0] for s in found)
    text = ("name,x,y,z,sigma_mm\n"
            f"P1,{x1[0] + 0.05},{x1[1]},{x1[2]},3\nP2,{x2[0]},{x2[1] - 0.1},{x2[2]},3\nFAR,50,0,1.3,3\n")
    points = parse_control_points(text, "cp.csv")
    assignment = assign_points(points, [traj], ControlConfig())
    assert assignment.names == ("P1", "P2")
    assert [s.t_s for s in assignment.stand_stills] == [found[0].t_s, found[1].t_s]
    assert len(assignment.problems) == 1
    assert "FAR" in assignment.problems[0] and "within 0.5 m" in assignment.problems[0]


def test_ambiguous_points_are_left_out_and_nothing_left_is_an_error():
    traj, _ = _still_trajectory()
    found = find_stand_stills(traj, ControlConfig())
    x1 = traj.pose_at(np.array([found[0].t_s])).t_xyz[0]
    text = f"name,x,y,z,sigma_mm\nP1,{x1[0]},{x1[1]},{x1[2]},3\nP1b,{x1[0] + 0.01},{x1[1]},{x1[2]},3\n"
    with pytest.raises(InputError) as info:
        assign_points(parse_control_points(text, "cp.csv"), [traj], ControlConfig())
    assert "cp.csv" in str(info.value) and "P1, P1b" in str(info.value)


def test_times_outside_the_trajectory_are_an_error():
    traj, _ = _still_trajectory()
    text = "name,x,y,z,sigma_mm,t_start,t_end\nP1,0,0,0,3,10,12\n"
    with pytest.raises(InputError, match="outside the trajectory's time range"):
        assign_points(parse_control_points(text, "cp.csv"), [traj], ControlConfig())


def _station(k: int, T: Pose, t_s: float) -> Station:
    return Station(k, f"qs_{k:05d}", ScanKind.QUASI_STATIC, t_s, t_s - 3.0, t_s + 3.0, T, 1000, 0.0)


def test_control_observations_pull_the_station_onto_the_control_coordinates():
    """One free station, three control points on levers q: the adjusted station maps each q onto
    its surveyed point (the rank-3 information J^T C^-1 J with J = R [I, -[q]x])."""
    T_true = Pose(rotvec_to_quat(np.array([0.02, -0.01, 0.6])), np.array([10.0, 20.0, 1.5]))
    T_start = T_true.compose(Pose.exp(np.array([0.05, -0.03, 0.02, 0.01, 0.02, -0.03])))
    levers = np.array([[1.0, 0.0, -1.2], [0.0, 2.0, -1.3], [-1.5, -0.5, -1.1]])
    ties = [ControlTie(f"P{k}", 0, q, T_true.apply(q[None, :])[0], 1e-6 * np.eye(3), 0.0, 0.0)
            for k, q in enumerate(levers)]
    station = _station(0, T_start, 0.0)
    rates = DriftRates(np.zeros(3), np.zeros(3), 1e-4, 1e-5)
    observations = control_observations(ties, [station], rates)
    assert all(o.rank == 3 and np.linalg.matrix_rank(o.info, tol=1e-6 * np.abs(o.info).max()) == 3
               for o in observations)
    result = adjust_block(Pose.stack([T_start]), observations, np.zeros(1, dtype=bool), BlockConfig())
    assert np.abs([t.predicted(result.poses) - t.xyz for t in ties]).max() < 1e-6
    assert np.allclose(result.poses.t_xyz[0], T_true.t_xyz, atol=1e-6)
    # Linearised at the adjusted pose, the observations hold it there.
    again = control_observations(ties, [station], rates, previous=result)
    assert np.allclose(adjust_block(result.poses, again, np.zeros(1, dtype=bool), BlockConfig()).poses.t_xyz,
                       T_true.t_xyz, atol=1e-7)


def test_one_or_two_points_leave_rotations_free_and_the_first_station_holds_them():
    def tie(x: float, y: float) -> ControlTie:
        return ControlTie("P", 0, np.zeros(3), np.array([x, y, 0.0]), np.eye(3), 0.0, 0.0)

    axes, words = free_rotations([tie(0, 0)])
    assert len(axes) == 3 and words == "translations"
    axes, words = free_rotations([tie(0, 0), tie(5, 0)])
    assert np.allclose(np.abs(axes), [[1, 0, 0]]) and "line through them (x)" in words
    assert len(free_rotations([tie(0, 0), tie(5, 0), tie(0, 4)])[0]) == 0
    T = Pose(rotvec_to_quat(np.array([0.0, 0.0, 0.5])), np.zeros(3))
    o = first_station_rotation(axes, 0, T, 1e-6)
    assert o.rank == 1 and np.allclose(o.info[:3], 0.0)
    # the information is on the rotation about object x, expressed in the station frame
    direction = T.rotation_matrix @ np.linalg.eigh(o.info[3:, 3:])[1][:, -1]
    assert np.allclose(np.abs(direction), [1, 0, 0], atol=1e-9)


def test_loa_bands():
    assert [loa_class(v) for v in (0.5, 1.0, 1.01, 5.0, 14.9, 15.0, 49.0, 50.0, 50.1)] == [
        "LOA50", "LOA50", "LOA40", "LOA40", "LOA30", "LOA30", "LOA20", "LOA20", "LOA10"]


@pytest.mark.parametrize(("text", "reason"), [
    ("name,x,y,sigma_mm\nA,1,2,3\n", "missing column(s) z"),
    ("name,x,y,z,sigma_mm\nA,1,2,nan,3\n", "z is not a finite number"),
    ("name,x,y,z,sigma_mm\nA,1,2,3,3\nA,1,2,3,3\n", "point A is given twice"),
    ("name,x,y,z,sigma_mm\nA,500,500,3,3\n", "no control point could be tied to the trajectory"),
    ("name,x,y,z,sigma_mm,t_start,t_end\nA,1,2,3,3,1,2\n", "outside the trajectory's time range"),
])
def test_bad_control_files_stop_with_one_line(tmp_path, capsys, text, reason):
    run = write_synthetic_run(tmp_path / "run", n_points=5000, duration_s=10.0)
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    out = tmp_path / "out"
    for option in ("--control", "--check"):
        code, _, err = run_cli(["process", "-t", run.trajectory_path, "-c", run.cloud_path, "-o", out, option, bad,
                                "--workers", "1"], capsys)
        lines = [line for line in err.splitlines() if line.startswith("kinreg: error")]
        assert code == 1 and len(lines) == 1 and str(bad) in lines[0], err
        assert (reason if option == "--control" else reason.replace("control point", "check point")) in lines[0]
        assert "Traceback" not in err
        assert not (out / "report.json").exists() and not (out / "stations.csv").exists()


@pytest.mark.slow
def test_simulated_run_with_four_control_points_and_a_wrong_one(tmp_path):
    """Four control points at the stand-stills of a simulated walk, the first moved by 5 cm; the
    others' check points: the wrong point is rejected and named, the stations land within a few mm."""
    from kinreg.io.trajectory import read_trajectory
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import control_csv, write_run
    from kinreg.simulation.run import config_from_dict, simulate_run

    sample = Path(__file__).resolve().parents[1] / "sample_data"
    base = config_from_dict(json.loads((sample / "run_meta.json").read_text())["config"])
    cfg = dataclasses.replace(base, seed=3, walk=dataclasses.replace(base.walk, stand_stills=6))
    run = simulate_run(cfg)
    data = tmp_path / "data"
    write_run(run, data)
    control, check = tmp_path / "control.csv", tmp_path / "check.csv"
    control.write_text(control_csv(run, names=["CP01", "CP02", "CP04", "CP05", "CP06"],
                                   moved={"CP04": (0.05, 0.0, 0.0)}))
    check.write_text(control_csv(run, noise=False, names=["CP03"]))
    out = tmp_path / "out"
    process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz", control=control, check=check), out,
            KinregConfig())
    report = json.loads((out / "report.json").read_text())
    assert report["control"]["rejected"] == ["CP04"]
    assert "5 control point(s)" in report["adjustment"]["datum"]
    assert report["check"]["summary"]["d3d_mm"]["rms"] < 10.0
    assert (out / "control_points.csv").read_text().count("\n") == 1 + 5 + 1
    rows = np.genfromtxt(out / "stations.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    truth = read_trajectory(data / "truth_trajectory.txt").pose_at(rows["t"].astype(float)).t_xyz
    err = np.column_stack([rows["x"], rows["y"], rows["z"]]) - truth
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.01


def _walk_stations(traj: Trajectory, times: np.ndarray) -> tuple[list[Station], Pose, Pose]:
    """Stations at ``times`` on ``traj`` and their adjusted poses: each turned about its own
    position and shifted by a correction that grows along the run (1 mdeg and (1, -0.5, 0.3) mm
    per station)."""
    initial = traj.pose_at(times)
    stations = [_station(k, initial[k], float(t)) for k, t in enumerate(times)]
    k = np.arange(len(times))[:, None]
    turn = rotvec_to_quat(np.radians(1e-3) * k * np.array([[0.3, -0.2, 1.0]]))
    adjusted = Pose(Pose(turn, np.zeros((len(k), 3))).compose(Pose(initial.quat_wxyz, np.zeros((len(k), 3)))).quat_wxyz,
                    initial.t_xyz + 1e-3 * k * np.array([[1.0, -0.5, 0.3]]))
    return stations, initial, adjusted


def test_the_control_point_lies_where_the_corrected_trajectory_puts_it():
    """A stand-still between two stations 6 s apart: the tie interpolates between them as the
    corrected trajectory does, where the nearer station alone errs by the correction's change
    over the time to it (2 s at 1.2 mm per station here)."""
    from kinreg.estimate.control import stand_still_between, tie_points
    from kinreg.estimate.correction import DriftCorrection

    traj, stills = _still_trajectory()
    config = ControlConfig(reference_point_m=(0.0, 0.0, -1.3))  # a pole to the ground
    still = stand_still_between(traj, *stills[0], np.asarray(config.reference_point_m))  # mean time 110 s
    stations, initial, adjusted = _walk_stations(traj, 102.0 + 6.0 * np.arange(6))
    assignment = Assignment(("P",), still.xyz[None, :], np.array([0.003]), (still,), ())
    (tie,) = tie_points(assignment, stations, [traj], config)
    assert (tie.station, tie.other) == (1, 2) and tie.share == pytest.approx(2.0 / 6.0, abs=0.01)
    correction = DriftCorrection.from_stations(np.array([s.t_s for s in stations]), initial, adjusted, traj)
    at_still = correction.apply_to_trajectory(Trajectory(np.array([still.t_s]), traj.pose_at(np.array([still.t_s]))))
    corrected = at_still.poses.apply(np.asarray(config.reference_point_m)[None, :])[0]
    nearest_only = adjusted[tie.station].apply(tie.q_scan[None, :])[0]
    assert np.linalg.norm(tie.predicted(adjusted) - corrected) < 2e-5
    assert np.linalg.norm(nearest_only - corrected) > 3e-4


def test_the_point_observation_jacobians_match_finite_differences():
    from kinreg.estimate.block import _arrays, _linearise

    traj, stills = _still_trajectory()
    stations, _, adjusted = _walk_stations(traj, 102.0 + 6.0 * np.arange(4))
    tie = ControlTie("P", 1, np.array([0.3, -0.2, -1.3]), np.array([5.0, 0.5, 0.0]), 1e-6 * np.eye(3), 110.0, 2.0,
                     2, np.array([-0.4, 0.1, -1.2]), 0.3)
    rates = DriftRates(np.zeros(3), np.zeros(3), 1e-4, 1e-5)
    observations = control_observations([tie], stations, rates)
    assert observations[0].rank == 3 and (observations[0].i, observations[0].j) == (1, 2)
    a = _arrays(observations, np.ones(1, dtype=bool), -np.ones(4, dtype=int), {"point": 1.0})
    e, J = _linearise(adjusted, np.zeros((0, 6)), a)
    assert np.allclose(e[0, :3], tie.predicted(adjusted) - tie.xyz) and np.allclose(e[0, 3:], 0.0)
    for slot, station in ((0, 1), (1, 2)):
        for axis in range(6):
            step = np.zeros((4, 6))
            step[station, axis] = 1e-6
            moved, _ = _linearise(adjusted.compose(Pose.exp(step)), np.zeros((0, 6)), a, jacobians=False)
            assert np.allclose((moved[0] - e[0]) / 1e-6, J[0, slot, :, axis], atol=1e-5)


def _held_trajectory(speed_mps: float, sway_m: float, sway_hz: float, yaw_deg_per_s: float = 0.0,
                     seconds: float = 20.0) -> Trajectory:
    """100 Hz: a walk along x at ``speed_mps`` (0: standing) with a hand's sway of ``sway_m``
    amplitude per axis at about ``sway_hz`` (out of phase between the axes), turning about z at
    ``yaw_deg_per_s``."""
    t = np.arange(0.0, seconds, 0.01)
    phase = 2.0 * np.pi * sway_hz * t
    xyz = np.column_stack([speed_mps * t + sway_m * np.sin(phase), sway_m * np.sin(0.83 * phase + 1.0),
                           1.3 + sway_m * np.sin(1.21 * phase + 2.0)])
    yaw = np.radians(yaw_deg_per_s) * t + np.radians(0.5) * np.sin(phase)
    q = rotvec_to_quat(np.column_stack([np.zeros_like(t), np.zeros_like(t), yaw]))
    return Trajectory(t, Pose(q, xyz))


@pytest.mark.parametrize(("sway_m", "sway_hz"), [(0.005, 1.2), (0.01, 0.6), (0.01, 0.3)])
def test_a_hand_held_stand_still_is_found_and_slow_walking_or_turning_is_not(sway_m, sway_hz):
    """Sway of up to 2 cm extent per axis at up to 5 cm/s is a stand-still; the same sway while
    walking at 0.25 m/s, or turning on the spot at 30 deg/s, is not."""
    standing = _held_trajectory(0.0, sway_m, sway_hz)
    speed = np.linalg.norm(np.diff(standing.poses.t_xyz, axis=0), axis=1) / 0.01
    assert np.ptp(standing.poses.t_xyz, axis=0).max() <= 0.0201 and np.median(speed) <= 0.051
    found = find_stand_stills(standing, ControlConfig())
    assert len(found) == 1 and found[0].duration_s > 19.0 and found[0].detected
    assert found[0].scatter_mm < 1000.0 * math.sqrt(3.0) * sway_m
    assert find_stand_stills(_held_trajectory(0.25, sway_m, sway_hz), ControlConfig()) == []
    assert find_stand_stills(_held_trajectory(0.0, sway_m, sway_hz, yaw_deg_per_s=30.0), ControlConfig()) == []


def test_the_simulators_stand_stills_sway_and_are_all_found():
    """The simulated walk's stand-stills keep a hand's sway (a few cm/s, 1-2 cm per axis); every one
    is found, with default settings, on the exported trajectory, at sway up to 5 cm/s median."""
    from kinreg.simulation.run import config_from_dict, simulate_run

    sample = Path(__file__).resolve().parents[1] / "sample_data"
    base = config_from_dict(json.loads((sample / "run_meta.json").read_text())["config"])
    for sway_m in (base.walk.stand_still_sway_m, 0.005):
        walk = dataclasses.replace(base.walk, stand_stills=6, stand_still_sway_m=sway_m)
        run = simulate_run(dataclasses.replace(base, seed=3, walk=walk))
        t, xyz = run.truth.stamps_s, run.truth.poses.t_xyz
        found = find_stand_stills(run.slam, ControlConfig())
        for a, b in run.stand_stills():
            held = (t >= a) & (t <= b)
            speed = np.linalg.norm(np.diff(xyz[held], axis=0), axis=1) / np.diff(t[held])
            assert 0.02 < np.median(speed) <= 0.06 and 0.008 < np.ptp(xyz[held], axis=0).max() <= 0.026
            assert sum(s.t_start_s <= a + 0.3 and b - 0.3 <= s.t_end_s for s in found) == 1
