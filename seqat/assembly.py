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
assembled entry by entry as before (:func:`add_factor_parts`, in this module too): the result
never depends on which way was taken but for rounding.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse

from seqat.information import (
    SparseMatrix,
    WindowMatrix,
    gather_parts,
    sparse_entries,
    split_indices,
    window_matrix,
)
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray


# ---------------------------------------------------------------- factors to information
# (entry by entry: the general way, and what the pattern assembly below falls back to)
def add_block_parts(parts: tuple[FloatArray, FloatArray, FloatArray], blocks: FloatArray,
                    cols: np.ndarray, r_idx: np.ndarray, p_idx: np.ndarray, n: int,
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``parts`` (of :func:`gather_parts`) plus symmetric blocks ``blocks`` (k, c, c) on
    window columns ``cols`` (k, c), each block touching at most one eliminated GP: the parts
    of ``L + sum_k blocks_k`` without forming the n x n matrix."""
    a = np.broadcast_to(cols[:, :, None], blocks.shape).ravel()
    b = np.broadcast_to(cols[:, None, :], blocks.shape).ravel()
    return _add_entries(parts, a, b, blocks.ravel(), r_idx, p_idx, n)


def add_factor_parts(parts: tuple[FloatArray, FloatArray, FloatArray], Je: FloatArray,
                     Jp: FloatArray, w: FloatArray, img: np.ndarray, cols: np.ndarray,
                     r_idx: np.ndarray, p_idx: np.ndarray, n: int,
                     ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`add_block_parts` of image-point factors ``J^T W J`` (``J = [Je, Jp]``, one per
    observation, on window columns ``cols`` (k, ce + 3): image block, then GP), with the
    image-block x image-block parts summed per image first (the factors of one image share
    those columns: with a self-calibrated camera 13 x 13 of every 16 x 16 block)."""
    if Je.shape[0] == 0:
        return parts
    return _add_entries(parts, *factor_entries(Je, Jp, w, img, cols), r_idx, p_idx, n)


def factor_information(Je: FloatArray, Jp: FloatArray, w: FloatArray, img: np.ndarray,
                       cols: np.ndarray, n: int,
                       minus: tuple[FloatArray, FloatArray, FloatArray] | None = None,
                       ) -> SparseMatrix:
    """``sum J^T W J`` of image-point factors as a sparse n x n matrix (exactly symmetric;
    the entries of :func:`factor_entries`); with ``minus = (Je0, Jp0, w0)`` the same
    factors' blocks at another linearisation are subtracted block by block (one entry per
    difference, not two)."""
    return sparse_entries(*factor_entries(Je, Jp, w, img, cols, minus), n)


def factor_entries(Je: FloatArray, Jp: FloatArray, w: FloatArray, img: np.ndarray,
                   cols: np.ndarray,
                   minus: tuple[FloatArray, FloatArray, FloatArray] | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, FloatArray]:
    """Rows, columns and values of ``sum J^T W J`` over image-point factors (both
    triangles; an entry may repeat): the image-block x image-block parts summed per image
    (36 entries per image, not per observation), the parts with a GP row or column per
    factor; every block symmetric to the last bit. ``minus``: see
    :func:`factor_information`."""
    k, ce = Je.shape[0], Je.shape[2]
    if k == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros(0)
    uniq, first, inv = np.unique(img, return_index=True, return_inverse=True)
    S, PE, PP = image_factor_blocks(Je, Jp, w, inv, uniq.size, minus)
    ecols = cols[first, :ce]
    gp_cols = cols[:, ce:]
    a = np.concatenate([
        np.broadcast_to(ecols[:, :, None], S.shape).ravel(),
        np.broadcast_to(gp_cols[:, :, None], PE.shape).ravel(),
        np.broadcast_to(cols[:, :ce, None], (k, ce, GP_SIZE)).ravel(),
        np.broadcast_to(gp_cols[:, :, None], PP.shape).ravel()])
    b = np.concatenate([
        np.broadcast_to(ecols[:, None, :], S.shape).ravel(),
        np.broadcast_to(cols[:, None, :ce], PE.shape).ravel(),
        np.broadcast_to(gp_cols[:, None, :], (k, ce, GP_SIZE)).ravel(),
        np.broadcast_to(gp_cols[:, None, :], PP.shape).ravel()])
    v = np.concatenate([S.ravel(), PE.ravel(), np.swapaxes(PE, 1, 2).ravel(), PP.ravel()])
    return a, b, v


def image_factor_blocks(Je: FloatArray, Jp: FloatArray, w: FloatArray, inv: np.ndarray,
                        nimg: int, minus: tuple[FloatArray, FloatArray, FloatArray] | None = None,
                        flat: np.ndarray | None = None,
                        ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The blocks of :func:`factor_entries`: image x image summed per image (``inv``: each
    factor's image among ``nimg``) (nimg, ce, ce), GP x image (k, 3, ce) and GP x GP
    (k, 3, 3), the square ones symmetric to the last bit; ``minus``: less the same factors'
    blocks at another linearisation; ``flat``: :func:`image_sum_index` (made if None)."""
    k, ce = Je.shape[0], Je.shape[2]
    if flat is None:
        flat = image_sum_index(inv, ce)

    def blocks(Je: FloatArray, Jp: FloatArray, w: FloatArray,
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
        EE = np.einsum("kri,krj->kij", Je * w[:, None, None], Je).reshape(k, ce * ce)
        S = np.bincount(flat, weights=EE.ravel(), minlength=nimg * ce * ce).reshape(
            nimg, ce, ce)
        wJp = Jp * w[:, None, None]
        return (S, np.einsum("kri,krj->kij", wJp, Je),  # PE: GP rows, image-block columns
                np.einsum("kri,krj->kij", wJp, Jp))

    S, PE, PP = blocks(Je, Jp, w)
    if minus is not None:
        S0, PE0, PP0 = blocks(*minus)
        S, PE, PP = S - S0, PE - PE0, PP - PP0
    return 0.5 * (S + np.swapaxes(S, 1, 2)), PE, 0.5 * (PP + np.swapaxes(PP, 1, 2))


def image_sum_index(inv: np.ndarray, ce: int) -> np.ndarray:
    """Where each factor's image x image entries go in the per-image sums of
    :func:`image_factor_blocks` (``inv``: each factor's image)."""
    return (inv[:, None] * (ce * ce) + np.arange(ce * ce)).ravel()


def factor_matvec(Je: FloatArray, Jp: FloatArray, w: FloatArray, cols: np.ndarray,
                  z: FloatArray) -> FloatArray:
    """``(sum J^T W J) z`` of image-point factors, O(factors): without forming the matrix."""
    J = np.concatenate([Je, Jp], axis=2)  # (k, 2, ce + 3)
    Jz = np.einsum("kri,ki->kr", J, z[cols])
    return np.bincount(cols.ravel(), weights=np.einsum("kri,kr->ki", J * w[:, None, None],
                                                       Jz).ravel(), minlength=z.size)


def _add_entries(parts: tuple[FloatArray, FloatArray, FloatArray], a: np.ndarray,
                 b: np.ndarray, v: FloatArray, r_idx: np.ndarray, p_idx: np.ndarray, n: int,
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``parts`` plus the entries ``v`` at window rows ``a`` and columns ``b`` (each entry
    once: a symmetric addition lists both triangles)."""
    D, L_RR, L_RP = parts
    r, npt = r_idx.size, p_idx.shape[0]
    rpos = np.full(n, -1, dtype=np.int64)
    rpos[r_idx] = np.arange(r)
    ppos = np.full(n, -1, dtype=np.int64)
    ppos[p_idx.ravel()] = np.arange(GP_SIZE * npt)
    ra, rb, pa, pb = rpos[a], rpos[b], ppos[a], ppos[b]
    sel = (ra >= 0) & (rb >= 0)
    RR = L_RR + np.bincount(ra[sel] * r + rb[sel], weights=v[sel],
                            minlength=r * r).reshape(r, r)
    sel = (ra >= 0) & (pb >= 0)
    if scipy.sparse.issparse(L_RP):  # a GP couples to few images: O(entries), not O(r np)
        RP = L_RP + scipy.sparse.coo_array(
            (v[sel], (ra[sel], pb[sel])), shape=(r, GP_SIZE * npt)).tocsr()
    else:
        RP = L_RP + np.bincount(ra[sel] * (GP_SIZE * npt) + pb[sel], weights=v[sel],
                                minlength=r * GP_SIZE * npt).reshape(r, GP_SIZE * npt)
    sel = (pa >= 0) & (pb >= 0)
    DD = D + np.bincount((pa[sel] // GP_SIZE) * GP_SIZE**2 + (pa[sel] % GP_SIZE) * GP_SIZE
                         + pb[sel] % GP_SIZE, weights=v[sel],
                         minlength=npt * GP_SIZE**2).reshape(npt, GP_SIZE, GP_SIZE)
    return DD, RR, RP


# ---------------------------------------------------------------- on L's pattern
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
