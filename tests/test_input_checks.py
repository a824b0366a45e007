"""Issue 17, the input side: every case the issue lists, each in its own test.

Cases that could end the process by a signal (lazrs aborting on a huge allocation) run ``kinreg``
in a subprocess (:mod:`fuzzing`); the others call the entry point in this process.
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import laspy
import numpy as np
import pytest
from clirunner import run_cli
from conftest import SyntheticRun, write_synthetic_run
from fuzzing import (
    REALDATA,
    _set,
    classify,
    e57_first_data_packet,
    e57_fix_checksums,
    run_kinreg,
    small_las,
    write_e57,
)

from kinreg.config import load_config
from kinreg.errors import CloudError, ConfigError, TrajectoryError
from kinreg.estimate.correction import DriftCorrection
from kinreg.io.cloud import TimeFilter, open_cloud
from kinreg.io.e57 import check_static_scans
from kinreg.io.las_header import check_las_file
from kinreg.io.reference_planes import parse_reference_planes
from kinreg.io.timebase import GPS_UNIX_EPOCH_S, GPS_WEEK_S, diagnose_time_base
from kinreg.io.trajectory import read_trajectory
from kinreg.run.corrected_cloud import write_corrected_las

PREFIX = "kinreg: error: "




def refused(args: list[object], bad: Path, capsys: pytest.CaptureFixture[str], reason: str) -> str:
    """Run in-process; assert one line ``kinreg: error: BAD: ...`` matching ``reason``, exit 1."""
    code, _, err = run_cli(args, capsys)
    lines = [line for line in err.splitlines() if line.strip() and "━" not in line]
    assert code == 1, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{PREFIX}{bad}: "), lines[0]
    assert reason in lines[0], lines[0]
    return lines[0]


def refused_in_subprocess(args: list[object], bad: Path, reason: str) -> str:
    code, _, err = run_kinreg(args, timeout_s=120)
    outcome = classify(str(bad), code, err, bad)
    assert outcome.kind == "refused", outcome
    assert len(outcome.lines) == 1 and outcome.names_file, outcome
    assert reason in outcome.lines[0], outcome
    return outcome.lines[0]


@pytest.fixture(scope="module")
def laz14(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return small_las(tmp_path_factory.mktemp("laz") / "base.laz")


@pytest.fixture(scope="module")
def las14(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return small_las(tmp_path_factory.mktemp("las") / "base.las", n_points=30_000)


def mutate(base: Path, tmp_path: Path, name: str, **fields: float) -> Path:
    data = base.read_bytes()
    for field, value in fields.items():
        data = _set(data, field, value)
    path = tmp_path / f"{name}{base.suffix}"
    path.write_bytes(data)
    return path


# --------------------------------------------------------------------------- LAS/LAZ header


def test_laz_with_one_byte_deleted_in_its_chunk_table_is_refused_not_aborted(laz14: Path, tmp_path: Path) -> None:
    """Today: SIGABRT, 'memory allocation of 40533753856 bytes failed' and ~100 Rust frames."""
    data = laz14.read_bytes()
    start = struct.unpack_from("<I", data, 96)[0]
    (table,) = struct.unpack_from("<q", data, start)
    for k in (0, 3, 4, 6, 8, 12):
        path = tmp_path / f"deleted_{k}.laz"
        path.write_bytes(data[:table + k] + data[table + k + 1:])
        with pytest.raises(CloudError, match="chunk table"):
            check_las_file(path)
        refused_in_subprocess(["info", "--full", path], path, "chunk table")


def test_laz_chunk_count_of_2_5_billion_is_refused_before_lazrs_allocates(laz14: Path, tmp_path: Path) -> None:
    data = bytearray(laz14.read_bytes())
    start = struct.unpack_from("<I", data, 96)[0]
    (table,) = struct.unpack_from("<q", data, start)
    struct.pack_into("<I", data, table + 4, 2_533_359_616)  # x 16 bytes = the 40.5 GB of the issue
    path = tmp_path / "chunks.laz"
    path.write_bytes(bytes(data))
    refused_in_subprocess(["info", "--full", path], path, "2,533,359,616 chunks")


@pytest.mark.parametrize("value", [0.0, float("nan"), float("inf"), 1e300, -0.001])
def test_scale_that_is_no_resolution_is_refused(las14: Path, tmp_path: Path, value: float,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    path = mutate(las14, tmp_path, "scale", scale_y=value)
    refused(["info", path], path, capsys, "y scale")


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_offset_that_is_not_finite_is_refused(laz14: Path, tmp_path: Path, value: float,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = mutate(laz14, tmp_path, "offset", offset_z=value)
    refused(["info", path], path, capsys, "z offset")


def test_point_count_0_is_refused(laz14: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error (IndexError)."""
    path = mutate(laz14, tmp_path, "zero", count64=0, legacy_count=0)
    refused(["info", "--full", path], path, capsys, "no points")


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_point_count_lowered_from_30000_to_1_is_refused(tmp_path: Path, suffix: str,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Today: one point read, no warning. The layered LAZ chunk stores its own count."""
    base = small_las(tmp_path / f"base{suffix}", n_points=30_000)
    path = mutate(base, tmp_path, "one", count64=1, legacy_count=1)
    line = refused(["info", "--full", path], path, capsys, "the header says 1 points")
    assert "30,000" in line


def test_point_count_raised_is_refused(las14: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = mutate(las14, tmp_path, "more", count64=30_001, legacy_count=30_001)
    refused(["info", path], path, capsys, "the file holds 30,000")


@pytest.mark.parametrize("minor", [0, 2, 3, 5, 9])
def test_las_minor_version_edited_is_refused(laz14: Path, tmp_path: Path, minor: int,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error (IndexError) for some, silent misreading for others."""
    path = mutate(laz14, tmp_path, f"minor{minor}", version_minor=minor)
    refused(["info", "--full", path], path, capsys, "1.")


@pytest.mark.parametrize("count", [1, 1000, 2**32 - 1])
def test_evlr_count_edited_is_refused(laz14: Path, tmp_path: Path, count: int,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error (MemoryError)."""
    path = mutate(laz14, tmp_path, "evlrs", n_evlrs=count)
    refused(["info", "--full", path], path, capsys, "extended VLR")


def test_truncated_laz_is_one_line_without_library_lines(tmp_path: Path) -> None:
    """Today: the error line plus two lazrs 'IoError' lines (laspy logs them)."""
    data = (REALDATA / "autzen_trim.laz").read_bytes() if (REALDATA / "autzen_trim.laz").exists() else None
    if data is None:
        data = small_las(tmp_path / "base.laz").read_bytes()
    path = tmp_path / "cut.laz"
    path.write_bytes(data[: len(data) // 2])
    refused_in_subprocess(["info", "--full", path], path, "truncated")


def test_real_las_and_laz_files_pass_the_header_checks() -> None:
    for name in ("autzen_trim.laz", "vegetation_1_3.las"):
        if not (REALDATA / name).exists():
            pytest.skip("realdata absent")
        facts = check_las_file(REALDATA / name)
        assert facts.n_points == laspy.open(REALDATA / name).header.point_count


# --------------------------------------------------------------------------- E57


def test_e57_cartesian_bounds_stored_as_string_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error (ValueError)."""
    path = write_e57(tmp_path / "bounds.e57", bounds_as_string=True)
    line = refused(["info", path], path, capsys, "cartesianBounds")
    assert "StringNode" in line


def test_e57_data_packet_type_255_is_refused(tmp_path: Path) -> None:
    """Today: internal error (UnicodeDecodeError from libE57Format's message)."""
    base = write_e57(tmp_path / "base.e57")
    data = bytearray(base.read_bytes())
    data[e57_first_data_packet(bytes(data))] = 255
    path = tmp_path / "packet.e57"
    path.write_bytes(bytes(e57_fix_checksums(data)))
    refused_in_subprocess(["info", "--full", path], path, "cannot read scan 0")


def test_e57_without_scans_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_e57(tmp_path / "empty.e57", n_scans=0)
    refused(["info", path], path, capsys, "no scans")


def test_static_scans_with_a_nan_point_are_refused_before_slicing(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Today: found only after slicing and plane detection."""
    xyz = np.random.default_rng(0).uniform(-5, 5, (100, 3))
    xyz[37, 1] = np.nan
    path = write_e57(tmp_path / "static.e57", n_scans=1, xyz=xyz)
    with pytest.raises(CloudError, match="record 37 has a coordinate that is not finite"):
        check_static_scans(path)
    run = write_synthetic_run(tmp_path / "run", n_points=20_000, duration_s=12.0)
    out = tmp_path / "out"
    refused(["process", "-t", run.trajectory_path, "-c", run.cloud_path, "--static", path, "-o", out, "--workers", 1],
            path, capsys, "not finite")
    assert not list(out.glob("*.laz")) and not (out / "stations.csv").exists()


def test_static_scans_without_pose_are_refused(tmp_path: Path) -> None:
    path = write_e57(tmp_path / "nopose.e57", pose=False)
    with pytest.raises(CloudError, match="has no pose"):
        check_static_scans(path)


# --------------------------------------------------------------------------- TOML


def test_config_nested_100000_deep_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error (RecursionError)."""
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    refused(["config", "--config", path], path, capsys, "nested too deep")


def test_reference_planes_nested_100000_deep_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "deep_ref.toml"
    path.write_text("plane_construction_accuracy_m = 0.05\nx = " + "[" * 100_000 + "]" * 100_000 + "\n")
    refused(["info", path], path, capsys, "nested too deep")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_config_non_finite_number_is_refused(tmp_path: Path, value: str) -> None:
    path = tmp_path / "k.toml"
    path.write_text(f"[slicing]\nwindow_s = {value}\n")
    with pytest.raises(ConfigError, match="finite"):
        load_config(path)


@pytest.mark.parametrize(("section", "key", "off", "on"), [("matching", "max_jump_m", "0.0", "0.5"),
                                                          ("block", "drift_per_axis", "false", "true")])
def test_a_removed_key_is_refused_unless_it_is_off(tmp_path: Path, caplog: pytest.LogCaptureFixture, section: str,
                                                   key: str, off: str, on: str) -> None:
    """A config.toml an earlier run wrote still loads (the removed key held its off value, asking
    for nothing that is gone), with a warning; a file asking for the removed behaviour is refused
    with the reason, as an unknown key is."""
    path = tmp_path / "k.toml"
    path.write_text(f"schema_version = 1\n[{section}]\n{key} = {off}\n")
    with caplog.at_level(logging.WARNING, logger="kinreg"):
        assert load_config(path) == load_config()
    assert any(f"[{section}] {key} was removed" in r.getMessage() for r in caplog.records)
    path.write_text(f"[{section}]\n{key} = {on}\n")
    with pytest.raises(ConfigError, match=rf"\[{section}\] {key} was removed \(.*\); delete the line"):
        load_config(path)


def test_reference_normal_that_overflows_is_normalised_not_nan() -> None:
    planes = parse_reference_planes(
        'plane_construction_accuracy_m = 0.05\n[[plane]]\nname = "a"\nnormal = [1e308, 1e308, 0]\nd_m = 1.0\n')
    np.testing.assert_allclose(planes.normals[0], [np.sqrt(0.5), np.sqrt(0.5), 0.0], atol=1e-15)
    with pytest.raises(ConfigError, match="zero"):
        parse_reference_planes(
            'plane_construction_accuracy_m = 0.05\n[[plane]]\nname = "a"\nnormal = [0, 0, 1e-300]\nd_m = 1.0\n')


def test_new_input_settings_are_checked(tmp_path: Path) -> None:
    path = tmp_path / "k.toml"
    path.write_text("[input]\nmax_dropped_share = 1.5\n")
    with pytest.raises(ConfigError, match="share from 0 to 1"):
        load_config(path)
    path.write_text("[input]\ncloud_time_offset_s = -18\nmax_dropped_share = 0\n")
    cfg = load_config(path)
    assert cfg.input.cloud_time_offset_s == -18.0 and cfg.input.max_dropped_share == 0.0


# --------------------------------------------------------------------------- trajectory header


def _rows(quat_xyzw: list[float]) -> str:
    x, y, z, w = quat_xyzw
    return "".join(f"{t:.1f} {t:.1f} 0 0 {x} {y} {z} {w}\n" for t in range(5))


QUAT_XYZW = [0.0, 0.0, 0.6, 0.8]  # 73.7 deg about z; read scalar-first it would be another rotation


@pytest.mark.parametrize("header", ["%time x y z qx qy qz qw", "#timestamp tx ty tz qx qy qz qw",
                                    "# t x y z q_x q_y q_z q_w"])
def test_header_names_decide_the_quaternion_order(tmp_path: Path, header: str) -> None:
    """Today: a TUM-ordered file with a '%time ...' header is read scalar-first, 180 deg off."""
    path = tmp_path / "traj.txt"
    path.write_text(header + "\n" + _rows(QUAT_XYZW))
    np.testing.assert_allclose(read_trajectory(path).poses.quat_wxyz[0], [0.8, 0.0, 0.0, 0.6])


def test_comment_line_before_the_tum_header_is_skipped(tmp_path: Path) -> None:
    path = tmp_path / "traj.txt"
    path.write_text("# exported by some SLAM tool\n# timestamp tx ty tz qx qy qz qw\n" + _rows(QUAT_XYZW))
    np.testing.assert_allclose(read_trajectory(path).poses.quat_wxyz[0], [0.8, 0.0, 0.0, 0.6])


def test_geoslam_header_keeps_scalar_first(tmp_path: Path) -> None:
    path = tmp_path / "traj.txt"
    path.write_text("%time x y z q0 q1 q2 q3 userfields\n" + "".join(
        f"{t}.0 0 0 0 0.8 0 0 0.6 7\n" for t in range(5)))
    np.testing.assert_allclose(read_trajectory(path).poses.quat_wxyz[0], [0.8, 0.0, 0.0, 0.6])


def test_header_naming_only_some_columns_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "traj.txt"
    path.write_text("%time x y z\n" + _rows(QUAT_XYZW))
    with pytest.raises(TrajectoryError, match="names no column for qw, qx, qy, qz"):
        read_trajectory(path)


@pytest.mark.parametrize(("edit", "reason"), [("nan", "not finite"), ("equal", "repeats")])
def test_trajectory_times_nan_or_all_equal_are_refused(tmp_path: Path, edit: str, reason: str) -> None:
    path = tmp_path / "traj.txt"
    rows = _rows(QUAT_XYZW).splitlines()
    if edit == "nan":
        rows[2] = "nan" + rows[2][3:]
    else:
        rows = ["1.0" + r[3:] for r in rows]
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(TrajectoryError, match=reason):
        read_trajectory(path)


# --------------------------------------------------------------------------- point times


@pytest.fixture
def run12(tmp_path: Path) -> SyntheticRun:
    return write_synthetic_run(tmp_path / "run", n_points=20_000, duration_s=12.0)


def _with_times(run: SyntheticRun, stamps: np.ndarray, path: Path) -> Path:
    las = laspy.read(run.cloud_path)
    las.gps_time = stamps
    las.write(path)
    return path


def test_cloud_offset_by_18_s_stops_naming_both_ranges_and_the_offset(
        run12: SyntheticRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Today: exit 0, 'global test passed', stations 7-11 m off; only a 7.5 % warning."""
    cloud = _with_times(run12, run12.stamps_s + 18.0, tmp_path / "gps.laz")
    out = tmp_path / "seq.e57"
    line = refused(["slice", "-t", run12.trajectory_path, "-c", cloud, "-o", out], cloud, capsys,
                   "likely offset -18 s (GPS-UTC leap seconds): set [input] cloud_time_offset_s = -18")
    t0, t1 = run12.trajectory.t_start_s, run12.trajectory.t_end_s
    assert f"the trajectory's {t0:.3f} .. {t1:.3f} s" in line and str(run12.trajectory_path) in line
    assert not out.exists()
    cfg = tmp_path / "k.toml"
    cfg.write_text("[input]\ncloud_time_offset_s = -18\n")
    code, stdout, err = run_cli(["slice", "-t", run12.trajectory_path, "-c", cloud, "-o", out, "--config", cfg],
                                capsys)
    assert code == 0, err
    shifted = [s.stamps_s for s in _e57_scans(out)]
    plain = tmp_path / "plain.e57"
    assert run_cli(["slice", "-t", run12.trajectory_path, "-c", run12.cloud_path, "-o", plain], capsys)[0] == 0
    for a, b in zip(shifted, [s.stamps_s for s in _e57_scans(plain)], strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def _e57_scans(path: Path) -> list:
    from kinreg.io.e57 import iter_e57_scans
    from kinreg.types import ScanKind

    return list(iter_e57_scans(path, require_pose=False, kind=ScanKind.QUASI_STATIC))


def test_cloud_with_all_times_equal_is_refused(run12: SyntheticRun, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error ('need at least one array to stack')."""
    t = np.full(len(run12.stamps_s), run12.stamps_s[100])
    cloud = _with_times(run12, t, tmp_path / "equal.laz")
    refused(["slice", "-t", run12.trajectory_path, "-c", cloud, "-o", tmp_path / "s.e57"], cloud, capsys,
            "all sampled point times are equal")


def test_nan_times_are_counted_per_file_and_refused_above_the_share(
        run12: SyntheticRun, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        caplog: pytest.LogCaptureFixture) -> None:
    t = run12.stamps_s.copy()
    t[::10] = np.nan  # 10 % of the points
    cloud = _with_times(run12, t, tmp_path / "nan.laz")
    refused(["slice", "-t", run12.trajectory_path, "-c", cloud, "-o", tmp_path / "a.e57"], cloud, capsys,
            "have no finite time; more than [input] max_dropped_share = 0.05")
    cfg = tmp_path / "k.toml"
    cfg.write_text("[input]\nmax_dropped_share = 0.2\n")
    with caplog.at_level(logging.WARNING, logger="kinreg"):
        code, _, err = run_cli(["slice", "-t", run12.trajectory_path, "-c", cloud, "-o", tmp_path / "b.e57",
                                "--config", cfg], capsys)
    assert code == 0, err
    messages = [r.getMessage() for r in caplog.records]
    assert any(f"{cloud}: 2000 of 20000 points have no finite time" in m for m in messages), messages
    # the exact count of the full pass refuses too, where the sample does not see it
    times = TimeFilter(max_dropped_share=0.05)
    with open_cloud(cloud, times=times) as reader, pytest.raises(CloudError, match="2,000 of 20,000 points"):
        for _ in reader.iter_chunks(5000):
            pass


def test_nan_time_points_are_not_written_into_the_corrected_cloud(run12: SyntheticRun, tmp_path: Path) -> None:
    """Today: written at x = -214736 m (NaN cast to int32)."""
    t = run12.stamps_s.copy()
    t[[5, 500, 5000]] = [np.nan, np.inf, -np.inf]
    cloud = _with_times(run12, t, tmp_path / "nan.laz")
    traj = run12.trajectory
    correction = DriftCorrection(np.array([traj.t_start_s, traj.t_end_s]), np.zeros((2, 3)),
                                 np.full((2, 3), 0.01), traj, np.zeros((2, 3)))
    n = write_corrected_las(cloud, tmp_path / "out.laz", correction)
    out = laspy.read(tmp_path / "out.laz")
    assert n == len(out.points) == len(t) - 3
    keep = np.isfinite(t)
    np.testing.assert_allclose(out.x, run12.xyz[keep, 0] + 0.01, atol=2e-4)
    assert np.isfinite(np.asarray(out.gps_time)).all()


def test_coordinate_overflowing_the_output_scale_is_one_line(run12: SyntheticRun, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Today: internal error (OverflowError, 8 lines)."""
    traj = run12.trajectory
    correction = DriftCorrection(np.array([traj.t_start_s, traj.t_end_s]), np.zeros((2, 3)),
                                 np.full((2, 3), 1e6), traj, np.zeros((2, 3)))  # 1e6 m / 1e-4 m > 2**31
    with pytest.raises(CloudError, match="does not fit the input's scale and offset"):
        write_corrected_las(run12.cloud_path, tmp_path / "out.laz", correction)
    assert not (tmp_path / "out.laz").exists()


# --------------------------------------------------------------------------- time-base diagnosis


T0 = 1_623_220_971.0  # Unix seconds, June 2021


def _diagnose(cloud_t0: float, traj_t0: float, duration_s: float = 240.0, share: float = 0.05):
    t = np.linspace(cloud_t0, cloud_t0 + duration_s, 5000)
    return diagnose_time_base(t, (traj_t0, traj_t0 + duration_s), share)


def test_matching_time_bases_pass() -> None:
    assert _diagnose(T0, T0) is None
    assert _diagnose(T0 + 1.0, T0) is None  # 0.4 % outside, no recognised offset


@pytest.mark.parametrize(("cloud_t0", "offset", "name"), [
    (T0 + 18.0, -18.0, "GPS-UTC leap seconds"),
    (T0 - 18.0, 18.0, "UTC-GPS leap seconds"),
    (T0 - GPS_UNIX_EPOCH_S + 18.0, GPS_UNIX_EPOCH_S - 18.0, "GPS seconds to Unix"),
    (T0 - GPS_UNIX_EPOCH_S + 18.0 - 1e9, GPS_UNIX_EPOCH_S - 18.0 + 1e9, "GPS adjusted standard time to Unix"),
])
def test_recognised_offsets_are_named(cloud_t0: float, offset: float, name: str) -> None:
    problem = _diagnose(cloud_t0, T0)
    assert problem is not None and problem.offset_s == pytest.approx(offset) and problem.offset_name == name
    assert f"set [input] cloud_time_offset_s = {offset:.0f}" in problem.message()


def test_gps_adjusted_standard_time_against_gps_time() -> None:
    gps = 1_300_000_000.0
    problem = _diagnose(gps - 1e9, gps)
    assert problem is not None and problem.offset_s == 1e9


def test_gps_week_seconds_against_gps_time() -> None:
    gps = 1_300_000_000.0
    week_seconds = gps % GPS_WEEK_S
    problem = _diagnose(week_seconds, gps)
    assert problem is not None and problem.offset_s == pytest.approx(gps - week_seconds)
    assert "GPS week seconds to GPS time" in problem.offset_name


def test_18_s_in_a_long_run_is_found_below_the_dropped_share() -> None:
    problem = _diagnose(T0 + 18.0, T0, duration_s=1800.0)  # 1 % outside: below 5 %, still a wrong base
    assert problem is not None and problem.offset_s == -18.0


def test_poor_overlap_without_a_recognised_offset() -> None:
    problem = _diagnose(T0 + 100.0, T0)
    assert problem is not None and problem.offset_s is None and "41.7 % outside" in problem.message()


# --------------------------------------------------------------------------- library noise


def test_library_warnings_and_panics_become_one_line_naming_the_file(caplog: pytest.LogCaptureFixture) -> None:
    import warnings

    from kinreg.io.quiet import library_calls

    class PanicException(BaseException):  # what pyo3 raises for a Rust panic
        pass

    with caplog.at_level(logging.WARNING, logger="kinreg"), library_calls("cloud.laz"):
        warnings.warn("invalid value encountered in cast\nsecond line", RuntimeWarning, stacklevel=1)
    assert [r.getMessage() for r in caplog.records] == [
        "cloud.laz: RuntimeWarning: invalid value encountered in cast"]
    with pytest.raises(CloudError, match=r"^cloud\.laz: the decoder failed: called unwrap on Err$"), \
            library_calls("cloud.laz"):
        raise PanicException("called unwrap on Err\nnote: run with RUST_BACKTRACE=1")


def test_cli_prints_a_warning_as_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from kinreg_cli.main import _one_line_warning

    _one_line_warning(RuntimeWarning("overflow encountered\nin multiply"), RuntimeWarning, "x.py", 3)
    assert capsys.readouterr().err == "kinreg: warning: RuntimeWarning: overflow encountered\n"
