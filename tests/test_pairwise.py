import numpy as np
import pytest
from planefixtures import ROOM, pose, scan_planes
from scipy import stats

from kinreg.config import DriftConfig, MatchingConfig, PairwiseConfig
from kinreg.estimate.drift import drift_sigmas
from kinreg.estimate.matching import candidate_pairs, chosen_partners, match_planes
from kinreg.estimate.pairwise import adjust_pair
from kinreg.geometry import Pose
from kinreg.types import LinkStatus, PlaneMatch

DRIFT = DriftConfig()
PAIR = PairwiseConfig()
MATCH = MatchingConfig()


def noisy_prior(T_true: Pose, dt: float, rng) -> Pose:
    return T_true.compose(Pose.exp(rng.normal(0.0, drift_sigmas(dt, DRIFT))))


def error_twist(T_est: Pose, T_true: Pose) -> np.ndarray:
    """The right-perturbation twist from the truth to the estimate (the convention of cov_xi)."""
    return T_true.inverse().compose(T_est).log()


def make_pair(rng, room=ROOM, dt=6.0):
    T_obj_i = pose(rng.normal(0, [0.05, 0.05, 0.3]), [4.0, 3.0, 1.4] + rng.normal(0, 0.3, 3))
    T_obj_j = pose(rng.normal(0, [0.05, 0.05, 0.3]), [7.0, 4.0, 1.5] + rng.normal(0, 0.3, 3))
    T_true = T_obj_i.inverse().compose(T_obj_j)
    planes_i = scan_planes(T_obj_i, 0, rng, room=room)
    planes_j = scan_planes(T_obj_j, 1, rng, room=room)
    return planes_i, planes_j, T_true, noisy_prior(T_true, dt, rng)


def test_matching_finds_every_true_pair_and_nothing_else():
    rng = np.random.default_rng(1)
    planes_i, planes_j, _, T_prior = make_pair(rng)
    matches = match_planes(planes_i, planes_j, T_prior, MATCH)
    assert [(m.plane_i, m.plane_j) for m in matches] == [(k, k) for k in range(len(ROOM))]
    assert all(m.angle_deg < 0.5 and m.offset_m < 0.05 for m in matches)


def test_pairwise_transforms_are_within_their_reported_sigmas():
    rng = np.random.default_rng(2)
    chi2, inside_3sigma = [], []
    for _ in range(600):  # enough that the 99 % criterion is not decided by one or two links
        planes_i, planes_j, T_true, T_prior = make_pair(rng)
        matches = match_planes(planes_i, planes_j, T_prior, MATCH)
        link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, matches, DRIFT, PAIR)
        e = error_twist(link.T_i_j, T_true)
        chi2.append(e @ np.linalg.solve(link.cov_xi, e))
        inside_3sigma.append(np.all(np.abs(e) <= 3 * np.sqrt(np.diag(link.cov_xi))))
        assert link.status is LinkStatus.OK and link.rank == 6 and link.n_directions >= 3
    chi2 = np.array(chi2)
    # at least 99 % of links within their reported 3 sigma on every axis (expected 98.4-99.7 %)
    assert np.mean(inside_3sigma) >= 0.98
    assert np.mean(chi2 <= stats.chi2.ppf(0.9973, 6)) >= 0.99
    # and the sigmas are not too pessimistic either: mean chi2 per dof near 1
    assert 0.8 < chi2.mean() / 6 < 1.25


def test_global_test_and_sigma0_are_consistent():
    rng = np.random.default_rng(3)
    sigma0 = []
    passed = []
    for _ in range(200):
        planes_i, planes_j, _, T_prior = make_pair(rng)
        link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, match_planes(planes_i, planes_j, T_prior, MATCH),
                           DRIFT, PAIR)
        sigma0.append(link.sigma0)
        passed.append(link.global_test_passed)
        assert link.redundancy == 3 * len(link.matches)
    assert 0.9 < np.sqrt(np.mean(np.square(sigma0))) < 1.1
    assert np.mean(passed) > 0.98


def test_injected_wrong_correspondence_is_flagged():
    rng = np.random.default_rng(4)
    planes_i, planes_j, T_true, T_prior = make_pair(rng)
    matches = list(match_planes(planes_i, planes_j, T_prior, MATCH))
    # floor of i claimed identical with the slanted plane of j (plane 7): a wrong match
    wrong = PlaneMatch(4, 7, 0.0, 0.0, 1.0)
    matches.append(wrong)
    link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, tuple(matches), DRIFT, PAIR)
    assert wrong in link.rejected and wrong not in link.matches
    assert link.global_test_passed
    e = error_twist(link.T_i_j, T_true)
    assert np.all(np.abs(e) <= 4 * np.sqrt(np.diag(link.cov_xi)))


def test_subtle_wrong_correspondence_parallel_wall_is_flagged():
    """A match to a parallel plane 3 cm away: too close for the gate, caught by snooping."""
    rng = np.random.default_rng(5)
    room = [*ROOM, ((1, 0, 0), 0.03, (0.03, 6.5, 1.5), (1.0, 1.0))]  # a panel 3 cm off the wall
    planes_i, planes_j, _, T_prior = make_pair(rng, room=room)
    planes_i = planes_i[:-1]  # scan i only sees the wall
    matches = [PlaneMatch(k, k, 0.0, 0.0, 1.0) for k in range(len(ROOM))]
    wrong = PlaneMatch(0, len(ROOM), 0.0, 0.03, 1.0)
    link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, (*matches, wrong), DRIFT, PAIR)
    assert wrong in link.rejected


def test_two_wall_directions_still_solve_and_show_the_weak_direction():
    rng = np.random.default_rng(6)
    corridor = [ROOM[2], ROOM[3], ROOM[4], ROOM[5]]  # walls normal to y, floor and ceiling: x is free
    planes_i, planes_j, T_true, T_prior = make_pair(rng, room=corridor)
    link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, match_planes(planes_i, planes_j, T_prior, MATCH),
                       DRIFT, PAIR)
    assert link.status is LinkStatus.OK and link.n_directions == 2
    assert link.rank == 5  # translation along the corridor is not fixed by the planes
    sigma = np.sqrt(np.diag(link.cov_xi))
    prior = drift_sigmas(6.0, DRIFT)
    # the weak direction (object x, i.e. along the corridor; scan axes are rotated) carries the prior
    T_obj_i_rot = Pose(link.T_i_j.quat_wxyz, np.zeros(3))  # any rotation: use the covariance's eigenvector
    w, V = np.linalg.eigh(link.cov_xi[:3, :3])
    assert np.sqrt(w[-1]) == pytest.approx(prior[0], rel=0.05)
    assert np.sqrt(w[0]) < 0.5 * prior[0]
    assert np.isinf(link.axis_sigma_planes[:3]).any()
    e = error_twist(link.T_i_j, T_true)
    assert e @ np.linalg.solve(link.cov_xi, e) < stats.chi2.ppf(0.999, 6)
    del T_obj_i_rot, sigma


def test_no_match_gives_a_prior_only_link():
    rng = np.random.default_rng(7)
    planes_i, planes_j, _, T_prior = make_pair(rng)
    link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, (), DRIFT, PAIR)
    assert link.status is LinkStatus.PRIOR_ONLY and link.rank == 0
    np.testing.assert_allclose(np.sqrt(np.diag(link.cov_xi)), drift_sigmas(6.0, DRIFT))


def test_plane_only_information_points_to_the_truth():
    """The plane-only estimate ignores the prior: with a badly biased prior it still hits the truth."""
    rng = np.random.default_rng(8)
    planes_i, planes_j, T_true, _ = make_pair(rng)
    biased = T_true.compose(Pose.exp([0.02, -0.02, 0.01, 0.002, 0.0, -0.002]))
    matches = match_planes(planes_i, planes_j, biased, MATCH)
    link = adjust_pair(0, 1, planes_i, planes_j, biased, 6.0, matches, DRIFT, PAIR)
    e = error_twist(link.T_i_j_planes, T_true)
    cov_planes = np.linalg.inv(link.info_planes)
    assert e @ np.linalg.solve(cov_planes, e) < stats.chi2.ppf(0.999, 6)


def test_candidate_pairs_sequence_and_loop_closures():
    positions = np.array([[0, 0, 0], [5, 0, 0], [10, 0, 0], [15, 0, 0], [20, 0, 0], [0.5, 0.5, 0]], float)
    cfg = MatchingConfig(neighbour_depth=1, radius_m=2.0)
    assert candidate_pairs(positions, cfg) == [(0, 1), (0, 5), (1, 2), (2, 3), (3, 4), (4, 5)]


def test_loop_candidates_are_thinned_over_the_passes_of_a_long_run():
    """A path walked 30 times round the same square: every station has loop candidates in every
    other pass. With a budget the candidate pairs are fewer and sequence neighbours all stay; under
    the budget the candidates are those without one."""
    laps, per_lap = 30, 16
    angle = np.linspace(0.0, 2 * np.pi, per_lap, endpoint=False)
    ring = np.column_stack([10 * np.cos(angle), 10 * np.sin(angle), np.zeros(per_lap)])
    rng = np.random.default_rng(3)
    positions = np.concatenate([ring + rng.normal(0.0, 0.3, ring.shape) for _ in range(laps)])
    unlimited = candidate_pairs(positions, MatchingConfig(radius_m=8.0, max_loop_pairs=0))
    thinned = candidate_pairs(positions, MatchingConfig(radius_m=8.0, max_loop_pairs=20))
    loops = np.bincount(np.array([p for p in unlimited if p[1] - p[0] > 4]).ravel())
    assert loops.min() > 60  # the budget binds everywhere
    assert set(thinned) < set(unlimited) and len(thinned) < 0.5 * len(unlimited)
    assert {(i, j) for i, j in unlimited if j - i <= 4} <= set(thinned)  # sequence neighbours all kept
    short = positions[: 3 * per_lap]
    assert candidate_pairs(short, MatchingConfig(radius_m=8.0, max_loop_pairs=20)) == \
        candidate_pairs(short, MatchingConfig(radius_m=8.0, max_loop_pairs=0))


def test_a_station_chooses_the_nearest_of_every_pass_before_a_second_of_any():
    """Station 0 is passed once slowly (30 stations 0.5-0.8 m away) and by 10 quick passes (one
    station each, 2-3 m away): with a budget of 20 it keeps every quick pass and 10 of the slow one,
    where the 20 nearest would all be the slow pass's."""
    far = lambda k: [100.0 + 10 * k, 0.0, 0.0]  # noqa: E731 (stations between the passes)
    positions = [[0.0, 0.0, 0.0]] + [far(k) for k in range(5)]
    slow = list(range(len(positions), len(positions) + 30))
    positions += [[0.5 + 0.01 * k, 0.0, 0.0] for k in range(30)]
    quick = []
    for k in range(10):
        positions.append(far(10 + k))
        quick.append(len(positions))
        positions.append([0.0, 2.0 + 0.1 * k, 0.0])
    partners = np.array(slow + quick)
    chosen = chosen_partners(np.array(positions), 0, partners, 20)
    assert set(quick) <= set(chosen.tolist()) and len(chosen) == 20
    assert set(chosen.tolist()) - set(quick) == set(slow[:10])  # the slow pass's 10 nearest
    assert chosen_partners(np.array(positions), 0, partners, 50).tolist() == partners.tolist()


def test_repeated_and_looped_matches_do_not_break_the_adjustment():
    """Two patches of one wall in each scan, all four cross-matched (a closed loop of conditions,
    seen in a seed-scale run), plus a match stated twice: Q_ww is singular, the adjustment copes."""
    from dataclasses import replace

    rng = np.random.default_rng(9)
    planes_i, planes_j, T_true, T_prior = make_pair(rng)
    extra_i = replace(planes_i[0], plane_id=100)  # a second patch of the same wall
    extra_j = replace(planes_j[0], plane_id=100)
    planes_i, planes_j = (*planes_i, extra_i), (*planes_j, extra_j)
    matches = list(match_planes(planes_i, planes_j, T_prior, MATCH))
    loop = [PlaneMatch(a, b, 0.0, 0.0, 1.0) for a in (0, 100) for b in (0, 100)]
    matches = [m for m in matches if m.plane_i not in (0, 100)] + loop + loop[:1]
    link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, tuple(matches), DRIFT, PAIR)
    assert link.status is LinkStatus.OK
    e = error_twist(link.T_i_j, T_true)
    assert e @ np.linalg.solve(link.cov_xi, e) < stats.chi2.ppf(0.999, 6)


def test_window_deformation_adds_the_drift_over_each_planes_time_offset():
    import dataclasses

    from kinreg.estimate.drift import DriftRates, with_window_deformation

    rng = np.random.default_rng(3)
    T = pose([0.0, 0.0, 0.3], [1.0, 2.0, 0.0])
    planes = scan_planes(T, 0, rng)
    seen = [dataclasses.replace(p, t_offset_s=t) for p, t in zip(planes, (0.0, 2.0, -1.0, 3.0, 0.5, 1.5), strict=False)]
    rates = DriftRates(np.array([1e-3, 2e-3, 0.0]), np.zeros(3), 0.0, 0.0)
    deformed = with_window_deformation(seen, T, rates)
    for before, after in zip(seen, deformed, strict=True):
        n_obj = T.rotation_matrix @ before.normal
        expected = np.sum((n_obj * rates.pos_m_per_s) ** 2) * before.t_offset_s**2
        assert after.cov_uvd[2, 2] - before.cov_uvd[2, 2] == pytest.approx(expected, rel=1e-9, abs=1e-18)
        assert np.allclose(after.cov_uvd[:2, :2], before.cov_uvd[:2, :2])  # no rotation drift given
    assert deformed[0] is seen[0]  # seen at the centre time: unchanged
    turning = DriftRates(np.zeros(3), np.array([0.0, 0.0, 1e-4]), 0.0, 0.0)
    tilted = with_window_deformation(seen, T, turning)
    for before, after in zip(seen, tilted, strict=True):
        n_obj = T.rotation_matrix @ before.normal
        if abs(n_obj[2]) > 0.99:  # a floor or ceiling does not tilt when the scanner turns about z
            assert np.allclose(after.cov_uvd, before.cov_uvd)
        elif before.t_offset_s != 0.0:  # a wall does, by the turn over its time offset
            total = np.trace(after.cov_uvd[:2, :2] - before.cov_uvd[:2, :2])
            assert total == pytest.approx((1e-4 * before.t_offset_s) ** 2, rel=1e-6)


def test_the_solve_steps_agree_with_the_poses_exp_and_log():
    # The pairwise solve steps with its own closed forms of one twist's exp and log (for speed).
    from kinreg.estimate.pairwise import _log, _so3

    rng = np.random.default_rng(7)
    for scale in (1e-9, 1e-6, 1e-3, 0.3):
        xi = rng.normal(0.0, scale, (20, 6))  # the helpers take a stack of twists
        R, J = _so3(xi[:, 3:])
        T = Pose.exp(xi)
        assert np.allclose(R, T.rotation_matrix, rtol=0, atol=1e-15)
        assert np.allclose(R @ R.swapaxes(1, 2), np.eye(3), rtol=0, atol=1e-15)
        assert np.allclose(np.einsum("gij,gj->gi", J, xi[:, :3]), T.t_xyz, rtol=0, atol=1e-15 * max(1.0, scale))
        assert np.allclose(_log(T.rotation_matrix, T.t_xyz), xi, rtol=1e-9, atol=1e-15)
