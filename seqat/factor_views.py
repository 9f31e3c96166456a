"""Views of a window's factorisation that answer for the window after it changed shape
without a new factorisation (docs/algorithm.md, *Engines*): after a departure
(:class:`MarginalFactor`, ``Q' = Q[keep, keep]``) and after a re-opening
(:class:`AugmentedFactor`, the window with a conditional prior of new parameters).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from seqat.information import InformationFactor
from seqat.types import FloatArray


class MarginalFactor:
    """The factorisation of a window's ``L`` answering for the window after parameters
    left it: marginalising is deleting rows and columns of ``Q = L^-1``, so
    ``Q' = Q[keep, keep]`` (``keep``: the staying parameters' indices in ``L``). The
    Schur complement ``L'`` the departure forms has exactly this inverse; until ``L'``
    changes, the update reads its cofactor blocks here instead of factorising ``L'``
    (docs/algorithm.md, *Engines*)."""

    def __init__(self, base: InformationFactor | AugmentedFactor, keep: np.ndarray) -> None:
        self.base = base
        self.keep = np.asarray(keep, dtype=np.int64)
        self.n = self.keep.size

    @classmethod
    def of(cls, base: SolverLike, keep: np.ndarray) -> MarginalFactor:
        """The marginal on ``keep`` of ``base`` (itself possibly a marginal)."""
        if isinstance(base, MarginalFactor):
            return cls(base.base, base.keep[keep])
        return cls(base, keep)

    def solve(self, b: FloatArray, rows: np.ndarray | None = None) -> FloatArray:
        """``Q' b`` (``b`` of shape (n,) or (n, k)); with ``rows``, only those rows."""
        full = np.zeros((self.base.n,) + b.shape[1:])
        full[self.keep] = b
        if rows is None:
            return self.base.solve(full)[self.keep]
        return self.base.solve(full, self.keep[np.asarray(rows, dtype=np.int64)])

    def columns(self, idx: np.ndarray) -> FloatArray:
        """``Q'[:, idx]``."""
        return self.base.columns(self.keep[idx])[self.keep]

    def block(self, idx: np.ndarray) -> FloatArray:
        """``Q'[idx, idx]``."""
        return self.base.block(self.keep[idx])

    def diagonal_blocks(self, idx: np.ndarray, sizes: np.ndarray) -> list[FloatArray]:
        """:meth:`InformationFactor.diagonal_blocks` of ``Q'``."""
        return self.base.diagonal_blocks(self.keep[idx], sizes)

    def entries(self, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
        """``Q'[rows, cols]`` (outer)."""
        return self.base.entries(self.keep[rows], self.keep[cols])


class AugmentedFactor:
    """The factorisation of a window's ``L`` answering for the window after departed
    parameters were re-opened at its end with the conditional prior
    ``x_R = mean + J x_W + e``, ``e ~ (0, C)`` (docs/algorithm.md, *Re-opening departed
    parameters*). A prior of new parameters given the window does not change the window's
    marginal, so with ``Q = L^-1``::

        Q' = [[Q,   Q J^T        ],
              [J Q, J Q J^T + C ]]

    is the exact inverse of the augmented ``L'`` the re-opening forms. Until ``L'`` changes
    (the update adds its rows), the update reads its cofactor blocks here, with solves of
    ``base`` on at most ``m`` columns, instead of factorising ``L'`` (a block's returning
    strip re-opened 35-45 keys per image into ~4000-parameter windows: a factorisation of
    ~50 ms each, twice per update). ``L'`` is positive definite when ``L`` and ``C`` are,
    so no rank check is lost."""

    def __init__(self, base: SolverLike, J: FloatArray, C: FloatArray,
                 support: np.ndarray | None = None) -> None:
        self.base = base
        self.J = np.asarray(J, dtype=np.float64)
        self.C = 0.5 * (C + C.T)
        self.nw = self.J.shape[1]
        self.n = self.nw + self.J.shape[0]
        #: the window parameters the prior refers to (J's non-zero columns; the caller's)
        self.support = (np.flatnonzero(np.any(self.J != 0.0, axis=0)) if support is None
                        else np.asarray(support, dtype=np.int64))

    def solve(self, b: FloatArray, rows: np.ndarray | None = None) -> FloatArray:
        """``Q' b`` (``b`` of shape (n,) or (n, k)): one solve of ``base``; with ``rows``,
        only those rows (of ``base``'s solution, those rows and ``J``'s support)."""
        b_w, b_r = b[: self.nw], b[self.nw :]
        if rows is None:
            y = self.base.solve(b_w + self.J.T @ b_r)
            return np.concatenate([y, self.J @ y + self.C @ b_r])
        rows = np.asarray(rows, dtype=np.int64)
        win = rows < self.nw
        need = np.union1d(rows[win], self.support if not win.all() else [])
        y = self.base.solve(b_w + self.J.T @ b_r, need.astype(np.int64))
        out = np.empty((rows.size,) + b.shape[1:])
        out[win] = y[np.searchsorted(need, rows[win])]
        if not win.all():
            re = rows[~win] - self.nw
            out[~win] = (self.J[np.ix_(re, self.support)] @ y[np.searchsorted(need,
                                                                            self.support)]
                         + self.C[re] @ b_r)
        return out

    def columns(self, idx: np.ndarray) -> FloatArray:
        """``Q'[:, idx]``."""
        idx = np.asarray(idx, dtype=np.int64)
        E = np.zeros((self.n, idx.size))
        E[idx, np.arange(idx.size)] = 1.0
        return self.solve(E)

    def entries(self, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
        """``Q'[rows, cols]`` (outer): ``base``'s entries on the window's parameters, one
        solve on the re-opened ones (``Q J^T``) for the rest."""
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        return self._outer(rows, cols, self.base.entries)

    def block(self, idx: np.ndarray) -> FloatArray:
        """``Q'[idx, idx]``, exactly symmetric (``base``'s own block on the window's)."""
        idx = np.asarray(idx, dtype=np.int64)
        out = self._outer(idx, idx, lambda r, c: self.base.block(r))
        return 0.5 * (out + out.T)

    def _outer(self, rows: np.ndarray, cols: np.ndarray,
               window: Callable[[np.ndarray, np.ndarray], FloatArray]) -> FloatArray:
        """``Q'[rows, cols]`` with ``window(rows_w, cols_w)`` giving ``Q``'s part."""
        nw = self.nw
        rw, cw = rows < nw, cols < nw
        out = np.empty((rows.size, cols.size))
        if rw.any() and cw.any():
            out[np.ix_(rw, cw)] = window(rows[rw], cols[cw])
        re = np.union1d(rows[~rw], cols[~cw]) - nw  # the re-opened parameters asked for
        if not re.size:
            return out
        # rows ``re`` of J Q on the window's parameters asked for and J's support only
        need = np.union1d(np.union1d(rows[rw], cols[cw]), self.support)
        JQ = self.base.solve(self.J[re].T, need).T  # (len(re), len(need))
        at = np.full(self.n - nw, -1, dtype=np.int64)
        at[re] = np.arange(re.size)
        r_re, c_re = rows[~rw] - nw, cols[~cw] - nw
        if r_re.size:  # J Q on the window's columns, J Q J^T + C on the re-opened ones
            out[np.ix_(~rw, cw)] = JQ[np.ix_(at[r_re], np.searchsorted(need, cols[cw]))]
            sup = np.searchsorted(need, self.support)
            out[np.ix_(~rw, ~cw)] = (JQ[np.ix_(at[r_re], sup)]
                                     @ self.J[np.ix_(c_re, self.support)].T
                                     + self.C[np.ix_(r_re, c_re)])
        if c_re.size and rw.any():  # Q J^T
            out[np.ix_(rw, ~cw)] = JQ[np.ix_(at[c_re], np.searchsorted(need, rows[rw]))].T
        return out

    def diagonal_blocks(self, idx: np.ndarray, sizes: np.ndarray) -> list[FloatArray]:
        """The diagonal blocks of ``Q'[idx, idx]``, ``idx`` consecutive groups of ``sizes``
        (one key each: wholly in the window or wholly re-opened)."""
        idx = np.asarray(idx, dtype=np.int64)
        sizes = np.asarray(sizes, dtype=np.int64)
        starts = np.cumsum(sizes) - sizes
        groups = [idx[a:a + m] for a, m in zip(starts, sizes, strict=True)]
        old = [g for g in range(len(groups)) if groups[g][0] < self.nw]
        out: list[FloatArray] = [np.zeros((0, 0))] * len(groups)
        if old:
            sub = self.base.diagonal_blocks(np.concatenate([groups[g] for g in old]),
                                            sizes[old])
            for g, q in zip(old, sub, strict=True):
                out[g] = q
        for g in range(len(groups)):
            if groups[g][0] >= self.nw:
                out[g] = self.block(groups[g])
        return out


#: What answers for a window's cofactor blocks: its factorisation, or a view of the one it
#: had before a departure (:class:`MarginalFactor`) or a re-opening
#: (:class:`AugmentedFactor`).
SolverLike = InformationFactor | MarginalFactor | AugmentedFactor
