import numpy as np
import pytest
from conftest import write_synthetic_run

from kinreg.config import SlicingConfig, WindowMode
from kinreg.errors import InputError
from kinreg.estimate.slicing import unit_edges
from kinreg.io.cloud import open_cloud
from kinreg.run.spill import slice_quasi_static


def slice_run(run, config, chunk_points=7_000, tmp_path=None):
    with open_cloud(run.cloud_path) as cloud:
        return slice_quasi_static(run.trajectory, cloud, config, chunk_points=chunk_points, workdir=tmp_path)


def gather_back(seq):
    """All scan points mapped back to the object frame, with their times, sorted by time."""
    xyz, t, owner = [], [], []
    for scan in seq.iter_scans():
        xyz.append(scan.points_in_object_frame())
        t.append(scan.stamps_s)
        owner.append(np.full(len(scan), scan.scan_id))
    xyz, t, owner = np.concatenate(xyz), np.concatenate(t), np.concatenate(owner)
    order = np.argsort(t, kind="stable")
    return xyz[order], t[order], owner[order]


@pytest.mark.parametrize("sort", [True, False], ids=["time-sorted", "unsorted"])
def test_slicing_round_trip_reproduces_every_point(tmp_path, sort):
    run = write_synthetic_run(tmp_path / "run", n_points=40_000, sort=sort, offset=(500000.0, 5400000.0, 250.0))
    with slice_run(run, SlicingConfig(window_s=6.0, min_points=10), tmp_path=tmp_path) as seq:
        assert len(seq) == 5  # 30 s / 6 s
        xyz, t, owner = gather_back(seq)
        summary = seq.summary
        windows = seq.windows
    order = np.argsort(run.stamps_s, kind="stable")
    assert len(t) == len(run.stamps_s) == summary.n_points_in_scans
    np.testing.assert_array_equal(t, run.stamps_s[order])
    assert np.max(np.abs(xyz - run.xyz[order])) < 1e-4  # < 0.1 mm at UTM magnitudes (seen: ~1e-9)
    # every point lies in its own window
    for w in windows:
        mine = t[owner == w.scan_id]
        assert mine.min() >= w.t_start_s and mine.max() <= w.t_end_s
    # the scan centre is the trajectory row nearest the window middle
    for w in windows:
        k = int(np.argmin(np.abs(run.trajectory.stamps_s - 0.5 * (w.t_start_s + w.t_end_s))))
        assert w.t_s == run.trajectory.stamps_s[k]
        np.testing.assert_array_equal(w.T_obj_scan.t_xyz, run.trajectory.poses.t_xyz[k])


def test_spill_files_closed_and_opened_again_keep_every_point(tmp_path, monkeypatch):
    """An unsorted cloud with one spill file open at a time: each is closed and appended to again
    many times; the same points in the same order as with every file open."""
    from kinreg.run import spill

    run = write_synthetic_run(tmp_path / "run", n_points=40_000, sort=False)
    config = SlicingConfig(window_s=6.0, min_points=10)
    with slice_run(run, config, chunk_points=3_000, tmp_path=tmp_path) as seq:
        expected = [seq.read_scan(i) for i in range(len(seq))]
    monkeypatch.setattr(spill, "_MAX_OPEN_FILES", 1)
    with slice_run(run, config, chunk_points=3_000, tmp_path=tmp_path) as seq:
        for i, scan in enumerate(expected):
            again = seq.read_scan(i)
            assert np.array_equal(again.points_xyz, scan.points_xyz) and np.array_equal(again.stamps_s, scan.stamps_s)
            assert np.array_equal(again.intensity, scan.intensity)


def test_points_are_in_the_scan_frame(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=20_000)
    with slice_run(run, SlicingConfig(window_s=3.0, min_points=10)) as seq:
        scan = seq.read_scan(2)
    # the synthetic sensor points are N(0, 5 m) around the platform: near the scan centre
    assert np.linalg.norm(scan.points_xyz.mean(axis=0)) < 1.5
    expected = scan.T_obj_scan.apply_inverse(scan.points_in_object_frame())
    np.testing.assert_allclose(expected, scan.points_xyz, atol=1e-9)


def test_chunk_size_does_not_change_the_result(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=15_000, sort=False)
    cfg = SlicingConfig(window_s=4.0, min_points=10)
    with slice_run(run, cfg, chunk_points=1_000) as a, slice_run(run, cfg, chunk_points=100_000) as b:
        for sa, sb in zip(a.iter_scans(), b.iter_scans(), strict=True):
            np.testing.assert_array_equal(sa.points_xyz, sb.points_xyz)
            np.testing.assert_array_equal(sa.stamps_s, sb.stamps_s)


def test_path_and_points_modes(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=30_000)
    with slice_run(run, SlicingConfig(mode=WindowMode.PATH, window_path_m=2.0, min_points=10)) as seq:
        path_len = run.trajectory.path_length_m()
        assert len(seq) == max(1, round(path_len / 2.0))
        assert seq.summary.n_points_in_scans == 30_000
    with slice_run(run, SlicingConfig(mode=WindowMode.POINTS, window_points=4_000, min_points=10)) as seq:
        counts = [seq.n_points(i) for i in range(len(seq))]
        assert sum(counts) == 30_000
        assert all(3_500 <= c <= 6_500 for c in counts[:-1])


def test_sparse_windows_are_reported_not_silently_dropped(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=3_000)
    with slice_run(run, SlicingConfig(window_s=1.0, min_points=100)) as seq:
        s = seq.summary
        assert len(s.skipped) > 0
        assert s.n_points_in_scans + s.n_points_in_skipped_windows == 3_000
        assert all(w.n_points < 100 for w in s.skipped) and len(seq) > 0
        assert [w.scan_id for w in seq.windows] == list(range(len(seq)))


def test_points_outside_the_trajectory_are_counted(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=10_000)
    short = type(run.trajectory)(run.trajectory.stamps_s[:1501], run.trajectory.poses[:1501])  # first 15 s
    with open_cloud(run.cloud_path) as cloud, slice_quasi_static(short, cloud, SlicingConfig(min_points=1)) as seq:
        s = seq.summary
    assert 0.4 < s.share_outside < 0.6
    assert s.n_points_in_scans + s.n_points_outside_trajectory == 10_000


def test_no_window_with_enough_points_is_an_error(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=500)
    with pytest.raises(InputError, match="no window has at least"), open_cloud(run.cloud_path) as cloud:
        slice_quasi_static(run.trajectory, cloud, SlicingConfig(window_s=6.0, min_points=10_000))


def test_no_overlap_in_time_is_an_error(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=500)
    late = type(run.trajectory)(run.trajectory.stamps_s + 1000.0, run.trajectory.poses)
    with pytest.raises(InputError, match="none of the 500 points"), open_cloud(run.cloud_path) as cloud:
        slice_quasi_static(late, cloud, SlicingConfig())


def test_unit_edges_cover_the_trajectory():
    from conftest import make_trajectory

    traj = make_trajectory(62.0)
    edges = unit_edges(traj, SlicingConfig(window_s=6.0))
    assert edges[0] == traj.t_start_s and edges[-1] == traj.t_end_s
    assert len(edges) - 1 == 10 and np.allclose(np.diff(edges), 6.2)


def test_spill_folder_is_removed(tmp_path):
    run = write_synthetic_run(tmp_path / "run", n_points=2_000)
    work = tmp_path / "work"
    work.mkdir()
    with slice_run(run, SlicingConfig(min_points=1), tmp_path=work):
        assert any(work.iterdir())
    assert not any(work.iterdir())


def test_the_sensor_track_covers_its_window_in_the_scan_frame(tmp_path):
    """Where the sensor was through a window (for the planes' sensor moments): the trajectory's rows
    from before its start to after its end, in the scan's frame, whose origin is the sensor at the
    window's centre time."""
    from kinreg.estimate.slicing import sensor_track
    from kinreg.geometry import interpolate_positions

    run = write_synthetic_run(tmp_path / "run", n_points=20_000)
    with slice_run(run, SlicingConfig(window_s=3.0, min_points=10)) as seq:
        windows = seq.windows
    for w in (windows[0], windows[2], windows[-1]):
        stamps, xyz = sensor_track(run.trajectory, w)
        assert stamps[0] <= max(w.t_start_s, run.trajectory.t_start_s)
        assert stamps[-1] >= min(w.t_end_s, run.trajectory.t_end_s)
        np.testing.assert_allclose(interpolate_positions(stamps, xyz, [w.t_s]), [[0.0, 0.0, 0.0]], atol=1e-9)
        rows = np.isin(run.trajectory.stamps_s, stamps)
        np.testing.assert_allclose(w.T_obj_scan.apply(xyz), run.trajectory.poses.t_xyz[rows], atol=1e-9)
