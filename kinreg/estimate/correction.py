"""Drift correction: from adjusted station poses to a correction of every pose and point.

At station k the correction ``C_k = T_k_adjusted . T_k_initial^-1`` maps the initial
(drifted) object frame into the adjusted one. It is parametrised as a rotation ``rotvec_k``
about the station's initial position ``p_k`` plus a shift ``delta_k = p_k_adjusted - p_k``::

    x' = R(rotvec) (x - p(t)) + p(t) + delta

so that the parameters stay small (no lever arm to a far-away origin, e.g. UTM) and can be
interpolated. Between station times all three are interpolated with a cubic spline (C2-smooth);
before the first and after the last station the end values are held. The pivot ``p(t)`` is the
spline through the stations' positions, not the trajectory's own position: then a correction
that is one rigid transform for all stations (e.g. what is left of a rough initial transform) is
reproduced exactly between them, and a slowly turning one carries no lever arm to the sway and
the turns of the path between stations (a tenth of a degree over a metre is 2 mm). That is so
where the trajectory's attitude error is integrated into its positions (SLAM). Where the positions
are measured apart from the attitude (GNSS/INS, a tracker: the drift's ``coupling`` 1), the
attitude error turns each point about where the sensor was when it measured it: the pivot is then
the trajectory's own position, its sway and its turns between stations included (in the share
``coupling`` between the two).

Jumps of the trajectory (:mod:`kinreg.estimate.jumps`) are taken out first: a point or pose after
jumps ``S_1 ... S_k`` is mapped by ``S_1^-1 ... S_k^-1`` (a point inside a jump's sample interval,
which the SLAM output interpolated across the step, by the matching fraction of it), and the
smooth correction then works on the stations' poses without the jumps.

Each point's position sigma (:meth:`DriftCorrection.sigma_at_points`) is that of the adjusted
stations' positions, interpolated in time the same way (on the grid of the correction, held beyond
the first and last station), but with a shape-preserving cubic (PCHIP) instead of the natural
spline: a sigma never swings below zero next to the datum station, where it is zero.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline, PchipInterpolator

from kinreg.estimate.jumps import jump_arrays, jump_removal
from kinreg.geometry import (
    FloatArray,
    Pose,
    interpolate_positions,
    quat_multiply,
    quat_normalize,
    quat_to_rotvec,
    rotvec_to_quat,
)
from kinreg.types import Trajectory, TrajectoryJump

# Grid of the correction for points [s] (:meth:`DriftCorrection.apply_to_points`).
POINT_GRID_S = 0.01
# Points per block of the interpolation (its temporaries, 31 node values a point, stay in the cache).
_POINT_BLOCK = 1 << 14


def _interval_runs(grid: FloatArray, t: FloatArray) -> NDArray[np.int64] | None:
    """For time-sorted ``t`` (n,), where each interval of ``grid`` (its interpolation's, clipped to
    the first and last) starts: ``runs[j]`` is the first point in interval ``j``, ``runs[-1] = n``,
    so that the points ``runs[j]:runs[j + 1]`` are those ``searchsorted(grid, t, "right") - 1``
    (clipped) puts there. ``None`` for unsorted times (a LAS file is usually in time order; then
    a block's node values are repeats of a few intervals' instead of a gather per point)."""
    if len(t) > 1 and not bool(np.all(t[1:] >= t[:-1])):
        return None
    runs = np.empty(len(grid), dtype=np.int64)
    runs[0], runs[-1] = 0, len(t)
    runs[1:-1] = np.searchsorted(t, grid[1:-1], side="left")  # the points at or after each inner node
    return runs


@dataclass(frozen=True, eq=False)
class DriftCorrection:
    """Interpolable correction: station times (k,), rotation vectors (k, 3), shifts (k, 3) [m],
    and the pivots (k, 3) [m], the stations' initial positions (``None``: the trajectory's
    positions at the station times, which is what they are for quasi-static stations)."""

    stamps_s: FloatArray
    rotvec: FloatArray
    delta_m: FloatArray
    trajectory: Trajectory
    pivot_xyz: FloatArray | None = None
    jump_times_s: FloatArray | None = None  # (m, 2): each jump's sample interval (before, at), in time order
    jump_steps: Pose | None = None  # (m,): the steps S (T_traj = S . T_continuous from the jump on)
    # How far the rotation turns about the trajectory's own position rather than the spline through
    # the stations' (kinreg.estimate.drift.DriftRates.coupling): 1 where the attitude error turns the
    # points about the sensor wherever it is (GNSS/INS, a tracker), 0 where it is one rigid motion
    # between stations (SLAM, a rigid drift of the world).
    coupling: float = 0.0
    # (k,) [m]: each station's 3D position sigma after the adjustment (root of the trace of its
    # position covariance; 0 for a fixed station), for the points' sigmas; None: not known.
    sigma_3d_m: FloatArray | None = None

    @classmethod
    def from_stations(cls, stamps_s: FloatArray, initial: Pose, adjusted: Pose, trajectory: Trajectory,
                      jumps: Sequence[TrajectoryJump] = (), coupling: float = 0.0,
                      sigma_3d_m: FloatArray | None = None) -> DriftCorrection:
        """From the initial and adjusted poses of the time-stamped stations (sorted by time).
        With ``jumps``, ``initial`` are the stations' poses without them (:meth:`without_jumps`).
        ``coupling``, ``sigma_3d_m`` (per station, in the order of ``stamps_s``): see the fields."""
        order = np.argsort(stamps_s)
        q_corr = quat_multiply(adjusted.quat_wxyz[order], initial.inverse().quat_wxyz[order])
        sigma = None if sigma_3d_m is None else np.asarray(sigma_3d_m, dtype=np.float64)[order]
        return cls(np.asarray(stamps_s, dtype=np.float64)[order], quat_to_rotvec(q_corr),
                   adjusted.t_xyz[order] - initial.t_xyz[order], trajectory, initial.t_xyz[order],
                   *jump_arrays(jumps), coupling=float(coupling), sigma_3d_m=sigma)

    def without_jumps(self, stamps_s: FloatArray) -> Pose:
        """Per time (n,): the map that takes the jumps out (see :func:`jump_removal`)."""
        return jump_removal(self.jump_times_s, self.jump_steps, stamps_s)

    def at(self, query_s: FloatArray, own_xyz: FloatArray | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Rotation vectors, shifts and pivots (each (n, 3)) at the times ``query_s`` (n,).
        ``own_xyz`` (n, 3): where the sensor was, instead of the trajectory's positions at
        ``query_s`` (for a point that stands for many, seen at different times: the mean of theirs)."""
        t = np.clip(query_s, self.stamps_s[0], self.stamps_s[-1])
        if len(self.stamps_s) == 1:
            pivots = self._pivots

            def held(v: FloatArray) -> FloatArray:
                return np.broadcast_to(v[0], (len(t), 3))

            return held(self.rotvec), held(self.delta_m), held(pivots)
        spline, origin = self._spline
        values = spline(t)
        pivot = values[:, 6:] + origin
        if self.coupling > 0.0:
            own = self._own_positions(np.asarray(query_s, dtype=np.float64)) if own_xyz is None else own_xyz
            pivot += self.coupling * (own - pivot)
        return values[:, :3], values[:, 3:6], pivot

    @functools.cached_property
    def _pivots(self) -> FloatArray:
        if self.pivot_xyz is not None:
            return self.pivot_xyz
        return interpolate_positions(self.trajectory.stamps_s, self.trajectory.poses.t_xyz, self.stamps_s)

    @functools.cached_property
    def _spline(self) -> tuple[CubicSpline, FloatArray]:
        """The spline of :meth:`at` and its origin, made once (the deskew asks for a few times at a
        time, once per plane)."""
        # Pivots relative to the first one: the spline then works on metres, not on UTM values.
        origin = self._pivots[0]
        return CubicSpline(self.stamps_s, np.hstack([self.rotvec, self.delta_m, self._pivots - origin]),
                           bc_type="natural"), origin

    def _own_positions(self, query_s: FloatArray) -> FloatArray:
        """The trajectory's positions at ``query_s``, without its jumps (those of the stations)."""
        xyz = interpolate_positions(self.trajectory.stamps_s, self.trajectory.poses.t_xyz, query_s)
        if self.jump_steps is None:
            return xyz
        return self.without_jumps(query_s).apply(xyz)

    def apply_to_points(self, xyz: FloatArray, stamps_s: FloatArray, out: FloatArray | None = None) -> FloatArray:
        """Corrected object-frame points (n, 3) for points measured at times ``stamps_s`` (n,).

        ``x' = x + (R - I)(x - p) + delta`` with ``R - I``, ``p`` and ``delta`` evaluated on a grid of
        :data:`POINT_GRID_S` and interpolated linearly to each point's time: the correction changes
        over seconds, so this is within 0.01 mm (a few micrometres) of evaluating it at every point (the pivot's error
        enters multiplied by the correction's small angle), at a fraction of the cost (no spline
        and no rotation matrix per point).

        The result is in column-major (Fortran) order, its three columns contiguous: that is how it
        is computed, and what the callers read (a column per coordinate of a LAS record). ``xyz``
        is read by columns too; one in that order (``rows.T`` of coordinate rows (3, n)) is read
        without gathering strided values. ``out`` (optional, coordinate rows (3, n), each row
        contiguous) receives the result, which is then ``out.T``: a caller correcting chunk after
        chunk keeps one buffer instead of a fresh array per chunk, whose pages the kernel would
        map and zero each time."""
        if self.jump_steps is not None:
            xyz = self.without_jumps(stamps_s).apply(xyz)
        t = np.asarray(stamps_s, dtype=np.float64)
        if len(t) == 0:
            return np.array(xyz, dtype=np.float64, copy=True)
        lo, hi = float(t.min()), float(t.max())
        nodes = lo + POINT_GRID_S * np.arange(int(np.ceil((hi - lo) / POINT_GRID_S)) + 2)
        # the first and last station are nodes too: the correction is held constant beyond them
        grid: FloatArray = np.union1d(nodes, self.stamps_s[[0, -1]]).astype(np.float64)
        rotvec, delta, pivot = self.at(grid)
        A = Pose(rotvec_to_quat(rotvec), np.zeros_like(delta)).rotation_matrix - np.eye(3)
        origin = pivot[0]  # interpolated relative to it: UTM-sized values keep their precision
        # np.interp's formula (value at the node below plus slope times the time since it), for
        # the 15 values at once and in blocks that stay in the cache: no per-column search, no
        # (n, 3, 3) matrices. Everything in rows (a row per value, a column per point): each
        # product below runs over contiguous memory (the same operations, in the same order, as
        # on (n, 15) arrays: the same bits).
        table = np.hstack([A.reshape(-1, 9), delta, pivot - origin])
        slope = np.diff(table, axis=0) / np.diff(grid)[:, None]
        # (31, len(grid) - 1): per interval the values at the node below, the slopes, the node's time
        nodes_rows = np.ascontiguousarray(np.hstack([table[:-1], slope, grid[:-1, None]]).T)
        x_rows = [xyz[:, i] for i in range(3)]
        if out is None:
            out = np.empty((3, len(t)))
        elif out.shape != (3, len(t)) or out.strides[1] != out.itemsize:
            raise ValueError(f"out must be coordinate rows (3, {len(t)}), each contiguous")
        runs = _interval_runs(grid, t)
        for a in range(0, len(t), _POINT_BLOCK):
            tb = t[a:a + _POINT_BLOCK]
            x = [c[a:a + _POINT_BLOCK] for c in x_rows]
            if runs is not None:  # time-sorted points: each interval's values repeated over its run
                first, last = np.searchsorted(runs, [a, a + len(tb)], side="right") - 1
                edges = np.clip(runs[first:last + 2], a, a + len(tb))
                g = np.repeat(nodes_rows[:, first:first + len(edges) - 1], np.diff(edges), axis=1)
            else:
                k = np.searchsorted(grid, tb, side="right")
                k -= 1
                np.clip(k, 0, len(grid) - 2, out=k)
                g = nodes_rows.take(k, axis=1)
            dt = tb - g[30]
            v = g[15:30]
            v *= dt
            v += g[:15]
            d = [x[i] - (v[12 + i] + origin[i]) for i in range(3)]
            o = out[:, a:a + len(tb)]
            for i in range(3):
                row = o[i]
                np.multiply(v[3 * i], d[0], out=row)
                row += v[3 * i + 1] * d[1]
                row += v[3 * i + 2] * d[2]
                row += x[i]
                row += v[9 + i]
        return out.T

    def sigma_at_points(self, stamps_s: FloatArray, out: FloatArray | None = None) -> FloatArray:
        """The 3D position sigma [m] (n,) of points measured at times ``stamps_s`` (n,): the
        stations' :attr:`sigma_3d_m` through a shape-preserving cubic in time (PCHIP), held beyond
        the first and last station, evaluated on the grid of :meth:`apply_to_points` and
        interpolated linearly to each point's time. ``out`` (optional, (n,)) receives it. Raises
        ``ValueError`` without station sigmas."""
        if self.sigma_3d_m is None:
            raise ValueError("the correction has no station sigmas")
        t = np.asarray(stamps_s, dtype=np.float64)
        if out is None:
            out = np.empty(len(t))
        if len(t) == 0:
            return out
        if len(self.stamps_s) == 1:
            out[:] = self.sigma_3d_m[0]
            return out
        lo = max(float(t.min()), float(self.stamps_s[0]))
        hi = min(float(t.max()), float(self.stamps_s[-1]))
        if hi <= lo:  # every point beyond one end: held
            out[:] = self._sigma_spline(np.clip(lo, self.stamps_s[0], self.stamps_s[-1]))
            return out
        grid = lo + POINT_GRID_S * np.arange(int(np.ceil((hi - lo) / POINT_GRID_S)) + 1)
        grid[-1] = hi
        # np.interp holds the end values beyond the grid: the stations' beyond the first and last
        out[:] = np.interp(t, grid, self._sigma_spline(grid))
        return out

    @functools.cached_property
    def _sigma_spline(self) -> PchipInterpolator:
        return PchipInterpolator(self.stamps_s, np.maximum(np.asarray(self.sigma_3d_m), 0.0))

    def apply_to_trajectory(self, trajectory: Trajectory) -> Trajectory:
        """The trajectory with every pose corrected (same rows, same times)."""
        if self.jump_steps is not None:
            unjumped = self.without_jumps(trajectory.stamps_s).compose(trajectory.poses)
            trajectory = Trajectory(trajectory.stamps_s, unjumped, trajectory.source, trajectory.extra,
                                    trajectory.extra_names)
        rotvec, delta, pivot = self.at(trajectory.stamps_s)
        q_corr = rotvec_to_quat(rotvec)
        q = quat_normalize(quat_multiply(q_corr, trajectory.poses.quat_wxyz))
        R = Pose(q_corr, np.zeros_like(delta)).rotation_matrix
        xyz = np.einsum("nij,nj->ni", R, trajectory.poses.t_xyz - pivot) + pivot + delta
        return Trajectory(trajectory.stamps_s, Pose(q, xyz), trajectory.source, trajectory.extra,
                          trajectory.extra_names)

    def magnitude(self) -> tuple[FloatArray, FloatArray]:
        """Per station: shift [m] and rotation [rad] of the correction."""
        return np.linalg.norm(self.delta_m, axis=1), np.linalg.norm(self.rotvec, axis=1)


