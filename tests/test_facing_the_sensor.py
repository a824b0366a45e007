"""A window that walks through a door sees both faces of the wall beside it: each face's normal
points towards the sensor that saw it, not towards the scan origin in the door (METHOD.md 4)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from kinreg.config import PlanesConfig
from kinreg.estimate.drift import plane_time_offsets
from kinreg.estimate.planes import detect_planes, facing_the_sensor
from kinreg.geometry import Pose
from kinreg.types import Scan, ScanKind

# A wall 0.2 m thick along x at y in [-0.1, 0.1], the room behind it (y > 0.1), the corridor in
# front (y < -0.1); the door at x in [-0.5, 0.5]. The sensor walks from the room (y = 2) to the
# corridor (y = -2) in 6 s; the scan origin (its centre pose) is in the door, at y = 0.
_ROOM_FACE_Y, _CORRIDOR_FACE_Y = 0.1, -0.1


def _door_walk(seed: int = 3) -> tuple[Scan, tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    n = 6000
    # the room face, seen from the room (first half of the window), the corridor face after it
    t_room = rng.uniform(-3.0, -0.3, n)
    t_corridor = rng.uniform(0.3, 3.0, n)
    room = np.column_stack([rng.uniform(1.0, 4.0, n), np.full(n, _ROOM_FACE_Y), rng.uniform(0.0, 2.5, n)])
    corridor = np.column_stack([rng.uniform(1.0, 4.0, n), np.full(n, _CORRIDOR_FACE_Y), rng.uniform(0.0, 2.5, n)])
    # a floor seen all the time, below the sensor
    t_floor = rng.uniform(-3.0, 3.0, 2 * n)
    floor = np.column_stack([rng.uniform(-3.0, 4.0, 2 * n), rng.uniform(-2.0, 2.0, 2 * n), np.full(2 * n, -1.3)])
    xyz = np.vstack([room, corridor, floor])
    xyz += rng.normal(0.0, 0.003, xyz.shape)
    stamps = 100.0 + np.concatenate([t_room, t_corridor, t_floor])
    scan = Scan(0, "door", ScanKind.QUASI_STATIC, Pose.identity(), xyz, stamps, t_s=100.0, t_start_s=97.0,
                t_end_s=103.0)
    track_t = 100.0 + np.linspace(-3.0, 3.0, 61)
    track_xyz = np.column_stack([np.zeros(61), -2.0 * (track_t - 100.0) / 3.0, np.zeros(61)])
    return scan, (track_t, track_xyz)


def _faces(planes):
    walls = [p for p in planes if abs(p.normal[1]) > 0.99]
    return {round(float(p.centroid_xyz[1]), 1): p for p in walls}


def test_both_faces_of_the_wall_face_the_side_they_were_seen_from():
    config = PlanesConfig()
    scan, track = _door_walk()
    found = detect_planes(scan, config)
    faces = _faces(found)
    assert set(faces) == {_ROOM_FACE_Y, _CORRIDOR_FACE_Y}
    # towards the origin, between them: the room face looks into the corridor and the other way
    assert faces[_ROOM_FACE_Y].normal[1] < 0 and faces[_CORRIDOR_FACE_Y].normal[1] > 0
    times = plane_time_offsets(scan.points_xyz, scan.stamps_s, scan.t_s, found, config.refit_distance_m, track)
    timed = times.applied(found)
    turned = facing_the_sensor(timed, config.refit_distance_m)
    faces = _faces(turned)
    assert faces[_ROOM_FACE_Y].normal[1] > 0.99 and faces[_CORRIDOR_FACE_Y].normal[1] < -0.99
    for y, p in faces.items():
        assert np.isclose(p.normal @ p.centroid_xyz, p.d_m) and np.isclose(p.d_m, p.normal[1] * y, atol=0.01)
        # the sensor that saw it is in front of it
        assert p.normal @ p.sensor_xyz - p.d_m > 0.3
    # the floor, seen from above all the time, is as detection left it
    floor = [p for p in turned if abs(p.normal[2]) > 0.99]
    assert len(floor) == 1 and floor[0].normal[2] > 0.99 and any(floor[0] is p for p in timed)


def test_a_turned_plane_is_the_same_plane_with_the_same_uncertainty():
    """(n, d) and (-n, -d) are one plane; the turned one stays right-handed, and its covariance in
    (nx, ny, nz, d) maps onto the original's through the sign change: the same uncertainty."""
    config = PlanesConfig()
    scan, track = _door_walk(seed=11)
    found = detect_planes(scan, config)
    before = plane_time_offsets(scan.points_xyz, scan.stamps_s, scan.t_s, found, config.refit_distance_m,
                                track).applied(found)
    after = facing_the_sensor(before, config.refit_distance_m)
    turned = [(a, b) for a, b in zip(before, after, strict=True) if a.normal @ b.normal < 0]
    assert len(turned) == 2
    for a, b in turned:
        u, v = b.basis_uv
        assert np.allclose(np.cross(u, v), b.normal)
        assert np.allclose(b.cov_nd(), a.cov_nd())  # (n, d) -> (-n, -d) flips both rows and columns
        # the time slope along v: the same physical direction, so the same slope per metre of it
        assert np.isclose(b.t_slope_s_per_m[0] * (b.basis_uv[0] @ a.basis_uv[0]), a.t_slope_s_per_m[0])
        assert np.isclose(b.t_slope_s_per_m[1] * (b.basis_uv[1] @ a.basis_uv[1]), a.t_slope_s_per_m[1])
        assert np.allclose(b.sensor_slope @ b.basis_uv, a.sensor_slope @ a.basis_uv)
    # a plane without a known sensor position is left as it is
    bare = [replace(p, sensor_xyz=None) for p in before]
    assert facing_the_sensor(tuple(bare), config.refit_distance_m) == tuple(bare)
