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
the turns of the path between stations (a tenth of a degree over a metre is 2 mm).

Jumps of the trajectory (:mod:`kinreg.discontinuity`) are taken out first: a point or pose after
jumps ``S_1 ... S_k`` is mapped by ``S_1^-1 ... S_k^-1`` (a point inside a jump's sample interval,
which the SLAM output interpolated across the step, by the matching fraction of it), and the
smooth correction then works on the stations' poses without the jumps.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from kinreg.discontinuity import TrajectoryJump, jump_arrays, jump_removal
from kinreg.errors import CloudError
from kinreg.geometry import (
    FloatArray,
    Pose,
    interpolate_positions,
    quat_multiply,
    quat_normalize,
    quat_to_rotvec,
    rotvec_to_quat,
)
from kinreg.io.atomic import atomic_path
from kinreg.progress import NullProgress, Progress
from kinreg.types import Trajectory


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

    @classmethod
    def from_stations(cls, stamps_s: FloatArray, initial: Pose, adjusted: Pose, trajectory: Trajectory,
                      jumps: Sequence[TrajectoryJump] = ()) -> DriftCorrection:
        """From the initial and adjusted poses of the time-stamped stations (sorted by time).
        With ``jumps``, ``initial`` are the stations' poses without them (:meth:`without_jumps`)."""
        order = np.argsort(stamps_s)
        q_corr = quat_multiply(adjusted.quat_wxyz[order], initial.inverse().quat_wxyz[order])
        return cls(np.asarray(stamps_s, dtype=np.float64)[order], quat_to_rotvec(q_corr),
                   adjusted.t_xyz[order] - initial.t_xyz[order], trajectory, initial.t_xyz[order],
                   *jump_arrays(jumps))

    def without_jumps(self, stamps_s: FloatArray) -> Pose:
        """Per time (n,): the map that takes the jumps out (see :func:`jump_removal`)."""
        return jump_removal(self.jump_times_s, self.jump_steps, stamps_s)

    def _at(self, query_s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Rotation vectors, shifts and pivots (each (n, 3)) at the times ``query_s`` (n,)."""
        pivots = self.pivot_xyz
        if pivots is None:
            pivots = interpolate_positions(self.trajectory.stamps_s, self.trajectory.poses.t_xyz, self.stamps_s)
        t = np.clip(query_s, self.stamps_s[0], self.stamps_s[-1])
        if len(self.stamps_s) == 1:
            def held(v: FloatArray) -> FloatArray:
                return np.broadcast_to(v[0], (len(t), 3))

            return held(self.rotvec), held(self.delta_m), held(pivots)
        # Pivots relative to the first one: the spline then works on metres, not on UTM values.
        origin = pivots[0]
        spline = CubicSpline(self.stamps_s, np.hstack([self.rotvec, self.delta_m, pivots - origin]),
                             bc_type="natural")
        values = spline(t)
        return values[:, :3], values[:, 3:6], values[:, 6:] + origin

    def apply_to_points(self, xyz: FloatArray, stamps_s: FloatArray) -> FloatArray:
        """Corrected object-frame points (n, 3) for points measured at times ``stamps_s`` (n,)."""
        if self.jump_steps is not None:
            xyz = self.without_jumps(stamps_s).apply(xyz)
        rotvec, delta, pivot = self._at(stamps_s)
        R = Pose(rotvec_to_quat(rotvec), np.zeros_like(delta)).rotation_matrix
        return np.einsum("nij,nj->ni", R, xyz - pivot) + pivot + delta

    def apply_to_trajectory(self, trajectory: Trajectory) -> Trajectory:
        """The trajectory with every pose corrected (same rows, same times)."""
        if self.jump_steps is not None:
            unjumped = self.without_jumps(trajectory.stamps_s).compose(trajectory.poses)
            trajectory = Trajectory(trajectory.stamps_s, unjumped, trajectory.source, trajectory.extra,
                                    trajectory.extra_names)
        rotvec, delta, pivot = self._at(trajectory.stamps_s)
        q_corr = rotvec_to_quat(rotvec)
        q = quat_normalize(quat_multiply(q_corr, trajectory.poses.quat_wxyz))
        R = Pose(q_corr, np.zeros_like(delta)).rotation_matrix
        xyz = np.einsum("nij,nj->ni", R, trajectory.poses.t_xyz - pivot) + pivot + delta
        return Trajectory(trajectory.stamps_s, Pose(q, xyz), trajectory.source, trajectory.extra,
                          trajectory.extra_names)

    def magnitude(self) -> tuple[FloatArray, FloatArray]:
        """Per station: shift [m] and rotation [rad] of the correction."""
        return np.linalg.norm(self.delta_m, axis=1), np.linalg.norm(self.rotvec, axis=1)


def write_corrected_las(
    source: str | Path,
    target: str | Path,
    correction: DriftCorrection,
    chunk_points: int = 2_000_000,
    overwrite: bool = False,
    progress: Progress | None = None,
    T_obj_cloud: Pose | None = None,
    time_offset_s: float = 0.0,
) -> int:
    """Stream a LAS/LAZ file, correct every point by its time, write it with the same header,
    point format, order and attributes (only X, Y, Z change). Returns the number of points.

    ``T_obj_cloud`` maps the file's coordinates into the frame of ``correction`` (its stations and
    trajectory) before the correction, when the two differ (``[initial_transform]`` of the
    reference planes); the output's header offsets are then mapped with it, so that the integer
    coordinates keep their range and the scale its resolution. ``time_offset_s`` puts the point
    times into the trajectory's time base (the stored times are kept). Points without a finite
    time are left out (they have no pose).
    """
    import copy

    import laspy

    from kinreg.io.las import _DECODE_ERRORS, _laz_backend

    progress = progress or NullProgress()
    source = Path(source)
    n = 0
    with atomic_path(target, overwrite=overwrite) as tmp:
        try:
            reader = laspy.open(source, laz_backend=_laz_backend())
        except _DECODE_ERRORS as e:
            raise CloudError(f"cannot open as LAS/LAZ: {e}", source) from None
        with reader:
            header = reader.header
            if T_obj_cloud is not None:
                header = copy.deepcopy(header)
                header.offsets = np.round(T_obj_cloud.apply(np.asarray(header.offsets, dtype=np.float64)), 3)
            compress = Path(target).suffix.lower() == ".laz"
            progress.start("write cloud", total=header.point_count, unit="points")
            with laspy.open(tmp, mode="w", header=header, do_compress=compress,
                            laz_backend=_laz_backend() if compress else None) as writer:
                for points in _chunks(reader, chunk_points, source):
                    t = np.asarray(points.gps_time, dtype=np.float64) + time_offset_s
                    if not np.isfinite(t).all():
                        points, t = points[np.isfinite(t)], t[np.isfinite(t)]
                    xyz = np.column_stack([points.x, points.y, points.z]).astype(np.float64)
                    if T_obj_cloud is not None:
                        xyz = T_obj_cloud.apply(xyz)
                        points.offsets = header.offsets  # X, Y, Z are overwritten below, in the new system
                    fixed = correction.apply_to_points(xyz, t)
                    try:
                        points.x, points.y, points.z = fixed[:, 0], fixed[:, 1], fixed[:, 2]
                    except OverflowError:
                        raise CloudError("a corrected coordinate does not fit the input's scale and offset "
                                         "(32-bit integers)", source) from None
                    writer.write_points(points)
                    n += len(points)
                    progress.advance(len(points))
            progress.finish()
    return n


def _chunks(reader, chunk_points: int, source: Path) -> Iterator:
    from kinreg.io.las import _DECODE_ERRORS

    iterator = reader.chunk_iterator(chunk_points)
    while True:
        try:
            points = next(iterator)
        except StopIteration:
            return
        except _DECODE_ERRORS as e:
            raise CloudError(f"decoding failed (truncated or corrupted?): {e}", source) from None
        if len(points) == 0:
            return
        yield points
