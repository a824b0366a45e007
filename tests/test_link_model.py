"""The links' own estimate of their observations' model (kinreg.estimate.pairwise.estimate_link_model):
planes of real surfaces depart from a plane by more than their points' noise says."""

import dataclasses

import numpy as np
import pytest
from planefixtures import pose, scan_planes
from test_pairwise import DRIFT, MATCH, PAIR, error_twist, noisy_prior

from kinreg.estimate.matching import match_planes
from kinreg.estimate.pairwise import LinkModel, PairInput, adjust_pairs, estimate_link_model, pooled_sigma0
from kinreg.types import LinkStatus

TILT, OFFSET = 1.5e-3, 6e-3  # the surfaces' own departure: far beyond the planes' reported 0.2 mrad / 0.5 mm


def departed(planes, rng, tilt=TILT, offset=OFFSET):
    """Each plane moved by a departure of the surface (tilts about its tangents, offset at its
    centroid) that its covariance does not know of."""
    out = []
    for p in planes:
        a, b = rng.normal(0.0, tilt, 2)
        n = p.normal + a * p.basis_uv[0] + b * p.basis_uv[1]
        n /= np.linalg.norm(n)
        out.append(dataclasses.replace(p, normal=n, d_m=float(n @ p.centroid_xyz - (p.normal @ p.centroid_xyz - p.d_m)
                                                               + rng.normal(0.0, offset))))
    return tuple(out)


def make_pairs(rng, count, departure=True):
    pairs, truth = [], []
    for k in range(count):
        T_obj_i = pose(rng.normal(0, [0.05, 0.05, 0.3]), [4.0, 3.0, 1.4] + rng.normal(0, 0.3, 3))
        T_obj_j = pose(rng.normal(0, [0.05, 0.05, 0.3]), [7.0, 4.0, 1.5] + rng.normal(0, 0.3, 3))
        T_true = T_obj_i.inverse().compose(T_obj_j)
        planes_i, planes_j = scan_planes(T_obj_i, 2 * k, rng), scan_planes(T_obj_j, 2 * k + 1, rng)
        if departure:
            planes_i, planes_j = departed(planes_i, rng), departed(planes_j, rng)
        T_prior = noisy_prior(T_true, 6.0, rng)
        matches = match_planes(planes_i, planes_j, T_prior, MATCH)
        pairs.append(PairInput(2 * k, 2 * k + 1, planes_i, planes_j, T_prior, 6.0, matches))
        truth.append(T_true)
    return pairs, truth


def test_the_departure_of_real_surfaces_is_measured_and_the_links_then_fit():
    pairs, truth = make_pairs(np.random.default_rng(11), 150)
    plain = adjust_pairs(pairs, DRIFT, PAIR)
    sigma0, _ = pooled_sigma0(plain)
    assert sigma0 > 3.0  # the a-priori model does not fit
    model = estimate_link_model(pairs, DRIFT, PAIR)
    assert model.estimated
    assert len(model.departure_tilt_rad) == 3  # a departure per size class of the planes
    assert model.departure_tilt_rad == pytest.approx([TILT] * 3, rel=0.3)
    assert model.departure_offset_m == pytest.approx([OFFSET] * 3, rel=0.3)
    assert model.prior_variance_factor < 1.5  # the trajectory's priors were right
    links = adjust_pairs(pairs, DRIFT, PAIR, model)
    assert 0.85 < pooled_sigma0(links)[0] < 1.15
    assert np.mean([link.status is LinkStatus.OK for link in links]) > 0.97
    chi2 = [error_twist(link.T_i_j, T) @ np.linalg.solve(link.cov_xi, error_twist(link.T_i_j, T))
            for link, T in zip(links, truth, strict=True)]
    assert 0.75 < np.mean(chi2) / 6 < 1.3  # the links' covariances are honest again


def test_a_model_that_fits_is_kept():
    pairs, _ = make_pairs(np.random.default_rng(12), 60, departure=False)
    model = estimate_link_model(pairs, DRIFT, PAIR)
    assert not model.estimated
    assert model.sigma0_a_priori < 1.1
    assert LinkModel().apply(pairs[0].planes_i) == pairs[0].planes_i
