"""Sparse normal equations: factorisation, solves and selected blocks of the inverse.

The block adjustment has 6 unknowns per station (3 translation, 3 rotation) and thousands of
stations, so ``N`` is large, sparse and block structured. This module factorises ``N`` once
(:func:`factorize`), solves with the factor, and computes the per-station covariances -- the
diagonal ``6 x 6`` blocks of ``N^-1`` and the blocks for directly linked station pairs -- without
forming the dense inverse (:func:`selected_inverse`).

Two backends:

- ``"cholmod"``: CHOLMOD through scikit-sparse (the optional ``kinreg[cholmod]`` extra).
- ``"scipy"``: SuperLU (``scipy.sparse.linalg.splu``) used as a symmetric ``L D L^T`` factorisation:
  a symmetric fill-reducing ordering, no row pivoting (``diag_pivot_thresh=0``), so that
  ``U = D L^T``. Slower, but needs nothing beyond scipy.

The selected inverse uses the Takahashi recursion on the block pattern of the factor: with
``P N P^T = L D L^T`` written in blocks as ``U Db U^T`` (``U`` unit block lower triangular), the
inverse ``Z`` restricted to the pattern of ``L + L^T`` satisfies, column block ``J`` from last to
first, with ``S`` the row blocks of column ``J`` below the diagonal::

    Z[S, J] = -Z[S, S] U[S, J]
    Z[J, J] = Db[J]^-1 - U[S, J]^T Z[S, J]

and every ``Z[S, S]`` block lies inside the pattern again (the pattern of a Cholesky factor is
chordal). The fill-reducing ordering is computed on the block graph, so each station's 6 unknowns
stay together and the recursion runs over ``6 x 6`` blocks. It takes a supernode at a time (a run
of block columns ``C`` sharing the rows ``R`` below them), with ``W = L[R, C] L[C, C]^-1``::

    Z[R, C] = -Z[R, R] W
    Z[C, C] = L[C, C]^-T D_C^-1 L[C, C]^-1 - W^T Z[R, C]

and, since ``R`` are ancestors in the elimination tree, all supernodes of one tree depth in one
batched numpy step (100,000 stations: 41,605 supernodes, 205 depths).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from kinreg.errors import EstimationError
from kinreg.heap import give_back_freed_memory, keep_freed_memory

log = logging.getLogger(__name__)

try:
    from sksparse.cholmod import CholmodError, CholmodNotPositiveDefiniteError, analyze, cholesky

    HAVE_CHOLMOD = True
except ImportError:  # SuiteSparse or the extra is missing: the scipy backend takes over
    HAVE_CHOLMOD = False

try:
    from threadpoolctl import ThreadpoolController
except ImportError:  # a dependency; without it the recursion runs with the BLAS default threads
    ThreadpoolController = None

Backend = Literal["cholmod", "scipy"]

FALLBACK_WARNING = "scikit-sparse (CHOLMOD) not available; using scipy's sparse LU, slower for large networks"

# A pivot of the L D L^T factor at or below this fraction of the matching diagonal entry of N counts as
# zero (it is the pivot of the Jacobi-scaled matrix). Without a datum the last pivots end at rounding
# level -- negative, or 1e-15 .. 1e-13 with the block ordering, up to ~1e-9 with CHOLMOD's simplicial
# scalar ordering on 20,000 stations -- while a fixed datum kept them above 1e-4 in the benchmark
# networks. A numerical test cannot separate a singular datum from an extremely weak network; the
# structural check (every station connected to the datum) belongs to the caller.
PIVOT_RTOL = 1e-10

# Right-hand sides per batch when blocks of the inverse are found by solving (a few MB per batch).
SOLVE_BATCH = 384

# The selected inverse works through the supernodal elimination tree one depth at a time; the
# supernodes of one depth are padded to one of these numbers of column and row blocks (bigger ones
# keep their own) and cut into batches of about _BATCH_BYTES of gathered blocks.
_PAD_SIZES = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96,
                       112, 128, 160, 192, 224, 256])
_BATCH_BYTES = 32 << 20

_fallback_warned = False  # the fallback warning is logged once per process, not once per iteration


def _singular(detail: str) -> EstimationError:
    return EstimationError(
        f"normal matrix is singular or not positive definite: the datum is not fixed ({detail})")


class SparseFactor:
    """A factorisation of a symmetric positive definite ``N`` (n x n), from :func:`factorize`.

    ``backend`` is ``"cholmod"`` or ``"scipy"``; ``block_size`` is the block size the ordering kept
    together (or ``None``). Use :meth:`solve`; :func:`selected_inverse` reads the factor itself.
    """

    def __init__(self, backend: Backend, n: int, block_size: int | None, order: np.ndarray,
                 solve_ordered: Callable[[np.ndarray], np.ndarray],
                 lower: Callable[[], tuple[sp.csc_matrix, np.ndarray, np.ndarray]]) -> None:
        self.backend = backend
        self.n = n
        self.block_size = block_size
        self._order = order  # the factor is of N[order][:, order]
        self._solve_ordered = solve_ordered
        self._lower = lower

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``x`` with ``N x = b``; ``b`` of shape (n,) or (n, k), ``x`` of the same shape."""
        b = np.asarray(b, dtype=float)
        if b.shape[0] != self.n or b.ndim not in (1, 2):
            raise ValueError(f"right-hand side of shape {b.shape} for a {self.n} x {self.n} matrix")
        b_ordered = b[self._order]
        x = np.empty_like(b)
        x[self._order] = np.asarray(self._solve_ordered(b_ordered)).reshape(b_ordered.shape)
        return x

    def lower(self) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        """``(L, d, perm)`` with ``N[perm][:, perm] = L diag(d) L^T``, ``L`` lower triangular (csc)."""
        return self._lower()


def factorize(N: sp.spmatrix | sp.sparray, *, backend: Backend | None = None,
              block_size: int | None = 6) -> SparseFactor:
    """Factorise the symmetric positive definite normal matrix ``N`` (n x n, sparse, csc preferred).

    ``backend``: ``"cholmod"``, ``"scipy"`` or ``None`` (CHOLMOD when scikit-sparse imports, else
    scipy, with one logged warning per process). ``block_size``: the fill-reducing ordering is
    computed on the graph of ``block_size x block_size`` blocks (kinreg: 6 unknowns per station) so
    the factor can serve :func:`selected_inverse`; ``None`` orders single unknowns.

    Raises :class:`EstimationError` if ``N`` is singular or not positive definite (e.g. no station
    fixed), ``ValueError`` if ``N`` is not square or ``n`` is not a multiple of ``block_size``, and
    ``ImportError`` if ``backend="cholmod"`` is asked for where scikit-sparse is missing.
    """
    N = sp.csc_matrix(N, dtype=float)
    n = N.shape[0]
    if N.shape != (n, n):
        raise ValueError(f"normal matrix must be square, got {N.shape}")
    if block_size is not None and (block_size < 1 or n % block_size):
        raise ValueError(f"matrix size {n} is not a multiple of block_size={block_size}")
    if backend is None:
        backend = "cholmod" if HAVE_CHOLMOD else "scipy"
    if backend == "cholmod" and not HAVE_CHOLMOD:
        raise ImportError("backend='cholmod' needs scikit-sparse (pip install 'kinreg[cholmod]')")
    if backend not in ("cholmod", "scipy"):
        raise ValueError(f"unknown backend {backend!r}")
    if backend == "scipy":
        _warn_fallback()
    diag = N.diagonal()
    if n and not np.all(diag > 0):
        k = int(np.argmin(diag))
        raise _singular(f"diagonal entry {k} is {diag[k]:.3g}")

    if block_size is None:
        order = np.arange(n)
        Nq = N
    else:
        block_order = (_block_order_cholmod if backend == "cholmod" else _block_order_scipy)(N, block_size)
        order = (block_size * block_order[:, None] + np.arange(block_size)).ravel()
        Nq = N[order][:, order]
    if backend == "cholmod":
        factor = _factorize_cholmod(Nq, natural=block_size is not None)
    else:
        factor = _factorize_scipy(Nq, natural=block_size is not None)
    solve_ordered, lower_ordered, pivots, perm = factor
    _check_pivots(pivots, Nq.diagonal()[perm])

    def lower() -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        L, d = lower_ordered()
        return L, d, order[perm]

    return SparseFactor(backend, n, block_size, order, solve_ordered, lower)


class BlockPattern:
    """A symmetric positive definite matrix of ``bs x bs`` blocks whose pattern stays while its values
    change (the normal matrix of every Gauss-Newton iteration), factorised many times.

    ``rows``, ``cols`` (m,): the block positions that may be nonzero, either triangle (duplicates
    allowed); the diagonal blocks of all ``n_blocks`` are part of the pattern. :attr:`rows`,
    :attr:`cols` are then the unique lower-triangle blocks (``rows >= cols``) in the order in which
    :meth:`factorize` and :meth:`matrix` take their values (``(len(rows), bs, bs)``, block
    ``N[rows[k], cols[k]]``). The fill-reducing block ordering, the permuted sparse structure and
    (CHOLMOD) the symbolic analysis are made here once; :meth:`factorize` only gathers the values
    and runs the numeric factorisation. Blocks of the pattern that stay zero cost some fill, never
    accuracy.
    """

    def __init__(self, n_blocks: int, rows: np.ndarray, cols: np.ndarray, block_size: int = 6,
                 backend: Backend | None = None) -> None:
        if backend is None:
            backend = "cholmod" if HAVE_CHOLMOD else "scipy"
        if backend == "cholmod" and not HAVE_CHOLMOD:
            raise ImportError("backend='cholmod' needs scikit-sparse (pip install 'kinreg[cholmod]')")
        if backend == "scipy":
            _warn_fallback()
        nb, bs = int(n_blocks), int(block_size)
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        keys = np.unique(np.concatenate([np.maximum(rows, cols) * nb + np.minimum(rows, cols),
                                         np.arange(nb, dtype=np.int64) * (nb + 1)]))
        self.rows, self.cols = np.divmod(keys, nb)
        self.backend: Backend = backend
        self.n_blocks, self.block_size = nb, bs
        self._keys = keys
        self._diag = np.flatnonzero(self.rows == self.cols)  # block i's diagonal block: _diag[i]
        off = self.rows != self.cols
        B = sp.coo_matrix((np.ones(np.count_nonzero(off)), (self.rows[off], self.cols[off])), shape=(nb, nb)).tocsc()
        B = ((B + B.T) > 0).astype(float).tocsc()
        block_order = (_graph_order_cholmod if backend == "cholmod" else _graph_order_scipy)(B)
        del B
        self._order = (bs * block_order[:, None] + np.arange(bs)).ravel()
        where = np.empty(nb, dtype=np.int64)
        where[block_order] = np.arange(nb)  # original block -> its position in the ordering
        # CHOLMOD reads the lower triangle only; SuperLU wants the whole matrix.
        lower = backend == "cholmod"
        self._indptr, self._indices, self._gather = _permuted_structure(
            nb, bs, where[self.rows], where[self.cols], lower)
        self._symbolic = None
        if backend == "cholmod" and nb:
            self._symbolic = analyze(self._permuted(np.zeros((len(keys), bs, bs))), ordering_method="natural")

    def index(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Positions in :attr:`rows`/:attr:`cols` of the blocks ``(rows, cols)`` (either triangle);
        ``ValueError`` for a block outside the pattern."""
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        want = np.maximum(rows, cols) * self.n_blocks + np.minimum(rows, cols)
        pos = np.minimum(np.searchsorted(self._keys, want), len(self._keys) - 1)
        if not np.array_equal(self._keys[pos], want):
            raise ValueError("block outside the pattern")
        return pos

    def matrix(self, blocks: np.ndarray) -> sp.csc_matrix:
        """The whole matrix (csc, original ordering) from the values of the blocks."""
        off = self.rows != self.cols
        r = np.concatenate([self.rows, self.cols[off]])
        c = np.concatenate([self.cols, self.rows[off]])
        v = np.concatenate([blocks, blocks[off].swapaxes(1, 2)])
        bs = self.block_size
        a = np.arange(bs)
        rr = np.broadcast_to(bs * r[:, None, None] + a[:, None], v.shape)
        cc = np.broadcast_to(bs * c[:, None, None] + a[None, :], v.shape)
        n = bs * self.n_blocks
        return sp.csc_matrix((v.ravel(), (rr.ravel(), cc.ravel())), shape=(n, n))

    def diagonal(self, blocks: np.ndarray) -> np.ndarray:
        """The matrix's diagonal (n,) from the values of the blocks."""
        return np.diagonal(blocks[self._diag], axis1=1, axis2=2).ravel()

    def factorize(self, blocks: np.ndarray, damping: float = 0.0) -> SparseFactor:
        """Factorise the matrix with these block values (``(len(rows), bs, bs)``), its diagonal
        raised by ``damping`` times itself (Marquardt). Raises :class:`EstimationError` as
        :func:`factorize` does."""
        n = self.n_blocks * self.block_size
        diag = self.diagonal(blocks)
        if damping:
            blocks = blocks.copy()
            d = np.arange(self.block_size)
            blocks[self._diag[:, None], d, d] += damping * diag.reshape(-1, self.block_size)
            diag = self.diagonal(blocks)
        if n and not np.all(diag > 0):
            k = int(np.argmin(diag))
            raise _singular(f"diagonal entry {k} is {diag[k]:.3g}")
        Nq = self._permuted(blocks)
        if self.backend == "cholmod":
            # One BLAS thread, as in the selected inverse: on the shared machine CHOLMOD's two threads
            # spun waiting on each other (100,000 stations: 1.8-4.1 s CPU per factorisation, against
            # 1.2-1.5 s with one, and no faster in wall time).
            with one_blas_thread(self.n_blocks):
                factor = _factorize_cholmod(Nq, natural=True, symbolic=self._symbolic)
        else:
            factor = _factorize_scipy(Nq, natural=True)
        solve_ordered, lower_ordered, pivots, perm = factor
        _check_pivots(pivots, diag[self._order][perm])
        order = self._order

        def lower() -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
            L, d = lower_ordered()
            return L, d, order[perm]

        return SparseFactor(self.backend, n, self.block_size, order, solve_ordered, lower)

    def _permuted(self, blocks: np.ndarray) -> sp.csc_matrix:
        n = self.n_blocks * self.block_size
        Nq = sp.csc_matrix((blocks.reshape(-1)[self._gather], self._indices, self._indptr), shape=(n, n))
        Nq.has_sorted_indices = True
        return Nq


def _permuted_structure(nb: int, bs: int, R: np.ndarray, C: np.ndarray,
                        lower: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The csc structure of the block matrix in the block ordering: ``(indptr, indices, gather)`` with
    ``data = blocks.ravel()[gather]``. Block k (``rows[k] >= cols[k]``) lies at ordered block
    position (R[k], C[k]); ``lower``: the lower triangle only (in the ordering), else both."""
    src = np.arange(len(R), dtype=np.int64)
    flip = R < C  # stored at (C, R) in the lower triangle, transposed
    if lower:
        R, C = np.maximum(R, C), np.minimum(R, C)
    else:
        off = R != C
        src = np.concatenate([src, src[off]])
        flip = np.concatenate([np.zeros(len(R), dtype=bool), np.ones(np.count_nonzero(off), dtype=bool)])
        R, C = np.concatenate([R, C[off]]), np.concatenate([C, R[off]])
    o = np.lexsort((R, C))
    R, C, src, flip = R[o], C[o], src[o], flip[o]
    per_col = np.bincount(C, minlength=nb)
    local = np.arange(len(C)) - (np.cumsum(per_col) - per_col)[C]  # the block's place in its column
    a = np.arange(bs)[None, None, :]  # row within the block
    b = np.arange(bs)[None, :, None]  # column within the block
    shift = b if lower else 0 * b  # the diagonal block (first in its column) keeps rows a >= b
    counts = (bs * per_col[:, None] - shift[0, :, 0]).ravel()
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    pos = indptr[:-1].reshape(nb, bs)[C][:, :, None] + bs * local[:, None, None] + a - shift
    keep = ~(lower & (R == C)[:, None, None] & (a < b)) if lower else np.ones(pos.shape, dtype=bool)
    keep = np.broadcast_to(keep, pos.shape)
    row = np.broadcast_to(bs * R[:, None, None] + a, pos.shape)
    index_type = np.int32 if max(len(R) * bs * bs, bs * nb) < 2**31 - 1 else np.int64
    source = bs * bs * src[:, None, None] + np.where(flip[:, None, None], bs * b + a, bs * a + b)
    indices = np.empty(indptr[-1], dtype=index_type)
    gather = np.empty(indptr[-1], dtype=index_type)
    indices[pos[keep]] = row[keep]
    gather[pos[keep]] = source[keep]
    return indptr.astype(index_type), indices, gather


def _warn_fallback() -> None:
    global _fallback_warned
    if not _fallback_warned:
        _fallback_warned = True
        log.warning(FALLBACK_WARNING)


def _check_pivots(pivots: np.ndarray, diag: np.ndarray) -> None:
    bad = ~(pivots > PIVOT_RTOL * diag)  # also catches NaN
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise _singular(f"{int(bad.sum())} pivot(s) at or below {PIVOT_RTOL:g} of the diagonal, "
                        f"first {pivots[k]:.3g} against {diag[k]:.3g}")


def _block_pattern(N: sp.csc_matrix, bs: int) -> sp.csc_matrix:
    """The graph of nonzero blocks, (n/bs x n/bs), symmetric, unit entries (no diagonal)."""
    nb = N.shape[0] // bs
    # Block column J is scalar columns bs J .. bs J + bs - 1: their row blocks, duplicates summed
    # away in C (no coordinate arrays of nnz(N) length beyond the row blocks themselves).
    B = sp.csc_matrix((np.ones(N.nnz, dtype=np.int32), N.indices // bs, N.indptr[::bs].copy()),
                     shape=(nb, nb))  # own indptr: summing duplicates rewrites it
    B.sum_duplicates()
    coo = B.tocoo()
    off = coo.row != coo.col
    B = sp.coo_matrix((np.ones(np.count_nonzero(off)), (coo.row[off], coo.col[off])), shape=(nb, nb)).tocsc()
    return ((B + B.T) > 0).astype(float).tocsc()


def _block_order_cholmod(N: sp.csc_matrix, bs: int) -> np.ndarray:
    return _graph_order_cholmod(_block_pattern(N, bs))


def _graph_order_cholmod(B: sp.csc_matrix) -> np.ndarray:
    # CHOLMOD's own choice (AMD, METIS when AMD fills badly) on the block graph: six times smaller
    # than the scalar graph, and it keeps each station's unknowns together. A large network gets
    # nested dissection: AMD on a long network (a walk of lanes) gives an elimination tree as deep
    # as the network is long, and the selected inverse goes down it one depth at a time (100,000
    # stations: 41,000 steps of one supernode each, against 280 batches; 10 s -> 4.8 s, and the
    # numeric factorisation 2.6 s -> 1.4 s, with 20 % more fill).
    B = (B + sp.eye(B.shape[0], format="csc")).tocsc()
    if B.shape[0] >= _MANY_BLOCKS:
        try:
            return np.asarray(analyze(B, ordering_method="nesdis").P(), dtype=np.int64)
        except CholmodError as error:  # CHOLMOD built without METIS (its partitioning library)
            log.debug("nested dissection not available (%s); CHOLMOD's default ordering", error)
    return np.asarray(analyze(B).P(), dtype=np.int64)


def _block_order_scipy(N: sp.csc_matrix, bs: int) -> np.ndarray:
    return _graph_order_scipy(_block_pattern(N, bs))


def _graph_order_scipy(B: sp.csc_matrix) -> np.ndarray:
    # SuperLU's minimum degree on A^T + A, run on a diagonally dominant matrix with the block graph's
    # pattern; scipy exposes no other symmetric fill-reducing ordering.
    nb = B.shape[0]
    M = (sp.diags(np.asarray(B.sum(axis=1)).ravel() + 1.0) - B).tocsc()
    lu = splu(M, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.argsort(lu.perm_c) if nb else np.arange(0)


def _factorize_cholmod(Nq: sp.csc_matrix, natural: bool, symbolic=None):
    try:
        if symbolic is not None:  # the same pattern analysed before: the numeric factorisation only
            f = symbolic.cholesky(Nq)
        else:
            f = cholesky(Nq, ordering_method="natural" if natural else "default")
    except CholmodNotPositiveDefiniteError as error:  # the supernodal factorisation stops at once
        raise _singular(str(error)) from error
    perm = np.asarray(f.P(), dtype=np.int64)

    def lower() -> tuple[sp.csc_matrix, np.ndarray]:
        L = sp.csc_matrix(f.L())
        return L, np.ones(L.shape[0])

    def solve_ordered(b: np.ndarray) -> np.ndarray:
        return f(b)

    return solve_ordered, lower, np.asarray(f.D()), perm


def _factorize_scipy(Nq: sp.csc_matrix, natural: bool):
    # No row pivoting: for an SPD matrix SuperLU then computes P N P^T = L U with U = D L^T.
    try:
        lu = splu(Nq, permc_spec="NATURAL" if natural else "MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except RuntimeError as error:  # "Factor is exactly singular"
        raise _singular(str(error)) from error
    if not np.array_equal(lu.perm_r, lu.perm_c):  # SuperLU left the diagonal: a zero pivot
        raise _singular("zero pivot")
    perm = np.argsort(lu.perm_c)
    pivots = lu.U.diagonal()

    def lower() -> tuple[sp.csc_matrix, np.ndarray]:
        return sp.csc_matrix(lu.L), pivots

    return lu.solve, lower, pivots, perm


def selected_inverse(N: sp.spmatrix | sp.sparray | None, block_size: int = 6, pairs: np.ndarray | None = None,
                     factor: SparseFactor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks of ``N^-1`` and its blocks at the requested block pairs.

    ``N``: symmetric positive definite (n x n, sparse), ``n = n_blocks * block_size``; ``None``
    with a ``factor`` of a block ordering (:meth:`BlockPattern.factorize`). ``pairs``:
    integer array (k, 2) of block indices ``(i, j)`` in the original ordering, normally pairs whose
    block ``N[i, j]`` is nonzero (linked stations). ``factor``: a :func:`factorize` result of the same
    ``N`` to reuse; one factorised with another block size is factorised again.

    Returns ``(diag_blocks, pair_blocks)`` of shapes (n_blocks, bs, bs) and (k, bs, bs):
    ``diag_blocks[i] = N^-1[i, i]`` (symmetric), ``pair_blocks[m] = N^-1[i_m, j_m]``, both in the
    original ordering. Pairs outside the pattern of the factor are still answered, by solving for
    their columns (slower). Raises :class:`EstimationError` if ``N`` is singular (no datum) and
    ``ValueError`` for a block index out of range.
    """
    bs = int(block_size)
    if N is None:  # the factor's matrix (BlockPattern.factorize)
        if factor is None or factor.block_size is None or factor.block_size % bs:
            raise ValueError("selected_inverse without N needs a factor with a block ordering")
        n = factor.n
    else:
        N = sp.csc_matrix(N, dtype=float)
        n = N.shape[0]
    if n % bs:
        raise ValueError(f"matrix size {n} is not a multiple of block_size={bs}")
    nb = n // bs
    pairs = np.zeros((0, 2), dtype=np.int64) if pairs is None else np.asarray(pairs, dtype=np.int64)
    pairs = pairs.reshape(-1, 2)
    if pairs.size and (pairs.min() < 0 or pairs.max() >= nb):
        raise ValueError(f"block pair index out of range 0..{nb - 1}")
    if factor is None or factor.n != n or factor.block_size is None or factor.block_size % bs:
        if factor is not None:
            log.debug("selected_inverse: refactorising with a block ordering (block_size=%d)", bs)
        factor = factorize(N, backend=None if factor is None else factor.backend, block_size=bs)

    L, d, perm = factor.lower()
    by_block = perm.reshape(nb, bs)
    try:
        # The backends may reorder after the block ordering (etree postorder); blocks must survive it.
        first = by_block[:, :1]
        if not (np.array_equal(by_block, first + np.arange(bs)) and np.all(first % bs == 0)):
            raise _PatternNotClosedError
        structure = _block_structure(L, bs)
        del L  # the blocks hold the same numbers
        # Batches of small dense products: BLAS threads gain nothing there, and with the cores
        # busy (a shared machine) they waited on each other: 100,000 stations 8 s -> 27 s.
        with one_blas_thread(nb):
            ptr, rows, Z = _takahashi(structure, d, bs)
    except _PatternNotClosedError:  # not expected with factorize's block ordering, kept as a safety net
        log.debug("selected_inverse: factor not block aligned or pattern not closed, solving instead")
        all_pairs = np.concatenate([np.repeat(np.arange(nb), 2).reshape(-1, 2), pairs])
        blocks = _blocks_by_solving(factor, bs, all_pairs)
        return 0.5 * (blocks[:nb] + blocks[:nb].swapaxes(1, 2)), blocks[nb:]
    block_perm = by_block[:, 0] // bs  # ordered block k is original block block_perm[k]
    iblock = np.empty(nb, dtype=np.int64)
    iblock[block_perm] = np.arange(nb)

    diag_blocks = np.empty((nb, bs, bs))
    diag_blocks[block_perm] = Z[ptr[:-1]]
    diag_blocks = 0.5 * (diag_blocks + diag_blocks.swapaxes(1, 2))

    pair_blocks = np.empty((len(pairs), bs, bs))
    if len(pairs):
        a, b = iblock[pairs[:, 0]], iblock[pairs[:, 1]]
        hi, lo = np.maximum(a, b), np.minimum(a, b)
        pos, found = _lookup(ptr, rows, lo, hi)
        stored = Z[np.where(found, pos, 0)]
        pair_blocks[:] = np.where((a >= b)[:, None, None], stored, stored.swapaxes(1, 2))
        if not np.all(found):
            pair_blocks[~found] = _blocks_by_solving(factor, bs, pairs[~found])
    return diag_blocks, pair_blocks


# From this many blocks on, the recursion runs with one BLAS thread (below, it takes milliseconds).
_MANY_BLOCKS = 10_000


def one_blas_thread(n_blocks: int) -> contextlib.AbstractContextManager:
    """One BLAS thread for a large network's work. threadpoolctl finds the libraries with a ctypes
    callback, in which a KeyboardInterrupt is lost (printed as ignored): a Ctrl-C in that moment
    would let the run go on and end with exit 0. So the libraries are looked up once per process,
    and only for a network large enough to gain from it."""
    if ThreadpoolController is None or n_blocks < _MANY_BLOCKS:
        return contextlib.nullcontext()
    return _blas_controller().limit(limits=1, user_api="blas")


# Threads for the chunks of a large network's per-observation work (numpy lets go of the GIL in its loops).
_THREADS = 2


def in_threads(work: Callable[[int], None], starts: Iterable[int], n_blocks: int) -> None:
    """``work(start)`` for every start, in ``_THREADS`` threads for a network of ``_MANY_BLOCKS`` blocks
    or more (else in order, here). ``work`` must write its own rows only; an exception is raised here."""
    starts = list(starts)
    if n_blocks < _MANY_BLOCKS or len(starts) < 2 or (os.cpu_count() or 1) < 2:
        for start in starts:
            work(start)
        return
    with ThreadPoolExecutor(max_workers=_THREADS, thread_name_prefix="kinreg-chunks") as pool:
        for _ in pool.map(work, starts):
            pass


@contextlib.contextmanager
def kept_heap(n_blocks: int) -> Iterator[bool]:
    """Large allocations from the heap, and freed memory kept in it, while a large network is
    adjusted (:func:`kinreg.heap.keep_freed_memory`; yields whether it was set): at 100,000
    stations 40 s of 92 s CPU were the kernel's (a million page faults), 16 s with this.
    Afterwards :func:`kinreg.heap.give_back_freed_memory`. Not below ``_MANY_BLOCKS`` blocks."""
    if n_blocks < _MANY_BLOCKS or not keep_freed_memory():
        yield False
        return
    try:
        yield True
    finally:
        give_back_freed_memory()


@functools.cache
def _blas_controller():
    """The process's threadpoolctl controller (its library lookup made once)."""
    return ThreadpoolController()


class _PatternNotClosedError(Exception):
    """The factor does not have the block structure the recursion needs."""


def _block_structure(L: sp.csc_matrix, bs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block csc form of a lower triangular ``L`` whose blocks are aligned: ``(ptr, rows, blocks_T)``.

    Column block ``J`` owns entries ``ptr[J]:ptr[J + 1]``, row blocks ``rows`` ascending, the
    diagonal block first; ``blocks_T`` (n_nonzero_blocks, bs, bs) holds the values transposed
    (``blocks_T[k] = L[rows[k], J]^T``, zeros filled in).
    """
    # Block column J of L is block row J of L^T: scipy's BSR conversion (in C, no index arrays of
    # nnz(L) length) does the grouping; L^T of a csc matrix is a csr view, not a copy.
    B = sp.csr_matrix(sp.csc_matrix(L).T).tobsr(blocksize=(bs, bs))
    B.sort_indices()
    return B.indptr.astype(np.int64), B.indices.astype(np.int64), B.data


def _lookup(ptr: np.ndarray, rows: np.ndarray, col: np.ndarray,
            row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of blocks (row, col) in the block csc structure, and whether each exists."""
    nb = len(ptr) - 1
    keys = np.repeat(np.arange(nb, dtype=np.int64), np.diff(ptr)) * nb + rows
    want = col * nb + row
    pos = np.minimum(np.searchsorted(keys, want), len(keys) - 1)
    return pos, keys[pos] == want


def _takahashi(structure: tuple[np.ndarray, np.ndarray, np.ndarray], d: np.ndarray,
               bs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Z = (L diag(d) L^T)^-1`` on the block pattern of ``L``: ``(ptr, rows, Z_blocks)``.

    ``structure`` is :func:`_block_structure` of ``L``; ``Z_blocks[k] = Z[rows[k], J]``.
    """
    ptr, rows, Lt = structure
    nb = len(ptr) - 1
    n_blocks = len(rows)
    below = np.diff(ptr) - 1  # row blocks below the diagonal, per column block
    keys = np.repeat(np.arange(nb, dtype=np.int64), below + 1) * nb + rows
    d_blocks = d.reshape(nb, bs)
    # Z, then the same blocks transposed (Z[I, J] above the diagonal is read from there); each
    # half ends with a zero block that the padding of a batch points to.
    half = n_blocks + 1
    Z2 = np.zeros((2 * half, bs, bs))
    for first, c_true, pc, pr in _batches(ptr, rows, below, bs):
        k = len(first)
        a = np.arange(pc)
        i = np.arange(pr)
        col_ok = a < c_true[:, None]  # (k, pc)
        last = first + c_true - 1
        r_true = below[last]
        row_ok = i < r_true[:, None]  # (k, pr)
        col_ptr = ptr[first[:, None] + np.minimum(a, c_true[:, None] - 1)]  # (k, pc)
        # L[C_a, C_b] (a >= b) is block a - b of column C_b; L[R_i, C_b] follows the supernode's own.
        at_cc = col_ptr[:, None, :] + (a[:, None] - a[None, :])
        ok_cc = col_ok[:, :, None] & col_ok[:, None, :] & (a[:, None] >= a[None, :])
        at_rc = col_ptr[:, None, :] + (c_true[:, None, None] - a) + i[:, None]
        ok_rc = row_ok[:, :, None] & col_ok[:, None, :]
        at_cc = np.where(ok_cc, at_cc, 0)
        at_rc = np.where(ok_rc, at_rc, 0)
        R = np.where(row_ok, rows[np.where(row_ok, ptr[last][:, None] + 1 + i, 0)], -1)
        G = Lt[at_cc]
        G[~ok_cc] = 0.0
        L_CC = G.transpose(0, 1, 4, 2, 3).reshape(k, pc * bs, pc * bs)
        # Padded columns: identity in L and d, zero in L_RC, so they drop out.
        pad = np.repeat(~col_ok, bs, axis=1)
        diag = np.arange(pc * bs)
        L_CC[:, diag, diag] += pad
        G = Lt[at_rc]
        G[~ok_rc] = 0.0
        L_RC = G.transpose(0, 1, 4, 2, 3).reshape(k, pr * bs, pc * bs)
        d_C = np.where(pad, 1.0, d_blocks[np.minimum(first[:, None] + a, nb - 1)].reshape(k, pc * bs))
        Linv = np.linalg.inv(L_CC)
        W = L_RC @ Linv
        # Z[R, R] is complete (R are ancestors); Z[R_i, R_j] is stored at (max, min).
        lo = np.minimum(R[:, :, None], R[:, None, :])
        hi = np.maximum(R[:, :, None], R[:, None, :])
        want = lo * nb + hi
        ok_rr = row_ok[:, :, None] & row_ok[:, None, :]
        pos = np.minimum(np.searchsorted(keys, want), n_blocks - 1)
        if not np.array_equal(keys[pos][ok_rr], want[ok_rr]):
            raise _PatternNotClosedError
        pos = np.where(ok_rr, pos + half * (R[:, :, None] < R[:, None, :]), n_blocks)
        M = Z2[pos].transpose(0, 1, 3, 2, 4).reshape(k, pr * bs, pr * bs)
        Z_RC = -(M @ W)
        Z_CC = Linv.swapaxes(1, 2) @ (Linv / d_C[:, :, None]) - W.swapaxes(1, 2) @ Z_RC
        for at, ok, Zd, p in ((at_rc, ok_rc, Z_RC, pr), (at_cc, ok_cc, Z_CC, pc)):
            blocks = Zd.reshape(k, p, bs, pc, bs).transpose(0, 1, 3, 2, 4)[ok]
            Z2[at[ok]] = blocks
            Z2[half + at[ok]] = blocks.swapaxes(1, 2)
    return ptr, rows, Z2[:n_blocks]


def _batches(ptr: np.ndarray, rows: np.ndarray, below: np.ndarray, bs: int):
    """Supernodes in an order the recursion can take them: ``(first, c, pc, pr)`` batches.

    A supernode is a run of column blocks ``C`` whose row blocks below ``C`` are the same ``R``
    (``first``: its first column block, ``c``: how many). Its ``R`` are ancestors in the elimination
    tree, so supernodes of one tree depth do not need each other: each depth is one step of numpy
    work, split by ``c`` and ``|R|`` padded to ``pc``, ``pr`` (the next of ``_PAD_SIZES``) and so
    that a batch's gathered blocks stay near ``_BATCH_BYTES``.
    """
    nb = len(below)
    if nb == 0:
        return
    first_below = np.where(below > 0, rows[np.minimum(ptr[:-1] + 1, len(rows) - 1)], -1)
    # J and J + 1 share a supernode when J's rows below J + 1 are J + 1's rows below its diagonal.
    joins = (first_below[:-1] == np.arange(1, nb)) & (below[:-1] == below[1:] + 1)
    J = np.flatnonzero(joins)
    if len(J):
        length = below[J] - 1
        offset = np.repeat(np.cumsum(length) - length, length)
        step = np.arange(int(length.sum())) - offset
        differ = rows[np.repeat(ptr[J] + 2, length) + step] != rows[np.repeat(ptr[J + 1] + 1, length) + step]
        owner = np.repeat(np.arange(len(J)), length)
        joins[J[np.unique(owner[differ])]] = False
    starts = np.concatenate([[True], ~joins])
    first = np.flatnonzero(starts)
    last = np.concatenate([first[1:] - 1, [nb - 1]])
    c = last - first + 1
    r = below[last]
    supernode_of = np.cumsum(starts) - 1
    parent = np.where(r > 0, supernode_of[first_below[last]], -1).tolist()
    depth_list = [0] * len(first)
    for k in range(len(first) - 1, -1, -1):  # a parent comes after its children
        if parent[k] >= 0:
            depth_list[k] = depth_list[parent[k]] + 1
    depth = np.asarray(depth_list, dtype=np.int64)
    pc, pr = _padded(c), _padded(r)
    order = np.lexsort((pr, pc, depth))
    key = np.column_stack([depth, pc, pr])[order]
    cuts = np.flatnonzero(np.any(np.diff(key, axis=0) != 0, axis=1)) + 1
    for group in np.split(order, cuts):
        g_c, g_r = int(pc[group[0]]), int(pr[group[0]])
        per_batch = max(1, _BATCH_BYTES // (8 * bs * bs * (g_r * g_r + 2 * g_r * g_c + 2 * g_c * g_c)))
        for start in range(0, len(group), per_batch):
            sel = group[start:start + per_batch]
            yield first[sel], c[sel], g_c, g_r


def _padded(sizes: np.ndarray) -> np.ndarray:
    out = _PAD_SIZES[np.minimum(np.searchsorted(_PAD_SIZES, sizes), len(_PAD_SIZES) - 1)]
    return np.where(sizes > _PAD_SIZES[-1], sizes, out)


def _blocks_by_solving(factor: SparseFactor, bs: int, pairs: np.ndarray) -> np.ndarray:
    """Blocks ``N^-1[i, j]`` for pairs (k, 2) by solving for the columns of the blocks ``j``."""
    out = np.empty((len(pairs), bs, bs))
    cols = np.unique(pairs[:, 1])
    per_batch = max(1, SOLVE_BATCH // bs)
    for start in range(0, len(cols), per_batch):
        batch = cols[start:start + per_batch]
        E = np.zeros((factor.n, len(batch) * bs))
        E[(bs * batch[:, None] + np.arange(bs)).ravel(), np.arange(len(batch) * bs)] = 1.0
        X = factor.solve(E)  # columns of N^-1 for the blocks in this batch
        sel = np.flatnonzero(np.isin(pairs[:, 1], batch))
        k = np.searchsorted(batch, pairs[sel, 1])
        r = bs * pairs[sel, 0][:, None] + np.arange(bs)  # (m, bs) rows
        c = bs * k[:, None] + np.arange(bs)  # (m, bs) columns within X
        out[sel] = X[r[:, :, None], c[:, None, :]]
    return out
