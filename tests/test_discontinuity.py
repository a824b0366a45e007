"""Jumps in a SLAM trajectory (issue 8): found at the right interval with the right step, no false
alarms on clean, jittered, gappy or slowly drifting trajectories, and removed exactly."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SAMPLE_DATA, make_trajectory

from kinreg.errors import ConfigError
from kinreg.estimate.jumps import (
    DiscontinuityConfig,
    detect_jumps,
    jumps_between,
    relative_pose_without_step,
    remove_jumps,
    step_between,
)
from kinreg.geometry import Pose, quat_to_matrix, rotation_angle_rad, rotvec_to_quat
from kinreg.io.trajectory import read_trajectory
from kinreg.simulation.drift import DriftConfig, apply_drift, make_drift
from kinreg.simulation.scene import BuildingConfig, BuildingLayout, make_building
from kinreg.simulation.walk import WalkConfig, make_walk
from kinreg.types import Trajectory, TrajectoryJump

UTM = np.array([500000.0, 5400000.0, 300.0])


@pytest.fixture(scope="module")
def sample() -> Trajectory:
    return read_trajectory(SAMPLE_DATA / "run_trajectory.txt")


def step_about(pivot_xyz, translation_m=(0.0, 0.0, 0.0), rotvec_deg=(0.0, 0.0, 0.0)) -> Pose:
    """The object-frame step x -> R (x - pivot) + pivot + translation."""
    q = rotvec_to_quat(np.radians(rotvec_deg))
    pivot = np.asarray(pivot_xyz, dtype=np.float64)
    return Pose(q, pivot + np.asarray(translation_m, dtype=np.float64) - quat_to_matrix(q) @ pivot)


def with_step(traj: Trajectory, index: int, step: Pose) -> Trajectory:
    """A SLAM failure at sample ``index``: T_traj = S . T from there on."""
    q, t = traj.poses.quat_wxyz.copy(), traj.poses.t_xyz.copy()
    moved = step.compose(traj.poses[index:])
    q[index:], t[index:] = moved.quat_wxyz, moved.t_xyz
    return Trajectory(traj.stamps_s, Pose(q, t), traj.source)


def with_offset(traj: Trajectory, offset) -> Trajectory:
    return Trajectory(traj.stamps_s, Pose(traj.poses.quat_wxyz, traj.poses.t_xyz + offset), traj.source)


def step_errors(found: Pose, true: Pose, at_xyz) -> tuple[float, float]:
    """Translation error (m) of the two steps at a point, rotation error (deg)."""
    d_t = float(np.linalg.norm(found.apply(at_xyz) - true.apply(at_xyz)))
    return d_t, float(np.degrees(rotation_angle_rad(true.inverse().compose(found))))


def trajectory_errors(a: Trajectory, b: Trajectory) -> tuple[float, float]:
    """Largest position (m) and rotation (deg) difference over all rows."""
    d_t = float(np.max(np.linalg.norm(a.poses.t_xyz - b.poses.t_xyz, axis=1)))
    return d_t, float(np.degrees(np.max(rotation_angle_rad(a.poses.inverse().compose(b.poses)))))


# --------------------------------------------------------------------------- no false alarms


@pytest.mark.parametrize("name", ["run_trajectory.txt", "truth_trajectory.txt"])
def test_clean_sample_run_has_no_jumps(name):
    assert detect_jumps(read_trajectory(SAMPLE_DATA / name)) == []


@pytest.mark.parametrize(("layout", "walk"), [
    (BuildingLayout.CENTRAL_CORRIDOR, WalkConfig()),
    (BuildingLayout.CORRIDOR_ROW, WalkConfig(speed_mps=1.4, max_speed_mps=1.6, bob_m=0.03, sway_deg=6.0,
                                             jitter_deg=3.0)),
    (BuildingLayout.CORRIDOR_ROW, WalkConfig(rate_hz=50.0)),
])
def test_other_simulated_walks_have_no_jumps(layout, walk):
    rng = np.random.default_rng(4)
    truth = make_walk(make_building(BuildingConfig(layout=layout, seed=4)), walk, 150.0, 1.6e9, rng)
    drift = make_drift(truth.stamps_s, truth.poses.t_xyz[0], DriftConfig(0.2, 1.0), rng)  # 5 x the default
    assert detect_jumps(truth) == []
    assert detect_jumps(apply_drift(truth, drift)) == []


def test_gradual_drift_of_the_same_size_is_not_a_jump(sample):
    # 0.5 m and 2 deg spread linearly over 10 s while walking (sharp start and end of the ramp)
    i0, i1 = 9000, 10000
    u = np.clip((np.arange(len(sample)) - i0) / (i1 - i0), 0.0, 1.0)
    xi = u[:, None] * np.array([0.5, 0.2, 0.0, 0.0, 0.0, np.radians(2.0)])
    drift = Pose.exp(xi)
    pivot = sample.poses.t_xyz[i0]
    centred = Pose(sample.poses.quat_wxyz, sample.poses.t_xyz - pivot)
    drifted = drift.compose(centred)
    traj = Trajectory(sample.stamps_s, Pose(drifted.quat_wxyz, drifted.t_xyz + pivot))
    assert detect_jumps(traj) == []


@pytest.mark.parametrize("missing_rows", [10, 50, 100])
def test_gap_in_the_time_stamps_is_not_a_jump(sample, missing_rows):
    # rows missing while walking and turning: up to 0.56 m and 105 deg (1 s in the fastest turn)
    # that the rates around the gap do not predict
    for start in (3000, 8000, 12000, 20000):
        keep = np.ones(len(sample), dtype=bool)
        keep[start:start + missing_rows] = False
        assert detect_jumps(Trajectory(sample.stamps_s[keep], sample.poses[keep])) == []


def test_jump_across_a_gap_beyond_the_scaled_floor_is_found(sample):
    # a 0.1 s gap spans 11 typical intervals: the floors there are 11 x 5 cm and 121 x 1 deg
    keep = np.ones(len(sample), dtype=bool)
    keep[8000:8010] = False
    traj = Trajectory(sample.stamps_s[keep], sample.poses[keep])
    S = step_about(traj.poses.t_xyz[7999], translation_m=(0.0, 1.0, 0.0))
    (jump,) = detect_jumps(with_step(traj, 8000, S))
    assert jump.index == 8000
    assert step_errors(jump.step, S, traj.poses.t_xyz[7999])[0] < 0.02
    assert detect_jumps(with_step(traj, 8000, step_about(traj.poses.t_xyz[7999], (0.0, 0.4, 0.0)))) == []


def jittered(traj: Trajectory, seed: int = 0) -> Trajectory:
    """Stamps written late or early by a few ms (as in the real GeoSLAM file), poses unchanged."""
    rng = np.random.default_rng(seed)
    stamps = traj.stamps_s + rng.choice([-0.003, 0.0, 0.003], len(traj))
    return Trajectory(stamps, traj.poses, traj.source)


def test_jittered_time_stamps_give_no_false_alarm_and_keep_the_step(sample):
    traj = jittered(sample)
    assert detect_jumps(traj) == []
    S = step_about(traj.poses.t_xyz[11999], translation_m=(0.1, 0.0, 0.0))
    (jump,) = detect_jumps(with_step(traj, 12000, S))
    assert jump.index == 12000
    assert step_errors(jump.step, S, traj.poses.t_xyz[11999])[0] < 0.001


# --------------------------------------------------------------------------- jumps found


CASES = {
    "0.5 m x": ((0.5, 0.0, 0.0), (0.0, 0.0, 0.0)),
    "0.2 m y": ((0.0, 0.2, 0.0), (0.0, 0.0, 0.0)),
    "0.1 m z": ((0.0, 0.0, 0.1), (0.0, 0.0, 0.0)),
    "0.1 m oblique": ((0.06, -0.06, 0.05), (0.0, 0.0, 0.0)),
    "2 deg yaw": ((0.0, 0.0, 0.0), (0.0, 0.0, 2.0)),
    "2 deg oblique": ((0.0, 0.0, 0.0), (1.2, -1.0, 1.2)),
    "0.1 m and 1.5 deg": ((0.05, 0.08, 0.0), (0.0, 1.5, 0.0)),
}
# walking, standing still at the start, the fastest turn (200 deg/s), standing still at the end
INSTANTS = [5000, 150, 20048, 23900]


@pytest.mark.parametrize("index", INSTANTS)
@pytest.mark.parametrize("case", list(CASES))
def test_single_jump_found_at_its_interval_with_its_step(sample, case, index):
    translation, rotvec_deg = CASES[case]
    pivot = sample.poses.t_xyz[index - 1]
    S = step_about(pivot, translation, rotvec_deg)
    jumps = detect_jumps(with_step(sample, index, S))
    assert len(jumps) == 1
    (jump,) = jumps
    assert jump.index == index
    assert jump.t_s == sample.stamps_s[index] and jump.t_before_s == sample.stamps_s[index - 1]
    np.testing.assert_allclose(jump.translation_m, translation, atol=0.002)
    assert jump.significance >= 1.0
    d_t, d_r = step_errors(jump.step, S, pivot)
    assert d_t < 0.002 and d_r < 0.05


def test_rotation_about_a_far_origin_is_the_same_step(sample):
    # 2 deg about the object frame's origin 10-20 m away: the scanner is displaced too
    index = 7000
    S = step_about((0.0, 0.0, 0.0), rotvec_deg=(0.0, 0.0, 2.0))
    (jump,) = detect_jumps(with_step(sample, index, S))
    assert jump.index == index
    d_t, d_r = step_errors(jump.step, S, sample.poses.t_xyz[index])
    assert d_t < 0.002 and d_r < 0.05
    assert jump.step_m == pytest.approx(
        float(np.linalg.norm(S.apply(sample.poses.t_xyz[index - 1]) - sample.poses.t_xyz[index - 1])), abs=0.002)


def test_jump_and_its_return_three_samples_later_are_both_found(sample):
    S = step_about(sample.poses.t_xyz[6000], translation_m=(0.0, 0.5, 0.0))
    traj = with_step(sample, 6001, S)
    traj = with_step(traj, 6004, S.inverse())
    jumps = detect_jumps(traj)
    assert [j.index for j in jumps] == [6001, 6004]
    np.testing.assert_allclose(jumps[0].translation_m, [0.0, 0.5, 0.0], atol=0.002)
    np.testing.assert_allclose(jumps[1].translation_m, [0.0, -0.5, 0.0], atol=0.002)
    assert trajectory_errors(remove_jumps(traj, jumps), sample)[0] < 0.002


def test_jumps_at_the_first_and_last_interval(sample):
    traj = Trajectory(sample.stamps_s[1000:3000], sample.poses[1000:3000])
    traj = with_step(traj, 1, step_about(traj.poses.t_xyz[0], translation_m=(0.2, 0.0, 0.0)))
    traj = with_step(traj, 1999, step_about(traj.poses.t_xyz[1998], translation_m=(0.0, 0.0, -0.2)))
    jumps = detect_jumps(traj)
    assert [j.index for j in jumps] == [1, 1999]
    np.testing.assert_allclose(jumps[0].translation_m, [0.2, 0.0, 0.0], atol=0.005)
    np.testing.assert_allclose(jumps[1].translation_m, [0.0, 0.0, -0.2], atol=0.005)


def test_below_the_floors_is_not_reported(sample):
    S = step_about(sample.poses.t_xyz[4999], translation_m=(0.03, 0.0, 0.0), rotvec_deg=(0.0, 0.0, 0.5))
    assert detect_jumps(with_step(sample, 5000, S)) == []
    smaller = DiscontinuityConfig(min_step_m=0.01, min_step_deg=0.2)
    (jump,) = detect_jumps(with_step(sample, 5000, S), smaller)
    assert jump.index == 5000


# --------------------------------------------------------------------------- the benchmark's jumps, removal


def benchmark_jumps(traj: Trajectory, t0_s: float, t1_s: float, jump_m: float = 0.5) -> Trajectory:
    """As benchmarks/eval_robustness.py::with_jumps: x + 0.5 m for stamps in [t0, t1)."""
    moved = traj.poses.t_xyz.copy()
    moved[:, 0] += np.where((traj.stamps_s >= t0_s) & (traj.stamps_s < t1_s), jump_m, 0.0)
    return Trajectory(traj.stamps_s, Pose(traj.poses.quat_wxyz, moved), traj.source)


@pytest.mark.parametrize("offset", [np.zeros(3), UTM])
def test_benchmark_jumps_found_and_removed(sample, offset):
    clean = with_offset(sample, offset)
    t0, t1 = clean.t_start_s + 70.0, clean.t_start_s + 150.0
    traj = benchmark_jumps(clean, t0, t1)
    jumps = detect_jumps(traj)
    i0, i1 = int(np.searchsorted(clean.stamps_s, t0)), int(np.searchsorted(clean.stamps_s, t1))
    assert [j.index for j in jumps] == [i0, i1]
    np.testing.assert_allclose(jumps[0].translation_m, [0.5, 0.0, 0.0], atol=0.002)
    np.testing.assert_allclose(jumps[1].translation_m, [-0.5, 0.0, 0.0], atol=0.002)
    assert max(j.step_deg for j in jumps) < 0.01
    d_t, d_r = trajectory_errors(remove_jumps(traj, jumps), clean)
    assert d_t < 0.001 and d_r < 0.01
    # the step between two stations: across the first jump +0.5 m, across both none
    ta, tb, tc = clean.stamps_s[i0 - 300], clean.stamps_s[i0 + 300], clean.stamps_s[i1 + 300]
    # (what a step does at the scanner: its t_xyz alone is meaningless far from the origin)
    x_b = clean.poses.t_xyz[i0 + 300]
    assert step_between(jumps, ta, tb).apply(x_b) - x_b == pytest.approx([0.5, 0.0, 0.0], abs=0.002)
    assert np.linalg.norm(step_between(jumps, ta, tc).apply(x_b) - x_b) < 0.002
    assert step_between(jumps, tb, ta).apply(x_b) - x_b == pytest.approx([-0.5, 0.0, 0.0], abs=0.002)
    assert [j.index for j in jumps_between(jumps, ta, tb)] == [i0]
    assert jumps_between(jumps, tb, clean.stamps_s[i1 - 1]) == []


def test_remove_jumps_restores_the_trajectory_after_several_steps(sample):
    steps = [
        (3000, step_about(sample.poses.t_xyz[2999], (0.5, 0.0, 0.0))),
        (9000, step_about((0.0, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, 0.0, 2.0))),
        (15000, step_about(sample.poses.t_xyz[14999], (0.0, 0.0, 0.1), (1.5, 0.0, 0.0))),
        (21000, step_about(sample.poses.t_xyz[20999], (-0.3, 0.1, 0.0), (0.0, -1.2, 1.2))),
    ]
    traj = sample
    for index, S in steps:
        traj = with_step(traj, index, S)
    jumps = detect_jumps(traj)
    assert [j.index for j in jumps] == [index for index, _ in steps]
    fixed = remove_jumps(traj, jumps)
    d_t, d_r = trajectory_errors(fixed, sample)
    assert d_t < 0.002 and d_r < 0.01
    assert detect_jumps(fixed) == []
    # relative poses between stations on either side of several jumps come back
    for a, b in [(2000, 4000), (2500, 16000), (8000, 23000)]:
        B = step_between(jumps, traj.stamps_s[a], traj.stamps_s[b])
        rel = relative_pose_without_step(traj.poses[a], traj.poses[b], B)
        true = sample.poses[a].inverse().compose(sample.poses[b])
        assert step_errors(rel, true, np.zeros(3))[0] < 0.003
        assert step_errors(rel, true, np.zeros(3))[1] < 0.01


def test_remove_jumps_keeps_stamps_extra_and_source(sample):
    extra = np.arange(len(sample), dtype=np.float64)[:, None]
    traj = Trajectory(sample.stamps_s, sample.poses, "file.txt", extra, ("user",))
    jump = TrajectoryJump(index=10, t_s=float(sample.stamps_s[10]), t_before_s=float(sample.stamps_s[9]),
                          translation_m=np.array([1.0, 0.0, 0.0]), rotvec_rad=np.zeros(3),
                          pivot_xyz=sample.poses.t_xyz[9], translation_sigmas=1e3, rotation_sigmas=0.0,
                          significance=20.0, sigma_translation_m=1e-4, sigma_rotation_rad=1e-4)
    out = remove_jumps(traj, [jump])
    assert out.source == "file.txt" and out.extra is extra and out.extra_names == ("user",)
    np.testing.assert_array_equal(out.stamps_s, sample.stamps_s)
    np.testing.assert_allclose(out.poses.t_xyz[:10], sample.poses.t_xyz[:10], atol=0)
    np.testing.assert_allclose(out.poses.t_xyz[10:, 0], sample.poses.t_xyz[10:, 0] - 1.0, atol=1e-12)
    assert remove_jumps(traj, []) is traj


# --------------------------------------------------------------------------- speed, settings, edges


def test_a_30_minute_run_without_jumps_has_none():
    # (Its speed, ~0.3 s, is not a unit test's business: a wall-clock limit failed under load.)
    traj = make_trajectory(1600.0)  # 160,001 rows at 100 Hz
    assert detect_jumps(traj) == []


def test_short_trajectories_and_bad_settings(sample):
    assert detect_jumps(Trajectory(sample.stamps_s[:3], sample.poses[:3])) == []
    short = Trajectory(sample.stamps_s[5000:5012], sample.poses[5000:5012])
    assert detect_jumps(short) == []
    with pytest.raises(ConfigError):
        detect_jumps(sample, DiscontinuityConfig(min_step_m=0.0))
    with pytest.raises(ConfigError):
        detect_jumps(sample, DiscontinuityConfig(window_samples=0))


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_real_geoslam_trajectory_has_no_jumps_and_injected_ones_are_found(realdata):
    traj = read_trajectory(realdata / "ScanSecondRun_traj.txt")  # 84 Hz, stamps jitter 6/12 ms
    assert detect_jumps(traj) == []
    S1 = step_about(traj.poses.t_xyz[4999], (0.1, 0.0, 0.0))
    S2 = step_about(traj.poses.t_xyz[12999], rotvec_deg=(0.0, 0.0, 2.0))
    jumped = with_step(with_step(traj, 5000, S1), 13000, S2)
    jumps = detect_jumps(jumped)
    assert [j.index for j in jumps] == [5000, 13000]
    d_t, d_r = step_errors(jumps[0].step, S1, traj.poses.t_xyz[4999])
    assert d_t < 0.002 and d_r < 0.3
    d_t, d_r = step_errors(jumps[1].step, S2, traj.poses.t_xyz[12999])
    assert d_t < 0.002 and d_r < 0.3
