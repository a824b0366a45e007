"""The planes' time offsets and slopes from a float32 preselection are those of a float64 pass."""

from __future__ import annotations

import numpy as np
from planefixtures import plane_in_scan

from kinreg.estimate.drift import plane_time_offsets
from kinreg.geometry import Pose


def _members(points_xyz, plane, band_m):
    """The definition of a plane's points: a float64 test of every point against the band and the
    extent. Their indices, and their coordinates about the centroid."""
    near = np.flatnonzero(np.abs(points_xyz @ plane.normal - plane.d_m) <= band_m)
    local = points_xyz[near] - plane.centroid_xyz
    hull = plane.hull_xyz - plane.centroid_xyz
    inside = np.ones(len(local), dtype=bool)
    for axis in plane.basis_uv:
        inside &= (local @ axis >= (hull @ axis).min() - 1e-9) & (local @ axis <= (hull @ axis).max() + 1e-9)
    return near[inside], local[inside]


def _one_pass(points_xyz, stamps_s, t_s, planes, band_m):
    """The definition: per plane, the mean and slope of its points' times (:func:`_members`)."""
    offsets = np.full(len(planes), np.nan)
    slopes = np.full((len(planes), 2), np.nan)
    for k, plane in enumerate(planes):
        idx, local = _members(points_xyz, plane, band_m)
        if len(idx):
            t = stamps_s[idx]
            offsets[k] = float(np.mean(t)) - t_s
            st = local @ plane.basis_uv.T
            st = st - st.mean(axis=0)
            A = st.T @ st
            if len(t) >= 3 and np.linalg.cond(A) < 1e8:
                slopes[k] = np.linalg.solve(A, st.T @ (t - t.mean()))
    return offsets, slopes


def test_offsets_and_slopes_equal_a_float64_pass_over_every_point():
    """Ten planes of a box-shaped room 30 m across (more than one float32 product's worth), points
    scattered across and beyond their bands (also exactly on a band's edge), a non-finite point
    and a plane without points: the same offsets to the bit, the same slopes to rounding."""
    rng = np.random.default_rng(7)
    normals = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (1, 1, 0), (0, 1, 1),
               (1, 0, 1), (1, 1, 1)]
    planes, chunks = [], []
    for k, n in enumerate(normals):
        n = np.asarray(n, dtype=float) / np.linalg.norm(n)
        d = -(4.0 + 1.5 * k)
        p = plane_in_scan(n, d, d * n, (3.0, 2.0), Pose.identity(), 0, k, 1e-4, 3e-4, None)
        planes.append(p)
        st = rng.uniform(-3.5, 3.5, (20_000, 2))  # some beyond the extent
        offset = rng.normal(0.0, 0.02, 20_000)  # some beyond the band of 0.03 m
        offset[:50] = 0.03  # on the edge
        chunks.append(p.centroid_xyz + st @ p.basis_uv + offset[:, None] * p.normal)
    empty = plane_in_scan((0.0, 0.0, 1.0), -200.0, (0.0, 0.0, -200.0), (1.0, 1.0), Pose.identity(), 0, 10,
                          1e-4, 3e-4, None)
    planes.append(empty)
    points = np.concatenate([*chunks, rng.uniform(-15, 15, (50_000, 3)), [[np.nan, 0.0, 0.0]]])
    stamps = 500.0 + rng.uniform(-5.0, 5.0, len(points))
    offsets, slopes, _, _ = plane_time_offsets(points, stamps, 500.0, planes, 0.03)
    want_offsets, want_slopes = _one_pass(points, stamps, 500.0, planes, 0.03)
    assert np.array_equal(offsets, want_offsets, equal_nan=True)
    np.testing.assert_allclose(slopes, want_slopes, rtol=0, atol=1e-12)
    assert np.isnan(offsets[-1]) and np.isfinite(offsets[:-1]).all()
    assert plane_time_offsets(points[:0], stamps[:0], 500.0, planes, 0.03)[0].shape == (len(planes),)


def test_a_hull_moved_by_rounding_keeps_its_vertex_points():
    """The hull's extreme vertices are points of the plane, on its extent's edge to the last bit:
    a hull that a refit moved by 1e-14 m must not put them out (offsets moved by up to 2.8 ms)."""
    from dataclasses import replace

    p = plane_in_scan((0.0, 0.0, 1.0), -2.0, (0.0, 0.0, -2.0), (2.0, 1.0), Pose.identity(), 0, 0, 1e-4, 3e-4, None)
    points = np.concatenate([p.hull_xyz, p.centroid_xyz + np.array([[0.1, 0.0, 0.0]])])
    stamps = np.concatenate([np.full(len(p.hull_xyz), 10.0), [0.0]])
    for shift in (0.0, 1e-14, -1e-14):
        moved = replace(p, hull_xyz=p.hull_xyz + shift * (p.hull_xyz - p.centroid_xyz))
        offsets = plane_time_offsets(points, stamps, 0.0, [moved], 0.03).offsets
        assert offsets[0] == np.mean(stamps)


def test_sensor_moments_equal_those_of_the_points_of_a_float64_pass():
    """With the sensor's track: each plane's mean sensor position is the mean of the track at its
    points' times (those of the float64 pass), and its slope across the plane that of a least-squares
    fit of those positions against the in-plane coordinates."""
    rng = np.random.default_rng(11)
    planes, chunks = [], []
    for k, n in enumerate([(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 0.0)]):
        n = np.asarray(n) / np.linalg.norm(n)
        d = -(3.0 + k)
        planes.append(plane_in_scan(n, d, d * n, (2.0, 1.5), Pose.identity(), 0, k, 1e-4, 3e-4, None))
        st = rng.uniform(-2.5, 2.5, (15_000, 2))
        chunks.append(planes[-1].centroid_xyz + st @ planes[-1].basis_uv + rng.normal(0, 0.02, (15_000, 1))
                      * planes[-1].normal)
    points = np.concatenate([*chunks, rng.uniform(-8, 8, (20_000, 3))])
    stamps = 100.0 + rng.uniform(-3.0, 3.0, len(points))
    track_t = np.linspace(96.0, 104.0, 81)
    track = (track_t, np.column_stack([0.5 * (track_t - 100), np.sin(track_t), 0.1 * track_t]))
    times = plane_time_offsets(points, stamps, 100.0, planes, 0.03, track)
    want_offsets, _ = _one_pass(points, stamps, 100.0, planes, 0.03)
    assert np.array_equal(times.offsets, want_offsets)
    for k, plane in enumerate(planes):
        idx, local = _members(points, plane, 0.03)
        t = stamps[idx]
        seen = np.column_stack([np.interp(t, track_t, track[1][:, i]) for i in range(3)])
        np.testing.assert_allclose(times.sensor[k], seen.mean(axis=0), rtol=0, atol=1e-12)
        st = local @ plane.basis_uv.T
        st = st - st.mean(axis=0)
        slope = np.linalg.solve(st.T @ st, st.T @ (seen - seen.mean(axis=0)))  # (2, 3)
        np.testing.assert_allclose(times.sensor_slopes[k], slope.T, rtol=0, atol=1e-12)
        assert np.abs(times.sensor_slopes[k]).max() > 1e-3  # the sensor moved while the plane was seen
