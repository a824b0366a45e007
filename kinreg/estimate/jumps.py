"""Gross errors in a SLAM trajectory: jumps (discontinuities), their steps, and their removal.

A SLAM failure makes the exported trajectory jump: between two consecutive samples the pose moves
by a step that has nothing to do with the motion, and everything after it is georeferenced with
the jumped trajectory (until a later jump, possibly the one that returns it). The step is a rigid
transformation ``S`` of the object frame applied from the jump on,

    ``T_traj(t) = S . T_continuous(t)``  for every sample at or after the jump,

which is how ``benchmarks/eval_robustness.py::with_jumps`` injects it (``S`` a translation of
0.5 m in x). Several jumps compose from the left, the latest outermost:
``T_traj = S_m ... S_1 . T_true``, each ``S_k`` seen in the frame the trajectory had just before it.

Detection works on the increments between consecutive samples: the translation ``d_i`` and the
object-frame rotation vector of ``R_{i+1} R_i^T``. Each is compared with a prediction from its
neighbours and the excess is judged against an absolute floor and a robust noise scale:

1. Pass 1 (all samples, vectorised, robust): the prediction is the mean of the median increment
   over ``window_samples`` intervals before and the median over as many after (unbiased for
   constant acceleration, blind to the interval itself and to a few other outliers); the noise
   scale is the MAD of these excesses in blocks of ``scale_window_samples``. Intervals half-way to
   the thresholds are suspects.
2. Pass 2 (suspects only, precise): a quadratic through the ``fit_samples`` nearest increments on
   each side that are not suspects. It follows the step cycle and hand vibration far better than
   the medians (largest excess of a clean interval: 0.0004 deg / 0.1 mm on the simulated run,
   0.24 deg / 0.5 mm on the real GeoSLAM file, against 0.07 deg and 0.64 deg for the medians),
   and it gives the step.

Two clocks predict an increment. The sample index: exporters often write poses at a regular rate
with jittery time stamps (the real GeoSLAM file in ``../shared/realdata`` alternates 6 and 12 ms
intervals while its positions advance evenly per row), so the passes above count samples. The
time stamps: a dropout of half a second leaves a long interval whose increment is large but
matches the velocity. Its prediction is the chord velocity over ``window_samples`` intervals on
each side times the interval's length (chords average out jittery stamps); across a gap of g
missing rows its thresholds grow g-fold (translation) and g^2-fold (rotation), as the motion
hidden in the gap is not predictable. An interval is a jump only if its excess passes the
thresholds under both clocks; its step comes from the index clock, or across a gap from the clock
that explains more of the increment. A jump hidden inside a dropout is therefore only found when
it is large against the motion the dropout may hide.

The step of a jump is one interval's increment minus its prediction, so its error is that of one
increment: sub-millimetre and millidegrees on smooth SLAM output (simulated run: 0.1 mm,
0.0003 deg; real GeoSLAM file: 0.5 mm, 0.2 deg), about 1.6 times the per-sample noise on a
trajectory with white noise.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from kinreg.config import DiscontinuityConfig
from kinreg.errors import ConfigError
from kinreg.geometry import (
    FloatArray,
    Pose,
    make_quat_continuous,
    pose_sigmas,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
    quat_to_rotvec,
    rotvec_to_quat,
)
from kinreg.types import Trajectory, TrajectoryJump

logger = logging.getLogger(__name__)

# MAD -> standard deviation for a normal distribution.
_MAD_TO_SIGMA = 1.4826
# Lower bound of the noise scales so that an exactly repeated pose (standing still, values
# quantised in the file) does not give a zero scale; the absolute floors decide there anyway.
_MIN_SIGMA_M = 1e-5
_MIN_SIGMA_RAD = 1e-5
# An interval longer than this many times the longest interval around it is a gap in the time
# stamps (rows missing), where the time clock may predict the step better than the index. Jittery
# stamps reach 1.99 in the real GeoSLAM file (24 ms after 12 ms ones).
_GAP_FACTOR = 2.5


def detect_jumps(trajectory: Trajectory, config: DiscontinuityConfig | None = None) -> list[TrajectoryJump]:
    """Jumps in ``trajectory``, in time order.

    Vectorised over the samples (about 0.3 s for 160,000 rows); only the suspect intervals are
    refined one by one. Trajectories with fewer than four samples cannot be judged and give no
    jumps. Raises :class:`ConfigError` for invalid settings.
    """
    cfg = config or DiscontinuityConfig()
    _check_config(cfg)
    n = len(trajectory)
    if n < 4:
        return []
    stamps = trajectory.stamps_s
    xyz = trajectory.poses.t_xyz
    quat = trajectory.poses.quat_wxyz
    dt = np.diff(stamps)
    d = np.diff(xyz, axis=0)  # (m, 3) translation increments, m = n - 1 intervals
    q_inc = quat_multiply(quat[1:], quat_conjugate(quat[:-1]))  # object frame: R_{i+1} R_i^T
    inc = np.concatenate([d, quat_to_rotvec(q_inc)], axis=1)  # (m, 6)
    m = len(inc)
    w = max(1, min(cfg.window_samples, (m - 1) // 2))
    floors = (cfg.min_step_m, math.radians(cfg.min_step_deg))

    # Index clock, pass 1, robust: the increment against the medians around it; noise scales;
    # suspects (half-way to the thresholds) that the precise fit of pass 2 must leave out.
    e_idx = inc - _predict_median(inc, w)
    sig_idx = _local_sigma(e_idx, cfg.scale_window_samples)
    s_idx = _passes(e_idx, sig_idx, floors, cfg.k_sigma)  # (m, 2): translation, rotation
    usable = np.asarray(~(s_idx >= 0.5).any(axis=1))  # not suspect: may enter the fits
    # Time clock: the chord velocities over the w intervals on each side, times this interval's
    # length. Chords average out jittery time stamps, which would bias per-interval velocities.
    # An interval (g + 1) times as long as the longest around it (g rows missing: a gap) hides
    # motion the rates around it do not predict: its translation excess is judged against g times
    # the floor and sigma, its rotation against g^2 times (measured on the sample run with 2-100 rows
    # removed: up to 1.5 mm-0.56 m and 0.3-40 deg, 105 deg in its fastest turn). Below one missing
    # row (jittery stamps: up to 1.99 times the longest neighbour in the real file) nothing changes.
    pred_time = _predict_chords(stamps, xyz, quat, w) * dt[:, None]
    e_time = inc - pred_time
    spans = dt / _neighbour_max(dt, w)
    missing = np.maximum(1.0, spans - 1.0)
    allowance = np.column_stack([np.repeat(missing[:, None], 3, axis=1), np.repeat(missing[:, None] ** 2, 3, axis=1)])
    sig_time = _local_sigma(e_time / allowance, cfg.scale_window_samples)
    s_time = _passes(e_time / allowance, sig_time, floors, cfg.k_sigma)
    candidates = np.flatnonzero(((s_idx >= 0.5) & (s_time >= 1.0)).any(axis=1))
    if len(candidates) == 0:
        return []

    # Index clock, pass 2, precise: a local quadratic through the increments around each
    # candidate, without the suspects.
    gap = spans > _GAP_FACTOR
    jumps = []
    for i in candidates.tolist():
        pred_idx = _predict_fit(inc, i, usable, cfg.fit_samples)
        p_idx = _passes((inc[i] - pred_idx)[None], sig_idx[i][None], floors, cfg.k_sigma)[0]
        if not ((p_idx >= 1.0) & (s_time[i] >= 1.0)).any():
            continue
        # an irregular interval: a gap (the time clock explains more) or a jittered stamp (the index)
        if gap[i] and np.linalg.norm(e_time[i, :3]) < np.linalg.norm(inc[i, :3] - pred_idx[:3]):
            pred, sig, passed = pred_time[i], sig_time[i] * allowance[i], s_time[i]
        else:
            pred, sig, passed = pred_idx, sig_idx[i], p_idx
        jumps.append(_make_jump(i, stamps, xyz, q_inc[i], pred, sig, float(passed.max())))
    for j in jumps:
        logger.info("trajectory jump at %.3f s (row %d): %.3f m, %.3f deg", j.t_s, j.index, j.step_m, j.step_deg)
    return jumps


def jumps_between(jumps: Iterable[TrajectoryJump], t_from_s: float, t_to_s: float) -> list[TrajectoryJump]:
    """The jumps whose sample interval ends in ``(t_from_s, t_to_s]``, in time order: those that
    separate a pose at ``t_from_s`` from a pose at ``t_to_s`` (sample times; a time strictly inside
    a jump interval sees part of the step through interpolation)."""
    return sorted((j for j in jumps if t_from_s < j.t_s <= t_to_s), key=lambda j: j.t_s)


def step_between(jumps: Iterable[TrajectoryJump], t_from_s: float, t_to_s: float) -> Pose:
    """The total step ``B`` of the jumps between two times: ``S_last ... S_first`` (identity if
    none), with ``T_traj(t_to) = B . T_continuous(t_to)`` where the continuation is that of the
    trajectory at ``t_from``. For ``t_to_s < t_from_s`` the inverse of the step the other way.

    The trajectory's relative pose between the two times without the jumps is
    :func:`relative_pose_without_step` of the two trajectory poses and ``B``.
    """
    if t_to_s < t_from_s:
        return step_between(jumps, t_to_s, t_from_s).inverse()
    total = Pose.identity()
    for j in jumps_between(jumps, t_from_s, t_to_s):
        total = j.step.compose(total)
    return total


def relative_pose_without_step(T_obj_i: Pose, T_obj_j: Pose, step: Pose) -> Pose:
    """``T_i_j`` of two trajectory poses with the step ``step`` between them taken out:
    ``T_obj_i^-1 . step^-1 . T_obj_j`` (``step`` from :func:`step_between` of their times)."""
    return T_obj_i.inverse().compose(step.inverse()).compose(T_obj_j)


def remove_jumps(trajectory: Trajectory, jumps: Sequence[TrajectoryJump]) -> Trajectory:
    """The trajectory with every jump's step undone from its instant on.

    A jump applies from the first sample at or after its ``t_s``; each sample after jumps
    ``S_1 ... S_k`` becomes ``S_1^-1 ... S_k^-1 . T_traj`` (the pose before the first jump is
    kept, so the result continues the trajectory's start). Time stamps, user columns and
    source are kept; quaternion signs are made continuous.
    """
    if not jumps:
        return trajectory
    fixed = jump_removal(*jump_arrays(jumps), trajectory.stamps_s).compose(trajectory.poses)
    return replace(trajectory, poses=Pose(make_quat_continuous(fixed.quat_wxyz), fixed.t_xyz))


def jump_removal(jump_times_s: FloatArray | None, jump_steps: Pose | None, stamps_s: FloatArray) -> Pose:
    """Per time (n,): ``S_1^-1 ... S_k^-1`` for the jumps before it (identity before the first).
    ``jump_times_s`` (m, 2) are the jumps' sample intervals (before, at) in time order, ``jump_steps``
    (m,) their steps. A time inside an interval gets the fraction of the step that interpolating
    the trajectory across it gives."""
    t = np.asarray(stamps_s, dtype=np.float64)
    removal = _identity(len(t))
    if jump_steps is None or jump_times_s is None:
        return removal
    for k in range(len(jump_steps)):
        before, at = jump_times_s[k]
        step = jump_steps[k]
        share = np.clip((t - before) / max(at - before, 1e-12), 0.0, 1.0)
        full = share >= 1.0
        if full.any():
            removal = _replace_rows(removal, full, removal[full].compose(step.inverse()))
        inside = (share > 0.0) & ~full
        if inside.any():
            partial = Pose.exp(share[inside, None] * step.log()[None, :])
            removal = _replace_rows(removal, inside, removal[inside].compose(partial.inverse()))
    return removal


def jump_arrays(jumps: Sequence[TrajectoryJump]) -> tuple[FloatArray | None, Pose | None]:
    """The jumps in time order as (sample intervals (m, 2), steps (m,)); ``(None, None)`` without."""
    ordered = sorted(jumps, key=lambda j: j.t_s)
    if not ordered:
        return None, None
    return (np.array([(j.t_before_s, j.t_s) for j in ordered], dtype=np.float64),
            Pose.stack([j.step for j in ordered]))


# --------------------------------------------------------------------------- internals


def _identity(n: int) -> Pose:
    return Pose(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), np.zeros((n, 3)))


def _replace_rows(poses: Pose, rows: np.ndarray, new: Pose) -> Pose:
    quat, t_xyz = poses.quat_wxyz.copy(), poses.t_xyz.copy()
    quat[rows], t_xyz[rows] = new.quat_wxyz, new.t_xyz
    return Pose(quat, t_xyz)


def _check_config(cfg: DiscontinuityConfig) -> None:
    if cfg.window_samples < 1 or cfg.fit_samples < 2 or cfg.scale_window_samples < 2:
        raise ConfigError("[discontinuity] window_samples must be >= 1, fit_samples and scale_window_samples >= 2")
    if not (cfg.k_sigma > 0 and cfg.min_step_m > 0 and cfg.min_step_deg > 0):
        raise ConfigError("[discontinuity] k_sigma, min_step_m and min_step_deg must be positive")


def _predict_median(inc: FloatArray, w: int) -> FloatArray:
    """Per interval, the mean of the median of the ``w`` increments before it and of the ``w``
    after it (one side only at the ends). ``inc`` (m, c) with m >= 2 w + 1."""
    med = np.median(sliding_window_view(inc, w, axis=0), axis=-1)  # med[k] = median(inc[k:k+w])
    m = len(inc)
    i = np.arange(m)
    has_left = i >= w
    has_right = i + w <= m - 1
    left = med[np.clip(i - w, 0, len(med) - 1)]
    right = med[np.clip(i + 1, 0, len(med) - 1)]
    both = (has_left & has_right)[:, None]
    return np.where(both, 0.5 * (left + right), np.where(has_left[:, None], left, right))


def _predict_chords(stamps: FloatArray, xyz: FloatArray, quat: FloatArray, w: int) -> FloatArray:
    """Per interval (samples i -> i + 1), the mean of the chord velocities (translation, then
    object-frame rotation vector per second) from sample i - w to i and from i + 1 to i + 1 + w
    (one side only at the ends). Shape (n - 1, 6); needs n >= w + 2."""
    n = len(stamps)

    def chord(a: np.ndarray, b: np.ndarray) -> FloatArray:
        span = (stamps[b] - stamps[a])[:, None]
        rot = quat_to_rotvec(quat_multiply(quat[b], quat_conjugate(quat[a])))
        return np.concatenate([xyz[b] - xyz[a], rot], axis=1) / span

    i = np.arange(n - 1)
    left = chord(np.maximum(i - w, 0), np.maximum(i, w))  # valid where i >= w
    right = chord(np.minimum(i + 1, n - 1 - w), np.minimum(i + 1 + w, n - 1))  # valid where i + 1 + w <= n - 1
    has_left = (i >= w)[:, None]
    has_right = (i + 1 + w <= n - 1)[:, None]
    return np.where(has_left & has_right, 0.5 * (left + right), np.where(has_left, left, right))


def _predict_fit(inc: FloatArray, i: int, usable: np.ndarray, per_side: int) -> FloatArray:
    """Increment ``inc[i]`` (translation, rotation vector) predicted by a least-squares polynomial
    in the sample index through the nearest ``per_side`` usable intervals on each side of ``i``
    (quadratic with both sides, linear with one side only; the nearest increment if fewer than
    two are usable).

    The increments after a jump are seen in the jumped frame (``R_S d``, ``R_S r``): a first
    prediction gives ``R_S``, and if it is more than a few millidegrees the increments after
    ``i`` are rotated back and the fit repeated."""
    lo, hi = max(0, i - 4 * per_side), min(len(inc), i + 4 * per_side + 1)
    left = np.flatnonzero(usable[lo:i])[::-1][:per_side] + lo
    right = np.flatnonzero(usable[i + 1:hi])[:per_side] + i + 1
    pick = np.concatenate([left[::-1], right])
    if len(pick) < 2:
        return inc[pick[0]].copy() if len(pick) else inc[i].copy()
    degree = 2 if (len(left) and len(right) and len(pick) >= 4) else 1
    x = (pick - i) / float(np.abs(pick - i).max())
    A = np.vander(x, degree + 1, increasing=True)
    values = inc[pick]
    pred: FloatArray = np.linalg.lstsq(A, values, rcond=None)[0][0]
    q_s = quat_multiply(rotvec_to_quat(inc[i, 3:]), quat_conjugate(rotvec_to_quat(pred[3:])))
    if len(right) and np.linalg.norm(quat_to_rotvec(q_s)) > 1e-4:
        after = pick > i
        Rt = quat_to_matrix(q_s).T
        values = values.copy()
        values[after, :3] = values[after, :3] @ Rt.T
        values[after, 3:] = values[after, 3:] @ Rt.T
        pred = np.linalg.lstsq(A, values, rcond=None)[0][0]
    return pred


def _passes(e: FloatArray, sigma: FloatArray, floors: tuple[float, float], k_sigma: float) -> FloatArray:
    """Per interval and channel (translation, rotation), the smaller of excess / floor and
    (excess in sigmas) / k_sigma: >= 1 where the excess passes both thresholds. ``e``, ``sigma``
    (m, 6)."""
    out = np.empty((len(e), 2))
    for c, (sl, floor) in enumerate(zip((slice(0, 3), slice(3, 6)), floors, strict=True)):
        size = np.linalg.norm(e[:, sl], axis=1)
        z = np.linalg.norm(e[:, sl] / sigma[:, sl], axis=1)
        out[:, c] = np.minimum(size / floor, z / k_sigma)
    return out


def _local_sigma(e: FloatArray, block: int) -> FloatArray:
    """Robust per-axis noise scale (m, 6) of the excesses ``e`` (translation, rotation): MAD over
    blocks of about ``block`` samples, the largest of a block and its two neighbours."""
    m = len(e)
    nb = max(1, math.ceil(m / block))
    size = math.ceil(m / nb)
    padded = np.pad(e, ((0, nb * size - m), (0, 0)), mode="symmetric") if nb * size > m else e
    blocks = padded.reshape(nb, size, e.shape[1])
    centre = np.median(blocks, axis=1, keepdims=True)
    sigma = _MAD_TO_SIGMA * np.median(np.abs(blocks - centre), axis=1)  # (nb, c)
    ext = np.concatenate([sigma[:1], sigma, sigma[-1:]])
    sigma = np.maximum(np.maximum(ext[:-2], ext[1:-1]), ext[2:])
    floor = pose_sigmas(_MIN_SIGMA_M, _MIN_SIGMA_RAD)
    return np.maximum(np.repeat(sigma, size, axis=0)[:m], floor)


def _neighbour_max(dt: FloatArray, w: int) -> FloatArray:
    """Per interval, the longest of the ``w`` intervals on each side (itself excluded). Against the
    longest rather than the typical one, jittery stamps (6, 12, 18 ms in turn) are no gap."""
    padded = np.pad(dt, w, mode="edge")
    win = sliding_window_view(padded, 2 * w + 1)  # win[i] centred on interval i
    return np.maximum(win[:, :w].max(axis=1), win[:, w + 1:].max(axis=1))


def _make_jump(i: int, stamps: FloatArray, xyz: FloatArray, q_obs: FloatArray, pred: FloatArray,
               sigma: FloatArray, significance: float) -> TrajectoryJump:
    """The step of interval i (samples i -> i + 1) from its observed and predicted increments
    (``pred`` = translation, rotation vector): ``R_S = R_inc_obs R_inc_pred^T`` and
    ``t_S = d_obs - R_S d_pred`` (the displacement at sample i)."""
    q_s = quat_normalize(quat_multiply(q_obs, quat_conjugate(rotvec_to_quat(pred[3:]))))
    rotvec = quat_to_rotvec(q_s)
    translation = (xyz[i + 1] - xyz[i]) - quat_to_matrix(q_s) @ pred[:3]
    return TrajectoryJump(
        index=i + 1,
        t_s=float(stamps[i + 1]),
        t_before_s=float(stamps[i]),
        translation_m=translation,
        rotvec_rad=rotvec,
        pivot_xyz=xyz[i].copy(),
        translation_sigmas=float(np.linalg.norm(translation / sigma[:3])),
        rotation_sigmas=float(np.linalg.norm(rotvec / sigma[3:])),
        significance=significance,
        sigma_translation_m=float(sigma[:3].max()),
        sigma_rotation_rad=float(sigma[3:].max()),
    )
