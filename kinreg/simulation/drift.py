"""The simulated trajectory error: drift of the exported trajectory against the true one."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from kinreg.geometry import (
    FloatArray,
    Pose,
    make_quat_continuous,
    rotvec_to_quat,
)
from kinreg.types import Trajectory

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriftConfig:
    """SLAM drift ``D(t)``: an integrated random walk of the drift rate (sigma grows ~ t^1.5).

    The realisation is scaled so that at 300 s after the start the position drift has magnitude
    ``drift_pos_m_at_300s`` and the rotation ``drift_rot_deg_at_300s`` exactly (whatever the
    run's duration). The rotation acts about the start position (where SLAM initialises), the
    tilt components (roll, pitch: gravity-aided in real units) weighted by ``tilt_weight``
    relative to yaw.
    """

    drift_pos_m_at_300s: float = 0.04
    drift_rot_deg_at_300s: float = 0.25
    tilt_weight: float = 0.4


def make_drift(stamps_s: FloatArray, pivot_xyz: FloatArray, config: DriftConfig,
               rng: np.random.Generator) -> Pose:
    """Drift poses ``D(t)`` (object frame) at ``stamps_s`` (equally spaced, shape (M,)).

    Each of the six components (translation xyz, rotation vector xyz) is an integrated random
    walk of its rate, so it is smooth (C1) and its sigma grows like t^1.5; the rotation acts about
    ``pivot_xyz``: ``x -> R_d (x - pivot) + pivot + tau``. ``D(stamps_s[0])`` is the identity.
    """
    dt = float(stamps_s[1] - stamps_s[0])
    t_rel = stamps_s - stamps_s[0]
    n_gen = math.ceil(max(float(t_rel[-1]), 300.0) / dt) + 2
    w = rng.standard_normal((n_gen, 6))
    w[0] = 0.0
    rate = np.cumsum(w, axis=0) * math.sqrt(dt)
    x = np.concatenate([np.zeros((1, 6)), np.cumsum(rate[:-1], axis=0) * dt])
    x[:, 3:5] *= config.tilt_weight
    t_gen = np.arange(n_gen) * dt
    at300 = np.array([np.interp(300.0, t_gen, x[:, i]) for i in range(6)])
    n_pos, n_rot = np.linalg.norm(at300[:3]), np.linalg.norm(at300[3:])
    x[:, :3] *= config.drift_pos_m_at_300s / n_pos if n_pos > 0 else 0.0
    x[:, 3:] *= math.radians(config.drift_rot_deg_at_300s) / n_rot if n_rot > 0 else 0.0
    xs = np.stack([np.interp(t_rel, t_gen, x[:, i]) for i in range(6)], axis=1)
    q = rotvec_to_quat(xs[:, 3:])
    R = Pose(q, np.zeros((len(q), 3))).rotation_matrix
    piv = np.asarray(pivot_xyz, dtype=np.float64)
    t = piv - np.einsum("nij,j->ni", R, piv) + xs[:, :3]
    return Pose(q, t)


def apply_drift(truth: Trajectory, drift: Pose) -> Trajectory:
    """The exported trajectory ``T_slam = D * T_true`` row by row."""
    poses = drift.compose(truth.poses)
    return Trajectory(truth.stamps_s.copy(), Pose(make_quat_continuous(poses.quat_wxyz), poses.t_xyz),
                      source="simulated SLAM (drifted)")


def _offset_trajectory(traj: Trajectory, origin: FloatArray) -> Trajectory:
    return Trajectory(traj.stamps_s, Pose(traj.poses.quat_wxyz, traj.poses.t_xyz + origin), traj.source)
