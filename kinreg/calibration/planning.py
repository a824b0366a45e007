"""Planning a calibration field: theoretical sigmas of lever arm and boresight, fitness f1-f3.

Seed 000, sections 4.1-4.3 (variance propagation only, no noise). Decisions where the seed is
silent, all configurable in :class:`PlanningConfig`:

* One profile of the Z+F IMAGER 5016 in profile mode (zenith step 0.036 deg, 10,000 rays per
  revolution; a 40 deg blind cone round the nadir, vertical field of view 320 deg) from a
  standing platform, with **one** tracker pose for the whole profile ("the intersection points at
  each RP with the laser scanner profile were calculated"). ``n_profiles`` identical profiles,
  each with its own tracker pose, only divide every sigma by ``sqrt(n_profiles)``.
* The plane size is not given in the seed. Default: squares of 0.3 m (Table 2 puts neighbouring
  planes 0.4 m apart, so larger squares would touch). Planes are centred on the profile.
* Plane orientation: ``R = Rz(gamma) Ry(beta) Rx(alpha)`` applied to a horizontal plane (see
  :mod:`kinreg.calibration.arrangement`).
* Scanner errors: sigma_d = 0.5 mm, sigma_phi = sigma_theta = 0.004 deg, propagated with the full
  3x3 covariance; tracker: 7.8 um per axis (half of 15 um + 6 um/m at 2 m, divided by sqrt(3))
  and 0.002 deg per axis as the seed states. The reference planes are error-free.
* Nominal set-up: body frame = scanner frame (lever arm 0, boresight 0) unless ``lever_arm_m``
  is set; the lever arm matters because a tracker rotation error times the lever arm is a
  translation error.

Why the computation is cheap: with a single pose the tracker error enters additively,
``Q = (N_scan^-1 + J Sigma_pose J^T) / n_profiles`` with ``J = [[I, -[b]x], [0, I]]`` (the pose
error is indistinguishable from a calibration error within one epoch). ``N_scan`` is a sum over
the planes of ``sum_j w_j a_j a_j^T`` with ``a_j = (n, P_j x n)``; in the Table 2 family each
plane depends on at most two of the five variables (e.g. RP1 on y1 and gamma1), so the 6x6 blocks
of every plane configuration are computed once (about 1,300 ray casts) and the 448,875
arrangements are sums of eight table entries followed by a batched 6x6 inversion. Planes do not
occlude each other in this family (checked against the full ray caster in the tests).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import differential_evolution

from kinreg.calibration.arrangement import (
    DEFAULT_BLIND_NADIR_HALF_ANGLE_DEG,
    DEFAULT_PLANE_SIZE_M,
    PlanePatch,
    cast_rays,
    profile_directions,
    projected_variance,
    table2_arrangement,
)
from kinreg.calibration.model import PARAMETER_NAMES, CovarianceFigures, ScannerSigmas, TrackerSigmas
from kinreg.errors import ConfigError, EstimationError
from kinreg.geometry import FloatArray, skew

logger = logging.getLogger(__name__)

FITNESS_NAMES = ("f1", "f2", "f3")
VARIABLE_NAMES = ("y1", "z1", "alpha1", "beta1", "gamma1")
# Relative eigenvalue of the equilibrated normal matrix below which an arrangement is singular.
_SINGULAR_TOL = 1e-12


@dataclass(frozen=True)
class PlanningConfig:
    """Measurement configuration of the planning (module docstring for the defaults)."""

    scanner: ScannerSigmas = field(default_factory=ScannerSigmas)
    tracker: TrackerSigmas | None = field(default_factory=TrackerSigmas)
    zenith_step_deg: float = 0.036
    blind_nadir_half_angle_deg: float = DEFAULT_BLIND_NADIR_HALF_ANGLE_DEG
    plane_size_m: float = DEFAULT_PLANE_SIZE_M
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    object_distance_m: float = 10.0
    n_profiles: int = 1

    def __post_init__(self) -> None:
        if self.zenith_step_deg <= 0 or self.plane_size_m <= 0 or self.n_profiles < 1:
            raise ConfigError("zenith step, plane size must be > 0 and n_profiles >= 1")

    def pose_covariance(self) -> FloatArray:
        """Calibration-space covariance ``J Sigma_pose J^T`` (6, 6) of one tracker pose."""
        if self.tracker is None:
            return np.zeros((6, 6))
        S = np.diag([self.tracker.sigma_t_m**2] * 3 + [self.tracker.sigma_rot_rad**2] * 3)
        J = np.eye(6)
        J[:3, 3:] = -skew(np.asarray(self.lever_arm_m, dtype=np.float64))
        return J @ S @ J.T


@dataclass(frozen=True, eq=False)
class ArrangementQuality(CovarianceFigures):
    """Theoretical quality of one arrangement: ``covariance`` (6, 6) in m and rad (order
    ``tx ty tz omega phi kappa``), fitness values in millimetres, points per plane."""

    covariance: FloatArray
    f1_mm: float
    f2_mm: float
    f3_mm: float
    points_per_plane: dict[str, int]



def _point_normal_matrix(points_s: FloatArray, normals_s: FloatArray, scanner: ScannerSigmas
                         ) -> FloatArray:
    """``sum_j w_j a_j a_j^T`` (6, 6) with ``a_j = (n_j, P_j x n_j)``, ``w_j = 1 / n^T Sigma_P n``."""
    if len(points_s) == 0:
        return np.zeros((6, 6))
    w = 1.0 / projected_variance(points_s, normals_s, scanner.sigma_d_m, scanner.sigma_phi_rad,
                                 scanner.sigma_theta_rad)
    a = np.concatenate([normals_s, np.cross(points_s, normals_s)], axis=1)
    return (a * w[:, None]).T @ a


def _profile(config: PlanningConfig) -> FloatArray:
    return profile_directions(math.radians(config.zenith_step_deg),
                              math.radians(config.blind_nadir_half_angle_deg))[1]


def scan_normal_matrix(patches: Sequence[PlanePatch], config: PlanningConfig
                       ) -> tuple[FloatArray, np.ndarray]:
    """Normal matrix (6, 6) of the scanner observations of one profile (scanner at the origin,
    identity orientation, patches in the scanner frame) and the hit count per patch."""
    dirs = _profile(config)
    rng, idx = cast_rays(patches, np.zeros(3), dirs)
    hit = idx >= 0
    P = rng[hit, None] * dirs[hit]
    normals = np.array([p.normal for p in patches])[idx[hit]]
    return (_point_normal_matrix(P, normals, config.scanner),
            np.bincount(idx[hit], minlength=len(patches)))


def fitness_from_normal(N_scan: FloatArray, config: PlanningConfig
                        ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Covariances ``(..., 6, 6)`` and fitness ``(..., 3)`` (f1, f2, f3 in mm) from scanner normal
    matrices ``(..., 6, 6)``; singular arrangements get ``inf`` fitness and ``nan`` covariance."""
    N = np.asarray(N_scan, dtype=np.float64)
    d = np.sqrt(np.maximum(np.diagonal(N, axis1=-2, axis2=-1), 0.0))
    scale = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
    M = N * scale[..., :, None] * scale[..., None, :]
    eig = np.linalg.eigvalsh(M)
    singular = (eig[..., 0] <= _SINGULAR_TOL * eig[..., -1]) | np.any(d == 0, axis=-1)
    M_safe = np.where(singular[..., None, None], np.eye(6), M)
    Q_scan = np.linalg.inv(M_safe) * scale[..., :, None] * scale[..., None, :]
    cov = (Q_scan + config.pose_covariance()) / config.n_profiles
    var = np.diagonal(cov, axis1=-2, axis2=-1)
    f1 = np.sqrt(var[..., :3].sum(-1)) * 1e3
    f2 = config.object_distance_m * np.sqrt(var[..., 3:].sum(-1)) * 1e3
    f = np.stack([f1, f2, np.hypot(f1, f2)], axis=-1)
    f = np.where(singular[..., None], np.inf, f)
    cov = np.where(singular[..., None, None], np.nan, cov)
    return cov, f, singular


def evaluate_arrangement(patches: Sequence[PlanePatch], config: PlanningConfig | None = None
                         ) -> ArrangementQuality:
    """Theoretical sigmas and fitness of an arbitrary arrangement (full ray casting, occlusion).

    Raises :class:`EstimationError` naming the undetermined parameters if the arrangement does
    not determine all six (e.g. all planes parallel).
    """
    cfg = config or PlanningConfig()
    N, counts = scan_normal_matrix(patches, cfg)
    cov, f, singular = fitness_from_normal(N, cfg)
    if bool(singular):
        from kinreg.calibration.model import undetermined_parameters

        ranges = [float(np.linalg.norm(p.center_m)) for p in patches]
        bad = undetermined_parameters(N, max(float(np.mean(ranges)), 1e-3), 1e-12) or list(PARAMETER_NAMES)
        raise EstimationError("the arrangement does not determine " + ", ".join(bad)
                              + " (all planes parallel, or planes not seen by the profile?)")
    return ArrangementQuality(cov, float(f[0]), float(f[1]), float(f[2]),
                              {p.name: int(c) for p, c in zip(patches, counts, strict=True)})


# --------------------------------------------------------------------------- Table 3 grid


@dataclass(frozen=True, eq=False)
class Table3Grid:
    """Values of the five arrangement variables (metres, radians). Default: seed Table 3."""

    y1_m: FloatArray = field(default_factory=lambda: np.arange(1.0, 10.0 + 1e-9, 0.5))
    z1_m: FloatArray = field(default_factory=lambda: np.arange(1.0, 4.0 + 1e-9, 0.5))
    alpha1_rad: FloatArray = field(default_factory=lambda: np.radians(np.arange(20.0, 90.0 + 1e-9, 5.0)))
    beta1_rad: FloatArray = field(default_factory=lambda: np.radians(np.arange(0.0, 70.0 + 1e-9, 5.0)))
    gamma1_rad: FloatArray = field(default_factory=lambda: np.radians(np.arange(0.0, 70.0 + 1e-9, 5.0)))

    @property
    def axes(self) -> tuple[FloatArray, ...]:
        return (self.y1_m, self.z1_m, self.alpha1_rad, self.beta1_rad, self.gamma1_rad)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(a) for a in self.axes)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def values(self, index: Sequence[int] | np.ndarray) -> FloatArray:
        """Variable values ``(..., 5)`` (m, m, rad, rad, rad) of grid indices ``(..., 5)``."""
        ix = np.asarray(index, dtype=np.int64)
        return np.stack([ax[ix[..., i]] for i, ax in enumerate(self.axes)], axis=-1)


class Table2Tables:
    """Per-plane normal matrices of the Table 2 family over a :class:`Table3Grid` (module docstring).

    ``evaluate(index)`` gives the scanner normal matrices of arrangements by their grid indices
    ``(M, 5)`` from eight table look-ups each.
    """

    def __init__(self, grid: Table3Grid, config: PlanningConfig) -> None:
        self.grid = grid
        self.config = config
        dirs = _profile(config)
        ny, nz, na, nb, ng = grid.shape
        size = config.plane_size_m

        def block(y: float, z: float, a: float, b: float, g: float, which: int) -> FloatArray:
            patch = table2_arrangement(y, z, a, b, g, size)[which]
            rng, idx = cast_rays([patch], np.zeros(3), dirs)
            hit = idx >= 0
            P = rng[hit, None] * dirs[hit]
            return _point_normal_matrix(P, np.broadcast_to(patch.normal, P.shape), config.scanner)

        Y, Z, A, B, G = grid.axes
        # Arguments that a plane does not depend on are set to any valid value (index 0).
        self.rp1 = np.array([[block(y, Z[0], A[0], B[0], g, 0) for g in G] for y in Y])
        self.rp2 = np.array([block(y, Z[0], A[0], B[0], G[0], 1) for y in Y])
        self.rp4 = np.array([[block(y, Z[0], a, B[0], G[0], 2) for a in A] for y in Y])
        self.rp5 = np.array([block(Y[0], z, A[0], B[0], G[0], 3) for z in Z])
        self.rp6 = np.array([[block(Y[0], z, A[0], b, G[0], 4) for b in B] for z in Z])
        self.rp8 = np.array([[block(y, Z[0], a, B[0], G[0], 5) for a in A] for y in Y])
        self.rp10 = np.array([block(y, Z[0], A[0], B[0], G[0], 6) for y in Y])
        self.rp11 = np.array([[block(y, Z[0], A[0], B[0], g, 7) for g in G] for y in Y])
        self.n_ray_casts = ny * ng * 2 + ny * na * 2 + ny * 2 + nz + nz * nb

    def evaluate(self, index: np.ndarray) -> FloatArray:
        """Scanner normal matrices ``(M, 6, 6)`` of arrangements with grid indices ``(M, 5)``."""
        iy, iz, ia, ib, ig = np.asarray(index, dtype=np.int64).T
        return (self.rp1[iy, ig] + self.rp2[iy] + self.rp4[iy, ia] + self.rp5[iz] + self.rp6[iz, ib]
                + self.rp8[iy, ia] + self.rp10[iy] + self.rp11[iy, ig])

    def evaluate_y_slab(self, iy: int) -> FloatArray:
        """Normal matrices ``(nz, na, nb, ng, 6, 6)`` of all arrangements with y1 index ``iy``."""
        c = (self.rp1[iy][None, None, None, :] + self.rp2[iy] + self.rp4[iy][None, :, None, None]
             + self.rp5[:, None, None, None] + self.rp6[:, None, :, None]
             + self.rp8[iy][None, :, None, None] + self.rp10[iy] + self.rp11[iy][None, None, None, :])
        return c


@dataclass(frozen=True, eq=False)
class GridResult:
    """All arrangements of a grid: ``index`` (M, 5) grid indices, ``values`` (M, 5) in m/rad,
    ``sigmas`` (M, 6) in m/rad, ``fitness`` (M, 3) f1, f2, f3 in mm (inf where singular)."""

    grid: Table3Grid
    index: np.ndarray
    values: FloatArray
    sigmas: FloatArray
    fitness: FloatArray
    seconds: float
    n_singular: int

    def best(self, fitness: str = "f3", top: int = 1) -> list[int]:
        """Row numbers of the ``top`` best arrangements for ``fitness`` (stable order)."""
        k = FITNESS_NAMES.index(fitness)
        return [int(i) for i in np.argsort(self.fitness[:, k], kind="stable")[:top]]

    def row(self, i: int) -> dict[str, float]:
        """One arrangement as a dict: variables in m and deg, sigmas in mm and mdeg, fitness in mm."""
        y, z, a, b, g = self.values[i]
        out = {"y1_m": float(y), "z1_m": float(z), "alpha1_deg": round(math.degrees(a), 6),
               "beta1_deg": round(math.degrees(b), 6), "gamma1_deg": round(math.degrees(g), 6)}
        s = self.sigmas[i]
        for name, v in zip(PARAMETER_NAMES, s, strict=True):
            out[f"sigma_{name}"] = float(v * 1e3 if name.startswith("t") else math.degrees(v) * 1e3)
        for name, v in zip(FITNESS_NAMES, self.fitness[i], strict=True):
            out[f"{name}_mm"] = float(v)
        return out


def exhaustive_search(config: PlanningConfig | None = None, grid: Table3Grid | None = None,
                      tables: Table2Tables | None = None) -> GridResult:
    """Evaluate every arrangement of the Table 2 family over ``grid`` (default: seed Table 3)."""
    cfg = config or PlanningConfig()
    g = grid or Table3Grid()
    t0 = time.perf_counter()
    tab = tables or Table2Tables(g, cfg)
    ny = g.shape[0]
    sig_parts, fit_parts = [], []
    n_singular = 0
    for iy in range(ny):
        N = tab.evaluate_y_slab(iy).reshape(-1, 6, 6)
        cov, f, singular = fitness_from_normal(N, cfg)
        sig_parts.append(np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)))
        fit_parts.append(f)
        n_singular += int(singular.sum())
    index = np.stack(np.unravel_index(np.arange(g.size), g.shape), axis=-1)
    seconds = time.perf_counter() - t0
    logger.info("exhaustive search over %d arrangements in %.2f s (%d singular)", g.size, seconds,
                n_singular)
    return GridResult(g, index, g.values(index), np.concatenate(sig_parts), np.concatenate(fit_parts),
                      seconds, n_singular)


@dataclass(frozen=True)
class EvolutionResult:
    """Best arrangement found by differential evolution: grid ``index`` (5,), values in m/rad,
    ``fitness_mm``, the number of fitness evaluations and generations."""

    fitness: str
    index: tuple[int, ...]
    values: tuple[float, ...]
    fitness_mm: float
    n_evaluations: int
    n_generations: int
    seconds: float


def optimise_evolution(fitness: str = "f3", config: PlanningConfig | None = None,
                       grid: Table3Grid | None = None, tables: Table2Tables | None = None,
                       seed: int | None = 0, popsize: int = 15, maxiter: int = 100,
                       fixed: dict[str, int] | None = None) -> EvolutionResult:
    """Minimise ``fitness`` over the grid with scipy's integer differential evolution.

    The five variables are grid indices (``integrality``); ``fixed`` pins variables (by name in
    :data:`VARIABLE_NAMES`) to a grid index, as in the seed's separate optimisations (Table 5).
    """
    if fitness not in FITNESS_NAMES:
        raise ConfigError(f"unknown fitness '{fitness}' (expected f1, f2 or f3)")
    cfg = config or PlanningConfig()
    g = grid or Table3Grid()
    t0 = time.perf_counter()
    tab = tables or Table2Tables(g, cfg)
    k = FITNESS_NAMES.index(fitness)
    fixed = fixed or {}
    unknown = set(fixed) - set(VARIABLE_NAMES)
    if unknown:
        raise ConfigError(f"unknown variable(s) {sorted(unknown)}")
    free = [i for i, n in enumerate(VARIABLE_NAMES) if n not in fixed]
    base = np.array([fixed.get(n, 0) for n in VARIABLE_NAMES], dtype=np.int64)
    count = {"n": 0}

    def full_index(x: FloatArray) -> np.ndarray:
        idx = np.tile(base, (x.shape[1], 1))
        idx[:, free] = np.rint(x.T).astype(np.int64)
        return idx

    def objective(x: FloatArray) -> FloatArray:
        x = np.atleast_2d(np.asarray(x, dtype=np.float64).T).T  # (n_free, S) also for one vector
        count["n"] += x.shape[1]
        _, f, _ = fitness_from_normal(tab.evaluate(full_index(x)), cfg)
        # A large finite penalty keeps DE's population statistics finite.
        return np.where(np.isfinite(f[:, k]), f[:, k], 1e6)

    bounds = [(0, g.shape[i] - 1) for i in free]
    res = differential_evolution(objective, bounds, integrality=[True] * len(free), seed=seed,
                                 popsize=popsize, maxiter=maxiter, vectorized=True,
                                 updating="deferred", polish=False, tol=1e-8)
    idx = full_index(np.asarray(res.x, dtype=np.float64)[:, None])[0]
    return EvolutionResult(fitness, tuple(int(i) for i in idx),
                           tuple(float(v) for v in g.values(idx)), float(res.fun), count["n"],
                           int(res.nit), time.perf_counter() - t0)


def grid_index_of(grid: Table3Grid, y1_m: float, z1_m: float, alpha1_deg: float, beta1_deg: float,
                  gamma1_deg: float) -> tuple[int, ...]:
    """Grid indices of given variable values (nearest grid value)."""
    vals = (y1_m, z1_m, math.radians(alpha1_deg), math.radians(beta1_deg), math.radians(gamma1_deg))
    return tuple(int(np.argmin(np.abs(ax - v))) for ax, v in zip(grid.axes, vals, strict=True))


# The seed's best arrangements (Tables 5 and 6), for the side-by-side comparison.
SEED_TABLE6 = {
    "f1": {"y1_m": 1.0, "z1_m": 4.0, "alpha1_deg": 60.0, "beta1_deg": 70.0, "gamma1_deg": 70.0,
           "fitness_mm": 0.03},
    "f2": {"y1_m": 8.0, "z1_m": 2.5, "alpha1_deg": 20.0, "beta1_deg": 70.0, "gamma1_deg": 70.0,
           "fitness_mm": 0.57},
    "f3": {"y1_m": 8.0, "z1_m": 2.5, "alpha1_deg": 20.0, "beta1_deg": 70.0, "gamma1_deg": 70.0,
           "fitness_mm": 0.57},
}
SEED_TABLE5 = {  # separate optimisation: (y1, z1) with alpha, beta, gamma = 30, 45, 45; then angles
    "f1": {"y1_m": 1.0, "z1_m": 4.0, "fitness_yz_mm": 0.04, "alpha1_deg": 65.0, "beta1_deg": 70.0,
           "gamma1_deg": 60.0, "fitness_angles_mm": 0.03},
    "f2": {"y1_m": 3.5, "z1_m": 3.0, "fitness_yz_mm": 0.67, "alpha1_deg": 30.0, "beta1_deg": 70.0,
           "gamma1_deg": 70.0, "fitness_angles_mm": 0.63},
    "f3": {"y1_m": 3.5, "z1_m": 3.0, "fitness_yz_mm": 0.67, "alpha1_deg": 30.0, "beta1_deg": 70.0,
           "gamma1_deg": 70.0, "fitness_angles_mm": 0.64},
}


def separate_optimisation(result: GridResult, fitness: str = "f3",
                          fixed_angles_deg: tuple[float, float, float] = (30.0, 45.0, 45.0)
                          ) -> dict[str, dict[str, float]]:
    """The seed's two-step optimisation (Table 5), exhaustively: best (y1, z1) with the angles
    fixed, then the best angles with that (y1, z1)."""
    g = result.grid
    k = FITNESS_NAMES.index(fitness)
    _, _, ia, ib, ig = grid_index_of(g, 1.0, 1.0, *fixed_angles_deg)
    F = result.fitness[:, k].reshape(g.shape)
    yz = F[:, :, ia, ib, ig]
    iy, iz = np.unravel_index(int(np.argmin(yz)), yz.shape)
    ang = F[iy, iz]
    ja, jb, jg = np.unravel_index(int(np.argmin(ang)), ang.shape)
    step1 = result.row(int(np.ravel_multi_index((iy, iz, ia, ib, ig), g.shape)))
    step2 = result.row(int(np.ravel_multi_index((iy, iz, ja, jb, jg), g.shape)))
    return {"positions": step1, "angles": step2}
