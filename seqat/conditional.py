"""The conditional cofactor ``Q_F|W = L_FF^-1`` of a departure record, kept factorised.

A departure record (:class:`seqat.departures.Departure`) needs ``Q_F|W`` only in pieces:
re-opening reads the blocks of the keys that come back (their prior), and splitting a
record reads the rows of those keys and leaves the rest conditioned on them
(``C_MM - K C_RM``). A dense ``Q_F|W`` costs O(|F|^2) memory and its formation
O(r^2 p + r p^2) time at every departure; when forty images and their points leave at once
(a window-cap cut on a block flight) that was ~3400 x 3400, 93 MB and ~1 s of a 2.5 s update
(docs/benchmarks.md, *Window-cap cuts on a block*). :class:`Conditional` keeps the
factorisation of ``L_FF`` (:class:`seqat.information.InformationFactor`, GPs eliminated per
3 x 3 block) and forms only the pieces asked for; each split adds a low-rank correction.
"""

from __future__ import annotations

import numpy as np

from seqat.information import InformationFactor
from seqat.types import FloatArray


class Conditional:
    """``C = Q[idx, idx] - sum_i A_i B_i`` of a base cofactor ``Q``.

    Parameters
    ----------
    base : InformationFactor or (n, n) float
        The factorised information of the leaving parameters (its cofactor is ``Q``), or a
        dense cofactor ``Q`` (small or refused blocks).
    idx : (m,) int, optional
        The base's parameters this conditional is on, in its order (default: all).
    downdates : sequence of ((m, k_i) float, (k_i, m) float)
        Low-rank corrections ``A_i B_i`` subtracted (one per split of the record).
    """

    def __init__(self, base: InformationFactor | FloatArray, idx: np.ndarray | None = None,
                 downdates: tuple[tuple[FloatArray, FloatArray], ...] = ()) -> None:
        self.base = base
        n = base.n if isinstance(base, InformationFactor) else np.shape(base)[0]
        self.idx = np.arange(n, dtype=np.int64) if idx is None else np.asarray(idx, np.int64)
        self.downdates = downdates

    @property
    def size(self) -> int:
        return int(self.idx.size)

    def _base(self, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
        """``Q[rows, cols]`` of the base (outer; base indices)."""
        if not isinstance(self.base, InformationFactor):
            return self.base[np.ix_(rows, cols)]
        if rows.size == cols.size and np.array_equal(rows, cols):
            return self.base.block(rows)
        if rows.size <= cols.size:  # Q[:, rows] by |rows| solves, then the entries asked
            return self.base.columns(rows)[cols].T
        return self.base.columns(cols)[rows]

    def entries(self, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
        """``C[rows, cols]`` (outer; positions in this conditional)."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        out = np.array(self._base(self.idx[rows], self.idx[cols]), dtype=np.float64)
        for A, B in self.downdates:
            out -= A[rows] @ B[:, cols]
        return out

    def block(self, rows: np.ndarray) -> FloatArray:
        """``C[rows, rows]``, exactly symmetric."""
        out = self.entries(rows, rows)
        return 0.5 * (out + out.T)

    def quadratic(self, rows: np.ndarray, J: FloatArray) -> FloatArray:
        """``J C[rows, rows] J^T`` for ``J`` (k, len(rows)), exactly symmetric: a re-opening
        chains records (:meth:`seqat.departures.DepartureMixin._conditional_prior`), where
        ``rows`` can be every parameter of a large record and ``k`` is the few re-opened
        ones. On a factorised base that is one solve with ``k`` columns
        (``Y^T Q Y``, ``Y`` = ``J^T`` on ``rows``), not the ``len(rows)^2`` block."""
        rows = np.asarray(rows, np.int64)
        if not isinstance(self.base, InformationFactor) or J.shape[0] >= rows.size:
            out = J @ self.block(rows) @ J.T
        else:
            Y = np.zeros((self.base.n, J.shape[0]))
            Y[self.idx[rows]] = J.T
            out = Y.T @ self.base.solve(Y)
            for A, B in self.downdates:
                out -= (J @ A[rows]) @ (B[:, rows] @ J.T)
        return 0.5 * (out + out.T)

    def restricted(self, keep: np.ndarray, K: FloatArray, C_rk: FloatArray) -> Conditional:
        """``C[keep, keep] - K C_rk``: the conditional of ``keep`` given the parameters ``r``
        it is split from (``K = C_kr C_rr^-1``, ``C_rk = C[r, keep]``)."""
        keep = np.asarray(keep, np.int64)
        kept = tuple((A[keep], B[:, keep]) for A, B in self.downdates)
        return Conditional(self.base, self.idx[keep], kept + ((K, C_rk),))
