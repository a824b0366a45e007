"""adjust_pairs solves many pairs on stacked arrays: each link must be the one the pair gives alone
(up to rounding), whatever else is in its batch, and each pair's decisions must be its own."""

from dataclasses import replace

import numpy as np
from planefixtures import ROOM
from test_pairwise import DRIFT, MATCH, PAIR, make_pair

from kinreg.estimate.matching import match_planes
from kinreg.estimate.pairwise import PairInput, adjust_pair, adjust_pairs
from kinreg.geometry import pose_sigmas
from kinreg.types import Link, LinkStatus, PlaneMatch


def correlated(planes, rng):
    """The planes with full 3x3 covariances of the same size, as a detector reports them (the
    fixture's are diagonal)."""
    out = []
    for p in planes:
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        out.append(replace(p, cov_uvd=Q @ p.cov_uvd @ Q.T))
    return tuple(out)


def pair_inputs(rng) -> list[PairInput]:
    """Pairs of every kind a batch meets: different numbers of matches, a plane matched twice,
    a wrong match that snooping removes, a link rejected at the snooping cap, a corridor whose
    planes leave one direction undetermined, no match at all, and a prior given by sigmas."""
    pairs = []
    for k in range(3, len(ROOM) + 1):  # 3 ... 8 matches; two pairs of each count
        for _ in range(2):
            planes_i, planes_j, _, T_prior = make_pair(rng)
            planes_i, planes_j = correlated(planes_i, rng), correlated(planes_j, rng)
            matches = match_planes(planes_i, planes_j, T_prior, MATCH)[:k]
            pairs.append(PairInput(0, k, planes_i, planes_j, T_prior, 6.0, matches))
    planes_i, planes_j, _, T_prior = make_pair(rng)
    twin = replace(planes_j[4], plane_id=len(planes_j))  # the floor seen twice in scan j
    matches = (*match_planes(planes_i, planes_j, T_prior, MATCH), PlaneMatch(4, twin.plane_id, 0.0, 0.0, 1.0))
    pairs.append(PairInput(1, 0, planes_i, (*planes_j, twin), T_prior, 6.0, matches))
    planes_i, planes_j, _, T_prior = make_pair(rng)
    wrong = PlaneMatch(4, 7, 0.0, 0.0, 1.0)  # the floor claimed identical with the slanted plane
    pairs.append(PairInput(2, 0, planes_i, planes_j, T_prior, 6.0,
                           (*match_planes(planes_i, planes_j, T_prior, MATCH), wrong)))
    planes_i, planes_j, _, T_prior = make_pair(rng)
    wrongs = tuple(PlaneMatch(a, b, 0.0, 0.0, 1.0) for a, b in ((0, 1), (2, 3), (4, 5), (6, 7)))
    pairs.append(PairInput(3, 0, planes_i, planes_j, T_prior, 6.0,
                           (*match_planes(planes_i, planes_j, T_prior, MATCH), *wrongs)))
    corridor = [ROOM[2], ROOM[3], ROOM[4], ROOM[5]]
    planes_i, planes_j, _, T_prior = make_pair(np.random.default_rng(6), room=corridor)  # rank 5 (test_pairwise)
    pairs.append(PairInput(4, 0, planes_i, planes_j, T_prior, 6.0, match_planes(planes_i, planes_j, T_prior, MATCH)))
    pairs.append(PairInput(5, 0, planes_i, planes_j, T_prior, 6.0, ()))
    planes_i, planes_j, _, T_prior = make_pair(rng)
    pairs.append(PairInput(6, 0, planes_i, planes_j, T_prior, float("inf"),
                           match_planes(planes_i, planes_j, T_prior, MATCH), pose_sigmas(0.2, np.radians(1.0))))
    return pairs


def alone(pair: PairInput) -> Link:
    return adjust_pair(pair.scan_i, pair.scan_j, pair.planes_i, pair.planes_j, pair.T_prior, pair.dt_s,
                       pair.matches, DRIFT, PAIR, sigma_prior=pair.sigma_prior)


def assert_same_link(batched: Link, single: Link) -> None:
    # The decisions are the pair's own ...
    assert (batched.scan_i, batched.scan_j, batched.status) == (single.scan_i, single.scan_j, single.status)
    assert batched.matches == single.matches and batched.rejected == single.rejected
    assert (batched.rank, batched.n_directions, batched.redundancy, batched.global_test_passed) == (
        single.rank, single.n_directions, single.redundancy, single.global_test_passed)
    # ... and the figures agree to rounding.
    close = {"rtol": 1e-9, "atol": 1e-15}
    for T_b, T_s in ((batched.T_i_j, single.T_i_j), (batched.T_i_j_planes, single.T_i_j_planes)):
        np.testing.assert_allclose(T_b.quat_wxyz, T_s.quat_wxyz, **close)
        np.testing.assert_allclose(T_b.t_xyz, T_s.t_xyz, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(batched.cov_xi, single.cov_xi, rtol=1e-9, atol=1e-9 * np.abs(single.cov_xi).max())
    np.testing.assert_allclose(batched.info_planes, single.info_planes, rtol=1e-9,
                               atol=1e-9 * np.abs(single.info_planes).max())
    np.testing.assert_allclose(batched.axis_sigma_planes, single.axis_sigma_planes, rtol=1e-7)
    np.testing.assert_allclose(batched.sigma0, single.sigma0, **close)
    np.testing.assert_allclose(batched.max_normalised_residual, single.max_normalised_residual, **close)


def test_a_batch_gives_each_pair_its_own_link():
    rng = np.random.default_rng(11)
    pairs = pair_inputs(rng)
    singles = [alone(p) for p in pairs]
    statuses = {link.status for link in singles}
    assert {LinkStatus.OK, LinkStatus.REJECTED, LinkStatus.PRIOR_ONLY} <= statuses
    assert any(link.rejected and link.status is LinkStatus.OK for link in singles)
    assert len({len(p.matches) for p in pairs}) >= 6
    assert any(link.rank == 5 for link in singles)
    for order in (np.arange(len(pairs)), rng.permutation(len(pairs))):
        batched = adjust_pairs([pairs[k] for k in order], DRIFT, PAIR)
        assert len(batched) == len(pairs)
        for k, link in zip(order, batched, strict=True):
            assert_same_link(link, singles[k])


def test_a_batch_of_one_and_an_empty_batch():
    rng = np.random.default_rng(12)
    pair = pair_inputs(rng)[7]
    [link] = adjust_pairs([pair], DRIFT, PAIR)
    assert_same_link(link, alone(pair))
    assert adjust_pairs([], DRIFT, PAIR) == []
