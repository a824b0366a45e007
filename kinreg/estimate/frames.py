"""Scan frames and sensor poses as separate unknowns of the block.

A quasi-static scan is assembled over a window with the trajectory's poses relative to its
centre; its planes then fix a frame that is not quite the sensor's pose at the centre time: the
drift inside the window deforms the scan, and the planes, seen at their own times, average that
into a shift and turn of the whole scan (the window bias,
:func:`~kinreg.estimate.drift.window_bias_covariance`). That error is common to every plane link
of the scan, and to neither of the trajectory's links, which tie sensor poses.

So the block carries both for each quasi-static station ``k``: its scan frame ``s_k`` (the node
the plane links, static scans and reference planes attach to) and its sensor pose ``x_k`` (the
node of the trajectory's links, their drift velocities and the control points), tied by a
``FRAME`` observation ``s_k^-1 x_k = I`` with the window bias as its covariance. A scan's window
bias is then one error shared by all its links, as it is in the data, instead of a share of
each trajectory link (which averaged it away over a run) plus a covariance added after the
adjustment. The stations' reported poses and covariances are the sensor poses'; the first
station as datum holds the sensor pose, so the network turns about it with that scan's own
window bias.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from kinreg.config import BlockConfig
from kinreg.estimate.block import adjust_block
from kinreg.estimate.drift import DriftRates, plane_motion_jacobian, window_bias_covariance, window_deformation_jacobian
from kinreg.geometry import FloatArray, Pose
from kinreg.progress import Progress
from kinreg.types import BlockResult, ObservationKind, Plane, RelativeObservation, ScanKind, Station

# Observations on the sensor pose (the trajectory's): moved to the sensor-pose nodes.
_ON_SENSOR = (ObservationKind.TRAJECTORY, ObservationKind.DRIFT, ObservationKind.POINT)
# The least variance of a frame tie [m^2, rad^2] (0.01 mm, 0.01 mrad): a window without drift ties them
# hard, but not so hard that the normal matrix loses the convergence test to rounding.
_TIE_FLOOR = 1e-10
_OPEN = 1.0  # [m], [rad]: a scan frame's direction that its own planes do not fix


def sensor_nodes(stations: Sequence[Station]) -> dict[int, int]:
    """Per quasi-static station with a time: the index of its sensor-pose node (after the
    stations' own)."""
    timed = [k for k, s in enumerate(stations) if s.kind is ScanKind.QUASI_STATIC and np.isfinite(s.t_s)]
    return {k: len(stations) + m for m, k in enumerate(timed)}


def window_gain(planes: Sequence[Plane]) -> FloatArray:
    """How a drift velocity (6, scan axes) inside the window moves the frame that a scan's planes
    fix (6x6, twist per velocity): the least-squares frame motion of the planes' deformation
    (:func:`~kinreg.estimate.drift.window_deformation_jacobian`), ``H^-1 sum J^T C^-1 G``."""
    H = np.diag(np.full(6, 1.0 / _OPEN**2))
    B = np.zeros((6, 6))
    for p in planes:
        J = plane_motion_jacobian(p)
        W = np.linalg.inv(p.cov_uvd)
        H += J.T @ W @ J
        B += J.T @ W @ window_deformation_jacobian(p)
    gain: FloatArray = np.linalg.solve(H, B).astype(np.float64)
    return gain


def extra_first(stations: Sequence[Station]) -> int:
    """The first node after the stations and their sensor poses (:func:`adjust_with_frames`)."""
    return len(stations) + len(sensor_nodes(stations))


def frame_ties(stations: Sequence[Station], nodes: dict[int, int], rates: DriftRates,
               gain: FloatArray | None = None, velocity_cov: FloatArray | None = None) -> list[RelativeObservation]:
    """The ``FRAME`` observations: each scan frame's sensor pose is its own, up to the window bias:
    with ``gain`` (n, 6, 6, :func:`window_gain`), the drift velocity's spread through it (the
    rates', or with ``velocity_cov`` (n, 6, 6, scan axes) what the deskewed planes leave,
    :func:`~kinreg.estimate.drift.window_velocity_covariance`); without, the station's
    :func:`~kinreg.estimate.drift.window_bias_covariance`."""
    ties = []
    for k, x in nodes.items():
        T = stations[k].T_obj_scan
        if gain is None:
            cov = window_bias_covariance(stations[k], T, rates)
        else:
            spread = rates.covariance(1.0, T, floor=False) if velocity_cov is None else velocity_cov[k]
            cov = gain[k] @ spread @ gain[k].T
        cov = cov + _TIE_FLOOR * np.eye(6)
        info = np.linalg.inv(0.5 * (cov + cov.T))
        ties.append(RelativeObservation(ObservationKind.FRAME, k, x, Pose.identity(), 0.5 * (info + info.T), 6))
    return ties


def adjust_with_frames(stations: Sequence[Station], poses_initial: Pose, observations: list[RelativeObservation],
                       fixed: np.ndarray, rates: DriftRates, config: BlockConfig,
                       progress: Progress | None = None, gain: FloatArray | None = None,
                       velocity_cov: FloatArray | None = None, extra: Pose | None = None) -> BlockResult:
    """The block adjustment with a scan frame and a sensor pose per quasi-static station (see the
    module's docstring), returned as the stations' result: poses, covariances and tests of the
    sensor poses (tests name stations; a ``FRAME`` test names its station twice). The
    observations come as :meth:`~kinreg.estimate.network.Network.observations` gives them, on
    the stations; their order is kept (the frame ties follow them). ``extra``: further pose nodes
    (the physical planes, :mod:`kinreg.estimate.plane_nodes`), after the sensor poses (their
    observations number them so: :func:`extra_first`); a test names an extra node by its number
    among them (a ``PLANE`` test: station and physical plane)."""
    nodes = sensor_nodes(stations)
    extra = Pose(np.zeros((0, 4)), np.zeros((0, 3))) if extra is None else extra
    order = np.array(list(nodes), dtype=int)
    moved = [replace(o, i=nodes.get(o.i, o.i), j=nodes.get(o.j, o.j) if o.j >= 0 else o.j)
             if o.kind in _ON_SENSOR else o for o in observations]
    poses = Pose(np.concatenate([poses_initial.quat_wxyz, poses_initial.quat_wxyz[order], extra.quat_wxyz]),
                 np.concatenate([poses_initial.t_xyz, poses_initial.t_xyz[order], extra.t_xyz]))
    held = np.concatenate([np.asarray(fixed, dtype=bool), np.asarray(fixed, dtype=bool)[order],
                           np.zeros(len(extra), dtype=bool)])
    held[order] = False  # a station held as datum holds its sensor pose; its frame follows by the tie
    result = adjust_block(poses, moved + frame_ties(stations, nodes, rates, gain, velocity_cov), held, config, progress)
    n = len(stations)
    back = np.arange(len(poses))
    back[n:n + len(order)] = order
    first_extra = n + len(order)
    back[first_extra:] = np.arange(len(extra))  # an extra node's test names its number among them
    pick = np.arange(n)
    pick[order] = n + np.arange(len(order))
    # (the holds of the extra nodes' free directions are no observations to report)
    tests = tuple(replace(t, i=int(back[t.i]), j=int(back[t.j]) if t.j >= 0 else t.j) for t in result.tests
                  if t.i < first_extra)
    return replace(result, poses=result.poses[pick], poses_initial=result.poses_initial[pick],
                   fixed=np.asarray(fixed, dtype=bool).copy(), cov_xi=result.cov_xi[pick],
                   cov_position=result.cov_position[pick], tests=tests)
