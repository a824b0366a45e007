"""Synthetic plane sets with known truth for matching and pairwise tests (no point clouds)."""

from __future__ import annotations

import numpy as np

from kinreg.geometry import Pose, rotvec_to_quat, tangent_basis
from kinreg.types import Plane

# A room 12 x 8 x 3 m: walls, floor, ceiling, an interior wall face and a slanted plane,
# each (normal, d, centre, half extents along the tangent basis) in the object frame.
ROOM = [
    ((1, 0, 0), 0.0, (0, 4, 1.5), (4, 1.5)),
    ((-1, 0, 0), -12.0, (12, 4, 1.5), (4, 1.5)),
    ((0, 1, 0), 0.0, (6, 0, 1.5), (6, 1.5)),
    ((0, -1, 0), -8.0, (6, 8, 1.5), (6, 1.5)),
    ((0, 0, 1), 0.0, (6, 4, 0), (6, 4)),
    ((0, 0, -1), -3.0, (6, 4, 3), (6, 4)),
    ((-1, 0, 0), -10.0, (10, 2, 1.5), (1.5, 1.5)),  # an interior wall face, seen from x < 10
    ((0, 0.6, 0.8), 4.0, (8, 3.0, 2.75), (1, 1)),
]


def plane_in_scan(normal, d, centre, half, T_obj_scan: Pose, scan_id, plane_id, sigma_tilt, sigma_d, rng):
    """The plane as scan ``scan_id`` at ``T_obj_scan`` sees it: scan frame, normal towards the
    scanner, noisy by (sigma_tilt [rad], sigma_d [m]) drawn from the reported covariance."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    R, t = T_obj_scan.rotation_matrix, T_obj_scan.t_xyz
    n_s = R.T @ n
    d_s = d - n @ t
    if d_s > 0:  # the normal must point towards the scanner (scan origin)
        n_s, d_s = -n_s, -d_s
    uv_obj = tangent_basis(n)
    corners = np.array([np.asarray(centre) + su * half[0] * uv_obj[0] + sv * half[1] * uv_obj[1]
                        for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    hull = T_obj_scan.apply_inverse(corners)
    centroid = T_obj_scan.apply_inverse(np.asarray(centre, float))
    basis = tangent_basis(n_s)
    cov = np.diag([sigma_tilt**2, sigma_tilt**2, sigma_d**2])
    a, b, e = rng.multivariate_normal(np.zeros(3), cov) if rng is not None else (0.0, 0.0, 0.0)
    n_noisy = n_s + a * basis[0] + b * basis[1]
    n_noisy /= np.linalg.norm(n_noisy)
    # As a detector reports it: the tangent basis belongs to the observed (noisy) normal.
    return Plane(scan_id, plane_id, n_noisy, float(d_s + e), centroid, tangent_basis(n_noisy), cov, hull,
                 float(4 * half[0] * half[1]), 20_000, 0.01)


def scan_planes(T_obj_scan: Pose, scan_id: int, rng, sigma_tilt=2e-4, sigma_d=5e-4, room=ROOM):
    return tuple(plane_in_scan(*spec, T_obj_scan, scan_id, k, sigma_tilt, sigma_d, rng)
                 for k, spec in enumerate(room))


def pose(rotvec, t) -> Pose:
    return Pose(rotvec_to_quat(np.asarray(rotvec, float)), np.asarray(t, float))
