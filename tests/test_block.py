"""Block adjustment on synthetic networks with known truth."""

import numpy as np
import pytest

from kinreg.config import BlockConfig
from kinreg.errors import EstimationError
from kinreg.estimate.block import adjust_block
from kinreg.estimate.snooping import MAX_WEIGHT_GAIN, variance_components
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.types import ObservationKind, ObservationTest, RelativeObservation


def true_stations(n: int, rng) -> Pose:
    s = np.arange(n)
    angle = s / n * 2 * np.pi
    xyz = np.column_stack([8 * np.cos(angle), 5 * np.sin(angle), 1.5 + 0.1 * rng.normal(size=n)])
    rot = np.column_stack([0.05 * rng.normal(size=n), 0.05 * rng.normal(size=n), s / n * 2 * np.pi])
    return Pose(rotvec_to_quat(rot), xyz)


def observe(truth: Pose, i: int, j: int, cov: np.ndarray, kind, rng, info=None) -> RelativeObservation:
    """A relative observation of T_i_j drawn from N(truth, cov) in the right-perturbation twist."""
    T = truth[i].inverse().compose(truth[j])
    Z = T.compose(Pose.exp(rng.multivariate_normal(np.zeros(6), cov)))
    info = np.linalg.inv(cov) if info is None else info
    return RelativeObservation(kind, i, j, Z, info, int(np.linalg.matrix_rank(info)))


def rank_deficient_obs(truth, i, j, sigmas, free_axis, rng):
    """Planes that do not fix translation along ``free_axis`` (of station i): info rank 5."""
    cov = np.diag(np.square(sigmas))
    e = rng.multivariate_normal(np.zeros(6), cov)
    e[free_axis] = rng.normal(0, 1.0)  # anything: not observed
    T = truth[i].inverse().compose(truth[j])
    info = np.linalg.inv(cov)
    info[free_axis, :] = 0
    info[:, free_axis] = 0
    return RelativeObservation(ObservationKind.PLANES, i, j, T.compose(Pose.exp(e)), info, 5)


def network(rng, n=60, traj_sigma=(3e-3, 3e-3, 3e-3, 5e-4, 5e-4, 5e-4), plane_sigma=(1e-3,) * 3 + (1e-4,) * 3):
    truth = true_stations(n, rng)
    obs = []
    cov_t = np.diag(np.square(traj_sigma))
    cov_p = np.diag(np.square(plane_sigma))
    for i in range(n - 1):
        obs.append(observe(truth, i, i + 1, cov_t, ObservationKind.TRAJECTORY, rng))
        for j in range(i + 1, min(n, i + 4)):
            if (i + j) % 5 == 0:
                obs.append(rank_deficient_obs(truth, i, j, plane_sigma, 0, rng))
            else:
                obs.append(observe(truth, i, j, cov_p, ObservationKind.PLANES, rng))
    for i in range(0, 8):  # loop closure
        obs.append(observe(truth, i, n - 1 - i, cov_p, ObservationKind.PLANES, rng))
    # approximate poses: the truth, drifted
    drift = Pose.exp(np.column_stack([np.linspace(0, 0.05, n)[:, None] * [1, -1, 0.5],
                                      np.linspace(0, 0.003, n)[:, None] * [0.2, 0.1, 1]]))
    initial = Pose(truth.quat_wxyz.copy(), truth.t_xyz.copy())
    initial = Pose(initial.quat_wxyz, initial.t_xyz)
    approx = initial.compose(drift)
    approx = Pose(np.concatenate([truth.quat_wxyz[:1], approx.quat_wxyz[1:]]),
                  np.concatenate([truth.t_xyz[:1], approx.t_xyz[1:]]))
    return truth, approx, obs


def normalised_errors(result, truth):
    err = truth.inverse().compose(result.poses).log()  # right-perturbation error per station
    free = ~result.fixed
    sig = np.sqrt(np.diagonal(result.cov_xi, axis1=1, axis2=2))
    return err[free] / sig[free]


def test_recovers_truth_with_honest_sigmas():
    cfg = BlockConfig(variance_components=False)
    ratios = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        truth, approx, obs = network(rng)
        fixed = np.zeros(len(approx), dtype=bool)
        fixed[0] = True
        res = adjust_block(approx, obs, fixed, cfg)
        assert res.iterations < cfg.max_iterations
        ratios.append(normalised_errors(res, truth))
        assert 0.7 < res.sigma0 < 1.3
    z = np.concatenate(ratios)
    rms = np.sqrt(np.mean(z**2))
    assert 0.85 < rms < 1.15, rms
    assert np.mean(np.abs(z) < 3) > 0.99


def test_position_sigma_is_rotated_into_the_object_frame():
    rng = np.random.default_rng(1)
    truth, approx, obs = network(rng)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    res = adjust_block(approx, obs, fixed, BlockConfig())
    k = 30
    R = res.poses.rotation_matrix[k]
    np.testing.assert_allclose(res.cov_position[k], R @ res.cov_xi[k, :3, :3] @ R.T)
    assert np.all(res.sigma_position_m[0] == 0)
    # sigma grows away from the datum
    assert res.sigma_position_m[30].max() > res.sigma_position_m[2].max()


def test_variance_components_rescale_a_too_optimistic_group():
    """Trajectory links claim 3x better than they are: the estimated component corrects the sigmas."""
    rng = np.random.default_rng(5)
    n = 60
    truth = true_stations(n, rng)
    true_cov_t = np.diag(np.square([6e-3] * 3 + [1e-3] * 3))
    claimed_info_t = np.linalg.inv(true_cov_t / 9.0)
    cov_p = np.diag(np.square([1e-3] * 3 + [1e-4] * 3))
    obs = []
    for i in range(n - 1):
        obs.append(observe(truth, i, i + 1, true_cov_t, ObservationKind.TRAJECTORY, rng, info=claimed_info_t))
        # the plane links are redundant among themselves, so each group's variance is estimable
        obs.append(observe(truth, i, i + 1, cov_p, ObservationKind.PLANES, rng))
        if i + 2 < n:
            obs.append(observe(truth, i, i + 2, cov_p, ObservationKind.PLANES, rng))
    fixed = np.zeros(n, dtype=bool)
    fixed[0] = True
    res = adjust_block(truth, obs, fixed, BlockConfig(variance_components=True, data_snooping=False))
    assert res.variance_components["trajectory"] == pytest.approx(9.0, rel=0.35)
    assert res.variance_components["planes"] == pytest.approx(1.0, rel=0.35)


def test_a_right_model_at_low_redundancy_is_not_inflated_on_average():
    """Four position observations of a rigid network (redundancy ~6, like four control points as
    the only datum), drawn from their own model: the STATION component stays 1 (it was inflated
    whenever the chi-square/6 draw exceeded 1, in about 40% of the draws)."""
    inflated = 0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        n = 12
        truth = true_stations(n, rng)
        cov_p = np.diag(np.square([2e-4] * 3 + [2e-5] * 3))
        obs = [observe(truth, i, j, cov_p, ObservationKind.PLANES, rng) for i in range(n) for j in range(i + 1, n)]
        info = np.zeros((6, 6))
        info[:3, :3] = np.eye(3) / 0.003**2
        for k in (0, 3, 6, 9):
            Z = Pose(truth.quat_wxyz[k], truth.t_xyz[k] + truth[k].rotation_matrix @ rng.normal(0, 0.003, 3))
            obs.append(RelativeObservation(ObservationKind.STATION, k, -1, Z, info, 3))
        res = adjust_block(truth, obs, np.zeros(n, dtype=bool), BlockConfig(data_snooping=False))
        inflated += res.variance_components["station"] > 1.0
    assert inflated <= 1


def test_variance_components_inflate_only_where_the_group_test_rejects():
    def group(kind, r, vtpv_each):
        return [ObservationTest(k, kind, k, -1, float("nan"), 3, 1.0, float("nan"), False, vtpv_each) for k in range(r)]

    weights = {"station": 1.0, "planes": 1.0}
    # r = 6 at 1.8 times the expected: chance (p = 0.06), kept; at 5 times: too optimistic, inflated
    assert variance_components(group(ObservationKind.STATION, 6, 1.8), weights, 0.001)["station"] == 1.0
    assert variance_components(group(ObservationKind.STATION, 6, 5.0), weights, 0.001)["station"] == pytest.approx(0.2)
    # a large group: 1.5 times is far beyond chance
    planes = variance_components(group(ObservationKind.PLANES, 500, 1.5), weights, 0.001)["planes"]
    assert planes == pytest.approx(1 / 1.5)


def test_variance_components_lower_only_the_kinds_whose_whole_error_shows():
    def group(kind, r, vtpv_each):
        return [ObservationTest(k, kind, k, -1, float("nan"), 1, 1.0, float("nan"), False, vtpv_each) for k in range(r)]

    weights = {"plane": 1.0, "planes": 1.0}
    tests = group(ObservationKind.PLANE, 300, 0.5) + group(ObservationKind.PLANES, 300, 0.5)
    new = variance_components(tests, weights, 0.001, frozenset({"plane"}))
    assert new["plane"] == pytest.approx(2.0)  # half the expected squares: the weight doubled
    assert new["planes"] == 1.0  # the links' errors are shared: never below the a-priori model
    # at a hundredth of the expected squares the weight stops at MAX_WEIGHT_GAIN; a scan plane
    # group takes its estimate also where a test could not tell it from 1 (0.95 at r = 300), and
    # below 1 where its residuals are larger than its model
    assert variance_components(group(ObservationKind.PLANE, 300, 0.01), weights, 0.001,
                               frozenset({"plane"}))["plane"] == MAX_WEIGHT_GAIN
    assert variance_components(group(ObservationKind.PLANE, 300, 0.95), weights, 0.001,
                               frozenset({"plane"}))["plane"] == pytest.approx(1.0 / 0.95)
    assert variance_components(group(ObservationKind.PLANE, 300, 1.1), weights, 0.001,
                               frozenset({"plane"}))["plane"] == pytest.approx(1.0 / 1.1)
    # a link group inside the test's band keeps its weight
    assert variance_components(group(ObservationKind.PLANES, 300, 1.1), weights, 0.001,
                               frozenset({"plane"}))["planes"] == 1.0


def test_gross_error_is_found_by_data_snooping():
    rng = np.random.default_rng(7)
    truth, approx, obs = network(rng)
    bad = next(k for k, o in enumerate(obs) if o.kind is ObservationKind.PLANES and o.i == 20 and o.rank == 6)
    o = obs[bad]
    obs[bad] = RelativeObservation(o.kind, o.i, o.j, o.Z.compose(Pose.exp([0.05, 0, 0, 0, 0, 0])), o.info, o.rank)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    res = adjust_block(approx, obs, fixed, BlockConfig())
    rejected = [t.index for t in res.tests if t.rejected]
    assert bad in rejected
    assert len(rejected) <= 3
    z = normalised_errors(res, truth)
    assert np.sqrt(np.mean(z**2)) < 1.5


def test_disconnected_network_is_a_clear_error():
    rng = np.random.default_rng(2)
    truth, approx, obs = network(rng, n=20)
    obs = [o for o in obs if not (o.i < 10 <= o.j)]  # cut all links across 9/10
    fixed = np.zeros(20, dtype=bool)
    fixed[0] = True
    with pytest.raises(EstimationError, match="1 part\\(s\\) without datum \\(stations 10-19\\)"):
        adjust_block(approx, obs, fixed, BlockConfig())


def test_no_datum_is_a_clear_error():
    rng = np.random.default_rng(2)
    _, approx, obs = network(rng, n=10)
    with pytest.raises(EstimationError, match="no datum"):
        adjust_block(approx, obs, np.zeros(10, dtype=bool), BlockConfig())


@pytest.mark.parametrize("y_info_share", [0.0, 1e-9])
def test_rejections_that_together_leave_a_direction_free_are_taken_back(y_info_share):
    """Stations 2-3 get their y only through the trajectory links 1-2 and 3-4 (their planes leave
    y free), both carrying a 5 cm error in y. Each alone is not their only support, so one round
    of data snooping would reject both and leave 2-3 free in y (singular, or nearly so): the
    round is taken back and the network stays determined."""
    rng = np.random.default_rng(7)
    n = 6
    truth = Pose(np.tile([1.0, 0, 0, 0], (n, 1)), np.column_stack([2.0 * np.arange(n), np.zeros(n), np.zeros(n)]))
    cov_t = np.diag(np.square([1e-3] * 3 + [1e-4] * 3))
    plane_sigma = (5e-4,) * 3 + (5e-5,) * 3
    obs = []
    for i in range(n - 1):
        o = observe(truth, i, i + 1, cov_t, ObservationKind.TRAJECTORY, rng)
        if (i, i + 1) in ((1, 2), (3, 4)):
            o = RelativeObservation(o.kind, o.i, o.j, o.Z.compose(Pose.exp(np.array([0, 0.05, 0, 0, 0, 0]))),
                                    o.info, o.rank)
        obs.append(o)
    for i in range(n):
        for j in range(i + 1, n):
            if (i, j) in ((0, 1), (1, 4), (4, 5)):
                obs.append(observe(truth, i, j, np.diag(np.square(plane_sigma)), ObservationKind.PLANES, rng))
            else:
                p = rank_deficient_obs(truth, i, j, plane_sigma, 1, rng)
                info = p.info.copy()
                info[1, 1] = y_info_share * info[0, 0]
                obs.append(RelativeObservation(p.kind, i, j, p.Z, info, p.rank))
    fixed = np.zeros(n, dtype=bool)
    fixed[0] = True
    result = adjust_block(truth, obs, fixed, BlockConfig())
    sigma = np.sqrt(np.einsum("kii->ki", result.cov_position))
    assert np.all(sigma[1:] < 0.05)  # determined everywhere (free in y: metres, or singular)
    rejected = {(t.i, t.j) for t in result.tests if t.rejected}
    assert not {(1, 2), (3, 4)} <= rejected


def test_drift_rates_measure_the_relative_motion_not_a_turned_walk():
    """A constant rotation error turns the whole walk: the correction's shift then grows along
    the path, but the relative motion between stations has no drift. A true drift velocity of
    0.2 mm/s along x is measured as such."""
    from types import SimpleNamespace

    from kinreg.estimate.drift import DriftRates, estimate_drift_rates
    from kinreg.types import ScanKind, Station

    n = 40
    t = 6.0 * np.arange(n)
    walk = Pose(np.tile([1.0, 0, 0, 0], (n, 1)), np.column_stack([0.4 * t, 20 + 0 * t, 0 * t]))
    stations = [Station(k, f"s{k}", ScanKind.QUASI_STATIC, t[k], t[k] - 3, t[k] + 3, walk[k], 1000)
                for k in range(n)]
    prior = DriftRates(np.full(3, 3e-4), np.full(3, 5e-5), 1e-3, 1e-4)
    turned = Pose.exp(np.array([0, 0, 0, 0, 0, np.radians(0.3)])).compose(walk)  # about the origin, 20 m off
    rates = estimate_drift_rates(stations, SimpleNamespace(poses=turned, poses_initial=walk, tests=()), prior,
                                 floor_share=0.01)
    assert np.all(rates.pos_m_per_s < 1e-5)  # 0.3 deg x 2.4 m a step would read 2 mm/s
    drifted = Pose(walk.quat_wxyz, walk.t_xyz + np.column_stack([2e-4 * t, 0 * t, 0 * t]))
    rates = estimate_drift_rates(stations, SimpleNamespace(poses=drifted, poses_initial=walk, tests=()), prior,
                                 floor_share=0.01)
    assert rates.pos_m_per_s[0] == pytest.approx(2e-4, rel=1e-6)
    assert rates.pos_m_per_s[1] < 1e-5
    rates = estimate_drift_rates(stations, SimpleNamespace(poses=drifted, poses_initial=walk, tests=()), prior,
                                 floor_share=0.25)
    assert rates.pos_m_per_s[1] == pytest.approx(0.25 * 3e-4)  # never below the share of the prior


def _shifted(poses: Pose, shift) -> Pose:
    return Pose(poses.quat_wxyz, poses.t_xyz + np.asarray(shift))


def test_survey_coordinates_converge_as_fast_and_to_the_same_result():
    # At UTM-sized coordinates (500 km, 5,400 km) a position's last bit is ~1e-9 m; the solver
    # works about a local origin and stops on the cost, so it converges as the local network does.
    rng = np.random.default_rng(3)
    truth, approx, obs = network(rng)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    local = adjust_block(approx, obs, fixed, BlockConfig())
    far = adjust_block(_shifted(approx, [500_000.0, 5_400_000.0, 300.0]), obs, fixed, BlockConfig())
    assert not local.failed and not far.failed
    assert far.iterations <= local.iterations + 1
    np.testing.assert_allclose(far.poses.t_xyz - [500_000.0, 5_400_000.0, 300.0], local.poses.t_xyz, atol=1e-7)
    assert far.sigma0 == pytest.approx(local.sigma0, rel=1e-6)


def test_an_adjustment_that_does_not_converge_is_a_failure_never_a_pass():
    rng = np.random.default_rng(4)
    truth, approx, obs = network(rng)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    result = adjust_block(approx, obs, fixed, BlockConfig(max_iterations=1, data_snooping=False,
                                                          variance_components=False))
    assert result.failed and result.failure == "no convergence after 1 iterations"
    assert not result.global_test_passed
    assert not adjust_block(approx, obs, fixed, BlockConfig()).failed


def test_a_plain_step_that_cannot_lower_the_cost_at_the_minimum_ends_the_adjustment(monkeypatch):
    # Near the minimum the undamped step (1e-9 m) may raise the cost by rounding; damping it only
    # shrinks it, so retrying up to the largest damping (and factorising once more for the
    # covariances) is wasted: at 235 M points 78 of 116 factorisations. Seed 0 is such a network.
    import kinreg.estimate.normal as normal

    damping = []
    factorize = normal.NormalEquations.factorize

    def counted(self, blocks, lam=0.0):
        damping.append(lam)
        return factorize(self, blocks, lam)

    monkeypatch.setattr(normal.NormalEquations, "factorize", counted)
    rng = np.random.default_rng(0)
    truth, approx, obs = network(rng)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    result = adjust_block(approx, obs, fixed, BlockConfig(data_snooping=False, variance_components=False))
    assert not result.failed
    assert damping == [0.0] * result.iterations  # one undamped factor per iteration, nothing else
    # the same minimum as a tight run that takes every step it can
    tight = adjust_block(result.poses, obs, fixed, BlockConfig(data_snooping=False, variance_components=False))
    np.testing.assert_allclose(tight.poses.t_xyz, result.poses.t_xyz, atol=1e-9)
    np.testing.assert_allclose(tight.cov_xi, result.cov_xi, rtol=1e-6, atol=1e-15)


def test_the_damped_step_recovers_from_a_start_where_gauss_newton_overshoots():
    # Headings 90 deg off: the linearisation is poor, a full Gauss-Newton step can raise the
    # cost; the damped solver must still reach the truth (within the observations' noise).
    rng = np.random.default_rng(5)
    truth, approx, obs = network(rng, n=20)
    turn = Pose.exp(np.tile([0, 0, 0, 0, 0, np.radians(90.0)], (len(approx), 1)))
    start = Pose(np.concatenate([truth.quat_wxyz[:1], approx.compose(turn).quat_wxyz[1:]]), approx.t_xyz)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    result = adjust_block(start, obs, fixed, BlockConfig(max_iterations=100, data_snooping=False))
    assert not result.failed
    assert np.max(np.linalg.norm(result.poses.t_xyz - truth.t_xyz, axis=1)) < 0.05


def test_a_plane_link_anywhere_along_its_free_direction_moves_nothing():
    # A link's planes leave a direction free (a corridor); its pose there is whatever its prior
    # gave, metres off after a large drift. The information is zero along it, so the adjustment
    # must not depend on it: not through the residual's rotation (the SE(3) log turned a 7 m
    # free shift into 3.5 mm a milliradian across it), nor in how fast it converges.
    rng = np.random.default_rng(11)
    truth, approx, obs = network(rng, n=30)
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    free = [k for k, o in enumerate(obs) if o.kind is ObservationKind.PLANES and o.rank == 5]
    assert free
    far = list(obs)
    for k in free:  # 7 m further along the free axis (x of station i's frame)
        far[k] = RelativeObservation(obs[k].kind, obs[k].i, obs[k].j,
                                     Pose(obs[k].Z.quat_wxyz, obs[k].Z.t_xyz + obs[k].Z.rotation_matrix @ [7.0, 0, 0]),
                                     obs[k].info, obs[k].rank)
    cfg = BlockConfig(data_snooping=False, variance_components=False)
    near_result, far_result = adjust_block(approx, obs, fixed, cfg), adjust_block(approx, far, fixed, cfg)
    assert not near_result.failed and not far_result.failed
    assert far_result.iterations <= near_result.iterations + 1
    np.testing.assert_allclose(far_result.poses.t_xyz, near_result.poses.t_xyz, atol=1e-7)
    assert far_result.sigma0 == pytest.approx(near_result.sigma0, rel=1e-6)


def _one_observation(kind, twist):
    from kinreg.estimate import block

    rng = np.random.default_rng(2)
    poses = Pose.exp(rng.normal(0.0, [3.0, 3.0, 0.5, 0.3, 0.3, 1.0], (2, 6)))
    j = -1 if kind is ObservationKind.STATION else 1
    rel = poses[0] if j < 0 else poses[0].inverse().compose(poses[1])
    Z = rel.compose(Pose.exp(twist))
    active = block._arrays([RelativeObservation(kind, 0, j, Z, np.eye(6), 6)], np.ones(1, dtype=bool),
                           -np.ones(2, dtype=int), {k.value: 1.0 for k in ObservationKind})
    return poses, rel, Z, active


@pytest.mark.parametrize("kind", [ObservationKind.PLANES, ObservationKind.FRAME, ObservationKind.STATION,
                                  ObservationKind.PLANE_FLOOR])
def test_pose_residual_jacobians_hold_across_a_large_free_shift(kind):
    # The residual (translation difference in Z's axes, rotation vector of Z^-1 rel; a scan plane's
    # tilts and offset, kinreg.estimate.block._scan_plane_residuals) against finite differences,
    # 7 m off along x and 1 mrad turned: every kind's Jacobians are exact, however large the shift
    # (the SE(3) log's were off by half of it, 3.5; the identity for the second station's, taken
    # before, by 1e-3 here, and its Gauss-Newton did not converge on held-out runs).
    from kinreg.estimate import block

    poses, rel, Z, active = _one_observation(kind, np.r_[-7.0, 0.02, -0.01, 4e-4, -6e-4, 7.5e-4])
    velocity = np.zeros((0, 6))
    e0, J = block._linearise(poses, velocity, active)
    if kind is ObservationKind.PLANE_FLOOR:
        n = Z.rotation_matrix.T @ rel.rotation_matrix[:, 2]
        np.testing.assert_allclose(e0[0], [0, 0, n @ (Z.rotation_matrix.T @ (rel.t_xyz - Z.t_xyz)), -n[1], n[0], 0],
                                   atol=1e-12)
    else:
        np.testing.assert_allclose(e0[0, :3], Z.rotation_matrix.T @ (rel.t_xyz - Z.t_xyz), atol=1e-12)
    for node in (0,) if kind is ObservationKind.STATION else (0, 1):
        numeric = np.zeros((6, 6))
        for axis in range(6):
            step = np.zeros((2, 6))
            step[node, axis] = 1e-6
            ahead, _ = block._linearise(poses.compose(Pose.exp(step)), velocity, active, jacobians=False)
            back, _ = block._linearise(poses.compose(Pose.exp(-step)), velocity, active, jacobians=False)
            numeric[:, axis] = (ahead[0] - back[0]) / 2e-6
        np.testing.assert_allclose(J[0, node], numeric, atol=1e-7)


def _inverse_adjoint(T: Pose) -> np.ndarray:
    """Ad(T^-1), twists (rho, phi): a left twist of T as its right twist."""
    from kinreg.geometry import skew

    R = T.rotation_matrix
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R.T
    A[:3, 3:] = skew(-R.T @ T.t_xyz) @ R.T
    return A


@pytest.mark.parametrize("kind", [ObservationKind.PLANES, ObservationKind.FRAME])
def test_one_motion_of_both_stations_leaves_a_relative_residual_as_it_is(kind):
    # The datum's gauge: moving the whole network (here both stations, by one object-frame twist,
    # 8 km from the origin) is not observed by a relative observation, also in its Jacobians; a
    # first slot exact against an identity second slot made the turn of a 100,000-station network
    # about its datum look observed (sigmas 73 mm instead of metres, errors 1.7 sigma).
    from kinreg.estimate import block

    poses, rel, Z, active = _one_observation(kind, np.r_[-7.0, 0.02, -0.01, 4e-3, -6e-3, 7.5e-3])
    far = Pose(poses.quat_wxyz, poses.t_xyz + [8000.0, 3000.0, 0.0])
    e0, J = block._linearise(far, np.zeros((0, 6)), active)
    motion = np.r_[0.0, 0.0, 0.0, 1.0, -2.0, 0.5]  # a turn about the object frame's origin
    xi = np.array([_inverse_adjoint(far[k]) @ motion for k in range(2)])  # each station's right twist
    np.testing.assert_allclose(J[0, 0] @ xi[0] + J[0, 1] @ xi[1], 0.0, atol=1e-6 * np.abs(J[0, 0] @ xi[0]).max())


def _recorded_block(name: str):
    """A block adjustment's input recorded from a run (poses, observations, held stations)."""
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / name)
    obs = []
    for k in range(len(d["kind"])):
        kind = ObservationKind(str(d["kind"][k]))
        step = d["step_obj"][k]
        obs.append(RelativeObservation(
            kind, int(d["i"][k]), int(d["j"][k]), Pose(d["Z_quat_wxyz"][k], d["Z_t_xyz"][k]), d["info"][k],
            int(d["rank"][k]), dt_s=float(d["dt_s"][k]),
            decay=d["decay"][k] if kind is ObservationKind.DRIFT else 0.0, coupling=float(d["coupling"][k]),
            step_obj=None if np.isnan(step).any() else step))
    return Pose(d["pose_quat_wxyz"], d["pose_t_xyz"]), obs, d["held"]


@pytest.mark.parametrize("name", ["block_gnss_ins_tilted_crawl.npz", "block_heldout_plane_nodes.npz",
                                  "block_heldout_gnss_ins_valley.npz"])
def test_recorded_blocks_that_did_not_converge_converge(name):
    # Recorded from runs that ended "no convergence after 50 iterations" (exit 1): the tilted head
    # with GNSS/INS-like drift (medium class, seed 1; a relinking round's block), the held-out
    # building (world, seed 4; the final block, with plane nodes) and (GNSS/INS, seed 4; the first
    # block). The identity taken for the second station's Jacobian put Gauss-Newton's fixed point
    # off the minimum, a scan plane's offset at its node's origin let the origin slide along the
    # plane, and damping from 1e-4 shrank every step in a curved valley to a hundredth.
    poses, obs, held = _recorded_block(name)
    result = adjust_block(poses, obs, held, BlockConfig(max_iterations=50))
    assert not result.failed and result.iterations < 10


def test_a_recorded_block_whose_first_minimum_is_far_along_a_weak_frame_converges_with_the_defaults():
    # Recorded from the held-out building (world, medium class, seed 5; the first block), which
    # ended "no convergence after 50 iterations" (exit 1). One scan frame is fixed along x to 0.8 m
    # by its own planes (they hardly face x), and a wrong link (rejected later) pulls it there:
    # the first round's minimum is far along a curved valley, 71 iterations of steadily falling
    # cost. Then snooping rejects the link and the next rounds take 19, 5 and 3.
    import kinreg.estimate.block as block

    rounds = []
    lm = block._levenberg_marquardt

    def counted(*args, **kwargs):
        out = lm(*args, **kwargs)
        rounds.append((out[1], out[3]))
        return out

    poses, obs, held = _recorded_block("block_heldout_world_far_minimum.npz")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(block, "_levenberg_marquardt", counted)
        result = adjust_block(poses, obs, held, BlockConfig())
    assert not result.failed and result.global_test_passed
    assert rounds[0][0] > 50 and all(converged for _, converged in rounds)
    assert any(t.rejected for t in result.tests)
    assert adjust_block(poses, obs, held, BlockConfig(max_iterations=50)).failed


def test_an_adjustment_at_its_minimum_to_a_thousandth_of_a_sigma_has_converged(monkeypatch):
    # Where the Jacobians are not quite the residuals' (here the identity for the second station's
    # but a FRAME tie's, and damping from 1e-4, as kinreg had it before), the undamped step near
    # the minimum raised the cost by 1.6e-7 where the model said 5e-10 was left, and the damped
    # steps crawled by 5e-9 m an iteration, above the 1e-9 m test, to the iteration limit. The
    # Newton decrement ends it.
    import kinreg.estimate.block as block

    exact = block._pose_residuals

    def approximate(poses, R, velocity, a, p, e, J):
        exact(poses, R, velocity, a, p, e, J)
        if J is not None:
            at = np.arange(p.start, p.stop) if isinstance(p, slice) else p
            rows = at[~a.station[at] & (a.kinds[at] != ObservationKind.FRAME.value)]
            J[rows, 0] = np.linalg.solve(J[rows, 1], J[rows, 0])  # -Ad(rel^-1): the second's taken out
            J[rows, 1] = np.eye(6)

    monkeypatch.setattr(block, "_pose_residuals", approximate)
    monkeypatch.setattr(block, "_FIRST_DAMPING", 1e-4)  # and the damping as it started then
    poses, obs, held = _recorded_block("block_gnss_ins_tilted_crawl.npz")
    config = BlockConfig(max_iterations=50)
    result = adjust_block(poses, obs, held, config)
    assert not result.failed and result.iterations < 10
    monkeypatch.setattr(block, "_DECREMENT", 0.0)  # without the model's own test: the crawl
    crawl = adjust_block(poses, obs, held, config)
    assert crawl.failed and crawl.failure == "no convergence after 50 iterations"
    # and it stopped where 40 more iterations would have left it, to the micrometre
    np.testing.assert_allclose(result.poses.t_xyz, crawl.poses.t_xyz, atol=1e-6)
    assert result.sigma0 == pytest.approx(crawl.sigma0, rel=1e-6)


def test_a_round_that_does_not_converge_ends_the_adjustment_failed():
    # Variance components and data snooping drawn from an unconverged round's residuals steer
    # the next rounds, which may converge somewhere wrong and pass: a held-out run (world, seed 5)
    # ended 63 mm off with its global test passed. Here the first round needs more than two
    # iterations from the drifted start; the next, warm-started, would converge in two.
    rng = np.random.default_rng(4)
    truth, approx, obs = network(rng)
    obs[5] = observe(truth, obs[5].i, obs[5].j, np.diag([0.05] * 3 + [1e-4] * 3), ObservationKind.PLANES, rng,
                     info=obs[5].info)  # a gross error for the snooping to find
    fixed = np.zeros(len(approx), dtype=bool)
    fixed[0] = True
    result = adjust_block(approx, obs, fixed, BlockConfig(max_iterations=2))
    assert result.failed and result.failure == "no convergence after 2 iterations"
    assert not result.global_test_passed
    assert not any(t.rejected for t in result.tests)  # nothing rejected on an unconverged round
    assert not adjust_block(approx, obs, fixed, BlockConfig()).failed
