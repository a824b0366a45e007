"""The block adjustment's normal equations from per-observation blocks on a fixed pattern.

Each observation k touches up to ``slots`` unknown blocks ``cols[k, s]`` (6 unknowns each; -1: a
fixed station or no node) and contributes ``J_ks^T P_k J_kt`` to the block ``N[cols[k, s],
cols[k, t]]`` and ``-J_ks^T P_k e_k`` to ``b``. The pattern of ``N`` is that of all observations
(also those that data snooping takes out later: their blocks stay, zero), so the fill-reducing
ordering and the symbolic factorisation (:class:`~kinreg.estimate.sparse.BlockPattern`) are made
once per adjustment; every Gauss-Newton iteration only computes the blocks (batched 6 x 6
products) and sums them into the pattern's lower triangle (one sparse product per slot pair).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from kinreg.estimate.sparse import BlockPattern, SparseFactor
from kinreg.geometry import FloatArray


@dataclasses.dataclass(frozen=True)
class _SlotPair:
    s: int
    t: int
    rows: np.ndarray  # the observations with both slots free
    flip: np.ndarray  # cols[s] < cols[t]: the block goes to (t, s), transposed
    same: np.ndarray  # cols[s] == cols[t] (s != t): both orders land on one diagonal block
    scatter: sp.csr_matrix  # (pattern blocks, len(rows)): where each product is summed


@dataclasses.dataclass(frozen=True)
class Selection:
    """The scatter of one set of observations (with their ``cols``) into a :class:`NormalEquations`."""

    cols: np.ndarray
    slot_rows: tuple[np.ndarray, ...]  # per slot: the observations with that slot free
    pairs: tuple[_SlotPair, ...]


class NormalEquations:
    """``N`` (in 6 x 6 blocks on a fixed pattern) and ``b`` of the block adjustment.

    ``n_free``: unknown blocks; ``cols`` (k, slots): the unknown block of each observation's slots
    for every observation that may take part (-1: none). ``backend`` as in
    :func:`~kinreg.estimate.sparse.factorize`.
    """

    def __init__(self, n_free: int, cols: np.ndarray, backend: str | None = None) -> None:
        rows_, cols_ = [], []
        for s, t in _slot_pairs(cols.shape[1]):
            ok = (cols[:, s] >= 0) & (cols[:, t] >= 0)
            rows_.append(cols[ok, s])
            cols_.append(cols[ok, t])
        self.n_free = int(n_free)
        self.pattern = BlockPattern(self.n_free, np.concatenate(rows_), np.concatenate(cols_), 6,
                                    backend)  # type: ignore[arg-type]

    def select(self, cols: np.ndarray) -> Selection:
        """The scatter for observations with these ``cols`` (a subset of those of the pattern)."""
        n_blocks = len(self.pattern.rows)
        slot_rows = tuple(np.flatnonzero(cols[:, s] >= 0) for s in range(cols.shape[1]))
        pairs = []
        for s, t in _slot_pairs(cols.shape[1]):
            rows = np.flatnonzero((cols[:, s] >= 0) & (cols[:, t] >= 0))
            if not len(rows):
                continue
            cs, ct = cols[rows, s], cols[rows, t]
            target = self.pattern.index(cs, ct)
            scatter = sp.csr_matrix((np.ones(len(rows)), (target, np.arange(len(rows)))), shape=(n_blocks, len(rows)))
            pairs.append(_SlotPair(s, t, rows, cs < ct, (cs == ct) & (s != t), scatter))
        return Selection(cols, slot_rows, tuple(pairs))

    def assemble(self, selection: Selection, J: FloatArray, P: FloatArray,
                 e: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The blocks of ``N`` (in the order of ``pattern.rows``) and ``b`` (6 n_free,) from the
        Jacobians ``J`` (k, slots, 6, 6), weights ``P`` (k, 6, 6) and residuals ``e`` (k, 6)."""
        blocks = np.zeros((len(self.pattern.rows), 36))
        b = np.zeros(6 * self.n_free)
        cols = selection.cols
        JT_P: dict[int, FloatArray] = {}
        for s, rows in enumerate(selection.slot_rows):
            if not len(rows):
                continue
            JT_P[s] = np.transpose(J[:, s], (0, 2, 1)) @ P  # all rows: cheaper than gathering them first
            g = np.einsum("kij,kj->ki", JT_P[s][rows], e[rows])
            b -= np.bincount((6 * cols[rows, s, None] + np.arange(6)).ravel(), weights=g.ravel(), minlength=len(b))
        for pair in selection.pairs:
            M = JT_P[pair.s][pair.rows] @ J[pair.rows, pair.t]
            if pair.s != pair.t:
                MT = np.transpose(M, (0, 2, 1))
                M = np.where(pair.flip[:, None, None], MT, M)
                if pair.same.any():
                    M[pair.same] += MT[pair.same]
            blocks += pair.scatter @ M.reshape(-1, 36)
        return blocks.reshape(-1, 6, 6), b

    def factorize(self, blocks: FloatArray, damping: float = 0.0) -> SparseFactor:
        """The factor of ``N`` (its diagonal raised by ``damping`` times itself)."""
        return self.pattern.factorize(blocks, damping)


def _slot_pairs(slots: int) -> list[tuple[int, int]]:
    return [(s, t) for s in range(slots) for t in range(s, slots)]
