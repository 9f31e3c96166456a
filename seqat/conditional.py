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

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse

from seqat.information import InformationFactor
from seqat.types import FloatArray
from seqat.window import Key, key_size


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

    def gain(self, L_fs: FloatArray) -> FloatArray:
        """``-C L_fs``, the RTS gain of a departure on the support of ``L_FW``: one solve on a
        factorised base, one product on a dense one (the conditional at departure, before any
        split: :meth:`Departure.rts_gain` applies the splits)."""
        factor = isinstance(self.base, InformationFactor)
        n = self.base.n if factor else np.shape(self.base)[0]  # type: ignore[union-attr]
        assert not self.downdates and self.idx.size == n, "the conditional at departure"
        L_fs = np.asarray(L_fs, dtype=np.float64)
        return -self.base.solve(L_fs) if factor else -self.base @ L_fs  # type: ignore[union-attr]

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


def split_gain(G: FloatArray, m_idx: np.ndarray, K: FloatArray,
               r_idx: np.ndarray) -> FloatArray:
    """The gain of a record split on its rows ``r_idx`` (re-opened; ``m_idx`` stay):
    ``[G_M - K G_R, K]`` (:meth:`seqat.departures.DepartureMixin._split_records`)."""
    return np.hstack([G[m_idx] - K @ G[r_idx], K])


@dataclass(frozen=True, kw_only=True, eq=False)
class Departure:
    """Parameters F leaving the Seq-R window and their Rauch-Tung-Striebel gain on the rest W.

    Later data reach F only through W (F is never observed again), so given the final
    (smoothed) estimate of W the final estimate of F is ``x_F + J (x_W_final - x_W)`` with
    ``J = Q_FW Q_WW^-1`` taken at departure (Rauch, Tung & Striebel 1965). W is F's Markov
    blanket in the window (the keys ``L_FW`` is non-zero on): ``J = -L_FF^-1 L_FW`` is zero
    on every other window key.

    ``J`` is not stored: the record keeps ``L_FS`` (``coupling``, sparse; S the columns of W
    where ``L_FW`` is non-zero, ``coupling_cols`` of ``gain_width``) and the splits made
    since (each ``(m_idx, K, r_idx)``, :func:`split_gain`), and :meth:`rts_gain` forms ``J``
    from them with the same operations as at departure (the 196-image block's 72 records:
    a dense ``J`` per record was 47 of their 100 MB).
    """

    leaving: tuple[Key, ...]
    staying: tuple[Key, ...]
    x_leaving: FloatArray
    x_staying: FloatArray
    conditional: Conditional  # (|F|, |F|) Q_F|W = L_FF^-1, factorised
    at: int  # index of the image before which F left
    coupling: scipy.sparse.csr_array  # L_FS at departure (|F0|, |S|)
    coupling_cols: np.ndarray  # S: positions in W's parameters at departure
    gain_width: int  # |W| at departure
    splits: tuple[tuple[np.ndarray, FloatArray, np.ndarray], ...] = ()

    @functools.cached_property
    def staying_sizes(self) -> np.ndarray:
        """Each staying key's number of parameters (the gain's columns, key by key)."""
        return np.fromiter((key_size(k) for k in self.staying), np.int64, len(self.staying))

    def departure_gain(self) -> FloatArray:
        """``J`` as the record left (|F0|, |W0|): before any split. It never changes while the
        record lives (a split replaces the record and keeps its ``L_FS`` and factor)."""
        G = np.zeros((self.coupling.shape[0], self.gain_width))
        if self.coupling.shape[1]:
            G[:, self.coupling_cols] = Conditional(self.conditional.base).gain(
                self.coupling.toarray())
        return G

    def split(self, G: FloatArray, start: int = 0) -> FloatArray:
        """``G``, the gain with the first ``start`` splits applied, with the rest applied
        too: every row (a re-opening keeps it for the next ones,
        :meth:`seqat.departures.DepartureMixin._record_gain`)."""
        for m_idx, K, r_idx in self.splits[start:]:
            G = split_gain(G, m_idx, K, r_idx)
        return G

    def rts_gain(self) -> FloatArray:
        """``J`` (|F|, |W|): :meth:`departure_gain` with the splits applied (a re-opening
        reads the gain kept with its splits applied, each split once:
        :meth:`seqat.departures.DepartureMixin._record_gain`)."""
        return self.split(self.departure_gain())
