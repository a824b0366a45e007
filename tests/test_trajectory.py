from pathlib import Path

import numpy as np
import pytest
from conftest import make_trajectory

from kinreg.errors import TrajectoryError
from kinreg.geometry import rotation_angle_rad
from kinreg.io.trajectory import (
    parse_column_mapping,
    read_trajectory,
    write_trajectory_geoslam,
    write_trajectory_ply,
    write_trajectory_tum,
)


def assert_same_trajectory(a, b, pos_tol=1e-6, ang_tol=1e-8):
    np.testing.assert_allclose(a.stamps_s, b.stamps_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.poses.t_xyz, b.poses.t_xyz, rtol=0, atol=pos_tol)
    rel = a.poses.inverse().compose(b.poses)
    assert np.max(rotation_angle_rad(rel)) < ang_tol


@pytest.mark.realdata
def test_real_geoslam_export(realdata):
    traj = read_trajectory(realdata / "ScanSecondRun_traj.txt")
    assert len(traj) == 19_879
    assert traj.duration_s == pytest.approx(198.79, abs=0.01)
    assert traj.path_length_m() == pytest.approx(263.3, abs=0.1)
    np.testing.assert_allclose(np.linalg.norm(traj.poses.quat_wxyz, axis=1), 1.0, atol=1e-12)
    # first row, scalar-first order, as in the file (sign continuity keeps the first row's sign)
    np.testing.assert_allclose(traj.poses.quat_wxyz[0], [-0.450888764527178, 0.502962443783221,
                                                         0.642309645603965, 0.36216905076342], atol=1e-12)
    np.testing.assert_allclose(traj.poses.t_xyz[0], [0.0493821200789658, 0.0143770292024249, 0.0314643918326913])
    assert traj.stamps_s.dtype == np.float64 and traj.stamps_s[0] == 1637765767.22855
    mid = 0.5 * (traj.stamps_s[100] + traj.stamps_s[101])
    p = traj.pose_at(mid)
    np.testing.assert_allclose(p.t_xyz, 0.5 * (traj.poses.t_xyz[100] + traj.poses.t_xyz[101]), atol=1e-12)


@pytest.mark.parametrize("writer", ["geoslam", "tum", "ply-binary", "ply-ascii"])
def test_writers_round_trip_through_readers(tmp_path, writer):
    traj = make_trajectory(5.0, offset=(500000.0, 5400000.0, 300.0))
    path = tmp_path / {"geoslam": "t.txt", "tum": "t.tum", "ply-binary": "t.ply", "ply-ascii": "a.ply"}[writer]
    if writer == "geoslam":
        write_trajectory_geoslam(path, traj)
    elif writer == "tum":
        write_trajectory_tum(path, traj)
    else:
        write_trajectory_ply(path, traj, binary=writer == "ply-binary")
    back = read_trajectory(path)
    tol = 1e-9 if writer == "ply-binary" else 1e-6
    assert_same_trajectory(traj, back, pos_tol=tol, ang_tol=1e-8)


def test_tum_order_is_xyzw(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n0.0 1 2 3 0 0 0 1\n"
                    "1.0 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n")
    traj = read_trajectory(path)  # recognised by its header
    np.testing.assert_allclose(traj.poses.quat_wxyz[1], [0.7071067811865476, 0, 0, 0.7071067811865476])


def test_csv_with_column_mapping(tmp_path):
    path = tmp_path / "traj.csv"
    path.write_text("gps;E;N;H;w;i;j;k;speed\n10.0;1;2;3;1;0;0;0;5\n10.5;2;2;3;1;0;0;0;5\n11.0;3;2;3;1;0;0;0;5\n")
    mapping = parse_column_mapping("time=gps,x=E,y=N,z=H,qw=w,qx=i,qy=j,qz=k")
    traj = read_trajectory(path, columns=mapping)
    np.testing.assert_allclose(traj.poses.t_xyz[:, 0], [1, 2, 3])
    with pytest.raises(TrajectoryError, match="no column for 'time'"):
        read_trajectory(path)


def test_csv_with_common_header_names(tmp_path):
    path = tmp_path / "traj.csv"
    path.write_text("time,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n1,1,0,0,1,0,0,0\n")
    assert len(read_trajectory(path)) == 2


def test_geoslam_extra_columns_and_trailing_spaces(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("%time x y z q0 q1 q2 q3 userfields\n1 0 0 0 1 0 0 0 7 8 \n2 1 0 0 1 0 0 0 7 8   \n\n")
    traj = read_trajectory(path)
    assert len(traj) == 2


BAD_TRAJECTORIES = {
    "non-numeric": ("%time x y z q0 q1 q2 q3\n1 0 0 0 1 0 0 0\n2 0 abc 0 1 0 0 0\n", r"row 3: 'abc' is not a number"),
    "nan": ("1 0 0 0 1 0 0 0\n2 0 nan 0 1 0 0 0\n", r"row 2: value is not finite"),
    "duplicate time": ("1 0 0 0 1 0 0 0\n2 0 0 0 1 0 0 0\n2 0 0 0 1 0 0 0\n", r"row 3: time 2.000000 repeats"),
    "decreasing time": ("1 0 0 0 1 0 0 0\n3 0 0 0 1 0 0 0\n2 0 0 0 1 0 0 0\n", r"row 3: .* goes back"),
    "non-unit quaternion": ("1 0 0 0 1 0 0 0\n2 0 0 0 1.01 0 0 0\n", r"row 2: quaternion norm 1.010000"),
    "one row": ("1 0 0 0 1 0 0 0\n", r"1 pose row\(s\); a trajectory needs at least two"),
    "empty": ("", r"0 pose row\(s\)"),
    "too few columns": ("1 0 0 0 1 0 0\n2 0 0 0 1 0 0\n", r"row 1: 7 values, expected at least 8"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRAJECTORIES))
def test_bad_trajectories_name_file_and_row(tmp_path, case):
    text, message = BAD_TRAJECTORIES[case]
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=message) as info:
        read_trajectory(path)
    assert str(info.value).startswith(str(path))


def test_quaternion_within_tolerance_is_renormalised_and_sign_made_continuous(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("1 0 0 0 1.0005 0 0 0\n2 0 0 0 -1 0 0 0\n3 0 0 0 0.99 0 0 0.141\n")
    traj = read_trajectory(path)
    np.testing.assert_allclose(np.linalg.norm(traj.poses.quat_wxyz, axis=1), 1.0, atol=1e-15)
    assert np.all(np.sum(traj.poses.quat_wxyz[1:] * traj.poses.quat_wxyz[:-1], axis=1) > 0)


def test_pose_at_outside_range_is_a_clear_error():
    traj = make_trajectory(2.0)
    with pytest.raises(TrajectoryError, match="outside the trajectory's range"):
        traj.pose_at(traj.t_end_s + 0.5)


def test_binary_file_is_rejected(tmp_path):
    path = tmp_path / "t.txt"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(TrajectoryError):
        read_trajectory(path)


def test_missing_file(tmp_path):
    with pytest.raises(TrajectoryError, match="file not found"):
        read_trajectory(tmp_path / "nope.txt")


def test_truncated_binary_ply(tmp_path):
    path = tmp_path / "t.ply"
    write_trajectory_ply(path, make_trajectory(1.0))
    data = path.read_bytes()
    Path(path).write_bytes(data[:-100])
    with pytest.raises(TrajectoryError, match="PLY file ends after"):
        read_trajectory(path)
