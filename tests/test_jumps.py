"""Trajectory jumps taken out end to end: the drift correction with jumps, and `kinreg process`
on the sample run with a 0.5 m jump injected in the trajectory and the cloud."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest
from conftest import SAMPLE_DATA

from kinreg.config import KinregConfig
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.jumps import detect_jumps, remove_jumps
from kinreg.geometry import Pose
from kinreg.io.trajectory import read_trajectory, write_trajectory_geoslam
from kinreg.report.json import rigid_fit
from kinreg.run.pipeline import ProcessInputs, process
from kinreg.types import Trajectory

JUMP = np.array([0.5, 0.0, 0.0])


def jumped(trajectory: Trajectory, t_jump: float, t_back: float) -> Trajectory:
    """The trajectory displaced by JUMP between the two times (a SLAM failure and its return)."""
    xyz = trajectory.poses.t_xyz.copy()
    xyz[(trajectory.stamps_s >= t_jump) & (trajectory.stamps_s < t_back)] += JUMP
    return Trajectory(trajectory.stamps_s, Pose(trajectory.poses.quat_wxyz, xyz), trajectory.source)


def test_the_correction_takes_a_jump_out_of_poses_and_points():
    truth = read_trajectory(SAMPLE_DATA / "run_trajectory.txt")
    t0 = truth.stamps_s[0]
    slam = jumped(truth, t0 + 70.0, t0 + 150.0)
    jumps = detect_jumps(slam)
    assert [round(j.t_s - t0, 2) for j in jumps] == [70.0, 150.0]
    stations = truth.stamps_s[::600]
    # the block would return the true poses; the initial ones are the stations' without the jumps
    correction = DriftCorrection.from_stations(stations, remove_jumps(slam, jumps).pose_at(stations),
                                               truth.pose_at(stations), slam, jumps)
    corrected = correction.apply_to_trajectory(slam)
    assert np.abs(corrected.poses.t_xyz - truth.poses.t_xyz).max() < 1e-5
    points = slam.poses.apply(np.tile([1.0, -2.0, 0.5], (len(slam), 1)))
    expected = truth.poses.apply(np.tile([1.0, -2.0, 0.5], (len(truth), 1)))
    assert np.abs(correction.apply_to_points(points, slam.stamps_s) - expected).max() < 1e-5
    # a point half-way through the jump's sample interval, interpolated across the step, gets half of it
    j = jumps[0]
    half = 0.5 * (j.t_before_s + j.t_s)
    inside = np.array([[10.0, 5.0, 1.0]]) + 0.5 * JUMP
    assert np.allclose(correction.without_jumps(np.array([half])).apply(inside), [[10.0, 5.0, 1.0]], atol=1e-9)


def test_without_jumps_the_correction_is_unchanged():
    truth = read_trajectory(SAMPLE_DATA / "run_trajectory.txt")
    stations = truth.stamps_s[::600]
    a = DriftCorrection.from_stations(stations, truth.pose_at(stations), truth.pose_at(stations), truth)
    assert a.jump_steps is None
    assert np.array_equal(a.apply_to_points(truth.poses.t_xyz, truth.stamps_s), truth.poses.t_xyz)


@pytest.mark.parametrize("detect", [True, False])
def test_process_takes_out_a_jump(tmp_path, detect):
    slam = read_trajectory(SAMPLE_DATA / "run_trajectory.txt")
    t0 = slam.stamps_s[0]
    t_jump, t_back = t0 + 150.0, t0 + 400.0  # jumps once, never returns within the run
    write_trajectory_geoslam(tmp_path / "traj.txt", jumped(slam, t_jump, t_back))
    las = laspy.read(SAMPLE_DATA / "run_cloud.laz")
    t = np.asarray(las.gps_time)
    las.x = np.asarray(las.x) + np.where((t >= t_jump) & (t < t_back), JUMP[0], 0.0)
    las.write(tmp_path / "cloud.laz")
    config = KinregConfig()
    if not detect:
        import dataclasses

        config = dataclasses.replace(config, jumps=dataclasses.replace(config.jumps, detect=False))
    process(ProcessInputs(tmp_path / "traj.txt", tmp_path / "cloud.laz"), tmp_path / "out", config)

    report = json.loads((tmp_path / "out" / "report.json").read_text())
    corrected = read_trajectory(tmp_path / "out" / "trajectory_corrected.txt")
    truth = read_trajectory(SAMPLE_DATA / "truth_trajectory.txt").pose_at(corrected.stamps_s).t_xyz
    R, shift = rigid_fit(corrected.poses.t_xyz, truth)
    error = np.linalg.norm(corrected.poses.t_xyz @ R.T + shift - truth, axis=1)
    if not detect:
        assert report["trajectory_jumps"] == []
        assert error.max() > 0.05  # the jump stays in the result: what the detection is for
        return
    assert len(report["trajectory_jumps"]) == 1
    found = report["trajectory_jumps"][0]
    assert found["t"] == pytest.approx(t_jump, abs=0.011)
    assert found["step_m"] == pytest.approx(0.5, abs=0.002)
    # the corrected trajectory is as good as without the jump (sample: a few mm at most)
    assert np.sqrt(np.mean(error**2)) < 0.003
    assert error.max() < 0.010
