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

# Observations per step of the assembly: temporaries of a few MB, which the allocator reuses (arrays
# of all observations are fresh pages from the kernel each time, and the kernel's page faults cost
# more than the products).
_CHUNK = 1 << 14


@dataclasses.dataclass(frozen=True)
class _SlotPair:
    s: int
    t: int
    rows: np.ndarray  # the observations with both slots free (ascending)
    # (pattern blocks, rows): where each row's product J_s^T P J_t is summed as it is (cols[s] >=
    # cols[t]) and where transposed (cols[s] <= cols[t]; both where equal and s != t)
    direct: sp.csr_matrix
    flipped: sp.csr_matrix | None
    offset: int  # its rows' place in Selection.products


@dataclasses.dataclass(frozen=True)
class Selection:
    """The scatter of one set of observations (with their ``cols``) into a :class:`NormalEquations`."""

    cols: np.ndarray
    slots: tuple[int, ...]  # the slots that some observation has free
    pairs: tuple[_SlotPair, ...]
    # the products of all slot pairs (each pair's rows from its offset, 36 values each): filled by
    # every assembly
    products: np.ndarray
    gradient_at: np.ndarray  # (slots, k, 6): where J_s^T P e goes in b (6 n_free: nowhere)
    unit: np.ndarray | None = None  # (k, slots): the Jacobian of this slot is the identity (None: unknown)
    # the sums per pattern block of the products as they are and transposed: filled by every assembly
    sums: np.ndarray = dataclasses.field(default_factory=lambda: np.empty((2, 0, 36)))


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

    def select(self, cols: np.ndarray, unit: np.ndarray | None = None) -> Selection:
        """The scatter for observations with these ``cols`` (a subset of those of the pattern);
        ``unit`` (k, slots) bool where the Jacobian of a slot is always the identity (its products
        are then not formed: ``I^T P = P`` and ``A I = A`` to the bit)."""
        n_blocks = len(self.pattern.rows)
        slots = tuple(s for s in range(cols.shape[1]) if np.any(cols[:, s] >= 0))
        pairs, offset = [], 0
        for s, t in _slot_pairs(cols.shape[1]):
            rows = np.flatnonzero((cols[:, s] >= 0) & (cols[:, t] >= 0))
            if not len(rows):
                continue
            cs, ct = cols[rows, s], cols[rows, t]
            target = self.pattern.index(cs, ct)
            flipped = (cs < ct) | ((cs == ct) & (s != t))
            direct = _scatter(target, cs >= ct, n_blocks)
            turned = _scatter(target, flipped, n_blocks) if flipped.any() else None
            pairs.append(_SlotPair(s, t, rows, direct, turned, offset))
            offset += len(rows)
        size = 6 * self.n_free
        gradient_at = np.stack([np.where(cols[:, s, None] >= 0, 6 * cols[:, s, None] + np.arange(6), size)
                                for s in slots]) if slots else np.zeros((0, len(cols), 6), dtype=np.int64)
        return Selection(cols, slots, tuple(pairs), np.empty((offset, 36)), gradient_at, unit,
                         np.empty((2, n_blocks, 36)))

    def assemble(self, selection: Selection, J: FloatArray, P: FloatArray,
                 e: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The blocks of ``N`` (in the order of ``pattern.rows``) and ``b`` (6 n_free,) from the
        Jacobians ``J`` (k, slots, 6, 6), weights ``P`` (k, 6, 6) and residuals ``e`` (k, 6)."""
        size = 6 * self.n_free
        k = len(e)
        n_blocks = len(self.pattern.rows)
        products = selection.products
        gradient = np.empty((len(selection.slots), k, 6))
        for start in range(0, k, _CHUNK):
            c = slice(start, min(start + _CHUNK, k))
            JT_P = {}
            # slots whose Jacobian is the identity in every observation of this step
            unit = set() if selection.unit is None else {s for s in selection.slots if selection.unit[c, s].all()}
            for m, s in enumerate(selection.slots):
                JT_P[s] = P[c] if s in unit else np.ascontiguousarray(np.swapaxes(J[c, s], 1, 2)) @ P[c]
                gradient[m, c] = np.einsum("kij,kj->ki", JT_P[s], e[c])
            for pair in selection.pairs:
                lo, hi = np.searchsorted(pair.rows, [c.start, c.stop])
                if lo == hi:
                    continue
                local = pair.rows[lo:hi] - c.start
                product = JT_P[pair.s] if pair.t in unit else JT_P[pair.s] @ J[c, pair.t]
                products[pair.offset + lo:pair.offset + hi] = product[local].reshape(-1, 36)
        # Summed per slot pair, then the transposed ones: the order of the sums as before the chunks.
        # in the selection's buffers: fresh arrays of this size each time were fresh pages each time
        direct, flipped = selection.sums if selection.sums.shape[1] == n_blocks else np.empty((2, n_blocks, 36))
        direct.fill(0.0)
        flipped.fill(0.0)
        for pair in selection.pairs:
            M = products[pair.offset:pair.offset + len(pair.rows)]
            direct += pair.direct @ M
            if pair.flipped is not None:
                flipped += pair.flipped @ M
        blocks = direct.reshape(-1, 6, 6) + flipped.reshape(-1, 6, 6).transpose(0, 2, 1)
        b = np.zeros(size + 1)
        for m in range(len(selection.slots)):
            b -= np.bincount(selection.gradient_at[m].ravel(), weights=gradient[m].ravel(), minlength=size + 1)
        return blocks, b[:size]

    def factorize(self, blocks: FloatArray, damping: float = 0.0) -> SparseFactor:
        """The factor of ``N`` (its diagonal raised by ``damping`` times itself)."""
        return self.pattern.factorize(blocks, damping)


def _scatter(target: np.ndarray, on: np.ndarray, n_blocks: int) -> sp.csr_matrix:
    """Ones at (target, row) where ``on``: the sum of a slot pair's products into pattern blocks."""
    rows = np.flatnonzero(on)
    return sp.csr_matrix((np.ones(len(rows)), (target[rows], rows)), shape=(n_blocks, len(on)))


def _slot_pairs(slots: int) -> list[tuple[int, int]]:
    return [(s, t) for s in range(slots) for t in range(s, slots)]
