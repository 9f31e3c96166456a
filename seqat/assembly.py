"""The window's information on its own sparsity pattern, step by step of a re-linearisation.

A window re-linearisation (:mod:`seqat.relinearise`) factorises, at every Gauss-Newton step,
``H = H_p + sum_f J_f^T W J_f``: the kept information ``H_p = L - (the own rows at their old
linearisation)`` plus the image-point factors linearised anew. Every factor's blocks fall on
entries of ``L``'s pattern (``L`` holds the same blocks at the old linearisation), so the
pattern is fixed for the whole re-linearisation: the positions of the factors' entries in
``L.data`` and of the GP-eliminated parts (``D``, ``L_RR``, ``L_RP``) are found once, and a
step is one scatter of the new blocks' values (``np.bincount``) onto ``H_p``'s values and
three gathers, with no sparse matrix built, converted or sorted. The new ``L`` is ``L``'s
pattern with the last step's values (docs/algorithm.md, *Re-linearising the window*).

Exactly symmetric: a block and its transpose receive the same values in the same order.
A factor entry outside the pattern must be an exact zero (a structural one: the camera's
``cx`` x ``cy`` entry, whose Jacobian columns are (1, 0) and (0, 1)); when one is not, or
``L`` is not a sparse matrix with a symmetric pattern (dense small windows), the parts are
assembled entry by entry as before (:func:`seqat.information.add_factor_parts`): the result
never depends on which way was taken but for rounding.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse

from seqat.information import (
    SparseMatrix,
    WindowMatrix,
    add_factor_parts,
    factor_information,
    gather_parts,
    image_factor_blocks,
    image_sum_index,
    split_indices,
    window_matrix,
)
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray


def _runs(cols: np.ndarray) -> list[tuple[int, int]] | None:
    """``(first, length)`` of the runs of consecutive columns in each factor's image block
    (k, ce): the EOP's 6, the camera's; None unless every factor has the same runs."""
    gaps = np.flatnonzero(np.diff(cols[0]) != 1) + 1
    if cols.shape[1] > EOP_SIZE:  # the EOP's and the camera's blocks, adjacent or not
        gaps = np.union1d(gaps, [EOP_SIZE]).astype(np.int64)
    starts = np.concatenate([[0], gaps])
    lengths = np.diff(np.concatenate([starts, [cols.shape[1]]]))
    within = np.ones(cols.shape[1] - 1, dtype=bool)
    within[gaps - 1] = False
    if not np.all(np.diff(cols, axis=1)[:, within] == 1):
        return None
    return [(int(s), int(m)) for s, m in zip(starts, lengths, strict=True)]


def _locate(keys: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Positions of the sorted ``keys`` equal to ``q`` (-1 where absent), queries sorted
    first (a sorted search walks ``keys`` once)."""
    flat = q.ravel()
    order = np.argsort(flat, kind="stable")
    found = np.minimum(np.searchsorted(keys, flat[order]), keys.size - 1)
    out = np.empty(flat.size, dtype=np.int64)
    out[order] = np.where(keys[found] == flat[order], found, -1)
    return out.reshape(q.shape)


class WindowAssembly:
    """``H_p`` plus image-point factors at any linearisation, as the GP-eliminated parts
    a factorisation takes (:meth:`parts`) and as the window's information (:meth:`matrix`).

    Parameters
    ----------
    L : (n, n) float, dense or sparse
        The window's information, holding the factors ``old`` (only read).
    img : (k,) int
        Each factor's image.
    cols : (k, ce + 3) int
        Each factor's window columns: image block (EOP, camera), then GP.
    gp : (np,) int
        Offsets of the GP blocks the factorisation eliminates.
    old : (Je, Jp, w)
        The factors as ``L`` holds them: ``H_p = L - sum J^T W J`` of them.
    """

    def __init__(self, L: WindowMatrix, img: np.ndarray, cols: np.ndarray, gp: np.ndarray,
                 old: tuple[FloatArray, FloatArray, FloatArray]) -> None:
        self.L, self.img, self.cols, self.gp, self.old = L, img, cols, gp, old
        self.n = L.shape[0]
        self.ce = old[0].shape[2]
        self._base: tuple[FloatArray, FloatArray, FloatArray] | None = None  # general way
        self._last: tuple[tuple[FloatArray, ...], FloatArray] | None = None
        #: ``H_p`` on L's pattern (CSR), when the factors are on it; else None
        self.kept: SparseMatrix | None = None
        self.fast = self._pattern()
        if self.fast:
            removed = self._scatter(*old)
            self.fast = removed is not None
            if removed is not None:
                self.data_p = self.data_p - removed
                self.kept = scipy.sparse.csr_array((self.data_p[:-1], self.indices,
                                                    self.indptr), shape=(self.n, self.n))

    # ------------------------------------------------------------------ the pattern
    def _pattern(self) -> bool:
        """Find the positions (see the module's docstring); False: not this way."""
        L, cols, ce = self.L, self.cols, self.ce
        if (not scipy.sparse.issparse(L) or L.format != "csr" or self.img.size == 0
                or L.nnz == 0):
            return False
        runs = _runs(cols[:, :ce])
        if runs is None or np.any(np.diff(self.gp) <= 0):  # (the window's GPs are in order)
            return False
        if not L.has_canonical_format:
            L = L.copy()
            L.sum_duplicates()
        n, nnz = self.n, L.indices.size
        indptr = L.indptr.astype(np.int64)
        indices = L.indices.astype(np.int64)
        T = scipy.sparse.csr_array((np.arange(nnz), indices, indptr), shape=(n, n)).tocsc()
        if not (np.array_equal(T.indptr, indptr) and np.array_equal(T.indices, indices)):
            return False  # the pattern is not symmetric
        transpose = np.append(np.asarray(T.data), nnz)  # each entry's transpose; the spare
        keys = np.repeat(np.arange(n, dtype=np.int64) * n, np.diff(indptr)) + indices
        uniq, first, self.inv = np.unique(self.img, return_index=True, return_inverse=True)
        self.nimg = uniq.size
        self.flat = image_sum_index(self.inv, ce)
        ecols = cols[:, :ce]

        def block(r: np.ndarray, c: np.ndarray, runs: list[tuple[int, int]]) -> np.ndarray:
            """Positions of rows ``r`` (...) x columns ``c`` (..., m) (runs of consecutive
            columns), ``nnz`` (the spare slot) for an entry outside the pattern."""
            out = np.empty(c.shape, dtype=np.int64)
            for s, m in runs:
                p = _locate(keys, r * n + c[..., s])
                last = p + m - 1
                whole = ((p >= 0) & (last < indptr[r + 1])
                         & (indices[np.clip(last, 0, nnz - 1)] == c[..., s] + m - 1))
                out[..., s:s + m] = p[..., None] + np.arange(m)
                if not np.all(whole):  # a run with holes: entry by entry
                    cw = c[~whole][:, s:s + m]
                    q = _locate(keys, r[~whole][:, None] * n + cw)
                    out[~whole, s:s + m] = np.where(q >= 0, q, nnz)
            return out

        pos_S = block(ecols[first], np.broadcast_to(ecols[first][:, None, :],
                                                    (self.nimg, ce, ce)), runs)
        gp_rows = cols[:, ce:]  # (k, 3)
        pos_PE = block(gp_rows, np.broadcast_to(ecols[:, None, :], gp_rows.shape + (ce,)),
                       runs)
        # each GP's own block once (a GP has several factors)
        gps, at = np.unique(gp_rows[:, 0], return_inverse=True)
        own = gps[:, None] + np.arange(GP_SIZE)
        pos_PP = block(own, np.broadcast_to(own[:, None, :], own.shape + (GP_SIZE,)),
                       [(0, GP_SIZE)])[at]
        self.pos = np.concatenate([pos_S.ravel(), pos_PE.ravel(), transpose[pos_PE].ravel(),
                                   pos_PP.ravel()])
        self.outside = np.flatnonzero(self.pos == nnz)  # must stay exact zeros
        self.indptr, self.indices = indptr, indices
        self._gather_positions(np.diff(indptr), indices, block)
        self.data_p = np.append(np.asarray(L.data, dtype=np.float64), 0.0)  # and the spare
        return True

    def _gather_positions(self, counts: np.ndarray, cols: np.ndarray,
                          block: Callable[..., np.ndarray]) -> None:
        """Positions of ``D``, ``L_RR`` and ``L_RP`` in the pattern (``counts``: entries
        per row)."""
        n = self.n
        r_idx, p_idx = split_indices(n, self.gp)
        r, npt = r_idx.size, p_idx.shape[0]
        self.r, self.npt = r, npt
        mask = np.zeros(n, dtype=bool)
        mask[r_idx] = True
        rpos = np.full(n, -1, dtype=np.int64)
        rpos[r_idx] = np.arange(r)
        col_r = mask[cols]
        in_r_rows = np.repeat(mask, counts)  # rows are sorted: one repeat, no gather
        self.rr = np.flatnonzero(in_r_rows & col_r)
        self.rr_flat = np.repeat(rpos * r, counts)[self.rr] + rpos[cols[self.rr]]
        # L_RP as the CSC of L's P rows (their R columns): L's CSR order is its CSC order
        self.rp = np.flatnonzero(~in_r_rows & col_r)
        self.rp_rows = rpos[cols[self.rp]]
        upto = np.concatenate([[0], np.cumsum(col_r)])
        indptr = np.concatenate([[0], np.cumsum(counts)])
        per_row = upto[indptr[1:]] - upto[indptr[:-1]]  # R columns of each row
        self.rp_indptr = np.concatenate([[0], np.cumsum(per_row[p_idx.ravel()])])
        # D: each eliminated point's own 3 x 3 block (entries between two of them are zero:
        # InformationFactor)
        self.d = block(p_idx, np.broadcast_to(p_idx[:, None, :], (npt, GP_SIZE, GP_SIZE)),
                       [(0, GP_SIZE)])

    def _scatter(self, Je: FloatArray, Jp: FloatArray, w: FloatArray) -> FloatArray | None:
        """The factors' ``sum J^T W J`` on the pattern (its data), exactly symmetric; None
        when an entry outside the pattern is not zero."""
        S, PE, PP = image_factor_blocks(Je, Jp, w, self.inv, self.nimg, flat=self.flat)
        v = np.concatenate([S.ravel(), PE.ravel(), PE.ravel(), PP.ravel()])
        if np.any(v[self.outside] != 0.0):
            return None
        return np.bincount(self.pos, weights=v, minlength=self.indices.size + 1)

    def _data(self, Je: FloatArray, Jp: FloatArray, w: FloatArray) -> FloatArray | None:
        """``H_p`` plus the factors on the pattern; None: not on the pattern (the
        assembly goes the general way from now on)."""
        last = self._last
        if last is not None and all(a is b for a, b in zip(last[0], (Je, Jp, w), strict=True)):
            return last[1]
        add = self._scatter(Je, Jp, w) if self.fast else None
        if add is None:
            self.fast = False
            return None
        data = self.data_p + add
        self._last = ((Je, Jp, w), data)
        return data

    # ------------------------------------------------------------------ results
    def parts(self, Je: FloatArray, Jp: FloatArray, w: FloatArray,
              ) -> tuple[FloatArray, FloatArray, FloatArray | SparseMatrix]:
        """``D`` (np, 3, 3), ``L_RR`` (r, r) and ``L_RP`` of ``H_p`` plus the factors at
        (``Je``, ``Jp``, ``w``), as :func:`seqat.information.gather_parts` gives them."""
        data = self._data(Je, Jp, w) if self.fast else None
        if data is None:
            return self._general_parts(Je, Jp, w)
        r, npt = self.r, self.npt
        RR = np.zeros(r * r)
        RR[self.rr_flat] = data[self.rr]
        RP = scipy.sparse.csc_array((data[self.rp], self.rp_rows, self.rp_indptr),
                                    shape=(r, GP_SIZE * npt))
        return data[self.d], RR.reshape(r, r), RP

    def matrix(self, Je: FloatArray, Jp: FloatArray, w: FloatArray) -> WindowMatrix:
        """``H_p`` plus the factors at (``Je``, ``Jp``, ``w``): the new ``L``, stored as the
        window keeps it (:func:`seqat.information.window_matrix`; sparse: exact zeros dropped,
        as a sparse sum drops them)."""
        data = self._data(Je, Jp, w) if self.fast else None
        if data is None:
            return window_matrix(self.L + factor_information(
                Je, Jp, w, self.img, self.cols, self.n, minus=self.old))
        H = scipy.sparse.csr_array((data[:-1].copy(), self.indices.copy(), self.indptr.copy()),
                                   shape=(self.n, self.n))
        H.eliminate_zeros()
        return window_matrix(H)

    def _general_parts(self, Je: FloatArray, Jp: FloatArray, w: FloatArray,
                       ) -> tuple[FloatArray, FloatArray, FloatArray | SparseMatrix]:
        """The parts entry by entry: ``L``'s less the old factors' once, plus the new."""
        r_idx, p_idx = split_indices(self.n, self.gp)
        if self._base is None:
            Je0, Jp0, w0 = self.old
            self._base = add_factor_parts(gather_parts(self.L, r_idx, p_idx), Je0, Jp0, -w0,
                                          self.img, self.cols, r_idx, p_idx, self.n)
        return add_factor_parts(self._base, Je, Jp, w, self.img, self.cols, r_idx, p_idx,
                                self.n)
