"""The simulator's real-world effects: each one has the size and structure it states, and none is on by default."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from kinreg.simulation.realism import (
    CLUTTER_PATCH_ID,
    Clutter,
    RealWorldConfig,
    gauss_markov,
    in_sweeps,
    make_waviness,
    mixed_pixel_ranges,
    range_noise,
)
from kinreg.simulation.run import SimulationConfig, config_as_dict, config_from_dict, simulate_run
from kinreg.simulation.scene import make_box_scene, make_building


def _short(real_world: RealWorldConfig, **kw) -> SimulationConfig:
    return SimulationConfig(**{"seed": 3, "duration_s": 12.0, "real_world": real_world, **kw})


def test_every_effect_is_off_by_default_and_the_files_stay_as_they_were():
    cfg = SimulationConfig()
    assert not cfg.real_world.shapes_the_rays and not cfg.real_world.jitters
    assert cfg.real_world.sweep_s == 0 and cfg.real_world.tail_share == 0
    assert "real_world" not in config_as_dict(cfg)  # run_meta.json of today's runs unchanged
    assert simulate_run(dataclasses.replace(cfg, duration_s=12.0)).world is None
    on = dataclasses.replace(cfg, real_world=RealWorldConfig.all_on())
    assert config_from_dict(config_as_dict(on)) == on


def test_waviness_has_its_rms_and_a_correlation_length_of_decimetres():
    scene = make_building()
    cfg = RealWorldConfig(waviness_rms_m=0.0025)
    wav = make_waviness(scene, cfg, np.random.default_rng(1))
    floor = next(p for p in scene.planes() if p.role == "floor")
    # a 200 m x 200 m patch of the floor's plane: many wavelengths, so the RMS is the stated one
    g = np.linspace(0.0, 200.0, 801)
    X, Y = np.meshgrid(g, g, indexing="ij")
    xyz = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    w = wav.offset_m(np.full(len(xyz), floor.plane_id), xyz).reshape(X.shape)
    assert float(np.sqrt(np.mean(w**2))) == pytest.approx(0.0025, rel=0.15)
    # correlation along lines in random directions: near 1 at 0.1 m, 1/2 at decimetres (a sixth
    # of the wavelengths), not at centimetres nor beyond the longest wavelength
    rng = np.random.default_rng(2)
    step, n_steps = 0.02, 5000
    heading = rng.uniform(0.0, 2.0 * np.pi, 200)
    start = rng.uniform(0.0, 100.0, (200, 2))
    s_m = np.arange(n_steps) * step
    line = start[:, None] + s_m[None, :, None] * np.column_stack([np.cos(heading), np.sin(heading)])[:, None]
    xyz_line = np.column_stack([line.reshape(-1, 2), np.zeros(line.shape[0] * line.shape[1])])
    w_line = wav.offset_m(np.full(len(xyz_line), floor.plane_id), xyz_line).reshape(200, n_steps)

    def corr(lag_m: float) -> float:
        k = round(lag_m / step)
        return float(np.mean(w_line[:, :-k] * w_line[:, k:]) / np.mean(w_line**2))

    assert corr(0.1) > 0.9
    half = next((lag for lag in np.arange(0.05, 3.01, 0.05) if corr(lag) < 0.5), None)
    assert half is not None and 0.15 <= half <= 1.5
    # each plane has its own surface
    wall = next(p for p in scene.planes() if p.role == "outer_wall")
    assert not np.allclose(wav.offset_m(np.full(len(xyz), wall.plane_id), xyz), w.ravel())


def test_wavy_surfaces_put_the_rays_hits_off_their_planes_by_the_waviness():
    run = simulate_run(_short(RealWorldConfig(waviness_rms_m=0.0025), sensor=dataclasses.replace(
        SimulationConfig().sensor, range_sigma_m=1e-9, angle_sigma_deg=0.0)))
    blk = run.cloud_block(0)
    assert run.world is not None and run.world.waviness is not None
    hit_obj = run.truth.pose_at(blk.stamps_s).apply(blk.xyz_sensor)
    n = np.array([p.normal for p in run.scene.patches])[blk.patch_id]
    d = np.array([p.d for p in run.scene.patches])[blk.patch_id]
    off_plane = np.einsum("ij,ij->i", hit_obj, n) - d
    expected = run.world.waviness.offset_m(run.scene.plane_of_patch()[blk.patch_id], hit_obj)
    assert 0.001 < float(np.sqrt(np.mean(off_plane**2))) < 0.005  # a few metres of surface: near the RMS
    # off the plane by its waviness (a grazing ray, whose step along it is bounded, a little less)
    assert np.median(np.abs(off_plane - expected)) < 2e-4


def test_the_range_noise_has_its_heavy_tail():
    rng = np.random.default_rng(0)
    n, sigma = 1_000_000, 0.01
    plain = range_noise(rng, n, sigma, RealWorldConfig())
    tailed = range_noise(rng, n, sigma, RealWorldConfig(tail_share=0.02, tail_scale=5.0))
    # beyond 4 sigma: a Gaussian has 6e-5 of its points there, a 2 % share of 5 sigma adds
    # 2 % * P(|z| > 0.8) = 0.85 %
    assert np.mean(np.abs(plain) > 4 * sigma) < 2e-4
    assert np.mean(np.abs(tailed) > 4 * sigma) == pytest.approx(0.02 * math.erfc(0.8 / math.sqrt(2)), rel=0.1)
    assert float(np.std(tailed)) == pytest.approx(sigma * math.sqrt(0.98 + 0.02 * 25), rel=0.02)


def test_mixed_pixels_lie_between_the_two_surfaces_an_edge_shows():
    rng = np.random.default_rng(0)
    r = np.full(100_000, 3.0)
    r_next = np.where(np.arange(len(r)) % 2 == 0, 5.0, 3.01)  # half of the rays on an edge
    r_next[:10] = np.inf  # the neighbour sees nothing: no mixed pixel
    out = mixed_pixel_ranges(r, r_next, RealWorldConfig(mixed_pixel_share=0.5), rng)
    moved = out != r
    assert not np.any(moved[1::2]) and not np.any(moved[:10])
    assert np.mean(moved[::2]) == pytest.approx(0.5, abs=0.01)
    assert np.all((out[moved] > 3.0) & (out[moved] < 5.0))
    # in the building: some points between surfaces, off every plane by more than the noise
    sensor = dataclasses.replace(SimulationConfig().sensor, range_sigma_m=1e-4, angle_sigma_deg=0.0)
    for footprint, share in ((0.0, (0.0, 0.0)), (0.003, (1e-4, 0.05))):
        run = simulate_run(_short(RealWorldConfig(mixed_pixel_footprint_rad=footprint), sensor=sensor))
        blk = run.cloud_block(0)
        hit_obj = run.truth.pose_at(blk.stamps_s).apply(blk.xyz_sensor)
        n = np.array([p.normal for p in run.scene.patches])[blk.patch_id]
        d = np.array([p.d for p in run.scene.patches])[blk.patch_id]
        off = np.mean(np.abs(np.einsum("ij,ij->i", hit_obj, n) - d) > 0.01)
        assert share[0] <= off <= share[1]


def test_the_sensor_records_sweeps_with_gaps():
    rw = RealWorldConfig(sweep_s=0.1, sweep_period_s=0.5)
    t = np.arange(0.0, 2.0, 1e-4)
    keep = in_sweeps(t, 0.0, rw)
    assert np.mean(keep) == pytest.approx(0.2, abs=1e-3)
    assert np.all(in_sweeps(t, 0.0, RealWorldConfig()))
    run = simulate_run(_short(rw))
    blk = run.cloud_block(0)
    phase = np.mod(blk.stamps_s - run.config.t0_s, 0.5)
    assert np.all(phase < 0.1)
    sweep = np.floor((blk.stamps_s - run.config.t0_s) / 0.5).astype(int)
    assert set(sweep) == set(range(20))  # every sweep of the 10 s block, nothing between them
    spans = [np.ptp(phase[sweep == k]) for k in range(20)]
    assert min(spans) > 0.09


def test_the_jitter_has_its_rms_and_correlation_time():
    x = gauss_markov(np.random.default_rng(0), 200_000, 0.01, 1.0, 0.01)  # 2000 s at 100 Hz
    assert np.sqrt(np.mean(x**2, axis=0)) == pytest.approx([0.01] * 3, rel=0.1)
    lag = 100  # 1 s: the correlation time
    rho = np.mean(x[:-lag] * x[lag:], axis=0) / np.mean(x**2, axis=0)
    assert rho == pytest.approx([math.exp(-1.0)] * 3, abs=0.08)
    # not smooth within seconds, yet continuous from row to row
    assert np.sqrt(np.mean(np.diff(x, axis=0) ** 2)) == pytest.approx(0.01 * math.sqrt(2 * 0.01), rel=0.1)
    # in a run: on top of the drift, applied to the trajectory and the points alike
    base = _short(RealWorldConfig(), duration_s=120.0)
    smooth = simulate_run(base)
    rough = simulate_run(dataclasses.replace(base, real_world=RealWorldConfig(jitter_m=0.01, jitter_rad=0.001)))
    dx = rough.slam.poses.t_xyz - smooth.slam.poses.t_xyz
    assert np.sqrt(np.mean(dx**2)) == pytest.approx(0.01, rel=0.3)
    from kinreg.geometry import quat_to_rotvec

    turn = quat_to_rotvec(smooth.slam.poses.inverse().compose(rough.slam.poses).quat_wxyz)
    assert np.sqrt(np.mean(turn**2)) == pytest.approx(0.001, rel=0.3)
    assert np.allclose(rough.drift.compose(rough.truth.poses).t_xyz, rough.slam.poses.t_xyz, atol=1e-9)
    blk = rough.cloud_block(0)
    assert np.allclose(rough.slam.pose_at(blk.stamps_s).apply(blk.xyz_sensor), blk.xyz_obj, atol=1e-6)


def test_a_ray_meets_a_cylinder_on_its_side_or_its_top():
    c = Clutter(np.array([[5.0, 0.0]]), np.array([0.5]), np.array([2.0]), np.zeros((0, 2)), np.zeros((0, 2)),
                np.zeros(0), np.zeros(0))
    o = np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 3.0], [0.0, 0.0, 2.5], [5.0, 0.0, 1.0]])
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    r, normal = c.raycast(o, d, np.zeros(4), 0.1)
    assert r[:2] == pytest.approx([4.5, 1.0])
    assert np.allclose(normal[:2], [[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.isinf(r[2]) and np.isinf(r[3])  # over it; from inside it


def test_clutter_stands_off_the_planes_and_a_person_walks():
    run = simulate_run(_short(RealWorldConfig(furniture_per_room=3, walkers=1)))
    assert run.world is not None and run.world.clutter is not None
    clutter = run.world.clutter
    assert len(clutter.radii_m) == 3 * 3
    xy = clutter.walker_xy(np.array([0.0, 1.0, 2.0]))[:, 0]
    assert np.linalg.norm(xy[1] - xy[0]) == pytest.approx(clutter.speed_mps[0], rel=1e-6)
    pts, times = [], []
    for blk in run.iter_cloud_blocks():
        on = blk.patch_id == CLUTTER_PATCH_ID
        pts.append(run.truth.pose_at(blk.stamps_s[on]).apply(blk.xyz_sensor[on]))
        times.append(blk.stamps_s[on])
    xyz, t = np.concatenate(pts), np.concatenate(times)
    assert len(xyz) > 100
    # every clutter point is on a cylinder's surface (furniture or the walker where it was then)
    centres = np.concatenate([np.broadcast_to(clutter.centres_xy, (len(t), *clutter.centres_xy.shape)),
                              clutter.walker_xy(t)], axis=1)
    radii = np.concatenate([clutter.radii_m, [clutter.walker_radius_m]])
    heights = np.concatenate([clutter.heights_m, [clutter.walker_height_m]])
    radial = np.linalg.norm(xyz[:, None, :2] - centres, axis=2) - radii
    top = np.where(np.linalg.norm(xyz[:, None, :2] - centres, axis=2) <= radii + 0.05, np.abs(xyz[:, 2:] - heights),
                   np.inf)
    assert np.quantile(np.min(np.minimum(np.abs(radial), top), axis=1), 0.95) < 0.05
    on_walker = np.argmin(np.minimum(np.abs(radial), top), axis=1) == len(radii) - 1
    assert on_walker.sum() > 10 and np.ptp(xyz[on_walker, 0]) > 1.0  # the walker was seen in several places


def test_all_on_in_the_box_scene_without_a_walk_plan_has_no_clutter():
    from kinreg.simulation.realism import make_clutter

    c = make_clutter(make_box_scene(), RealWorldConfig.all_on(), np.random.default_rng(0))
    assert len(c.radii_m) == 0 and len(c.speed_mps) == 0


def test_the_effects_are_switched_on_by_name():
    jitter = RealWorldConfig.only("jitter")
    assert jitter.jitters and not jitter.shapes_the_rays and jitter.sweep_s == 0 and jitter.tail_share == 0
    assert RealWorldConfig.only("waviness", "noise", "sweeps", "jitter", "clutter") == RealWorldConfig.all_on()
    with pytest.raises(ValueError, match="unknown"):
        RealWorldConfig.only("rain")
