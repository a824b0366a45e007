"""What real scans have and exact planes with white noise do not: wavy surfaces, heavy-tailed range
noise and mixed pixels, sweeps with gaps, a trajectory error that is not smooth, clutter off the planes.

Every effect is off by default (:class:`RealWorldConfig`), so a run without them is the simulator
as it was, byte for byte; :meth:`RealWorldConfig.all_on` turns them all on at magnitudes of real
indoor scans (a spinning LiDAR's keyframes on odometry-grade poses, as in issue #43's hall).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kinreg.geometry import FloatArray, Pose, make_quat_continuous, rotvec_to_quat
from kinreg.simulation.scene import Scene
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)

IntArray = NDArray[np.int64]

#: ``patch_id`` of a point on the clutter (furniture, a walker): on no patch of the scene
CLUTTER_PATCH_ID = -1


@dataclass(frozen=True)
class RealWorldConfig:
    """The real-world effects of a simulated run; the defaults switch every one off.

    - ``waviness_rms_m``: each scene plane departs from its plane along its normal by a sum of
      ``waviness_terms`` sinusoids of wavelengths drawn in ``waviness_wavelength_m`` (random
      direction in the plane, random phase), scaled to this RMS.
    - ``tail_share``: the share of points whose range noise has ``tail_scale`` times the sensor's
      sigma (a heavy tail).
    - ``mixed_pixel_footprint_rad``: where a ray's neighbour at this angle hits something more than
      ``mixed_pixel_min_jump_m`` nearer or farther (the beam grazes an edge), ``mixed_pixel_share``
      of those points get a range between the two (uniform).
    - ``sweep_s``, ``sweep_period_s``: the sensor records a ``sweep_s`` sweep every
      ``sweep_period_s`` (keyframes) instead of continuously; 0 records continuously.
    - ``jitter_m``, ``jitter_rad``, ``jitter_corr_s``: the exported trajectory's pose error has, on
      top of the drift, a first-order Gauss-Markov jitter of this RMS per axis (position in the
      object frame, attitude in the platform frame) and correlation time.
    - ``furniture_per_room``: vertical cylinders (bins, round tables, stools) in each room's
      furniture band; ``walkers``: people (vertical cylinders) walking up and down the corridor.
    """

    waviness_rms_m: float = 0.0
    waviness_wavelength_m: tuple[float, float] = (1.0, 5.0)
    waviness_terms: int = 4
    tail_share: float = 0.0
    tail_scale: float = 5.0
    mixed_pixel_footprint_rad: float = 0.0
    mixed_pixel_share: float = 0.5
    mixed_pixel_min_jump_m: float = 0.05
    sweep_s: float = 0.0
    sweep_period_s: float = 0.5
    jitter_m: float = 0.0
    jitter_rad: float = 0.0
    jitter_corr_s: float = 1.0
    furniture_per_room: int = 0
    walkers: int = 0

    @classmethod
    def all_on(cls) -> RealWorldConfig:
        """Every effect on: 2.5 mm waviness over 1-5 m, a 2 % tail of 5 sigma, mixed pixels of a
        3 mrad footprint, 0.1 s sweeps every 0.5 s, 1 cm / 1 mrad jitter per axis of 1 s correlation
        time, three pieces of round furniture per room and one person walking."""
        return cls(waviness_rms_m=0.0025, tail_share=0.02, mixed_pixel_footprint_rad=0.003, sweep_s=0.1,
                   jitter_m=0.01, jitter_rad=0.001, furniture_per_room=3, walkers=1)

    @classmethod
    def only(cls, *effects: str) -> RealWorldConfig:
        """The effects named (keys of :data:`EFFECTS`) on as in :meth:`all_on`, the others off."""
        on = cls.all_on()
        unknown = set(effects) - set(EFFECTS)
        if unknown:
            raise ValueError(f"unknown real-world effects {sorted(unknown)}; known: {', '.join(EFFECTS)}")
        return cls(**{f: getattr(on, f) for e in effects for f in EFFECTS[e]})

    @property
    def shapes_the_rays(self) -> bool:
        """Whether a ray's range needs more than the scene's planes (waviness, clutter, mixed pixels)."""
        return (self.waviness_rms_m > 0 or self.mixed_pixel_footprint_rad > 0 or self.furniture_per_room > 0
                or self.walkers > 0)

    @property
    def jitters(self) -> bool:
        return self.jitter_m > 0 or self.jitter_rad > 0


#: the effects by name, each with the fields of :class:`RealWorldConfig` that switch it on
EFFECTS: dict[str, tuple[str, ...]] = {
    "waviness": ("waviness_rms_m",),
    "noise": ("tail_share", "mixed_pixel_footprint_rad"),
    "sweeps": ("sweep_s",),
    "jitter": ("jitter_m", "jitter_rad"),
    "clutter": ("furniture_per_room", "walkers"),
}


# ---------------------------------------------------------------------------------- waviness


@dataclass(frozen=True, eq=False)
class SurfaceWaviness:
    """Per scene plane (by ``plane_id``): wave vectors (P, K, 3) [1/m, in the plane], amplitudes
    (P, K) [m] and phases (P, K) [rad] of the sinusoids whose sum is the surface's departure from
    its plane along the normal."""

    wave_vectors: FloatArray
    amplitudes_m: FloatArray
    phases: FloatArray

    def offset_m(self, plane_ids: IntArray, xyz: FloatArray) -> FloatArray:
        """The departure (N,) [m, along the plane's normal, into the free space] of the surface of
        plane ``plane_ids`` (N,) at the points ``xyz`` (N, 3) (building coordinates)."""
        k = self.wave_vectors[plane_ids]  # (N, K, 3)
        arg = 2.0 * np.pi * np.einsum("nkj,nj->nk", k, xyz) + self.phases[plane_ids]
        return np.sum(self.amplitudes_m[plane_ids] * np.sin(arg), axis=1)


def make_waviness(scene: Scene, config: RealWorldConfig, rng: np.random.Generator) -> SurfaceWaviness:
    """Random waviness of every plane of ``scene``: ``config.waviness_terms`` sinusoids of equal
    amplitude (their sum has RMS ``config.waviness_rms_m`` over a large area), wavelengths uniform
    in ``config.waviness_wavelength_m``, directions uniform in the plane."""
    planes = scene.planes()
    n_planes = max(p.plane_id for p in planes) + 1
    K = max(1, config.waviness_terms)
    k = np.zeros((n_planes, K, 3))
    lo, hi = config.waviness_wavelength_m
    for p in planes:
        n = p.normal
        u = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        angle = rng.uniform(0.0, 2.0 * np.pi, K)
        wavelength = rng.uniform(lo, hi, K)
        k[p.plane_id] = (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v) / wavelength[:, None]
    amplitude = np.full((n_planes, K), config.waviness_rms_m * math.sqrt(2.0 / K))
    return SurfaceWaviness(k, amplitude, rng.uniform(0.0, 2.0 * np.pi, (n_planes, K)))


# ------------------------------------------------------------------------------------ clutter


@dataclass(frozen=True, eq=False)
class Clutter:
    """Vertical cylinders off the building's planes: furniture standing still (centres (F, 2),
    radii (F,), heights (F,), all from the floor) and walkers (radius, height, and their path: a
    corridor line from ``walk_xy0`` to ``walk_xy1`` (W, 2) walked up and down at ``speed_mps`` (W,)
    from the phase ``phase_m`` (W,))."""

    centres_xy: FloatArray
    radii_m: FloatArray
    heights_m: FloatArray
    walk_xy0: FloatArray
    walk_xy1: FloatArray
    speed_mps: FloatArray
    phase_m: FloatArray
    walker_radius_m: float = 0.22
    walker_height_m: float = 1.75

    def walker_xy(self, stamps_s: FloatArray) -> FloatArray:
        """The walkers' centres (N, W, 2) at ``stamps_s`` (N,): up and down their line (a triangle wave)."""
        length = np.linalg.norm(self.walk_xy1 - self.walk_xy0, axis=1)  # (W,)
        s = self.phase_m[None, :] + stamps_s[:, None] * self.speed_mps[None, :]
        s = np.abs(np.mod(s, 2.0 * length) - length)  # 0 .. length .. 0
        u = s / length
        return self.walk_xy0[None] + u[..., None] * (self.walk_xy1 - self.walk_xy0)[None]

    def raycast(self, origins: FloatArray, directions: FloatArray, stamps_s: FloatArray,
                min_range_m: float) -> tuple[FloatArray, FloatArray]:
        """Nearest hit (N,) [m, ``inf`` where none] of the rays with the clutter at the rays' times,
        and the surface normal (N, 3) there (zeros where none). A ray from inside a cylinder sees
        through it."""
        n = len(origins)
        F, W = len(self.radii_m), len(self.speed_mps)
        centres = np.broadcast_to(self.centres_xy[None], (n, F, 2))
        if W:
            centres = np.concatenate([centres, self.walker_xy(stamps_s)], axis=1)
        radii = np.concatenate([self.radii_m, np.full(W, self.walker_radius_m)])
        heights = np.concatenate([self.heights_m, np.full(W, self.walker_height_m)])
        if centres.shape[1] == 0:
            return np.full(n, np.inf), np.zeros((n, 3))
        p = origins[:, None, :2] - centres  # (N, C, 2)
        dxy = directions[:, None, :2]
        a = np.maximum(np.sum(dxy**2, axis=2), 1e-15)
        b = 2.0 * np.sum(p * dxy, axis=2)
        c = np.sum(p**2, axis=2) - radii**2
        disc = b**2 - 4.0 * a * c
        outside = c > 0.0
        with np.errstate(invalid="ignore"):
            t_side = (-b - np.sqrt(disc)) / (2.0 * a)
        z_side = origins[:, None, 2] + t_side * directions[:, None, 2]
        side = outside & (disc > 0) & (t_side > min_range_m) & (z_side >= 0.0) & (z_side <= heights)
        # the top: a disc at the cylinder's height, seen from above
        dz = directions[:, None, 2]
        with np.errstate(divide="ignore", invalid="ignore"):  # a horizontal ray meets no top
            t_top = (heights - origins[:, None, 2]) / dz
            on_top = np.sum((p + t_top[..., None] * dxy) ** 2, axis=2) <= radii**2
        top = (origins[:, None, 2] > heights) & (dz < 0) & (t_top > min_range_m) & on_top
        t = np.minimum(np.where(side, t_side, np.inf), np.where(top, t_top, np.inf))
        best = np.argmin(t, axis=1)
        rows = np.arange(n)
        r = t[rows, best]
        normal = np.zeros((n, 3))
        via_top = top[rows, best] & (t_top[rows, best] == r)
        radial = np.isfinite(r) & ~via_top
        hit_xy = origins[radial, :2] + r[radial, None] * directions[radial, :2] - centres[rows[radial], best[radial]]
        normal[radial, :2] = hit_xy / radii[best[radial], None]
        normal[via_top, 2] = 1.0
        return r, normal


def make_clutter(scene: Scene, config: RealWorldConfig, rng: np.random.Generator) -> Clutter:
    """Round furniture in each room's furniture band (not along the door's wall) and walkers on
    lines along the corridor, 0.5 m either side of its middle, at 0.8-1.3 m/s."""
    plan = scene.walk_plan
    centres, radii, heights = [], [], []
    if plan is not None:
        band = plan.keep_out_m
        for room in plan.rooms:
            (x0, y0), (x1, y1) = room.xy_min, room.xy_max
            door_low_y = room.door_inward_xy[1] > 0  # the door is in the room's low-y wall
            walls = ("west", "east", "north" if door_low_y else "south")
            for _ in range(config.furniture_per_room):
                r = rng.uniform(0.15, 0.35)
                off = rng.uniform(r + 0.05, max(r + 0.06, band - r - 0.1))
                wall = walls[rng.integers(len(walls))]
                if wall in ("west", "east"):
                    xy = (x0 + off if wall == "west" else x1 - off, rng.uniform(y0 + band, y1 - band))
                else:
                    xy = (rng.uniform(x0 + band, x1 - band), y1 - off if wall == "north" else y0 + off)
                centres.append(xy)
                radii.append(r)
                heights.append(rng.uniform(0.45, 1.1))
    W = config.walkers if plan is not None else 0
    xy0, xy1 = np.zeros((W, 2)), np.zeros((W, 2))
    if W:
        (cx0, cy0), (cx1, cy1) = plan.corridor_xy_min, plan.corridor_xy_max  # type: ignore[union-attr]
        y = 0.5 * (cy0 + cy1) + np.where(np.arange(W) % 2 == 0, 0.5, -0.5)
        xy0 = np.column_stack([np.full(W, cx0 + 0.6), y])
        xy1 = np.column_stack([np.full(W, cx1 - 0.6), y])
    return Clutter(np.array(centres, dtype=np.float64).reshape(-1, 2), np.array(radii, dtype=np.float64),
                   np.array(heights, dtype=np.float64), xy0, xy1, rng.uniform(0.8, 1.3, W),
                   rng.uniform(0.0, 100.0, W))


# ---------------------------------------------------------------------------- the world a ray sees


@dataclass(frozen=True, eq=False)
class RealWorld:
    """The scene as the rays of a real-world run see it: its planes made wavy, its clutter."""

    scene: Scene
    config: RealWorldConfig
    waviness: SurfaceWaviness | None
    clutter: Clutter | None

    def raycast(self, origins: FloatArray, directions: FloatArray, stamps_s: FloatArray | None,
                max_range_m: float, min_range_m: float) -> tuple[FloatArray, IntArray, FloatArray]:
        """Nearest hit of each ray (building coordinates): range (N,) (``inf`` where none),
        ``patch_id`` (N,) (:data:`CLUTTER_PATCH_ID` on the clutter, -1 also where nothing is hit:
        tell them apart by the range) and the surface normal (N, 3). ``stamps_s`` (N,) place the
        walkers (``None``: no walkers, e.g. a static scan)."""
        r, pid = self.scene.raycast(origins, directions, max_range_m, min_range_m)
        hit = pid >= 0
        normals = np.zeros((len(r), 3))
        normals[hit] = np.array([p.normal for p in self.scene.patches])[pid[hit]]
        if self.waviness is not None and np.any(hit):
            r[hit] = wavy_ranges(self.scene, self.waviness, origins[hit], directions[hit], r[hit], pid[hit])
        if self.clutter is not None:
            clutter = self.clutter
            if stamps_s is None:
                clutter = Clutter(clutter.centres_xy, clutter.radii_m, clutter.heights_m, np.zeros((0, 2)),
                                  np.zeros((0, 2)), np.zeros(0), np.zeros(0))
                stamps_s = np.zeros(len(r))
            r_c, n_c = clutter.raycast(origins, directions, stamps_s, min_range_m)
            nearer = (r_c < r) & (r_c <= max_range_m)
            r[nearer], pid[nearer], normals[nearer] = r_c[nearer], CLUTTER_PATCH_ID, n_c[nearer]
        return r, pid, normals

    def mixed_pixels(self, origins: FloatArray, directions: FloatArray, stamps_s: FloatArray, r: FloatArray,
                     max_range_m: float, min_range_m: float, rng: np.random.Generator) -> FloatArray:
        """The ranges ``r`` (N,) with mixed pixels: a neighbour ray at the footprint's angle (a random
        side) is cast; where it hits something else (a range jump of more than the minimum),
        a share of the points take a range between the two."""
        cfg = self.config
        if cfg.mixed_pixel_footprint_rad <= 0 or len(r) == 0:
            return r
        side = np.cross(directions, rng.standard_normal((len(r), 3)))
        side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-12)
        neighbour = directions + cfg.mixed_pixel_footprint_rad * side
        neighbour /= np.linalg.norm(neighbour, axis=1, keepdims=True)
        r_next, _, _ = self.raycast(origins, neighbour, stamps_s, max_range_m, min_range_m)
        return mixed_pixel_ranges(r, r_next, cfg, rng)


def make_real_world(scene: Scene, config: RealWorldConfig, rng_waviness: np.random.Generator,
                    rng_clutter: np.random.Generator) -> RealWorld | None:
    """The world of ``config`` on ``scene``, or ``None`` where no effect shapes the rays."""
    if not config.shapes_the_rays:
        return None
    waviness = make_waviness(scene, config, rng_waviness) if config.waviness_rms_m > 0 else None
    clutter = (make_clutter(scene, config, rng_clutter) if config.furniture_per_room > 0 or config.walkers > 0
               else None)
    return RealWorld(scene, config, waviness, clutter)


def wavy_ranges(scene: Scene, waviness: SurfaceWaviness, origins: FloatArray, directions: FloatArray,
                r: FloatArray, patch_ids: IntArray) -> FloatArray:
    """The ranges (N,) of the rays to the wavy surfaces instead of their planes: the hit on the
    plane moved along the ray so that it lies the waviness off the plane along its normal (its
    cosine of incidence bounded below by 0.1, so a grazing ray is not thrown metres)."""
    normals = np.array([p.normal for p in scene.patches])[patch_ids]
    plane = scene.plane_of_patch()[patch_ids]
    w = waviness.offset_m(plane, origins + r[:, None] * directions)
    cos_inc = np.maximum(-np.einsum("ij,ij->i", normals, directions), 0.1)
    return r - w / cos_inc


def mixed_pixel_ranges(r: FloatArray, r_neighbour: FloatArray, config: RealWorldConfig,
                       rng: np.random.Generator) -> FloatArray:
    """``r`` (N,) where the neighbour's range ``r_neighbour`` (N,) jumps by more than
    ``config.mixed_pixel_min_jump_m``: ``config.mixed_pixel_share`` of those take a range uniform
    between the two."""
    edge = np.isfinite(r_neighbour) & (np.abs(r_neighbour - r) > config.mixed_pixel_min_jump_m)
    mixed = edge & (rng.uniform(size=len(r)) < config.mixed_pixel_share)
    out = r.copy()
    out[mixed] += rng.uniform(size=int(mixed.sum())) * (r_neighbour[mixed] - r[mixed])
    return out


def range_noise(rng: np.random.Generator, n: int, sigma_m: float, config: RealWorldConfig) -> FloatArray:
    """Range errors (n,) [m]: Gaussian of ``sigma_m``, ``config.tail_share`` of them with
    ``config.tail_scale`` times that sigma."""
    e = sigma_m * rng.standard_normal(n)
    if config.tail_share > 0:
        e[rng.uniform(size=n) < config.tail_share] *= config.tail_scale
    return e


def in_sweeps(stamps_s: FloatArray, t0_s: float, config: RealWorldConfig) -> NDArray[np.bool_]:
    """Which of the pulse times ``stamps_s`` fall into a sweep (all, where ``config.sweep_s`` is 0):
    sweeps of ``sweep_s`` start every ``sweep_period_s`` from ``t0_s``."""
    if config.sweep_s <= 0:
        return np.ones(len(stamps_s), dtype=bool)
    return np.mod(stamps_s - t0_s, config.sweep_period_s) < config.sweep_s - 1e-9


# --------------------------------------------------------------------------- the trajectory's jitter


def gauss_markov(rng: np.random.Generator, n: int, dt_s: float, corr_s: float, sigma: float,
                 dims: int = 3) -> FloatArray:
    """A stationary first-order Gauss-Markov process (n, dims): RMS ``sigma`` per component, its
    autocorrelation ``exp(-lag / corr_s)``; a random walk pulled back to zero over ``corr_s``."""
    a = math.exp(-dt_s / corr_s)
    w = rng.standard_normal((n, dims)) * sigma
    w[1:] *= math.sqrt(1.0 - a * a)
    x = np.empty_like(w)
    x[0] = w[0]
    for k in range(1, n):  # a few 10^4 rows of 3 components: a Python loop is fast enough
        x[k] = a * x[k - 1] + w[k]
    return x


def jittered(trajectory: Trajectory, config: RealWorldConfig, rng: np.random.Generator) -> Trajectory:
    """``trajectory`` with its jitter: a Gauss-Markov offset of ``config.jitter_m`` per axis
    (object frame) on its positions and a rotation of ``config.jitter_rad`` per axis (platform
    frame, a right perturbation) on its attitudes; the walk's own rows (equally spaced)."""
    n = len(trajectory.stamps_s)
    dt = float(trajectory.stamps_s[1] - trajectory.stamps_s[0])
    dx = gauss_markov(rng, n, dt, config.jitter_corr_s, config.jitter_m)
    dphi = gauss_markov(rng, n, dt, config.jitter_corr_s, config.jitter_rad)
    poses = Pose(trajectory.poses.quat_wxyz, trajectory.poses.t_xyz + dx).compose(
        Pose(rotvec_to_quat(dphi), np.zeros((n, 3))))
    return Trajectory(trajectory.stamps_s.copy(), Pose(make_quat_continuous(poses.quat_wxyz), poses.t_xyz),
                      source=trajectory.source)
