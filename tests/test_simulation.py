"""The ground-truth simulator: scene, ray casting, walk, drift, cloud, static scans, files."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import laspy
import numpy as np
import pytest
import tomllib

from kinreg.geometry import Pose, interpolate_poses, quat_to_rotvec
from kinreg.simulation.drift import DriftConfig, make_drift
from kinreg.simulation.files import write_run
from kinreg.simulation.run import SimulatedRun, SimulationConfig, simulate_run
from kinreg.simulation.scene import BuildingConfig, BuildingLayout, Patch, Scene, make_box_scene, make_building
from kinreg.simulation.sensor import SensorConfig, StaticConfig, _interpolate_fast

TINY = SimulationConfig(
    seed=5,
    duration_s=20.0,
    block_s=5.0,
    sensor=SensorConfig(pulse_rate_hz=3000.0),
    static=StaticConfig(n_scans=2, angle_step_deg=4.0),
)
NOISELESS = dataclasses.replace(
    TINY, sensor=dataclasses.replace(TINY.sensor, range_sigma_m=0.0, angle_sigma_deg=0.0)
)


@pytest.fixture(scope="module")
def tiny_run() -> SimulatedRun:
    return simulate_run(TINY)


@pytest.fixture(scope="module")
def tiny_files(tiny_run: SimulatedRun, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim")
    write_run(tiny_run, out)
    return out


def _plane_residuals(scene: Scene, patch_id: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    n = np.array([p.normal for p in scene.patches])[patch_id]
    d = np.array([p.d for p in scene.patches])[patch_id]
    return np.einsum("ij,ij->i", n, xyz) - d


# --------------------------------------------------------------------------- ray casting


def test_raycast_box_scene_matches_analytic_ranges() -> None:
    size = np.array([4.0, 3.0, 2.5])
    scene = make_box_scene(tuple(size))
    rng = np.random.default_rng(0)
    o = rng.uniform(0.2, 1.0, (5000, 3)) * size * 0.9
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r, pid = scene.raycast(o, d, max_range_m=100.0)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (size - o) / d, -o / d)  # distance to the bounding face per axis
    axis = np.argmin(t, axis=1)
    np.testing.assert_allclose(r, t[np.arange(len(o)), axis], rtol=0, atol=1e-9)
    # patch order of make_box_scene: x0, x1, y0, y1, floor, ceiling
    expected = 2 * axis + (d[np.arange(len(o)), axis] > 0)
    assert np.array_equal(pid, expected)
    hit = o + r[:, None] * d
    assert np.abs(_plane_residuals(scene, pid, hit)).max() < 1e-9


def test_raycast_max_range_back_faces_and_outside() -> None:
    scene = make_box_scene((4.0, 3.0, 2.5))
    o = np.array([[1.0, 1.5, 1.0], [1.0, 1.5, 1.0], [-1.0, 1.5, 1.0], [-1.0, 1.5, 1.0]])
    d = np.array([[1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0]])
    r, pid = scene.raycast(o, d, max_range_m=2.0)
    # 3 m to the far wall is beyond 2 m; 1 m to x0 is a hit; from outside only back faces: miss
    assert pid.tolist() == [-1, 0, -1, -1]
    assert r[1] == pytest.approx(1.0)
    assert np.isinf(r[[0, 2, 3]]).all()
    r, pid = scene.raycast(o[:1], d[:1], max_range_m=2.0, min_range_m=0.0)
    r_min, pid_min = scene.raycast(o[1:2], d[1:2], min_range_m=1.5)
    assert pid_min[0] == -1
    assert np.isinf(r_min[0])


def test_raycast_convex_polygon_edges() -> None:
    # a triangle in the plane z = 1 facing down; its bounding box corner (1, 1) lies outside it
    verts = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    tri = Patch(0, "tri", "tri", "object", np.array([0.0, 0.0, -1.0]), -1.0, verts, plane_id=0)
    scene = Scene("tri", (tri,))
    xy = np.array([[0.2, 0.2], [0.45, 0.45], [0.55, 0.55], [0.9, 0.9], [-0.1, 0.5]])
    o = np.column_stack([xy, np.zeros(len(xy))])
    r, pid = scene.raycast(o, np.tile([0.0, 0.0, 1.0], (len(xy), 1)))
    assert pid.tolist() == [0, 0, -1, -1, -1]
    np.testing.assert_allclose(r[:2], 1.0)


@pytest.mark.parametrize("layout", list(BuildingLayout))
def test_building_is_closed_and_has_planes_in_many_directions(layout: BuildingLayout) -> None:
    scene = make_building(BuildingConfig(layout=layout, seed=3))
    planes = scene.planes()
    normals = np.array([p.normal for p in planes])
    slanted = (np.abs(normals[:, 2]) > 0.05) & (np.abs(normals[:, 2]) < 0.995)
    assert slanted.any(), "at least one slanted plane"
    horizontal_dirs = {round(float(np.degrees(np.arctan2(n[1], n[0]))) % 180) for n in normals
                       if abs(n[2]) < 0.05}
    assert len(horizontal_dirs) >= 4, "walls and yawed boxes give several wall directions"
    # walls with doors: one plane, several patches; thin walls: two opposite faces 0.2 m apart
    assert max(len(p.patch_ids) for p in planes if p.role == "interior_wall") >= 3
    floor = [p for p in planes if p.name == "floor"]
    assert len(floor) == 1
    assert len(floor[0].patch_ids) > 3
    for p in (p for p in planes if p.role == "interior_wall"):
        twins = [q for q in planes if q.role == "interior_wall" and np.allclose(q.normal, -p.normal)
                 and abs(q.d + p.d - 0.2) < 1e-6]
        assert twins, f"wall face {p.name} has no opposite face"
    # closed: rays in random directions from walkable points never leave the building
    cfg = dataclasses.replace(TINY, duration_s=60.0, building=BuildingConfig(layout=layout, seed=3))
    run = simulate_run(cfg)
    pos = run.truth.poses.t_xyz[::50]
    rng = np.random.default_rng(1)
    o = np.repeat(pos, 400, axis=0)
    d = rng.normal(size=o.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, pid = scene.raycast(o, d, max_range_m=100.0)
    assert (pid >= 0).all()


@pytest.mark.parametrize("layout", list(BuildingLayout))
def test_walk_keeps_clear_of_walls_and_furniture(layout: BuildingLayout) -> None:
    cfg = dataclasses.replace(TINY, duration_s=200.0, building=BuildingConfig(layout=layout))
    run = simulate_run(cfg)
    scene = run.scene
    tab = scene._tables
    pos = run.truth.poses.t_xyz[::20]
    min_dist = np.inf
    for i, p in enumerate(scene.patches):
        if p.role in ("floor", "ceiling"):
            continue
        rel = pos - tab["origin"][i]
        u = np.clip(rel @ tab["e_u"][i], tab["box"][i, 0], tab["box"][i, 2])
        v = np.clip(rel @ tab["e_v"][i], tab["box"][i, 1], tab["box"][i, 3])
        closest = tab["origin"][i] + u[:, None] * tab["e_u"][i] + v[:, None] * tab["e_v"][i]
        min_dist = min(min_dist, float(np.linalg.norm(pos - closest, axis=1).min()))
    assert min_dist > 0.3
    # it visits every room and ends near the start (loop closure)
    for room in scene.walk_plan.rooms:
        inside = ((pos[:, 0] > room.xy_min[0]) & (pos[:, 0] < room.xy_max[0])
                  & (pos[:, 1] > room.xy_min[1]) & (pos[:, 1] < room.xy_max[1]))
        assert inside.any(), room.name
    assert np.linalg.norm(pos[-1, :2] - pos[0, :2]) < 1.0


# --------------------------------------------------------------------------- trajectories and drift


def test_fast_interpolation_equals_geometry_interpolation(tiny_run: SimulatedRun) -> None:
    traj = tiny_run.slam
    q = np.sort(np.random.default_rng(0).uniform(traj.t_start_s, traj.t_end_s, 5000))
    R, t = _interpolate_fast(traj.stamps_s, traj.poses, q)
    ref = interpolate_poses(traj.stamps_s, traj.poses, q)
    assert np.abs(R - ref.rotation_matrix).max() < 1e-12
    assert np.abs(t - ref.t_xyz).max() < 1e-12


def test_drift_is_smooth_grows_and_hits_its_target() -> None:
    stamps = 1e9 + np.arange(40001) / 100.0  # 400 s
    cfg = DriftConfig(drift_pos_m_at_300s=0.04, drift_rot_deg_at_300s=0.3)
    pivot = np.array([1.0, 2.0, 1.3])
    D = make_drift(stamps, pivot, cfg, np.random.default_rng(3))
    rot = np.linalg.norm(quat_to_rotvec(D.quat_wxyz), axis=1)
    # translation part of the drift: where the pivot goes
    moved = np.einsum("nij,j->ni", D.rotation_matrix, pivot) + D.t_xyz - pivot
    assert np.linalg.norm(moved[30000]) == pytest.approx(0.04, rel=1e-9)
    assert np.degrees(rot[30000]) == pytest.approx(0.3, rel=1e-9)
    assert np.linalg.norm(moved[0]) == 0.0
    assert rot[0] == 0.0
    # grows: t^1.5 means the first minute holds a small part of the drift at 300 s
    assert np.abs(moved[:6000]).max() < 0.5 * 0.04
    # smooth: no jumps between 100 Hz rows, the steps themselves vary slowly
    assert np.linalg.norm(np.diff(moved, axis=0), axis=1).max() < 2e-5
    assert np.abs(np.diff(rot)).max() < np.radians(3e-4)
    assert np.linalg.norm(np.diff(moved, 2, axis=0), axis=1).max() < 1e-7


def test_run_drift_grows_and_is_smooth(tiny_run: SimulatedRun) -> None:
    err = tiny_run.slam.poses.t_xyz - tiny_run.truth.poses.t_xyz
    e = np.linalg.norm(err, axis=1)
    assert e[0] == pytest.approx(0.0, abs=1e-12)
    assert e[-1] > e[len(e) // 4] > 0.0
    assert np.linalg.norm(np.diff(err, axis=0), axis=1).max() < 5e-5
    composed = tiny_run.drift.compose(tiny_run.truth.poses)
    assert np.abs(composed.t_xyz - tiny_run.slam.poses.t_xyz).max() < 1e-9


def test_trajectory_files_parse_in_geoslam_format(tiny_run: SimulatedRun, tiny_files: Path) -> None:
    for name, traj in (("run_trajectory.txt", tiny_run.slam), ("truth_trajectory.txt", tiny_run.truth)):
        path = tiny_files / name
        assert path.read_text().splitlines()[0] == "%time x y z q0 q1 q2 q3 userfields"
        data = np.loadtxt(path, comments="%")
        assert data.shape == (len(traj), 8)
        np.testing.assert_allclose(data[:, 0], traj.stamps_s, rtol=0, atol=1e-6)
        np.testing.assert_allclose(data[:, 1:4], traj.poses.t_xyz, rtol=0, atol=1e-6)
        np.testing.assert_allclose(data[:, 4:8], traj.poses.quat_wxyz, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(data[:, 4:8], axis=1), 1.0, atol=1e-8)
        assert np.all(np.diff(data[:, 0]) > 0)


# --------------------------------------------------------------------------- the cloud


def test_points_lie_on_true_planes_noiseless_and_noisy(tiny_run: SimulatedRun) -> None:
    exact = simulate_run(NOISELESS)
    for run, bound in ((exact, 1e-9), (tiny_run, None)):
        blk = run.cloud_block(1)
        T = interpolate_poses(run.truth.stamps_s, run.truth.poses, blk.stamps_s)
        res = _plane_residuals(run.scene, blk.patch_id, T.apply(blk.xyz_sensor))
        if bound is not None:
            assert np.abs(res).max() < bound
        else:
            sigma = run.config.sensor.range_sigma_m
            # range noise projected on the normal: between ~0.5 and 1 sigma overall
            assert 0.4 * sigma < res.std() < 1.1 * sigma
            assert np.abs(res.mean()) < 0.1 * sigma


def test_exported_cloud_and_trajectory_reproduce_sensor_points(tiny_run: SimulatedRun,
                                                                tiny_files: Path) -> None:
    las = laspy.read(tiny_files / "run_cloud.laz")
    assert las.header.version.minor == 4
    assert las.header.point_format.id == 6
    np.testing.assert_allclose(las.header.scales, 1e-4)
    blocks = list(tiny_run.iter_cloud_blocks())
    stamps = np.concatenate([b.stamps_s for b in blocks])
    sensor = np.concatenate([b.xyz_sensor for b in blocks])
    assert len(las.points) == len(stamps)
    assert np.array_equal(np.asarray(las.gps_time), stamps)  # float64 times, bit for bit
    assert np.all(np.diff(stamps) > 0)
    assert [b.first_index for b in blocks] == list(np.cumsum([0] + [len(b) for b in blocks[:-1]]))
    traj = np.loadtxt(tiny_files / "run_trajectory.txt", comments="%")
    T = interpolate_poses(traj[:, 0], Pose(traj[:, 4:8], traj[:, 1:4]), np.asarray(las.gps_time))
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    back = T.apply_inverse(xyz)
    # 0.1 mm coordinate resolution: at most 0.05 mm per axis, 0.087 mm in 3D
    assert np.linalg.norm(back - sensor, axis=1).max() < 1e-4
    assert np.asarray(las.intensity).max() > 0
    # and the exported points are NOT on the planes by the drift (drift exists)
    Tt = interpolate_poses(tiny_run.truth.stamps_s, tiny_run.truth.poses, stamps)
    assert np.linalg.norm(Tt.apply(sensor) - xyz, axis=1).max() > 1e-4


def test_same_seed_same_bytes_other_seed_other_data(tmp_path: Path, tiny_files: Path) -> None:
    write_run(simulate_run(TINY), tmp_path)
    for name in ("run_trajectory.txt", "truth_trajectory.txt", "run_cloud.laz", "truth_scene.json",
                 "reference.toml", "run_meta.json", "static_truth.json"):
        assert (tmp_path / name).read_bytes() == (tiny_files / name).read_bytes(), name
    other = simulate_run(dataclasses.replace(TINY, seed=6))
    assert not np.allclose(other.slam.poses.t_xyz, simulate_run(TINY).slam.poses.t_xyz)


def test_utm_origin_shifts_everything_exactly(tiny_run: SimulatedRun) -> None:
    origin = (500000.0, 5400000.0, 100.0)
    utm = simulate_run(dataclasses.replace(TINY, origin_xyz=origin))
    shift = utm.slam.poses.t_xyz - tiny_run.slam.poses.t_xyz
    np.testing.assert_allclose(shift, np.broadcast_to(origin, shift.shape), rtol=0, atol=1e-8)
    a, b = utm.cloud_block(0), tiny_run.cloud_block(0)
    # the rays start from the interpolated UTM trajectory minus the origin: 1e-9 m rounding
    np.testing.assert_allclose(a.xyz_sensor, b.xyz_sensor, rtol=0, atol=1e-8)
    shift = a.xyz_obj - b.xyz_obj
    np.testing.assert_allclose(shift, np.broadcast_to(origin, shift.shape), rtol=0, atol=1e-8)
    plane = utm.scene_planes_obj()[0]
    assert plane.d == pytest.approx(tiny_run.scene.planes()[0].d + plane.normal @ np.array(origin))


# --------------------------------------------------------------------------- static scans and truth files


def test_static_e57_readable_with_correct_poses(tiny_run: SimulatedRun, tiny_files: Path) -> None:
    import pye57

    truth = json.loads((tiny_files / "static_truth.json").read_text())
    e57 = pye57.E57(str(tiny_files / "static.e57"))
    try:
        assert e57.scan_count == len(tiny_run.static_scans) == len(truth["scans"])
        for i, scan in enumerate(tiny_run.static_scans):
            header = e57.get_header(i)
            np.testing.assert_allclose(header.rotation, scan.T_obj_scan.quat_wxyz, atol=1e-12)
            np.testing.assert_allclose(header.translation, scan.T_obj_scan.t_xyz, atol=1e-12)
            np.testing.assert_allclose(truth["scans"][i]["t_xyz"], scan.T_obj_scan.t_xyz, atol=1e-12)
            raw = e57.read_scan_raw(i)
            pts = np.column_stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]])
            assert len(pts) == len(scan) > 1000
            assert np.abs(pts - scan.points_xyz).max() < 1e-5  # float32 storage
            # the pose maps the stored points onto the building's planes (2 mm range noise)
            obj = Pose(np.asarray(header.rotation), np.asarray(header.translation)).apply(pts)
            _, pid = tiny_run.scene.raycast(np.broadcast_to(scan.T_obj_scan.t_xyz, obj.shape),
                                            (obj - scan.T_obj_scan.t_xyz)
                                            / np.linalg.norm(obj - scan.T_obj_scan.t_xyz, axis=1)[:, None],
                                            max_range_m=100.0)
            res = _plane_residuals(tiny_run.scene, pid, obj)
            assert np.abs(res).max() < 0.012
            assert res.std() < 0.0025
    finally:
        e57.close()


def test_reference_toml_and_scene_json(tiny_run: SimulatedRun, tiny_files: Path) -> None:
    ref = tomllib.loads((tiny_files / "reference.toml").read_text())
    assert ref["plane_construction_accuracy_m"] == 0.05
    by_axis = {p["axis"]: p for p in ref["plane"]}
    assert set(by_axis) == {"x", "y", "z"}
    scene = json.loads((tiny_files / "truth_scene.json").read_text())
    planes = {p["reference_plane"]: p for p in scene["planes"] if p["reference_plane"]}
    for name, axis in (("west_wall", "x"), ("south_wall", "y"), ("ceiling", "z")):
        p, r = planes[name], by_axis[axis]
        k = "xyz".index(axis)
        normal = np.zeros(3)
        normal[k] = r["normal_sign"]
        np.testing.assert_allclose(p["normal"], normal, atol=1e-12)
        assert p["d"] == pytest.approx(r["normal_sign"] * r["offset_m"])
    # every normal points to the inside, where the walk is
    centre = tiny_run.truth.poses.t_xyz.mean(axis=0)
    for r in ref["plane"]:
        k = "xyz".index(r["axis"])
        assert r["normal_sign"] * (centre[k] - r["offset_m"]) > 0
    meta = json.loads((tiny_files / "run_meta.json").read_text())
    assert meta["counts"]["cloud_points"] == laspy.open(tiny_files / "run_cloud.laz").header.point_count
    assert meta["config"]["seed"] == TINY.seed
