"""One simulated run: configuration, true and drifted trajectories, and the cloud cast block by block."""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import (
    FloatArray,
    Pose,
    quat_to_rotvec,
    rotvec_to_quat,
)
from kinreg.simulation.drift import DriftConfig, DriftModel, _offset_trajectory, drifted_trajectory
from kinreg.simulation.realism import (
    RealWorld,
    RealWorldConfig,
    in_sweeps,
    jittered,
    make_real_world,
    range_noise,
)
from kinreg.simulation.scene import BuildingConfig, BuildingLayout, Scene, ScenePlane, make_building
from kinreg.simulation.sensor import (
    SensorConfig,
    StaticConfig,
    _head_directions,
    _intensity,
    _interpolate_fast,
    make_static_scans,
)
from kinreg.simulation.walk import WalkConfig, make_walk, stand_still_intervals
from kinreg.types import Scan, Trajectory

logger = logging.getLogger(__name__)

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class SimulationConfig:
    """Everything :func:`simulate_run` needs. Deterministic given the configuration.

    ``origin_xyz`` is added to every object-frame output (a UTM-like offset, e.g.
    ``(500000.0, 5400000.0, 0.0)``); the simulation itself runs in building coordinates.
    """

    seed: int = 1
    duration_s: float = 240.0
    t0_s: float = 1623220971.0
    building: BuildingConfig = field(default_factory=BuildingConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    walk: WalkConfig = field(default_factory=WalkConfig)
    drift: DriftConfig = field(default_factory=DriftConfig)
    static: StaticConfig = field(default_factory=StaticConfig)
    origin_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    block_s: float = 10.0  # the cloud is generated in blocks of this much scanning time
    # The surveyed coordinates of the control points at the walk's stand-stills (control.csv) carry
    # a survey error of this standard deviation per axis; control_truth.csv holds the true ones.
    control_sigma_mm: float = 3.0
    # Targets in the static scans (SimulatedRun.static_targets): the scan measures each target's
    # centre in its frame with this standard deviation per axis (the survey's is control_sigma_mm).
    target_sigma_mm: float = 2.0
    # What real scans have (wavy surfaces, heavy-tailed noise, mixed pixels, sweeps with gaps,
    # jitter, clutter): all off by default, RealWorldConfig.all_on() turns every effect on.
    real_world: RealWorldConfig = field(default_factory=RealWorldConfig)


def config_as_dict(config: SimulationConfig) -> dict[str, Any]:
    """The configuration as plain JSON-able values (enums by value); ``real_world`` only where
    some effect is on (so that a run without them writes the files it always wrote)."""

    def conv(x: Any) -> Any:
        if isinstance(x, enum.Enum):
            return x.value
        if isinstance(x, dict):
            return {k: conv(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [conv(v) for v in x]
        return x

    out = conv(dataclasses.asdict(config))
    if config.real_world == RealWorldConfig():
        del out["real_world"]
    return out


def config_from_dict(data: dict[str, Any]) -> SimulationConfig:
    """The inverse of :func:`config_as_dict` (e.g. from ``run_meta.json``): rebuilds the run."""
    sections = {"building": BuildingConfig, "sensor": SensorConfig, "walk": WalkConfig, "drift": DriftConfig,
                "static": StaticConfig, "real_world": RealWorldConfig}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key in sections:
            sub = dict(value)
            if key == "building" and "layout" in sub:
                sub["layout"] = BuildingLayout(sub["layout"])
            if key == "drift" and "model" in sub:
                sub["model"] = DriftModel(sub["model"])
            kwargs[key] = sections[key](**{k: tuple(v) if isinstance(v, list) else v for k, v in sub.items()})
        else:
            kwargs[key] = tuple(value) if isinstance(value, list) else value
    return SimulationConfig(**kwargs)


def _rng(seed: int, stream: int) -> np.random.Generator:
    # One independent stream per purpose, so that changing e.g. the noise leaves the walk alone.
    return np.random.default_rng([seed, stream])


@dataclass(frozen=True, eq=False)
class CloudBlock:
    """One block of simulated points, in acquisition order.

    ``stamps_s`` (N,) float64 point times; ``xyz_sensor`` (N, 3) measured points in the platform
    frame (range noise included); ``xyz_obj`` (N, 3) exported object-frame points (mapped with the
    interpolated DRIFTED trajectory, ``origin_xyz`` included); ``intensity`` (N,) uint16;
    ``patch_id`` (N,) the scene patch each ray hit (``realism.CLUTTER_PATCH_ID``, -1, on clutter);
    ``range_m`` (N,) measured ranges.
    """

    stamps_s: FloatArray
    xyz_sensor: FloatArray
    xyz_obj: FloatArray
    intensity: NDArray[np.uint16]
    patch_id: IntArray
    range_m: FloatArray
    first_index: int = 0

    def __len__(self) -> int:
        return len(self.stamps_s)


@dataclass(frozen=True, eq=False)
class SimulatedTarget:
    """A target on a wall seen by a static scan: its name, the scan (position in ``static_scans``
    and name), the true object-frame coordinates (3,), the surveyed ones (3,) and the coordinates
    (3,) the scan measured in its own frame (from its true pose)."""

    name: str
    scan: int
    scan_name: str
    true_xyz: FloatArray
    xyz: FloatArray
    scan_xyz: FloatArray


@dataclass(frozen=True, eq=False)
class SimulatedRun:
    """A simulated acquisition with its ground truth. Object-frame values include ``origin_xyz``.

    ``truth`` and ``slam`` are the true and the exported (drifted) 100 Hz trajectories
    ``T_obj_p``; ``drift`` (one pose per row) satisfies ``slam = drift * truth``. ``scene`` is in
    building coordinates (add ``origin_xyz``, or use :meth:`scene_planes_obj`). The cloud is
    generated on demand, block by block, by :meth:`iter_cloud_blocks`. ``world`` is the scene as
    the rays see it with ``config.real_world``'s waviness and clutter (``None`` without them).
    """

    config: SimulationConfig
    scene: Scene
    truth: Trajectory
    slam: Trajectory
    drift: Pose
    static_scans: tuple[Scan, ...]
    world: RealWorld | None = None

    @property
    def origin(self) -> FloatArray:
        return np.asarray(self.config.origin_xyz, dtype=np.float64)

    def n_blocks(self) -> int:
        return max(1, math.ceil(self.config.duration_s / self.config.block_s - 1e-9))

    def iter_cloud_blocks(self) -> Iterator[CloudBlock]:
        """The cloud in time blocks of ``config.block_s``; deterministic, independent of callers."""
        first = 0
        for b in range(self.n_blocks()):
            blk = self.cloud_block(b, first_index=first)
            first += len(blk)
            yield blk

    def cloud_block(self, index: int, first_index: int = 0) -> CloudBlock:
        """Block ``index`` of the cloud (its pulses ``[index, index + 1) * block_s``)."""
        return _simulate_block(self, index, first_index)

    def scene_planes_obj(self) -> list[ScenePlane]:
        """The scene's planes in the output object frame (``origin_xyz`` applied)."""
        o = self.origin
        return [dataclasses.replace(p, d=float(p.d + p.normal @ o)) for p in self.scene.planes()]

    def stand_stills(self) -> FloatArray:
        """The (start, end) times (k, 2) of the walk's stand-stills (the unit on a control point)."""
        return stand_still_intervals(self.config.walk, self.config.duration_s, self.config.t0_s)

    def control_points(self, reference_point_m: FloatArray | None = None,
                       noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """Per stand-still: its (start, end) times (k, 2) and the position (k, 3) of the platform
        point ``reference_point_m`` (platform frame, default its origin) there, in the object
        frame: the true one (its mean over the stand-still: the hand sways the unit about the
        point it holds it on), plus (``noise``) a survey error of ``config.control_sigma_mm`` per
        axis (its own random stream: the walk, drift and cloud do not change with it)."""
        intervals = self.stand_stills()
        r = np.zeros(3) if reference_point_m is None else np.asarray(reference_point_m, dtype=np.float64)
        stamps = self.truth.stamps_s
        held = [self.truth.poses[(stamps >= a) & (stamps <= b)] for a, b in intervals]
        xyz = np.array([poses.apply(np.broadcast_to(r, (len(poses), 3))).mean(axis=0) for poses in held]).reshape(-1, 3)
        if noise:
            xyz = xyz + 1e-3 * self.config.control_sigma_mm * _rng(self.config.seed, 5).standard_normal(xyz.shape)
        return intervals, xyz

    def static_targets(self, n_per_scan: int = 4, noise: bool = True) -> list[SimulatedTarget]:
        """``n_per_scan`` targets on the walls around each static scan, spread in azimuth (every
        ``360 / n`` degrees from a random start) and alternately 0 and 20 degrees above the
        scanner's horizon: the farthest wall or ceiling point (up to 25 m) within 40 degrees of that
        azimuth. With ``noise`` the surveyed coordinates carry ``config.control_sigma_mm`` and the
        scan's coordinates ``config.target_sigma_mm`` per axis; each has its own random stream, so
        the walk, drift, cloud and static scans do not change with the targets. Named ``S00T1``,
        ``S00T2``, ... by scan and target."""
        targets = []
        start = _rng(self.config.seed, 6).uniform(0.0, 2.0 * np.pi, len(self.static_scans))
        for k, scan in enumerate(self.static_scans):
            R, t_local = scan.T_obj_scan.rotation_matrix, scan.T_obj_scan.t_xyz - self.origin
            for j in range(n_per_scan):
                # The farthest wall or ceiling point within +-40 degrees of the target's azimuth.
                elevation = math.radians(0.0 if j % 2 == 0 else 20.0)
                a = start[k] + 2.0 * np.pi * j / n_per_scan + np.radians(np.arange(-40.0, 40.1, 5.0))
                d_scan = np.column_stack([np.cos(elevation) * np.cos(a), np.cos(elevation) * np.sin(a),
                                          np.full(len(a), math.sin(elevation))])
                r, pid = self.scene.raycast(np.broadcast_to(t_local, d_scan.shape), d_scan @ R.T, 25.0, 1.5)
                r = np.where(pid >= 0, r, -1.0)
                best = int(np.argmax(r))
                if r[best] < 1.5:
                    continue
                true_xyz = t_local + R @ d_scan[best] * r[best] + self.origin
                targets.append(SimulatedTarget(f"S{k:02d}T{j + 1}", k, scan.name, true_xyz, true_xyz.copy(),
                                               d_scan[best] * r[best]))
        if noise and targets:
            survey = _rng(self.config.seed, 8).standard_normal((len(targets), 3)) * 1e-3 * self.config.control_sigma_mm
            measured = _rng(self.config.seed, 9).standard_normal((len(targets), 3)) * 1e-3 * self.config.target_sigma_mm
            targets = [dataclasses.replace(t, xyz=t.true_xyz + survey[n], scan_xyz=t.scan_xyz + measured[n])
                       for n, t in enumerate(targets)]
        return targets

    def static_scans_misregistered(self, shift_m: float = 0.02, turn_deg: float = 0.1) -> tuple[Scan, ...]:
        """The static scans with poses off by ``shift_m`` (horizontal, random direction) and
        ``turn_deg`` (about a random axis) each: a registration error, for runs where the scans'
        targets, not their poses, are to hold the datum (own random stream)."""
        rng = _rng(self.config.seed, 10)
        out = []
        for scan in self.static_scans:
            heading, axis = rng.uniform(0.0, 2.0 * np.pi), rng.standard_normal(3)
            error = Pose(rotvec_to_quat(math.radians(turn_deg) * axis / np.linalg.norm(axis)),
                         shift_m * np.array([math.cos(heading), math.sin(heading), 0.0]))
            out.append(dataclasses.replace(scan, T_obj_scan=scan.T_obj_scan.compose(error)))
        return tuple(out)

    def drift_at_end(self) -> tuple[float, float]:
        """(position difference slam - truth in metres, drift rotation angle in degrees) at the end."""
        dp = float(np.linalg.norm(self.slam.poses.t_xyz[-1] - self.truth.poses.t_xyz[-1]))
        da = float(np.degrees(np.linalg.norm(quat_to_rotvec(self.drift.quat_wxyz[-1]))))
        return dp, da


def simulate_run(config: SimulationConfig | None = None) -> SimulatedRun:
    """Build the scene, the true walk, the drifted trajectory and the static scans.

    The point cloud is not generated here (it may be hundreds of millions of points): iterate
    :meth:`SimulatedRun.iter_cloud_blocks` or call :func:`write_run`.
    """
    cfg = config or SimulationConfig()
    if cfg.duration_s <= 2 * cfg.walk.pause_s + 4.0:
        raise ValueError(f"duration_s must exceed 2 * pause_s + 4 s, got {cfg.duration_s}")
    scene = make_building(cfg.building)
    truth_local = make_walk(scene, cfg.walk, cfg.duration_s, cfg.t0_s, _rng(cfg.seed, 1))
    slam_local, drift = drifted_trajectory(truth_local, cfg.drift, _rng(cfg.seed, 2))
    if cfg.real_world.jitters:
        slam_local = jittered(slam_local, cfg.real_world, _rng(cfg.seed, 20))
        drift = slam_local.poses.compose(truth_local.poses.inverse())
    world = make_real_world(scene, cfg.real_world, _rng(cfg.seed, 21), _rng(cfg.seed, 22))
    origin = np.asarray(cfg.origin_xyz, dtype=np.float64)
    # The drift in the output frame: D' = O D O^-1 (same rotation, pivot moved with the origin).
    drift_out = Pose(drift.quat_wxyz, drift.t_xyz + origin - np.einsum("nij,j->ni", drift.rotation_matrix,
                                                                          origin))
    static = make_static_scans(scene, cfg.static, _rng(cfg.seed, 4), origin, world)
    return SimulatedRun(cfg, scene, _offset_trajectory(truth_local, origin),
                        _offset_trajectory(slam_local, origin), drift_out, static, world)


def _simulate_block(run: SimulatedRun, index: int, first_index: int) -> CloudBlock:
    cfg = run.config
    sen = cfg.sensor
    rng = _rng(cfg.seed, 1000 + index)
    pr = sen.pulse_rate_hz
    k0 = round(index * cfg.block_s * pr)
    k1 = min(round((index + 1) * cfg.block_s * pr), math.floor(cfg.duration_s * pr))
    k = np.arange(k0, max(k0, k1), dtype=np.int64)
    # float64 seconds: t0 + k / rate is exact to ~0.2 microseconds at GPS-like magnitudes
    stamps = cfg.t0_s + k / pr
    if cfg.real_world.sweep_s > 0:  # the sensor records sweeps with gaps between them
        recorded = in_sweeps(stamps, cfg.t0_s, cfg.real_world)
        k, stamps = k[recorded], stamps[recorded]
    beam = k % sen.n_beams
    theta = 2 * np.pi * np.mod(k * (sen.line_rate_hz / pr), 1.0)
    psi = 2 * np.pi * np.mod(k * (sen.head_rate_hz / pr), 1.0)
    if sen.n_beams > 1:
        elev = np.radians(np.linspace(-sen.beam_spread_deg / 2, sen.beam_spread_deg / 2, sen.n_beams))[beam]
    else:
        elev = np.zeros(len(k))
    # The head's spin axis tilted forward about the platform's y axis (a head mounted at 45 deg).
    tilt = math.radians(sen.head_tilt_deg)
    R_tilt = np.array([[math.cos(tilt), 0.0, math.sin(tilt)], [0.0, 1.0, 0.0], [-math.sin(tilt), 0.0, math.cos(tilt)]])
    d_nom = _head_directions(theta, elev, psi) @ R_tilt.T
    blind_axis = np.asarray(sen.blind_axis_p, dtype=np.float64)
    blind_axis /= np.linalg.norm(blind_axis)
    seen = d_nom @ blind_axis < math.cos(math.radians(sen.blind_cone_deg))
    stamps, theta, elev, psi, d_nom = stamps[seen], theta[seen], elev[seen], psi[seen], d_nom[seen]
    n = len(stamps)
    # The laser goes where the encoders do not quite say: cast along the perturbed direction,
    # report along the nominal one.
    sa = math.radians(sen.angle_sigma_deg)
    d_true = _head_directions(theta + sa * rng.standard_normal(n), elev + sa * rng.standard_normal(n), psi) @ R_tilt.T
    # Ray casting in building coordinates from the interpolated TRUE trajectory.
    origin = run.origin
    truth = run.truth
    R_true, o_true = _interpolate_fast(truth.stamps_s, truth.poses, stamps)
    dirs_obj = np.einsum("nij,nj->ni", R_true, d_true)
    if run.world is not None:
        return _simulate_real_block(run, index, first_index, rng, stamps, d_nom, o_true - origin, dirs_obj)
    r_true, pid = run.scene.raycast(o_true - origin, dirs_obj, sen.max_range_m, sen.min_range_m)
    hit = pid >= 0
    stamps, d_nom, dirs_obj, r_true, pid = stamps[hit], d_nom[hit], dirs_obj[hit], r_true[hit], pid[hit]
    n = len(stamps)
    r_meas = r_true + (range_noise(_rng(cfg.seed, 3000 + index), n, sen.range_sigma_m, cfg.real_world)
                       if cfg.real_world.tail_share > 0 else sen.range_sigma_m * rng.standard_normal(n))
    xyz_sensor = r_meas[:, None] * d_nom
    # Exported cloud: the interpolated DRIFTED trajectory, exactly as SLAM software georeferences.
    R_slam, t_slam = _interpolate_fast(run.slam.stamps_s, run.slam.poses, stamps)
    xyz_obj = np.einsum("nij,nj->ni", R_slam, xyz_sensor) + t_slam
    normals = np.array([p.normal for p in run.scene.patches])[pid]
    refl = np.array([p.reflectivity for p in run.scene.patches])[pid]
    intensity = _intensity(refl, -np.einsum("ij,ij->i", normals, dirs_obj), r_true, sen.intensity_noise, rng)
    return CloudBlock(stamps, xyz_sensor, xyz_obj, intensity, pid, r_meas, first_index)


def _simulate_real_block(run: SimulatedRun, index: int, first_index: int, rng: np.random.Generator,
                         stamps: FloatArray, d_nom: FloatArray, origins: FloatArray,
                         dirs_obj: FloatArray) -> CloudBlock:
    """The rest of :func:`_simulate_block` in a real world (``run.world``): rays on wavy surfaces
    and the clutter, mixed pixels at edges, heavy-tailed range noise (their draws from the
    block's own second stream)."""
    cfg, sen, world = run.config, run.config.sensor, run.world
    assert world is not None
    extra = _rng(cfg.seed, 3000 + index)
    r_true, pid, normals = world.raycast(origins, dirs_obj, stamps, sen.max_range_m, sen.min_range_m)
    hit = np.isfinite(r_true)
    stamps, d_nom, origins, dirs_obj, r_true, pid, normals = (
        stamps[hit], d_nom[hit], origins[hit], dirs_obj[hit], r_true[hit], pid[hit], normals[hit])
    n = len(stamps)
    r_true = world.mixed_pixels(origins, dirs_obj, stamps, r_true, sen.max_range_m, sen.min_range_m, extra)
    r_meas = r_true + range_noise(extra, n, sen.range_sigma_m, cfg.real_world)
    xyz_sensor = r_meas[:, None] * d_nom
    # Exported cloud: the interpolated DRIFTED (and jittered) trajectory, as SLAM software does it.
    R_slam, t_slam = _interpolate_fast(run.slam.stamps_s, run.slam.poses, stamps)
    xyz_obj = np.einsum("nij,nj->ni", R_slam, xyz_sensor) + t_slam
    on_patch = pid >= 0
    refl = np.full(n, 0.5)
    refl[on_patch] = np.array([p.reflectivity for p in run.scene.patches])[pid[on_patch]]
    intensity = _intensity(refl, -np.einsum("ij,ij->i", normals, dirs_obj), r_true, sen.intensity_noise, rng)
    return CloudBlock(stamps, xyz_sensor, xyz_obj, intensity, pid, r_meas, first_index)
