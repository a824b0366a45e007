"""The accuracy matrix's cloud figures (``benchmarks/accuracy_matrix.py cloud_fit``): the plane
thickness is the points' spread about each physical plane's own fit, blind to a rigid motion of
the whole cloud; the distance to the true planes is not."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from accuracy_matrix import cloud_fit

from kinreg.geometry import Pose, rotvec_to_quat


def two_planes_run(noise_m: float, rng: np.random.Generator) -> tuple[SimpleNamespace, list, np.ndarray]:
    """A floor (z = 0, two patches of one plane) and a wall (x = 5), as a simulated run's scene and
    cloud blocks (patch ids), with ``noise_m`` along each normal."""
    patches = [SimpleNamespace(normal=np.array([0.0, 0.0, 1.0]), d=0.0, plane_id=0),
               SimpleNamespace(normal=np.array([0.0, 0.0, 1.0]), d=0.0, plane_id=0),
               SimpleNamespace(normal=np.array([1.0, 0.0, 0.0]), d=5.0, plane_id=1)]
    scene = SimpleNamespace(patches=patches, plane_of_patch=lambda: np.array([p.plane_id for p in patches]))
    n = 20_000
    floor = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.normal(0, noise_m, n)])
    wall = np.column_stack([5.0 + rng.normal(0, noise_m, n), rng.uniform(-5, 5, n), rng.uniform(0, 3, n)])
    ids = np.concatenate([np.where(floor[:, 0] < 0, 0, 1), np.full(n, 2)])
    xyz = np.vstack([floor, wall])
    blocks = [SimpleNamespace(patch_id=ids[:n + 100]), SimpleNamespace(patch_id=ids[n + 100:])]
    return SimpleNamespace(scene=scene, origin=np.array([100.0, 200.0, 10.0])), blocks, xyz


def cloud(blocks: list, xyz: np.ndarray, origin: np.ndarray):
    first = 0
    for block in blocks:
        yield block, xyz[first:first + len(block.patch_id)] + origin
        first += len(block.patch_id)


def test_thickness_is_the_noise_and_ignores_a_rigid_motion_that_moves_the_planes() -> None:
    rng = np.random.default_rng(5)
    run, blocks, xyz = two_planes_run(0.003, rng)
    to_planes, thickness = cloud_fit(run, cloud(blocks, xyz, run.origin))
    assert abs(thickness - 0.003) < 1e-4 and abs(to_planes - 0.003) < 1e-4

    # the whole cloud turned by 2 mrad and shifted by 1 cm: farther from the true planes, as thick
    moved = Pose(rotvec_to_quat(np.array([0.002, -0.001, 0.0005])), np.array([0.01, 0.0, -0.01])).apply(xyz)
    to_planes_moved, thickness_moved = cloud_fit(run, cloud(blocks, moved, run.origin))
    assert to_planes_moved > 2 * to_planes
    assert abs(thickness_moved - thickness) < 1e-6

    # the floor's middle strip 6 mm above the rest (passes that disagree; no tilt fits it away):
    # the floor 4.2 mm thick, both planes pooled 3.7 mm
    stepped = xyz.copy()
    stepped[(np.arange(len(xyz)) < 20_000) & (np.abs(xyz[:, 0]) < 2.5), 2] += 0.006
    _, thickness_stepped = cloud_fit(run, cloud(blocks, stepped, run.origin))
    assert 1.15 * thickness < thickness_stepped < 1.3 * thickness
