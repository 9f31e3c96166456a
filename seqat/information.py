"""The window's information matrix, factorised with its ground points eliminated (Schur).

The square-root engine of the sequential estimator (docs/algorithm.md, *Engines*) keeps the
information matrix ``L = N`` of the window as the one source of truth: observations only ever
*add* ``A^T P A`` to it, and marginalisation replaces it by a Schur complement, so it stays
symmetric positive (semi)definite by construction. Everything else (the estimate's
corrections, the cofactor blocks the Seq-R correlation rule and the published sigmas need) is
taken from a Cholesky factorisation of ``L``, never from an inverse carried from update to
update.

Ground points (GPs) that no prior couples to another GP have a 3x3 diagonal block and are
eliminated block by block, as in a bundle adjustment's reduced camera system::

    L = [[L_RR, L_RP],      S = L_RR - L_RP D^-1 L_PR,   D = blockdiag(L_pp)
         [L_PR, D   ]]

``R`` holds the EOPs and the GPs a marginal prior couples (few); ``S`` is factorised by
Cholesky (``S = U^T U``). Marginal covariance recovery:

* ``Q_RR = S^-1``, ``Q_PR = -D^-1 L_PR Q_RR``,
* ``Q_pp = D_p^-1 + D_p^-1 L_pR Q_RR L_Rp D_p^-1`` for each eliminated point.

Rank and conditioning are checked here: a GP block or reduced system that is not positive
definite raises :class:`RankDeficiency` naming the parameters, instead of producing NaN or
negative variances downstream.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse

from seqat.errors import EstimationError
from seqat.types import GP_SIZE, FloatArray

#: A GP block or reduced system whose smallest eigenvalue is below this fraction of its
#: largest is treated as singular (relative to double precision: 1e-12 leaves four digits).
RANK_TOLERANCE = 1e-12


#: Coupling blocks ``L_RP`` larger than this (elements) are handled as sparse matrices.
SPARSE_FROM = 200_000
#: A GP block whose largest eigenvalue is below this fraction of the median GP's carries next
#: to no information (its rays all down-weighted to nothing by the robust loss).
WEAK_TOLERANCE = 1e-6


class RankDeficiency(EstimationError):
    """The information matrix is singular: ``indices`` are the parameters the data do not
    determine (GP blocks whose own 3x3 block is singular, or the largest components of the
    reduced system's weakest eigenvector)."""

    def __init__(self, message: str, indices: np.ndarray, gp_blocks: np.ndarray) -> None:
        super().__init__(message)
        self.indices = indices
        self.gp_blocks = gp_blocks  # offsets of singular eliminated GP blocks


def split_indices(n: int, eliminate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kept indices ``R`` (r,) and eliminated GP blocks ``P`` (np, 3) of an n-parameter
    window whose eliminated GP blocks start at ``eliminate``."""
    eliminate = np.asarray(eliminate, dtype=np.int64)
    p_idx = (eliminate[:, None] + np.arange(GP_SIZE)).reshape(-1, GP_SIZE)
    mask = np.ones(n, dtype=bool)
    mask[p_idx.ravel()] = False
    return np.flatnonzero(mask), p_idx


def gather_parts(L: FloatArray, r_idx: np.ndarray,
                 p_idx: np.ndarray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``D`` (np, 3, 3), ``L_RR`` (r, r) and ``L_RP`` (r, 3 np) of ``L``."""
    D = L[p_idx[:, :, None], p_idx[:, None, :]]
    return D, L[np.ix_(r_idx, r_idx)], L[np.ix_(r_idx, p_idx.ravel())]


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
    k, ce = Je.shape[0], Je.shape[2]
    if k == 0:
        return parts
    uniq, first, inv = np.unique(img, return_index=True, return_inverse=True)
    wJe = Je * w[:, None, None]
    EE = np.einsum("kri,krj->kij", wJe, Je).reshape(k, ce * ce)
    flat = (inv[:, None] * (ce * ce) + np.arange(ce * ce)).ravel()
    S = np.bincount(flat, weights=EE.ravel(), minlength=uniq.size * ce * ce)
    parts = add_block_parts(parts, S.reshape(uniq.size, ce, ce), cols[first, :ce], r_idx,
                            p_idx, n)
    # the entries with a GP row or column: [E, P]^T W P and its transpose without P^T W P twice
    J = np.concatenate([Je, Jp], axis=2)
    PJ = np.einsum("kri,krj->kij", Jp * w[:, None, None], J)  # (k, 3, ce + 3): GP rows
    gp_cols = cols[:, ce:]
    a = np.concatenate([np.broadcast_to(gp_cols[:, :, None], PJ.shape).ravel(),
                        np.broadcast_to(cols[:, :ce, None], (k, ce, GP_SIZE)).ravel()])
    b = np.concatenate([np.broadcast_to(cols[:, None, :], PJ.shape).ravel(),
                        np.broadcast_to(gp_cols[:, None, :], (k, ce, GP_SIZE)).ravel()])
    v = np.concatenate([PJ.ravel(), np.swapaxes(PJ[:, :, :ce], 1, 2).ravel()])
    return _add_entries(parts, a, b, v, r_idx, p_idx, n)


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
    RP = L_RP + np.bincount(ra[sel] * (GP_SIZE * npt) + pb[sel], weights=v[sel],
                            minlength=r * GP_SIZE * npt).reshape(r, GP_SIZE * npt)
    sel = (pa >= 0) & (pb >= 0)
    DD = D + np.bincount((pa[sel] // GP_SIZE) * GP_SIZE**2 + (pa[sel] % GP_SIZE) * GP_SIZE
                         + pb[sel] % GP_SIZE, weights=v[sel],
                         minlength=npt * GP_SIZE**2).reshape(npt, GP_SIZE, GP_SIZE)
    return DD, RR, RP


class InformationFactor:
    """Cholesky factorisation of a window information matrix with its GPs eliminated.

    Parameters
    ----------
    L : (n, n) float
        Symmetric positive definite information matrix (only read).
    eliminate : (np,) int
        Offsets in ``L`` of the 3x3 GP blocks to eliminate. Each must be coupled to the other
        eliminated blocks by zeros only (the caller knows the structure; it is not scanned).
    kept_gp : (nk,) int, optional
        Offsets of the GP blocks kept in the reduced system: a singular reduced system whose
        weakest direction lies on them names them in :attr:`RankDeficiency.gp_blocks`.

    Raises
    ------
    RankDeficiency
    """

    def __init__(self, L: FloatArray | None, eliminate: np.ndarray,
                 kept_gp: np.ndarray | None = None, *,
                 parts: tuple[FloatArray, FloatArray, FloatArray] | None = None,
                 n: int | None = None) -> None:
        n = L.shape[0] if L is not None else int(n)  # type: ignore[arg-type]
        self._kept_gp = (np.zeros(0, dtype=np.int64) if kept_gp is None
                         else np.asarray(kept_gp, dtype=np.int64))
        self.n = n
        eliminate = np.asarray(eliminate, dtype=np.int64)
        r_idx, p_idx = split_indices(n, eliminate)
        self.r_idx, self.p_idx = r_idx, p_idx
        npt = p_idx.shape[0]
        if parts is None:
            assert L is not None
            D, L_RR, L_RP = gather_parts(L, r_idx, p_idx)
        else:  # the blocks given (a re-linearisation assembles them without forming L)
            D, L_RR, L_RP = parts
        if npt:
            ev = np.linalg.eigvalsh(D)
            bad = ~(ev[:, 0] > RANK_TOLERANCE * np.maximum(ev[:, -1], 1e-300))
            # ... or next to no information at all (every ray down-weighted to nothing):
            # its elimination would carry rounding into the reduced system
            bad |= ev[:, -1] < WEAK_TOLERANCE * np.median(ev[:, -1])
            if np.any(bad):
                raise RankDeficiency(
                    f"singular 3x3 ground point information block ({int(bad.sum())} points)",
                    p_idx[bad].ravel(), eliminate[bad])
            self.Dinv = np.linalg.inv(D)
            self.Dinv = 0.5 * (self.Dinv + np.swapaxes(self.Dinv, 1, 2))
        else:
            self.Dinv = np.zeros((0, GP_SIZE, GP_SIZE))
        kept = self._kept_gp
        if kept.size and npt:
            pos = np.searchsorted(r_idx, kept[:, None] + np.arange(GP_SIZE))
            dk = np.diagonal(L_RR)[pos].max(axis=1)
            weak = dk < WEAK_TOLERANCE * np.median(np.einsum("pii->pi", D).max(axis=1))
            if np.any(weak):
                raise RankDeficiency(
                    f"next to no information on {int(weak.sum())} ground points",
                    (kept[weak, None] + np.arange(GP_SIZE)).ravel(), kept[weak])
        r = r_idx.size  # L_RP (r, 3 np): a GP couples to the few images that see it
        # B = L_RP D^-1, block by block; large ones kept sparse (CSR): a point's column block
        # is non-zero only on the EOPs of the images that see it, so the Schur product, the
        # solves and the marginals cost O(nnz r), not O(r^2 np)
        B = np.matmul(L_RP.reshape(r, npt, GP_SIZE).transpose(1, 0, 2),
                      self.Dinv).transpose(1, 0, 2).reshape(r, GP_SIZE * npt)
        if L_RP.size > SPARSE_FROM:
            self.L_RP = scipy.sparse.csr_array(L_RP)
            self.B = scipy.sparse.csr_array(B)
            BL = (self.B @ self.L_RP.T).toarray()
        else:  # small windows: dense BLAS beats the sparse bookkeeping
            self.L_RP, self.B = L_RP, B
            BL = B @ L_RP.T
        S = L_RR - BL
        S = 0.5 * (S + S.T)
        self._chol(S)

    def _chol(self, S: FloatArray) -> None:
        r = S.shape[0]
        if r == 0:
            self.U = np.zeros((0, 0))
            return
        d = np.sqrt(np.abs(np.diagonal(S)))
        ok = d > 0
        scale = np.where(ok, 1.0 / np.where(ok, d, 1.0), 1.0)
        Ss = S * scale[:, None] * scale[None, :]  # unit diagonal: conditioning, not units
        try:
            U = scipy.linalg.cholesky(Ss, lower=False, check_finite=True)
            rcond = (np.min(np.diagonal(U)) / np.max(np.diagonal(U))) ** 2
        except (np.linalg.LinAlgError, ValueError):
            rcond = 0.0
        if not rcond > RANK_TOLERANCE:
            ev, V = np.linalg.eigh(np.nan_to_num(Ss))
            weak = np.abs(V[:, 0])
            top = np.argsort(-weak)[:6]
            # GP blocks (kept in R) on which the weakest direction lies
            big = self.r_idx[weak > 0.1 * weak.max()]
            kept = self._kept_gp
            on = kept[np.any((big[None, :] >= kept[:, None])
                             & (big[None, :] < kept[:, None] + GP_SIZE), axis=1)]
            raise RankDeficiency(
                f"reduced normal matrix ({r}x{r}) is singular or ill-conditioned "
                f"(eigenvalues of the scaled matrix from {ev[0]:.3g} to {ev[-1]:.3g})",
                self.r_idx[top], on)
        # S = diag(d) Ss diag(d) = (U diag(d))^T (U diag(d))
        self.U = U / scale[None, :]
        self._Uinv: FloatArray | None = None

    # ------------------------------------------------------------------ solves
    def _solve_S(self, b: FloatArray) -> FloatArray:
        if self.U.shape[0] == 0:
            return b
        y = scipy.linalg.solve_triangular(self.U, b, trans="T", lower=False,
                                          check_finite=False)
        return scipy.linalg.solve_triangular(self.U, y, lower=False, check_finite=False)

    def solve(self, b: FloatArray) -> FloatArray:
        """``L^-1 b`` for ``b`` of shape (n,) or (n, k)."""
        vec = b.ndim == 1
        B2 = b[:, None] if vec else b
        k = B2.shape[1]
        npt = self.p_idx.shape[0]
        bR = B2[self.r_idx]
        bP = B2[self.p_idx.ravel()]  # (3 np, k)
        xR = self._solve_S(bR - self.B @ bP)
        rhsP = (bP - self.L_RP.T @ xR).reshape(npt, GP_SIZE, k)
        xP = np.matmul(self.Dinv, rhsP).reshape(GP_SIZE * npt, k)
        out = np.empty((self.n, k))
        out[self.r_idx] = xR
        out[self.p_idx.ravel()] = xP
        return out[:, 0] if vec else out

    def columns(self, idx: np.ndarray) -> FloatArray:
        """Columns ``Q[:, idx]`` of the cofactor ``Q = L^-1``, (n, len(idx))."""
        E = np.zeros((self.n, idx.size))
        E[idx, np.arange(idx.size)] = 1.0
        return self.solve(E)

    # ------------------------------------------------------------------ marginals
    def _u_inverse(self) -> FloatArray:
        if self._Uinv is None:
            r = self.U.shape[0]
            self._Uinv = scipy.linalg.solve_triangular(self.U, np.eye(r), lower=False,
                                                       check_finite=False)
        return self._Uinv

    def diagonal(self) -> FloatArray:
        """``diag(Q)``: every marginal variance (cofactor units), all > 0."""
        out = np.empty(self.n)
        out[self.r_idx] = self.reduced_diagonal()
        npt = self.p_idx.shape[0]
        if npt:
            Uinv = self._u_inverse()  # Q_RR = Uinv Uinv^T
            Z = (self.B.T @ Uinv).T  # (r, 3 np): Q_pp = Dinv + Z_p^T Z_p
            extra = np.einsum("ij,ij->j", Z, Z)
            out[self.p_idx.ravel()] = np.einsum("pii->pi", self.Dinv).ravel() + extra
        return out

    def reduced_diagonal(self) -> FloatArray:
        """``diag(Q_RR)``: marginal variances of the kept (not eliminated) parameters."""
        if self.U.shape[0] == 0:
            return np.zeros(0)
        Uinv = self._u_inverse()
        return np.einsum("ij,ij->i", Uinv, Uinv)

    def block(self, idx: np.ndarray) -> FloatArray:
        """``Q[idx, idx]`` (small blocks: a leaving key's frozen cofactor)."""
        return self.columns(idx)[idx]

    def dense(self) -> FloatArray:
        """The whole cofactor ``Q = L^-1`` (tests and small windows only)."""
        Q = self.solve(np.eye(self.n))
        return 0.5 * (Q + Q.T)
