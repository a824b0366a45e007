"""Shared fixtures: real-data folder, and a tiny synthetic run with known truth (fixed seed)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
import pytest

from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.trajectory import write_trajectory_geoslam
from kinreg.types import Trajectory

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"
SAMPLE_DATA = REPO / "sample_data"


@pytest.fixture
def realdata() -> Path:
    if not REALDATA.is_dir():
        pytest.skip("../shared/realdata is absent")
    return REALDATA


def make_trajectory(duration_s: float = 30.0, rate_hz: float = 100.0, t0: float = 1623220971.15523,
                    offset=(0.0, 0.0, 0.0)) -> Trajectory:
    """A smooth walk with turning heading and some sway (object frame, optional UTM offset)."""
    t = t0 + np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    s = t - t0
    xyz = np.column_stack([3.0 * np.sin(0.05 * s) + 0.8 * s / 4, 2.0 * np.cos(0.07 * s), 1.5 + 0.05 * np.sin(s)])
    xyz = xyz + np.asarray(offset)
    rotvec = np.column_stack([0.1 * np.sin(0.9 * s), 0.08 * np.cos(1.3 * s), 0.3 * s])
    return Trajectory(t, Pose(rotvec_to_quat(rotvec), xyz))


def random_correction(traj: Trajectory, n_stations: int, rng: np.random.Generator, sigma_rad: float,
                      sigma_m: float, margin_s: float):
    """A :class:`~kinreg.estimate.correction.DriftCorrection` of ``n_stations`` evenly spaced along
    ``traj`` (``margin_s`` from either end), each adjusted by a random turn (``sigma_rad``) and shift
    (``sigma_m``); returns it, the station times and their initial poses."""
    from kinreg.estimate.correction import DriftCorrection

    ts = np.linspace(traj.t_start_s + margin_s, traj.t_end_s - margin_s, n_stations)
    initial = traj.pose_at(ts)
    turns, shifts = rng.normal(0, sigma_rad, (n_stations, 3)), rng.normal(0, sigma_m, (n_stations, 3))
    adjusted = initial.compose(Pose(rotvec_to_quat(turns), shifts))
    return DriftCorrection.from_stations(ts, initial, adjusted, traj), ts, initial


@dataclass
class SyntheticRun:
    trajectory: Trajectory
    trajectory_path: Path
    cloud_path: Path
    xyz: np.ndarray  # object-frame points as stored (after LAS quantisation)
    stamps_s: np.ndarray


def write_synthetic_run(folder: Path, n_points: int = 60_000, duration_s: float = 30.0, sort: bool = True,
                        seed: int = 7, offset=(0.0, 0.0, 0.0), point_format: int = 6,
                        laz: bool = True) -> SyntheticRun:
    """Trajectory (GeoSLAM text) + cloud (LAZ with gps_time): the walls, floor and ceiling of a
    room around the walk, each point within 3 m (along the surface) of where the platform was
    when it was seen, with 2 mm noise: a run that ``kinreg process`` can link and adjust."""
    rng = np.random.default_rng(seed)
    traj = make_trajectory(duration_s, offset=offset)
    stamps = np.sort(rng.uniform(traj.t_start_s, traj.t_end_s, n_points))
    xyz = _room_points(traj.pose_at(stamps).t_xyz - np.asarray(offset), rng) + np.asarray(offset)
    order = np.arange(n_points) if sort else rng.permutation(n_points)
    xyz, stamps = xyz[order], stamps[order]
    folder.mkdir(parents=True, exist_ok=True)
    traj_path = folder / "traj.txt"
    write_trajectory_geoslam(traj_path, traj, overwrite=True)
    header = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if "gps_time" in las.point_format.dimension_names:
        las.gps_time = stamps
    las.intensity = rng.integers(0, 65535, n_points, dtype=np.uint16)
    cloud_path = folder / ("cloud.laz" if laz else "cloud.las")
    las.write(cloud_path)
    stored = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    return SyntheticRun(traj, traj_path, cloud_path, stored, stamps)


# The room of write_synthetic_run (object frame before the offset): its lower and upper corners.
_ROOM_LOW, _ROOM_HIGH = np.array([-4.0, -5.0, 0.0]), np.array([13.0, 5.0, 3.5])


def _room_points(sensor_xyz: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One point per sensor position on one of the room's six faces (chosen at random), within
    3 m of the sensor's foot on that face, with 2 mm noise across it."""
    n = len(sensor_xyz)
    face = rng.integers(0, 6, n)
    axis, upper = face // 2, face % 2 == 1
    xyz = sensor_xyz + rng.uniform(-3.0, 3.0, (n, 3))
    xyz = np.clip(xyz, _ROOM_LOW, _ROOM_HIGH)
    xyz[np.arange(n), axis] = np.where(upper, _ROOM_HIGH[axis], _ROOM_LOW[axis]) + rng.normal(0.0, 0.002, n)
    return xyz


@pytest.fixture
def synthetic_run(tmp_path: Path) -> SyntheticRun:
    return write_synthetic_run(tmp_path / "run")
