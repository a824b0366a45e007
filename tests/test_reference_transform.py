"""``[initial_transform]`` of a reference-plane file (issue 5): the parser, the corrected cloud's
frame change, and ``kinreg process --reference`` on the committed sample run moved into an
arbitrary SLAM frame (origin 170 m away, heading 137 degrees, not levelled)."""

from __future__ import annotations

import csv
import json

import laspy
import numpy as np
import pytest
from conftest import SAMPLE_DATA, make_trajectory
from kinreg_cli.main import main

from kinreg.calibration.model import SystemCalibration, assign_points_to_planes
from kinreg.errors import ConfigError
from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.reference_planes import parse_reference_planes, read_reference_planes, rotation_from_degrees
from kinreg.io.trajectory import read_trajectory, write_trajectory_geoslam
from kinreg.run.corrected_cloud import write_corrected_las
from kinreg.types import Trajectory

PLANES = "plane_construction_accuracy_m = 0.05\n[[plane]]\nname = 'floor'\nnormal = [0, 0, 1]\nd_m = 0\n"

# The SLAM frame of the test run: T_ref_slam, x_ref = R x_slam + t. Far enough that, without the
# transform, no detected plane (boxes have random yaw) falls by chance within the association gates.
ROTATION_DEG = [2.0, -3.0, 137.0]
TRANSLATION_M = [-150.0, 80.0, -20.0]
DURATION_S = 100.0  # of the 240 s sample run, to keep this file fast


def transform(text: str) -> Pose:
    T = parse_reference_planes(PLANES + "[initial_transform]\n" + text, source="ref.toml").T_ref_traj
    assert T is not None
    return T


def matrix_toml(M: np.ndarray, decimals: int = 12) -> str:
    rows = ", ".join("[" + ", ".join(f"{v:.{decimals}f}" for v in row) + "]" for row in M)
    return f"matrix = [{rows}]\n"


def test_without_initial_transform_there_is_none():
    assert parse_reference_planes(PLANES).T_ref_traj is None


def test_rotation_and_translation():
    T = transform("rotation_deg = [0, 0, 90]\ntranslation_m = [10.0, 20.0, 30.0]\n")
    np.testing.assert_allclose(T.apply([1.0, 0.0, 0.0]), [10.0, 21.0, 30.0], atol=1e-12)  # heading +90: x -> y


def test_rotation_convention_is_fixed_axes_x_then_y_then_z():
    from scipy.spatial.transform import Rotation

    angles = [10.0, -20.0, 30.0]
    T = transform(f"rotation_deg = {angles}\n")
    rx, ry, rz = (Rotation.from_rotvec(np.radians(a) * e).as_matrix() for a, e in zip(angles, np.eye(3), strict=True))
    np.testing.assert_allclose(T.rotation_matrix, rz @ ry @ rx, atol=1e-12)
    np.testing.assert_allclose(T.rotation_matrix, Rotation.from_euler("xyz", angles, degrees=True).as_matrix(),
                               atol=1e-12)
    np.testing.assert_allclose(T.t_xyz, 0.0)  # a missing translation is zero


def test_translation_alone():
    T = transform("translation_m = [512300.25, 5402100.5, 312]\n")
    np.testing.assert_allclose(T.rotation_matrix, np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(T.t_xyz, [512300.25, 5402100.5, 312.0])


def test_matrix_gives_the_same_pose():
    expected = Pose.from_rotation_translation(rotation_from_degrees(np.array(ROTATION_DEG)), np.array(TRANSLATION_M))
    T = transform(matrix_toml(expected.as_matrix()))
    np.testing.assert_allclose(T.as_matrix(), expected.as_matrix(), atol=1e-11)


def test_matrix_printed_with_six_decimals_is_accepted_as_the_nearest_rotation():
    expected = Pose.from_rotation_translation(rotation_from_degrees(np.array(ROTATION_DEG)), np.array(TRANSLATION_M))
    T = transform(matrix_toml(expected.as_matrix(), decimals=6))
    R = T.rotation_matrix
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R, expected.rotation_matrix, atol=2e-6)


SCALED = matrix_toml(np.diag([1.01, 1.0, 1.0, 1.0]))
SHEARED = matrix_toml(np.array([[1.0, 0.01, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
MIRRORED = matrix_toml(np.diag([1.0, 1.0, -1.0, 1.0]))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (SCALED, "not orthonormal"),
        (SHEARED, "not orthonormal"),
        (matrix_toml(np.diag([1e300, 1.0, 1.0, 1.0])), "not orthonormal"),
        (MIRRORED, "determinant -1"),
        ("matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]\n", "4 rows of 4 numbers"),
        ("matrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]]\n", "4 rows of 4 numbers"),
        ("matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]\n", "last row must be 0 0 0 1"),
        ("matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 'one']]\n", "must be a number"),
        ("matrix = 1\n", "4 rows of 4 numbers"),
        ("rotation_deg = [0, 0, 90]\nmatrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n",
         "not both"),
        ("rotation_deg = [0, 90]\n", "rotation_deg must be a list of 3 numbers"),
        ("translation_m = [0, 0, nan]\n", "must be finite"),
        ("heading_deg = 90\n", "unknown key"),
        ("", "give rotation_deg and translation_m, or matrix"),
    ],
)
def test_bad_initial_transform_is_one_line_config_error(text, message):
    with pytest.raises(ConfigError, match=message) as info:
        parse_reference_planes(PLANES + "[initial_transform]\n" + text, source="ref.toml")
    assert "\n" not in str(info.value)
    assert info.value.path == "ref.toml"
    assert "[initial_transform]" in str(info.value)


def test_initial_transform_must_be_a_table():
    with pytest.raises(ConfigError, match=r"\[initial_transform\] must be a table"):
        parse_reference_planes("initial_transform = 5\n" + PLANES, source="ref.toml")


def test_error_names_the_file(tmp_path):
    path = tmp_path / "reference.toml"
    path.write_text(PLANES + "[initial_transform]\n" + SCALED)
    with pytest.raises(ConfigError, match="not orthonormal") as info:
        read_reference_planes(path)
    assert str(info.value).startswith(f"{path}: [initial_transform]")


def test_calibration_refuses_an_initial_transform():
    planes = parse_reference_planes(PLANES + "[initial_transform]\ntranslation_m = [1, 0, 0]\n", source="ref.toml")
    trajectory = Trajectory(np.array([0.0, 1.0]), Pose.identity(2))
    with pytest.raises(ConfigError, match="calibration needs the trajectory in the planes' frame"):
        assign_points_to_planes(np.zeros((1, 3)), np.zeros(1), trajectory, planes,
                                SystemCalibration(np.zeros(3), np.zeros(3)), 0.05)


def test_corrected_cloud_is_mapped_into_a_far_frame_with_its_offsets(tmp_path):
    """A UTM-size translation would overflow the 0.1 mm integers of the input's offsets."""
    rng = np.random.default_rng(5)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.0001] * 3, [10.0, 5.0, 1.0]
    las = laspy.LasData(header)
    xyz = rng.uniform([0, 0, 0], [20, 10, 3], (1000, 3))
    las.x, las.y, las.z = xyz.T
    las.gps_time = np.sort(rng.uniform(0.0, 10.0, 1000))
    las.intensity = rng.integers(0, 65535, 1000)
    las.write(tmp_path / "in.laz")
    T_ref_cloud = Pose(rotvec_to_quat(np.radians([1.0, -2.0, 120.0])), np.array([512300.0, 5402100.0, 300.0]))
    trajectory = Trajectory(np.array([-1.0, 11.0]), T_ref_cloud.compose(Pose.identity(2)))
    none = DriftCorrection(np.array([5.0]), np.zeros((1, 3)), np.zeros((1, 3)), trajectory)
    write_corrected_las(tmp_path / "in.laz", tmp_path / "out.laz", none, T_obj_cloud=T_ref_cloud)
    out = laspy.read(tmp_path / "out.laz")
    src = laspy.read(tmp_path / "in.laz")
    expected = T_ref_cloud.apply(np.column_stack([src.x, src.y, src.z]))
    np.testing.assert_allclose(np.column_stack([out.x, out.y, out.z]), expected, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(out.gps_time, src.gps_time)
    np.testing.assert_array_equal(out.intensity, src.intensity)
    np.testing.assert_allclose(out.header.offsets, T_ref_cloud.apply(np.array([10.0, 5.0, 1.0])), atol=1e-3)
    np.testing.assert_allclose(out.header.mins, expected.min(axis=0), atol=1e-4)


def test_a_constant_correction_is_exact_between_stations():
    """What a rough initial transform leaves is one rigid transform for every station; the
    correction must reproduce it on every pose and point, not only at the stations."""
    trajectory = make_trajectory(duration_s=30.0, offset=(512300.0, 5402100.0, 300.0))
    E = Pose(rotvec_to_quat(np.radians([0.1, -0.1, 0.3])), np.array([0.05, -0.04, 0.03]))
    E = Pose(E.quat_wxyz, E.t_xyz + trajectory.poses.t_xyz[0] - E.apply(trajectory.poses.t_xyz[0]))  # about the run
    stamps = trajectory.stamps_s[300::600]  # a station every 6 s
    initial = trajectory.pose_at(stamps)
    correction = DriftCorrection.from_stations(stamps, initial, E.compose(initial), trajectory)
    corrected = correction.apply_to_trajectory(trajectory)
    np.testing.assert_allclose(corrected.poses.t_xyz, E.apply(trajectory.poses.t_xyz), rtol=0, atol=1e-8)
    q_expected = E.compose(trajectory.poses).quat_wxyz
    np.testing.assert_allclose(np.abs(np.sum(corrected.poses.quat_wxyz * q_expected, axis=1)), 1.0, atol=1e-12)
    points = trajectory.poses.t_xyz + [1.0, -2.0, 0.5]
    np.testing.assert_allclose(correction.apply_to_points(points, trajectory.stamps_s), E.apply(points), rtol=0,
                               atol=1e-8)


# --------------------------------------------------------------------------- the sample run, in a SLAM frame


@pytest.fixture(scope="module")
def slam_run(tmp_path_factory):
    """The first ``DURATION_S`` of the sample run (corridor and first room: all three reference
    planes in view), trajectory and cloud mapped with T_slam_ref = T_ref_slam^-1; the truth and the
    reference planes stay in the building's frame."""
    root = tmp_path_factory.mktemp("slam_frame")
    T_slam_ref = Pose.from_rotation_translation(rotation_from_degrees(np.array(ROTATION_DEG)),
                                                np.array(TRANSLATION_M)).inverse()
    trajectory = read_trajectory(SAMPLE_DATA / "run_trajectory.txt")
    keep = trajectory.stamps_s <= trajectory.t_start_s + DURATION_S
    write_trajectory_geoslam(root / "run_trajectory.txt",
                             Trajectory(trajectory.stamps_s[keep], T_slam_ref.compose(trajectory.poses[keep])))
    las = laspy.read(SAMPLE_DATA / "run_cloud.laz")
    las.points = las.points[las.gps_time <= trajectory.stamps_s[keep][-1]]
    xyz = T_slam_ref.apply(np.column_stack([las.x, las.y, las.z]))
    las.change_scaling(offsets=np.round(T_slam_ref.apply(np.asarray(las.header.offsets)), 3))
    las.x, las.y, las.z = xyz.T
    las.write(root / "run_cloud.laz")
    return root


def write_reference(root, name: str, initial_transform: str) -> str:
    path = root / name
    path.write_text((SAMPLE_DATA / "reference.toml").read_text() + initial_transform)
    return str(path)


def run_process(root, name, reference, *more: str):
    with pytest.raises(SystemExit) as info:
        main(["process", "-t", str(root / "run_trajectory.txt"), "-c", str(root / "run_cloud.laz"),
              "-o", str(root / name), "--reference", reference, "--workers", "1", *more])
    return info.value.code


def absolute_errors_mm(out) -> np.ndarray:
    """Station position errors against the truth, no fit (as benchmarks/eval_datum.py)."""
    with open(out / "stations.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["t"]]
    t = np.array([float(r["t"]) for r in rows])
    adjusted = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    truth = read_trajectory(SAMPLE_DATA / "truth_trajectory.txt").pose_at(t).t_xyz
    return np.linalg.norm(adjusted - truth, axis=1) * 1000.0


def check_in_reference_frame(out) -> None:
    # Aligned sample run (benchmarks/datum.json): 0.63 mm RMS, 1.2 mm max.
    errors = absolute_errors_mm(out)
    print(f"{out.name}: absolute station errors {np.sqrt(np.mean(errors**2)):.2f} mm RMS, {errors.max():.2f} mm max")
    assert np.sqrt(np.mean(errors**2)) < 1.5 and errors.max() < 3.0
    report = json.loads((out / "report.json").read_text())
    assert report["adjustment"]["datum"].startswith("reference planes")
    assert all(p["n_ties"] > 0 and abs(p["offset_mean_mm"]) < 2.0 for p in report["reference"]["planes"])
    corrected = read_trajectory(out / "trajectory_corrected.txt")
    truth = read_trajectory(SAMPLE_DATA / "truth_trajectory.txt")
    gap = np.linalg.norm(corrected.poses.t_xyz - truth.pose_at(corrected.stamps_s).t_xyz, axis=1) * 1000.0
    assert np.sqrt(np.mean(gap**2)) < 1.5 and gap.max() < 3.0
    # The corrected cloud is the building again: 24 m x 12 m x 3 m from the origin (inner faces of
    # the outer walls; 1 cm range noise).
    with laspy.open(out / "corrected.laz") as reader:
        mins, maxs = reader.header.mins, reader.header.maxs
    np.testing.assert_allclose(mins, [0.0, 0.0, 0.0], atol=0.1)
    np.testing.assert_allclose(maxs, [24.0, 12.0, 3.0], atol=0.1)


def test_exact_initial_transform_gives_the_reference_frame(slam_run):
    text = f"\n[initial_transform]\nrotation_deg = {ROTATION_DEG}\ntranslation_m = {TRANSLATION_M}\n"
    assert run_process(slam_run, "exact", write_reference(slam_run, "exact.toml", text)) == 0
    check_in_reference_frame(slam_run / "exact")


def test_rough_initial_transform_as_matrix_is_enough(slam_run):
    """0.1-0.3 degrees (about the run's centre) and 5 cm off, pasted with 6 decimals: the
    adjustment finds the exact datum."""
    T_ref_slam = Pose.from_rotation_translation(rotation_from_degrees(np.array(ROTATION_DEG)), np.array(TRANSLATION_M))
    centre = Pose.identity()
    centre = Pose(centre.quat_wxyz, read_trajectory(slam_run / "run_trajectory.txt").poses.t_xyz.mean(axis=0))
    error = centre.compose(Pose.exp(np.concatenate([[0.05, -0.04, 0.03], np.radians([0.1, -0.1, 0.3])])))
    error = error.compose(centre.inverse())
    text = "\n[initial_transform]\n" + matrix_toml(T_ref_slam.compose(error).as_matrix(), decimals=6)
    assert run_process(slam_run, "rough", write_reference(slam_run, "rough.toml", text)) == 0
    check_in_reference_frame(slam_run / "rough")


def test_without_initial_transform_nothing_is_tied(slam_run, capsys):
    reference = write_reference(slam_run, "plain.toml", "")
    assert run_process(slam_run, "plain", reference) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"kinreg: error: {reference}: no detected plane could be tied to a reference plane")
    assert len(err.splitlines()) == 1
    assert not (slam_run / "plain" / "stations.csv").exists()
