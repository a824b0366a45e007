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
    # (pattern blocks, observations): where each observation's product J_s^T P J_t is summed as it
    # is (cols[s] >= cols[t]) and where transposed (cols[s] <= cols[t]; both where equal and s != t)
    direct: sp.csr_matrix
    flipped: sp.csr_matrix | None


@dataclasses.dataclass(frozen=True)
class Selection:
    """The scatter of one set of observations (with their ``cols``) into a :class:`NormalEquations`."""

    cols: np.ndarray
    slots: tuple[int, ...]  # the slots that some observation has free
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
        n_blocks, k = len(self.pattern.rows), len(cols)
        slots = tuple(s for s in range(cols.shape[1]) if np.any(cols[:, s] >= 0))
        pairs = []
        for s, t in _slot_pairs(cols.shape[1]):
            rows = np.flatnonzero((cols[:, s] >= 0) & (cols[:, t] >= 0))
            if not len(rows):
                continue
            cs, ct = cols[rows, s], cols[rows, t]
            target = self.pattern.index(cs, ct)
            flipped = (cs < ct) | ((cs == ct) & (s != t))
            direct = _scatter(target, rows, cs >= ct, (n_blocks, k))
            turned = _scatter(target, rows, flipped, (n_blocks, k)) if flipped.any() else None
            pairs.append(_SlotPair(s, t, direct, turned))
        return Selection(cols, slots, tuple(pairs))

    def assemble(self, selection: Selection, J: FloatArray, P: FloatArray,
                 e: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The blocks of ``N`` (in the order of ``pattern.rows``) and ``b`` (6 n_free,) from the
        Jacobians ``J`` (k, slots, 6, 6), weights ``P`` (k, 6, 6) and residuals ``e`` (k, 6)."""
        n_blocks = len(self.pattern.rows)
        direct, flipped = np.zeros((n_blocks, 36)), np.zeros((n_blocks, 36))
        size = 6 * self.n_free
        b = np.zeros(size + 6)
        cols = selection.cols
        # Every product over all observations (contiguous operands: numpy's small-matrix loops are
        # several times faster than on strided views); the scatter leaves out those without the slot.
        JT_P, J_t = {}, {}
        for s in selection.slots:
            J_t[s] = np.ascontiguousarray(J[:, s])
            JT_P[s] = np.ascontiguousarray(np.transpose(J_t[s], (0, 2, 1))) @ P
            g = np.einsum("kij,kj->ki", JT_P[s], e)
            at = np.where(cols[:, s, None] >= 0, 6 * cols[:, s, None] + np.arange(6), size)
            b -= np.bincount(at.ravel(), weights=g.ravel(), minlength=len(b))
        for pair in selection.pairs:
            M = (JT_P[pair.s] @ J_t[pair.t]).reshape(-1, 36)
            direct += pair.direct @ M
            if pair.flipped is not None:
                flipped += pair.flipped @ M
        blocks = direct.reshape(-1, 6, 6) + flipped.reshape(-1, 6, 6).transpose(0, 2, 1)
        return blocks, b[:size]

    def factorize(self, blocks: FloatArray, damping: float = 0.0) -> SparseFactor:
        """The factor of ``N`` (its diagonal raised by ``damping`` times itself)."""
        return self.pattern.factorize(blocks, damping)


def _scatter(target: np.ndarray, rows: np.ndarray, on: np.ndarray, shape: tuple[int, int]) -> sp.csr_matrix:
    """Ones at (target, rows) where ``on``: the sum of observations' blocks into pattern blocks."""
    return sp.csr_matrix((np.ones(np.count_nonzero(on)), (target[on], rows[on])), shape=shape)


def _slot_pairs(slots: int) -> list[tuple[int, int]]:
    return [(s, t) for s in range(slots) for t in range(s, slots)]
