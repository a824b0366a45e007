"""Sparse factorisation, solves and the selected inverse against dense linear algebra."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import scipy.sparse as sp

from kinreg.errors import EstimationError
from kinreg.estimate import sparse as ks
from kinreg.estimate.sparse import factorize, selected_inverse

BACKENDS = [pytest.param("cholmod", marks=pytest.mark.skipif(not ks.HAVE_CHOLMOD, reason="no scikit-sparse")),
            "scipy"]
SCALES = np.array([1e6] * 3 + [1e8] * 3)  # information of 1 mm and 0.1 mrad


def survey_network(n_blocks: int = 300, seed: int = 0, datum: bool = True, closures: int = 30):
    """``N`` (6 n x 6 n, csc) and its links (m, 2): a chain linked to 4 successors plus loop closures.

    Every link adds ``[[W, -W], [-W, W]]`` for a random SPD 6 x 6 information ``W`` (so the network
    alone is singular: a common shift of all stations is free); ``datum`` adds a prior on station 0.
    """
    rng = np.random.default_rng(seed)
    chain = [(i, j) for i in range(n_blocks) for j in range(i + 1, min(n_blocks, i + 5))]
    loops = [tuple(sorted(rng.choice(n_blocks, 2, replace=False))) for _ in range(closures)]
    links = np.unique(np.array(chain + loops), axis=0)
    A = rng.normal(size=(len(links), 6, 6))
    W = (A @ A.swapaxes(1, 2) + 0.5 * np.eye(6)) * np.sqrt(SCALES[:, None] * SCALES)
    i, j = links.T
    rows, cols, vals = [], [], []
    for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
        rows.append(np.broadcast_to((6 * a[:, None, None] + np.arange(6)[:, None]), W.shape).ravel())
        cols.append(np.broadcast_to((6 * b[:, None, None] + np.arange(6)), W.shape).ravel())
        vals.append(sign * W.ravel())
    if datum:
        rows.append(np.arange(6))
        cols.append(np.arange(6))
        vals.append(SCALES)
    n = 6 * n_blocks
    N = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return N, links


@pytest.fixture(scope="module")
def network():
    N, links = survey_network()
    Z = np.linalg.inv(N.toarray()).reshape(300, 6, 300, 6)
    return N, links, Z


def _rel(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_selected_inverse_matches_dense_inverse(network, backend):
    N, links, Z = network
    k = np.arange(300)
    # Pairs in both orders: (j, i) must come back as the transpose of (i, j).
    pairs = np.concatenate([links, links[::7, ::-1]])
    factor = factorize(N, backend=backend)
    diag, off = selected_inverse(N, 6, pairs, factor=factor)
    assert diag.shape == (300, 6, 6)
    assert off.shape == (len(pairs), 6, 6)
    assert _rel(diag, Z[k, :, k, :]) < 1e-9
    assert _rel(off, Z[pairs[:, 0], :, pairs[:, 1], :]) < 1e-9
    np.testing.assert_array_equal(diag, diag.swapaxes(1, 2))


@pytest.mark.parametrize("backend", BACKENDS)
def test_selected_inverse_without_factor_and_unlinked_pairs(network, backend, monkeypatch):
    N, _, Z = network
    monkeypatch.setattr(ks, "HAVE_CHOLMOD", backend == "cholmod")
    monkeypatch.setattr(ks, "_fallback_warned", True)
    # (0, 299) is not a block of the factor: answered by solving, still exact.
    pairs = np.array([[0, 299], [5, 6], [120, 3]])
    diag, off = selected_inverse(N, 6, pairs)
    assert _rel(off, Z[pairs[:, 0], :, pairs[:, 1], :]) < 1e-9
    assert _rel(diag[:10], Z[np.arange(10), :, np.arange(10), :]) < 1e-9
    empty = selected_inverse(N, 6, None)[1]
    assert empty.shape == (0, 6, 6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_scalar_ordered_factor_is_refactorised(network, backend):
    N, links, Z = network
    factor = factorize(N, backend=backend, block_size=None)
    _, off = selected_inverse(N, 6, links[:20], factor=factor)
    assert _rel(off, Z[links[:20, 0], :, links[:20, 1], :]) < 1e-9


def test_solving_path_when_recursion_cannot_run(network, monkeypatch):
    N, links, Z = network

    def not_closed(*args):
        raise ks._PatternNotClosedError

    monkeypatch.setattr(ks, "_takahashi", not_closed)
    diag, off = selected_inverse(N, 6, links[:30])
    assert _rel(diag, Z[np.arange(300), :, np.arange(300), :]) < 1e-9
    assert _rel(off, Z[links[:30, 0], :, links[:30, 1], :]) < 1e-9


@pytest.mark.parametrize("backend", BACKENDS)
def test_solve_matches_dense_solve(network, backend):
    N, _, _ = network
    Nd = N.toarray()
    b = np.random.default_rng(1).normal(size=(1800, 3)) * np.tile(np.sqrt(SCALES), 300)[:, None]
    factor = factorize(N, backend=backend)
    x = factor.solve(b)
    x_ref = np.linalg.solve(Nd, b)
    assert x.shape == (1800, 3)
    assert _rel(x, x_ref) < 1e-9
    assert _rel(factor.solve(b[:, 0]), x_ref[:, 0]) < 1e-9
    with pytest.raises(ValueError, match="right-hand side"):
        factor.solve(b[:10])


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("n_blocks", [12, 300])
def test_singular_datum_raises(backend, n_blocks):
    N, links = survey_network(n_blocks, datum=False, closures=n_blocks // 10)
    with pytest.raises(EstimationError, match="datum is not fixed"):
        factorize(N, backend=backend)
    with pytest.raises(EstimationError, match="datum is not fixed"):
        selected_inverse(N, 6, links, factor=None)


@pytest.mark.parametrize("backend", BACKENDS)
def test_negative_definite_raises(backend):
    with pytest.raises(EstimationError, match="not positive definite"):
        factorize(-sp.eye(12, format="csc"), backend=backend)
    N = sp.csc_matrix(np.kron(np.eye(2), np.array([[1.0, 2.0], [2.0, 1.0]])))
    with pytest.raises(EstimationError):
        factorize(N, backend=backend, block_size=2)


def test_scipy_backend_warns_once(network, monkeypatch, caplog):
    N, _, _ = network
    monkeypatch.setattr(ks, "_fallback_warned", False)
    with caplog.at_level(logging.WARNING, logger="kinreg.estimate.sparse"):
        factorize(N, backend="scipy")
        factorize(N, backend="scipy")
    messages = [r.getMessage() for r in caplog.records if r.name == "kinreg.estimate.sparse"]
    assert messages == [ks.FALLBACK_WARNING]


def test_fallback_when_cholmod_missing(network, monkeypatch, caplog):
    N, _, _ = network
    monkeypatch.setattr(ks, "HAVE_CHOLMOD", False)
    monkeypatch.setattr(ks, "_fallback_warned", False)
    with caplog.at_level(logging.WARNING, logger="kinreg.estimate.sparse"):
        assert factorize(N).backend == "scipy"
    assert "CHOLMOD" in caplog.text
    with pytest.raises(ImportError):
        factorize(N, backend="cholmod")


def test_bad_arguments(network):
    N, _, _ = network
    with pytest.raises(ValueError, match="multiple"):
        factorize(N[:1799, :1799], backend="scipy")
    with pytest.raises(ValueError, match="square"):
        factorize(N[:, :1794])
    with pytest.raises(ValueError, match="out of range"):
        selected_inverse(N, 6, np.array([[0, 300]]))


def _takahashi_by_columns(L, d, bs):
    """The recursion one block column at a time (as before the supernodal batches): the reference."""
    ptr, rows, blocks_T = ks._block_structure(L, bs)
    blocks = blocks_T.swapaxes(1, 2)
    nb = len(ptr) - 1
    Ljj_inv = np.linalg.inv(blocks[ptr[:-1]])
    Dinv = Ljj_inv.swapaxes(1, 2) @ (Ljj_inv / d.reshape(nb, bs, 1))
    col_of = np.repeat(np.arange(nb), np.diff(ptr))
    U = blocks @ Ljj_inv[col_of]
    Z = np.empty_like(U)
    lookup = {(int(c), int(rows[k])): k for c in range(nb) for k in range(ptr[c], ptr[c + 1])}
    for J in range(nb - 1, -1, -1):
        S = np.arange(ptr[J] + 1, ptr[J + 1])
        if not len(S):
            Z[ptr[J]] = Dinv[J]
            continue
        R = rows[S]
        M = np.block([[Z[lookup[(min(a, b), max(a, b))]] if a >= b else Z[lookup[(a, b)]].T
                       for b in R] for a in R])
        Z_SJ = -(M @ U[S].reshape(-1, bs))
        Z[S] = Z_SJ.reshape(-1, bs, bs)
        Z[ptr[J]] = Dinv[J] - U[S].reshape(-1, bs).T @ Z_SJ
    return Z


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("n_blocks", "closures"), [(120, 10), (160, 80)])
def test_supernodal_recursion_matches_column_recursion(backend, n_blocks, closures):
    # Many loop closures make wide supernodes (padded batches of several sizes).
    N, _ = survey_network(n_blocks, seed=3, closures=closures)
    L, d, _ = factorize(N, backend=backend).lower()
    ptr, rows, Z = ks._takahashi(ks._block_structure(L, 6), d, 6)
    sizes = {(pc, pr) for _, _, pc, pr in ks._batches(ptr, rows, np.diff(ptr) - 1, 6)}
    assert len(sizes) > 3
    ref = _takahashi_by_columns(L, d, 6)
    assert _rel(Z, ref) < 1e-11


def test_block_pattern_leaves_N_alone(network):
    N, links, _ = network
    before = (N.indptr.copy(), N.indices.copy(), N.data.copy())
    B = ks._block_pattern(N, 6)
    assert all(np.array_equal(a, b) for a, b in zip(before, (N.indptr, N.indices, N.data), strict=True))
    expected = np.zeros((300, 300), dtype=bool)
    expected[links[:, 0], links[:, 1]] = expected[links[:, 1], links[:, 0]] = True
    np.testing.assert_array_equal(B.toarray() > 0, expected)
