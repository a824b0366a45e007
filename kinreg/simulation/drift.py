"""The simulated trajectory error: drift of the exported trajectory against the true one."""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import numpy as np

from kinreg.geometry import (
    FloatArray,
    Pose,
    make_quat_continuous,
    quat_multiply,
    rotvec_to_quat,
)
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)


class DriftModel(enum.Enum):
    """How the trajectory's attitude error couples into its position (METHOD.md section 1)."""

    WORLD = "world"  # one rigid transform of the whole world about the start: T_slam = D(t) T_true
    SLAM = "slam"  # dead reckoning: x_slam = x_true + n(t) + int (D(t) - I) v dt, R_slam = D(t) R_true
    GNSS_INS = "gnss-ins"  # position measured apart from attitude: x_slam = x_true + n(t), R_slam = D(t) R_true


@dataclass(frozen=True)
class DriftConfig:
    """Trajectory drift: an integrated random walk of the drift rate (sigma grows ~ t^1.5).

    The realisation is scaled so that ``at_s`` seconds after the start (300 s unless set; the
    field names keep the historical 300) the position drift ``n`` has magnitude
    ``drift_pos_m_at_300s`` and the attitude error ``D`` the angle ``drift_rot_deg_at_300s``
    exactly (whatever the run's duration). The tilt components (roll, pitch: gravity-aided in
    real units) are weighted by ``tilt_weight`` relative to yaw. ``model`` says how the attitude
    error enters the positions (:class:`DriftModel`).
    """

    drift_pos_m_at_300s: float = 0.04
    drift_rot_deg_at_300s: float = 0.25
    tilt_weight: float = 0.4
    model: DriftModel = DriftModel.WORLD
    at_s: float = 300.0


def make_drift(stamps_s: FloatArray, pivot_xyz: FloatArray, config: DriftConfig,
               rng: np.random.Generator) -> Pose:
    """Drift poses ``D(t)`` (object frame) at ``stamps_s`` (equally spaced, shape (M,)).

    Each of the six components (translation xyz, rotation vector xyz) is an integrated random
    walk of its rate, so it is smooth (C1) and its sigma grows like t^1.5; the rotation acts about
    ``pivot_xyz``: ``x -> R_d (x - pivot) + pivot + tau``. ``D(stamps_s[0])`` is the identity.
    """
    dt = float(stamps_s[1] - stamps_s[0])
    t_rel = stamps_s - stamps_s[0]
    n_gen = math.ceil(max(float(t_rel[-1]), config.at_s) / dt) + 2
    w = rng.standard_normal((n_gen, 6))
    w[0] = 0.0
    rate = np.cumsum(w, axis=0) * math.sqrt(dt)
    x = np.concatenate([np.zeros((1, 6)), np.cumsum(rate[:-1], axis=0) * dt])
    x[:, 3:5] *= config.tilt_weight
    t_gen = np.arange(n_gen) * dt
    at300 = np.array([np.interp(config.at_s, t_gen, x[:, i]) for i in range(6)])
    n_pos, n_rot = np.linalg.norm(at300[:3]), np.linalg.norm(at300[3:])
    x[:, :3] *= config.drift_pos_m_at_300s / n_pos if n_pos > 0 else 0.0
    x[:, 3:] *= math.radians(config.drift_rot_deg_at_300s) / n_rot if n_rot > 0 else 0.0
    xs = np.stack([np.interp(t_rel, t_gen, x[:, i]) for i in range(6)], axis=1)
    q = rotvec_to_quat(xs[:, 3:])
    R = Pose(q, np.zeros((len(q), 3))).rotation_matrix
    piv = np.asarray(pivot_xyz, dtype=np.float64)
    t = piv - np.einsum("nij,j->ni", R, piv) + xs[:, :3]
    return Pose(q, t)


def drifted_trajectory(truth: Trajectory, config: DriftConfig, rng: np.random.Generator) -> tuple[Trajectory, Pose]:
    """The exported (drifted) trajectory of ``truth`` under ``config.model``, and the drift per
    row ``D_k = T_slam_k T_true_k^-1`` (for the world model the rigid drift itself)."""
    drift = make_drift(truth.stamps_s, truth.poses.t_xyz[0], config, rng)
    if config.model is DriftModel.WORLD:
        return apply_drift(truth, drift), drift
    R_err = Pose(drift.quat_wxyz, np.zeros_like(drift.t_xyz))
    # The position error n(t): the drift's translation less its rotation about the start.
    pivot = np.broadcast_to(truth.poses.t_xyz[0], drift.t_xyz.shape)
    n = drift.t_xyz - (pivot - R_err.apply(pivot))
    xyz = truth.poses.t_xyz + n
    if config.model is DriftModel.SLAM:
        step = np.diff(truth.poses.t_xyz, axis=0)
        turned = np.einsum("nij,nj->ni", R_err.rotation_matrix[:-1], step) - step  # (D - I) v dt, per row
        xyz = xyz + np.concatenate([np.zeros((1, 3)), np.cumsum(turned, axis=0)])
    q = make_quat_continuous(quat_multiply(drift.quat_wxyz, truth.poses.quat_wxyz))
    slam = Trajectory(truth.stamps_s.copy(), Pose(q, xyz), source=f"simulated {config.model.value} (drifted)")
    return slam, slam.poses.compose(truth.poses.inverse())


def apply_drift(truth: Trajectory, drift: Pose) -> Trajectory:
    """The exported trajectory ``T_slam = D * T_true`` row by row."""
    poses = drift.compose(truth.poses)
    return Trajectory(truth.stamps_s.copy(), Pose(make_quat_continuous(poses.quat_wxyz), poses.t_xyz),
                      source="simulated SLAM (drifted)")


def _offset_trajectory(traj: Trajectory, origin: FloatArray) -> Trajectory:
    return Trajectory(traj.stamps_s, Pose(traj.poses.quat_wxyz, traj.poses.t_xyz + origin), traj.source)
