"""Calibration (Gauss-Helmert) and planning against simulated ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kinreg.calibration import (
    CalibrationConfig,
    PlanningConfig,
    SimulationConfig,
    SystemCalibration,
    Table3Grid,
    assign_points_to_planes,
    calibrate_with_gating,
    estimate_calibration,
    evaluate_arrangement,
    exhaustive_search,
    optimise_evolution,
    simulate_calibration,
    table2_arrangement,
)
from kinreg.calibration.arrangement import PlanePatch, read_arrangement
from kinreg.calibration.model import _boresight_and_derivatives, boresight_matrix
from kinreg.calibration.planning import Table2Tables, fitness_from_normal, grid_index_of
from kinreg.calibration.report import calibration_report, calibration_text, write_report
from kinreg.calibration.simulate import static_single_profile
from kinreg.errors import ConfigError, EstimationError


def _approx(truth: SystemCalibration) -> SystemCalibration:
    # 2 cm and 0.5 deg off: the kind of starting value a tape and a level give.
    return SystemCalibration(truth.lever_arm_m + np.array([0.02, -0.01, 0.015]),
                             truth.boresight_rad + np.radians([0.5, -0.3, 0.4]))


def test_boresight_matrix_is_a_rotation_with_its_derivatives():
    ang = np.radians([3.0, -20.0, 140.0])
    R = boresight_matrix(*ang)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    _, dR = _boresight_and_derivatives(ang)
    h = 1e-7
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (boresight_matrix(*(ang + e)) - boresight_matrix(*(ang - e))) / (2 * h)
        np.testing.assert_allclose(dR[k], num, atol=1e-8)


def test_estimate_recovers_truth_within_reported_sigmas():
    sim = simulate_calibration(seed=3)
    res = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory,
                               sim.planes, _approx(sim.truth))
    assert res.converged
    z = (res.calibration.as_vector() - sim.truth.as_vector()) / res.sigmas
    assert np.all(np.abs(z) < 4.0), z
    assert 0.95 < res.sigma0 < 1.05
    assert res.global_test.passed
    assert res.sigmas[0] < 1e-4
    assert math.degrees(res.sigmas[3]) < 2e-3
    np.testing.assert_allclose(np.diag(res.correlation), 1.0)
    assert sum(s.n_points for s in res.plane_stats) == res.n_points
    assert all(0.8 < s.normalized_rms < 1.2 for s in res.plane_stats)


def test_reported_sigmas_match_spread_small_monte_carlo():
    """30 repetitions here (the benchmark runs 200): coverage and sigma ratio, loose bounds."""
    cfg = SimulationConfig(n_profiles=20, zenith_step_deg=0.3)
    err, sig = [], []
    for seed in range(30):
        sim = simulate_calibration(cfg, seed=seed)
        res = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory,
                                   sim.planes, _approx(sim.truth))
        err.append(res.calibration.as_vector() - sim.truth.as_vector())
        sig.append(res.sigmas)
    err, sig = np.array(err), np.array(sig)
    assert np.mean(np.abs(err) < 3 * sig) > 0.95
    ratio = np.sqrt(np.mean(err**2, axis=0)) / sig.mean(axis=0)
    # with 30 samples the empirical sigma itself scatters by ~13 %
    assert np.all((ratio > 0.6) & (ratio < 1.45)), ratio


def test_plane_parameters_as_observations():
    cfg = SimulationConfig(plane_sigma_d_m=3e-4, plane_sigma_normal_rad=3e-4)
    sim = simulate_calibration(cfg, seed=5)
    ccfg = CalibrationConfig(plane_sigma_d_m=3e-4, plane_sigma_normal_rad=3e-4)
    res = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory,
                               sim.planes, _approx(sim.truth), ccfg)
    fixed = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory,
                                 sim.planes, _approx(sim.truth))
    assert res.plane_corrections is not None
    assert res.plane_corrections.shape == (8, 3)
    assert np.all(res.sigmas > fixed.sigmas)  # plane uncertainty adds to the parameters'
    z = (res.calibration.as_vector() - sim.truth.as_vector()) / res.sigmas
    assert np.all(np.abs(z) < 4.0)
    assert res.global_test.passed


def test_gating_assigns_points_to_their_planes():
    sim = simulate_calibration(seed=1)
    idx = assign_points_to_planes(sim.points_s, sim.stamps_s, sim.trajectory, sim.planes,
                                  _approx(sim.truth), gate_m=0.05)
    assigned = idx >= 0
    # Table 2 planes intersect near the profile, so many points are ambiguous at a 5 cm gate.
    assert assigned.mean() > 0.05
    assert np.all(idx[assigned] == sim.plane_index[assigned])
    res, idx2 = calibrate_with_gating(sim.points_s, sim.stamps_s, sim.trajectory, sim.planes,
                                      _approx(sim.truth))
    assert np.mean(idx2 >= 0) > 0.8
    assert np.all(idx2[idx2 >= 0] == sim.plane_index[idx2 >= 0])
    assert np.all(np.abs(res.calibration.as_vector() - sim.truth.as_vector()) < 4 * res.sigmas)


def _parallel_planes() -> tuple[PlanePatch, ...]:
    # Four horizontal planes (floor-like below, ceiling-like above): all normals along z.
    return tuple(PlanePatch.from_angles(f"h{i}", c, (0.0, 0.0, 0.0), 0.6)
                 for i, c in enumerate([(0, 1.0, -1.2), (0, -1.0, -1.2), (0, 0.5, 2.0), (0, -0.7, 2.5)]))


def test_parallel_planes_name_the_undetermined_parameters():
    cfg = SimulationConfig(planes=_parallel_planes(), angular_rate_rad_s=(0.0, 0.0, 0.0),
                           velocity_m_s=(0.1, 0.0, 0.0), n_profiles=10)
    sim = simulate_calibration(cfg, seed=0)
    with pytest.raises(EstimationError, match=r"tx, ty, kappa") as info:
        estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory, sim.planes,
                             _approx(sim.truth))
    assert "parallel" in str(info.value)
    # A single profile (all points at x_s = 0) cannot tilt about y on horizontal planes either.
    with pytest.raises(EstimationError, match=r"tx, ty, phi, kappa"):
        evaluate_arrangement(_parallel_planes(), PlanningConfig(zenith_step_deg=0.2))


def test_planning_covariance_equals_estimator_covariance():
    """Variance propagation of the planner == a-priori covariance of the adjustment on the same
    (noise-free, single profile, single pose) data; with a non-zero lever arm."""
    truth = SystemCalibration([0.05, -0.02, 0.3], [0.0, 0.0, 0.0])
    patches = table2_arrangement(3.0, 2.5, *np.radians([30.0, 45.0, 45.0]), size_m=0.3)
    cfg = PlanningConfig(zenith_step_deg=0.1, lever_arm_m=(0.05, -0.02, 0.3))
    plan = evaluate_arrangement(patches, cfg)
    sim = static_single_profile(patches, truth, zenith_step_deg=0.1)
    res = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory, sim.planes,
                               truth)
    np.testing.assert_allclose(res.covariance, plan.covariance, rtol=1e-5, atol=1e-18)
    np.testing.assert_allclose(res.calibration.as_vector(), truth.as_vector(), atol=1e-9)


def test_table_decomposition_matches_full_ray_casting():
    cfg = PlanningConfig(zenith_step_deg=0.1)
    grid = Table3Grid()
    tables = Table2Tables(grid, cfg)
    rng = np.random.default_rng(0)
    index = np.stack([rng.integers(0, n, 25) for n in grid.shape], axis=-1)
    _, f_tab, singular = fitness_from_normal(tables.evaluate(index), cfg)
    for i, ix in enumerate(index):
        patches = table2_arrangement(*grid.values(ix), size_m=cfg.plane_size_m)
        if singular[i]:
            with pytest.raises(EstimationError):
                evaluate_arrangement(patches, cfg)
            continue
        q = evaluate_arrangement(patches, cfg)
        np.testing.assert_allclose(f_tab[i], [q.f1_mm, q.f2_mm, q.f3_mm], rtol=1e-9)


def test_exhaustive_and_evolution_agree_on_grid():
    cfg = PlanningConfig(zenith_step_deg=0.2)
    grid = Table3Grid()
    tables = Table2Tables(grid, cfg)
    res = exhaustive_search(cfg, grid, tables)
    assert res.fitness.shape == (448_875, 3)
    # beta1 = gamma1 = 0: no plane has a normal component along x -> tx, phi, kappa undetermined
    ib, ig = grid_index_of(grid, 1, 1, 20, 0, 0)[3:]
    assert np.all(np.isinf(res.fitness.reshape(*grid.shape, 3)[:, :, :, ib, ig]))
    best = res.best("f3")[0]
    evo = optimise_evolution("f3", cfg, grid, tables, seed=1, popsize=20, maxiter=60)
    assert evo.fitness_mm == pytest.approx(res.fitness[best, 2], rel=2e-3)
    assert evo.n_evaluations < res.grid.size / 10


def test_read_arrangement(tmp_path):
    p = tmp_path / "arr.toml"
    p.write_text('[[plane]]\nname = "w"\ncenter_m = [0.0, 2.0, 0.0]\nangles_deg = [90, 0, 30]\n'
                 'size_m = [0.3, 0.4]\n')
    (patch,) = read_arrangement(p)
    assert patch.normal @ (np.zeros(3) - patch.center_m) > 0  # faces the scanner
    np.testing.assert_allclose(2 * patch.half_size_m, [0.3, 0.4])
    p.write_text('[[plane]]\nname = "w"\ncenter_m = [0.0, 2.0]\nangles_deg = [90, 0, 30]\n')
    with pytest.raises(ConfigError, match="center_m"):
        read_arrangement(p)


def test_report_round_trip(tmp_path):
    sim = simulate_calibration(SimulationConfig(n_profiles=10), seed=2)
    res = estimate_calibration(sim.points_s, sim.stamps_s, sim.plane_index, sim.trajectory, sim.planes,
                               _approx(sim.truth))
    rep = calibration_report(res, CalibrationConfig())
    paths = write_report(tmp_path, "calibration", rep, calibration_text(res))
    import json

    back = json.loads(paths[0].read_text())
    assert back["schema_version"] == 1
    assert back["parameters"]["tz"]["value"] == pytest.approx(res.calibration.lever_arm_m[2] * 1e3)
    assert "global test" in paths[1].read_text()


def _cli_app():
    import typer
    from kinreg_cli.calibrate import calibrate, plan_calibration

    app = typer.Typer()
    app.command("calibrate")(calibrate)
    app.command("plan-calibration")(plan_calibration)
    return app


def test_cli_plan_calibration_arrangement(tmp_path, capsys):
    from typer.testing import CliRunner

    arr = tmp_path / "arr.toml"
    arr.write_text("".join(
        f'[[plane]]\nname = "{p.name}"\ncenter_m = {p.center_m.tolist()}\nangles_deg = {a}\n'
        for p, a in zip(table2_arrangement(3.0, 2.5, *np.radians([45, 45, 45])),
                        ["[90, 0, -45]", "[90, 0, 0]", "[-45, 0, 0]", "[0, 0, 0]", "[0, 45, 0]",
                         "[45, 0, 0]", "[90, 0, 0]", "[90, 0, 45]"], strict=True)))
    out = CliRunner().invoke(_cli_app(), ["plan-calibration", "--arrangement", str(arr),
                                          "--zenith-step-deg", "0.2"])
    assert out.exit_code == 0, out.output
    q = evaluate_arrangement(table2_arrangement(3.0, 2.5, *np.radians([45, 45, 45])),
                             PlanningConfig(zenith_step_deg=0.2))
    assert f"f3 {q.f3_mm:.4f} mm" in out.output
    from kinreg_cli.main import main

    missing = tmp_path / "x.toml"
    with pytest.raises(SystemExit) as bad:
        main(["plan-calibration", "--arrangement", str(missing)])
    assert bad.value.code == 1
    assert capsys.readouterr().err.strip() == f"kinreg: error: {missing}: arrangement file not found"


def test_cli_calibrate_from_files(tmp_path):
    import laspy
    from typer.testing import CliRunner

    from kinreg.io.trajectory import write_trajectory_geoslam

    sim = simulate_calibration(SimulationConfig(n_profiles=20), seed=4)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([1e-6, 1e-6, 1e-6])
    header.offsets = np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = sim.points_s.T
    las.gps_time = sim.stamps_s
    las.write(tmp_path / "scan.las")
    write_trajectory_geoslam(tmp_path / "traj.txt", sim.trajectory)
    planes = tmp_path / "planes.toml"
    planes.write_text("plane_construction_accuracy_m = 0.0003\n" + "".join(
        f'[[plane]]\nname = "{p.name}"\nnormal = {p.normal.tolist()}\nd_m = {p.d_m!r}\n'
        for p in sim.planes.planes))
    la = ",".join(f"{v + 0.01:.4f}" for v in sim.truth.lever_arm_m)
    bs = ",".join(f"{v + 0.3:.4f}" for v in np.degrees(sim.truth.boresight_rad))
    out = CliRunner().invoke(_cli_app(), [
        "calibrate", "--cloud", str(tmp_path / "scan.las"), "--trajectory", str(tmp_path / "traj.txt"),
        "--planes", str(planes), "--lever-arm", la, "--boresight-deg", bs, "--out", str(tmp_path / "out")])
    assert out.exit_code == 0, out.output
    import json

    rep = json.loads((tmp_path / "out" / "calibration.json").read_text())
    est = np.array([rep["parameters"][n]["value"] for n in ("tx", "ty", "tz")]) * 1e-3
    sig = np.array([rep["parameters"][n]["sigma"] for n in ("tx", "ty", "tz")]) * 1e-3
    assert np.all(np.abs(est - sim.truth.lever_arm_m) < 5 * sig + 2e-6)
