"""Virtual reference station: known building planes as datum (METHOD.md step 9, seed section 5).

Every detected plane associated with a reference plane gets its own virtual tie plane. The tie
plane is not held fixed: its offset has the standard deviation ``plane_construction_accuracy_m``
and its normal may "wobble" by that amount over the patch's extent (a tilt of
``accuracy / extent``). Three conditions per tie say that the detected plane, mapped into the
object frame with its station's pose, is the tie plane::

    c1 = u_r . (R n_s)                      (normal difference along the reference's tangents)
    c2 = v_r . (R n_s)
    c3 = n_r . (R c_s + t) - d_r            (offset at the patch centroid)

Solved for the pose nearest the station's initial pose that satisfies them, and linearised
there, they become a rank-3 observation of that pose, which the block adjustment takes like any
other direct observation. After the adjustment the tie
planes' corrections compare the as-built building with the plan.

Frames. The network is adjusted in the reference planes' frame. When the trajectory's frame is
roughly that frame already, the station poses are used as they are. When it is not (an arbitrary
SLAM frame), the file's ``[initial_transform]`` ``T_ref_traj`` is applied to the quasi-static
stations and to the trajectory *before* linking (:func:`to_reference_frame`), so that
association, tie planes, block adjustment and every output (stations, corrected trajectory and
cloud, E57 sequence) are in the reference frame, as in the aligned case. Linking and the block's
trajectory observations use relative poses only, which a common rigid transform leaves unchanged
(measured drift rates are then per axis of the reference frame). The alternative, keeping the
SLAM frame and adding ``T_ref_traj`` to the tie model as six more unknowns, would leave the
outputs in the SLAM frame and need a second transformation of every output. The transform only
has to be rough: the ties are solved exactly at their own poses (:func:`tie_observations`), and
the drift correction reproduces a constant remainder of it exactly (:mod:`kinreg.estimate.correction`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from kinreg.config import ReferenceConfig
from kinreg.errors import ConfigError
from kinreg.geometry import FloatArray, Pose, skew, tangent_basis
from kinreg.survey import ReferencePlanes
from kinreg.types import ObservationKind, Plane, RelativeObservation, ScanKind, Station, Tie, Trajectory

log = logging.getLogger(__name__)

# Gauss-Newton steps of a tie's pose onto its conditions (converges in 3-4 from a rough start).
_TIE_ITERATIONS = 8


def to_reference_frame(stations: Sequence[Station], trajectory: Trajectory,
                       references: ReferencePlanes | None) -> tuple[list[Station], Trajectory]:
    """The quasi-static stations and the trajectory in the reference planes' frame.

    ``stations`` have poses ``T_traj_scan`` in the trajectory's frame and ``trajectory`` the poses
    ``T_traj_platform``; with an ``[initial_transform]`` ``T_ref_traj`` in ``references`` both
    become ``T_ref_traj . T``; without one (or without ``references``) they are returned as they
    are. Static stations are left alone: their poses come from a registered E57 and are taken to be
    in the reference frame. The scans' points and planes are in the scan frames and need nothing.
    The cloud file stays in the trajectory's frame: its writer maps it with the same transform.
    """
    if references is None or references.T_ref_traj is None:
        return list(stations), trajectory
    T = references.T_ref_traj
    moved = [replace(s, T_obj_scan=T.compose(s.T_obj_scan)) if s.kind is ScanKind.QUASI_STATIC else s
             for s in stations]
    log.info("stations and trajectory mapped into the reference frame with the initial transform")
    return moved, replace(trajectory, poses=T.compose(trajectory.poses))


def plane_in_object_frame(plane: Plane, T_obj_scan: Pose) -> tuple[FloatArray, float, FloatArray]:
    """Normal, offset and centroid of a detected plane in the object frame."""
    n = T_obj_scan.rotation_matrix @ plane.normal
    c = T_obj_scan.apply(plane.centroid_xyz)
    return n, float(n @ c), c


def associate(
    station_names: Sequence[str],
    poses: Pose,
    planes: Sequence[tuple[Plane, ...]],
    references: ReferencePlanes,
    config: ReferenceConfig,
) -> list[Tie]:
    """Ties of detected planes to reference planes.

    ``poses`` are the stations' initial poses in the reference frame (mapped there with the
    ``[initial_transform]`` by :func:`to_reference_frame` if the file has one), so the detected
    planes are compared with the reference planes in that frame. Explicit ``[[link]]`` entries of
    the reference file are taken as given (station by name, plane by id). All other planes are
    associated automatically where the station's initial pose puts them within the angle and
    distance gates of exactly one reference plane (the second candidate, if any, must be
    ``ambiguity_ratio`` times farther). Raises :class:`ConfigError` for an explicit link naming an
    unknown station or plane.
    """
    ties: list[Tie] = []
    taken: set[tuple[int, int]] = set()
    by_name = {name: k for k, name in enumerate(station_names)}
    for link in references.links:
        if link.station not in by_name:
            raise ConfigError(f"[[link]] names station '{link.station}', which is not in this run", references.source)
        k = by_name[link.station]
        ids = {p.plane_id for p in planes[k]}
        try:
            plane_id = int(link.plane)
        except ValueError:
            raise ConfigError(f"[[link]] plane '{link.plane}' must be a plane number of station {link.station}",
                              references.source) from None
        if plane_id not in ids:
            raise ConfigError(f"[[link]] station {link.station} has no plane {plane_id} (it has {sorted(ids)})",
                              references.source)
        ties.append(Tie(k, plane_id, references.index(link.reference), explicit=True))
        taken.add((k, plane_id))

    normals, offsets = references.normals, references.d_m
    cos_gate = np.cos(np.radians(config.angle_gate_deg))
    for k, found in enumerate(planes):
        for plane in found:
            if (k, plane.plane_id) in taken:
                continue
            n, _, c = plane_in_object_frame(plane, poses[k])
            distance = np.abs(c @ normals.T - offsets)
            ok = (normals @ n >= cos_gate) & (distance <= config.distance_gate_m)
            if not ok.any():
                continue
            order = np.argsort(np.where(ok, distance, np.inf))
            best = int(order[0])
            if ok.sum() > 1 and distance[order[1]] < config.ambiguity_ratio * distance[best] + 0.01:
                continue  # two reference planes fit about equally well: leave it to the network
            ties.append(Tie(k, plane.plane_id, best))
    return ties


def _tie_model(plane: Plane, T: Pose, n_r: FloatArray, d_r: float, accuracy_m: float,
               min_extent_m: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Misclosures w (3,), Jacobian A (3, 6) w.r.t. the station's right perturbation, and the
    misclosures' covariance Q (3, 3) from the detected plane and the tie plane."""
    R, t = T.rotation_matrix, T.t_xyz
    u_r, v_r = tangent_basis(n_r)
    u_s, v_s = plane.basis_uv
    m = R @ plane.normal
    c_obj = R @ plane.centroid_xyz + t
    w = np.array([u_r @ m, v_r @ m, n_r @ c_obj - d_r])
    dm_dphi = -R @ skew(plane.normal)
    A = np.zeros((3, 6))
    A[0, 3:] = u_r @ dm_dphi
    A[1, 3:] = v_r @ dm_dphi
    A[2, :3] = n_r @ R
    A[2, 3:] = n_r @ (-R @ skew(plane.centroid_xyz))
    # The detected plane's covariance moved from the scan origin to its centroid (tilts about the
    # centroid do not move the plane there).
    J_c = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                    [-(u_s @ plane.centroid_xyz), -(v_s @ plane.centroid_xyz), 1.0]])
    cov_c = J_c @ plane.cov_uvd @ J_c.T
    Ru, Rv = R @ u_s, R @ v_s
    B = np.array([[u_r @ Ru, u_r @ Rv, 0.0], [v_r @ Ru, v_r @ Rv, 0.0], [0.0, 0.0, float(n_r @ m)]])
    extent = max(np.sqrt(plane.area_m2), min_extent_m)
    tilt = accuracy_m / extent
    Q = B @ cov_c @ B.T + np.diag([tilt**2, tilt**2, accuracy_m**2])
    return w, A, Q


def tie_observations(
    ties: Sequence[Tie],
    poses: Pose,
    planes: Sequence[tuple[Plane, ...]],
    references: ReferencePlanes,
    config: ReferenceConfig,
) -> list[RelativeObservation]:
    """One rank-3 direct observation of a station's pose per tie: the pose ``Z`` nearest the
    station's initial pose (``poses``, reference frame) on which the detected plane *is* the
    reference plane, with the conditions' information linearised at ``Z``."""
    observations = []
    for tie in ties:
        plane = next(p for p in planes[tie.station] if p.plane_id == tie.plane_id)
        ref = references.planes[tie.reference]
        Z = poses[tie.station]
        # Minimum-norm Gauss-Newton steps onto the conditions. One step leaves an error of second
        # order in the misclosure (millimetres for a tenth of a degree over 20 m, as a rough
        # initial alignment gives); at the exact Z the block's residual log(Z^-1 T) weighted by
        # `info` moves T only along the plane's own symmetries (in-plane shifts, rotation about
        # its normal), which keep the conditions exactly.
        for _ in range(_TIE_ITERATIONS):
            w, A, Q = _tie_model(plane, Z, ref.normal, ref.d_m, references.accuracy_m, config.min_extent_m)
            step = -np.linalg.pinv(A) @ w
            Z = Z.compose(Pose.exp(step))
            if np.abs(step).max() < 1e-12:
                break
        w, A, Q = _tie_model(plane, Z, ref.normal, ref.d_m, references.accuracy_m, config.min_extent_m)
        info = A.T @ np.linalg.solve(Q, A)
        observations.append(RelativeObservation(ObservationKind.STATION, tie.station, -1, Z, info, 3))
    return observations


def as_built(
    ties: Sequence[Tie],
    poses: Pose,
    planes: Sequence[tuple[Plane, ...]],
    references: ReferencePlanes,
) -> list[dict[str, Any]]:
    """Per reference plane: number of tie planes and the mean, spread and extremes of their
    corrections (signed distance of the adjusted detected plane's centroid from the reference
    plane, mm; angle between the normals, mdeg): the as-built vs plan comparison."""
    rows = []
    for r, ref in enumerate(references.planes):
        offsets, angles = [], []
        for tie in ties:
            if tie.reference != r:
                continue
            plane = next(p for p in planes[tie.station] if p.plane_id == tie.plane_id)
            n, _, c = plane_in_object_frame(plane, poses[tie.station])
            offsets.append(float(c @ ref.normal - ref.d_m) * 1000.0)
            angles.append(float(np.degrees(np.arccos(np.clip(n @ ref.normal, -1.0, 1.0)))) * 1000.0)
        o = np.array(offsets)
        rows.append({
            "name": ref.name, "n_ties": len(o),
            "offset_mean_mm": float(o.mean()) if len(o) else None,
            "offset_std_mm": float(o.std(ddof=1)) if len(o) > 1 else None,
            "offset_min_mm": float(o.min()) if len(o) else None,
            "offset_max_mm": float(o.max()) if len(o) else None,
            "angle_mean_mdeg": float(np.mean(angles)) if angles else None,
        })  # fmt: skip
    return rows
