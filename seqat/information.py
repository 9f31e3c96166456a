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

from seqat import kernels
from seqat.dense import take_columns
from seqat.errors import EstimationError
from seqat.types import GP_SIZE, FloatArray
from seqat.update import lower_inverse

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


def _median(x: FloatArray) -> float:
    """``np.median`` of a short 1-D array, without its general machinery."""
    s = np.sort(x)
    m = s.size // 2
    return float(s[m]) if s.size % 2 else float(0.5 * (s[m - 1] + s[m]))


def split_indices(n: int, eliminate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kept indices ``R`` (r,) and eliminated GP blocks ``P`` (np, 3) of an n-parameter
    window whose eliminated GP blocks start at ``eliminate``."""
    eliminate = np.asarray(eliminate, dtype=np.int64)
    p_idx = (eliminate[:, None] + np.arange(GP_SIZE)).reshape(-1, GP_SIZE)
    mask = np.ones(n, dtype=bool)
    mask[p_idx.ravel()] = False
    return np.flatnonzero(mask), p_idx


#: The window's information matrix of a large window: sparse (CSR). A bundle adjustment's
#: information is sparse — a GP couples to the few images that see it, GPs to no other GP but
#: through a marginal prior — and a dense n x n copy per update was most of the cost of a
#: real flight's window (n ~ 4000 on Seneca: 128 MB touched per update; docs/algorithm.md,
#: *Engines*).
SparseMatrix = scipy.sparse.csr_array
#: Windows of up to this many parameters keep ``L`` dense: there numpy's dense kernels beat
#: scipy.sparse's per-call overhead (the paper strip's ~250-parameter window: 1.3-1.6x
#: slower sparse, measured 2026-12-02); beyond it ``L`` is sparse.
DENSE_UP_TO = 1200
#: A window's information matrix: dense (small windows) or sparse.
WindowMatrix = FloatArray | SparseMatrix
#: ``S^-1 b`` from the factor ``S = U^T U`` in one LAPACK call (two ``solve_triangular``
#: calls cost twice scipy's argument checking, a measurable share of a small window's update).
_POTRS = scipy.linalg.lapack.dpotrs
_POTRF = scipy.linalg.lapack.dpotrf
_LAUUM = scipy.linalg.lapack.dlauum


def sparse_information(L: WindowMatrix) -> SparseMatrix:
    """``L`` as a sparse information matrix (CSR, explicit zeros dropped)."""
    out = scipy.sparse.csr_array(L, dtype=np.float64)
    out.eliminate_zeros()
    return out


def window_matrix(L: WindowMatrix) -> WindowMatrix:
    """``L`` stored as the window keeps it at its size: dense up to :data:`DENSE_UP_TO`
    parameters, sparse beyond."""
    if L.shape[0] <= DENSE_UP_TO:
        return L.toarray() if scipy.sparse.issparse(L) else np.asarray(L)
    return L if scipy.sparse.issparse(L) else sparse_information(L)


def submatrix(L: WindowMatrix, rows: np.ndarray, cols: np.ndarray) -> WindowMatrix:
    """``L[np.ix_(rows, cols)]`` of a dense or sparse matrix (outer indexing)."""
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    if scipy.sparse.issparse(L):
        return L[rows][:, cols]
    return L[np.ix_(rows, cols)]


def padded(L: WindowMatrix, n: int) -> WindowMatrix:
    """``L`` (m, m) as the top-left block of an (n, n) matrix, n >= m (zeros elsewhere)."""
    m = L.shape[0]
    if n == m:
        return L
    if not scipy.sparse.issparse(L):
        out = np.zeros((n, n))
        out[:m, :m] = L
        return out
    indptr = np.concatenate([L.indptr, np.full(n - m, L.indptr[-1], dtype=L.indptr.dtype)])
    return scipy.sparse.csr_array((L.data, L.indices, indptr), shape=(n, n))


def add_block(L: WindowMatrix, cols: np.ndarray, M: FloatArray) -> WindowMatrix:
    """``L`` plus the dense block ``M`` on rows and columns ``cols`` (a copy)."""
    if scipy.sparse.issparse(L):
        return L + block_matrix(np.asarray(cols, dtype=np.int64), M, L.shape[0])
    out = np.array(L, dtype=np.float64)
    out[np.ix_(cols, cols)] += M
    return out


def nonzero_columns(L: WindowMatrix) -> np.ndarray:
    """Columns of ``L`` with a non-zero entry."""
    if scipy.sparse.issparse(L):
        L = L.tocsr()
        L.eliminate_zeros()
        return np.unique(L.indices)
    return np.flatnonzero(np.any(np.asarray(L) != 0.0, axis=0))


def block_matrix(cols: np.ndarray, M: FloatArray, n: int) -> SparseMatrix:
    """``M`` on rows and columns ``cols`` (distinct) of an (n, n) CSR matrix, laid out in order
    (a block flight's ~1700 x 1700 departure fill: half the time of COO, which sorts it)."""
    order = np.argsort(cols, kind="stable")
    c, k = cols[order], cols.size
    counts = np.zeros(n, dtype=np.int64)
    counts[c] = k  # a row per column asked for, each with all of them, in order
    out = SparseMatrix((np.asarray(M, dtype=np.float64)[np.ix_(order, order)].ravel(),
                        np.tile(c, k), np.concatenate([[0], np.cumsum(counts)])), shape=(n, n))
    out.eliminate_zeros()
    return out


def sparse_entries(rows: np.ndarray, cols: np.ndarray, values: FloatArray,
                   n: int) -> SparseMatrix:
    """An (n, n) sparse matrix of ``values`` at (``rows``, ``cols``), duplicates summed."""
    rows, cols, values = (np.asarray(a).ravel() for a in (rows, cols, values))
    nz = values != 0.0
    return scipy.sparse.coo_array((values[nz], (rows[nz], cols[nz])), shape=(n, n)).tocsr()


def dense_block(L: WindowMatrix, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
    """``L[np.ix_(rows, cols)]`` as a dense array, for a dense or sparse ``L``."""
    if scipy.sparse.issparse(L):
        return submatrix(L, rows, cols).toarray()
    return np.asarray(L)[np.ix_(rows, cols)]


def gather_parts(L: FloatArray | SparseMatrix, r_idx: np.ndarray, p_idx: np.ndarray,
                 ) -> tuple[FloatArray, FloatArray, FloatArray | SparseMatrix]:
    """``D`` (np, 3, 3), ``L_RR`` (r, r, dense) and ``L_RP`` (r, 3 np; sparse for a sparse
    ``L``) of ``L``. Of the GP-GP part only the 3x3 diagonal blocks are read: the caller
    eliminates GPs that nothing else couples."""
    if not scipy.sparse.issparse(L):
        L = np.asarray(L)
        D = L[p_idx[:, :, None], p_idx[:, None, :]]
        rows_r = L.take(r_idx, axis=0)
        return D, take_columns(rows_r, r_idx), rows_r[:, p_idx.ravel()]
    p_flat = p_idx.ravel()
    npt = p_idx.shape[0]
    rows_r = L[r_idx]
    L_RR = rows_r[:, r_idx].toarray()
    L_RP = rows_r[:, p_flat].tocsr()
    Lpp = submatrix(L, p_flat, p_flat).tocoo()
    i, j = np.asarray(Lpp.row), np.asarray(Lpp.col)
    same = i // GP_SIZE == j // GP_SIZE
    flat = (i[same] // GP_SIZE) * GP_SIZE**2 + (i[same] % GP_SIZE) * GP_SIZE + j[same] % GP_SIZE
    D = np.bincount(flat, weights=Lpp.data[same],
                    minlength=npt * GP_SIZE**2).reshape(npt, GP_SIZE, GP_SIZE)
    return D, L_RR, L_RP


def _csc_ranges(indptr: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Positions in a CSC matrix's ``indices``/``data`` of the entries of columns ``cols``."""
    lo, hi = indptr[cols], indptr[cols + 1]
    counts = hi - lo
    return np.repeat(lo - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())


def _canonical_csc(M: FloatArray | SparseMatrix) -> scipy.sparse.csc_array:
    """``M`` by columns, rows sorted and no duplicate entries."""
    out = scipy.sparse.csc_array(M)
    out.sum_duplicates()
    return out


class InformationFactor:
    """Cholesky factorisation of a window information matrix with its GPs eliminated.

    Parameters
    ----------
    L : (n, n) float, dense or sparse
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

    def __init__(self, L: WindowMatrix | None, eliminate: np.ndarray,
                 kept_gp: np.ndarray | None = None, *,
                 parts: tuple[FloatArray, FloatArray, FloatArray] | None = None,
                 n: int | None = None) -> None:
        n = L.shape[0] if L is not None else int(n)  # type: ignore[arg-type]
        self._kept_gp = np.asarray([] if kept_gp is None else kept_gp, dtype=np.int64)
        self.n = n
        self._pos: tuple[np.ndarray, np.ndarray] | None = None  # _positions(), on request
        self._Qrr: FloatArray | None = None
        self._V: FloatArray | None = None
        eliminate = np.asarray(eliminate, dtype=np.int64)
        self.r_idx, self.p_idx = r_idx, p_idx = split_indices(n, eliminate)
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
            bad |= ev[:, -1] < WEAK_TOLERANCE * _median(ev[:, -1])
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
            weak = dk < WEAK_TOLERANCE * _median(np.einsum("pii->pi", D).max(axis=1))
            if np.any(weak):
                raise RankDeficiency(
                    f"next to no information on {int(weak.sum())} ground points",
                    (kept[weak, None] + np.arange(GP_SIZE)).ravel(), kept[weak])
        r = r_idx.size  # L_RP (r, 3 np): a GP couples to the few images that see it
        # B = L_RP D^-1, block by block; large ones kept sparse (CSR): a point's column block
        # is non-zero only on the EOPs of the images that see it, so the Schur product, the
        # solves and the marginals cost O(nnz r), not O(r^2 np)
        if scipy.sparse.issparse(L_RP) and r * GP_SIZE * npt <= SPARSE_FROM:
            L_RP = L_RP.toarray()  # small windows: dense BLAS beats the sparse bookkeeping
        if scipy.sparse.issparse(L_RP):
            k = np.arange(GP_SIZE * npt)
            Dinv_blocks = scipy.sparse.csr_array(
                (self.Dinv.ravel(), np.repeat(k.reshape(npt, GP_SIZE), GP_SIZE, axis=0).ravel(),
                 np.arange(0, GP_SIZE * GP_SIZE * npt + 1, GP_SIZE)),
                shape=(GP_SIZE * npt, GP_SIZE * npt))
            # kept by columns (a point's three): what the kernels, Q[touched, touched] and
            # the products read, one copy each (a departure record keeps its factor)
            self.L_RP = _canonical_csc(L_RP)
            self.B = _canonical_csc(self.L_RP @ Dinv_blocks)
            BL = self._schur_product(r)
        else:
            B = np.matmul(L_RP.reshape(r, npt, GP_SIZE).transpose(1, 0, 2),
                          self.Dinv).transpose(1, 0, 2).reshape(r, GP_SIZE * npt)
            if L_RP.size > SPARSE_FROM:
                self.L_RP = _canonical_csc(L_RP)
                self.B = _canonical_csc(B)
                BL = self._schur_product(r)
            else:
                self.L_RP, self.B = L_RP, B
                BL = B @ L_RP.T
        # S = L_RR - BL, symmetric but for the rounding of BL: the Cholesky reads its upper
        # triangle only (a symmetrising pass cost as much as the product on small windows);
        # L_RR is the gathered copy unless the caller gave the parts
        if parts is None:
            L_RR -= BL
            S = L_RR
        else:
            S = L_RR - BL
        self._chol(S)

    def _schur_product(self, r: int) -> FloatArray:
        """``L_RP D^-1 L_PR`` (r x r, dense, exactly symmetric) of a large window, point by
        point on the rows each point's columns of the sparse ``L_RP`` hold
        (:func:`seqat.kernels.schur_product`)."""
        C = self.L_RP
        return kernels.schur_product(C.indptr, C.indices, C.data, self.Dinv, r)

    def _chol(self, S: FloatArray) -> None:
        r = S.shape[0]
        if r == 0:
            self.U = np.zeros((0, 0))
            return
        d = np.sqrt(np.abs(np.diagonal(S)))
        ok = d > 0
        scale = np.where(ok, 1.0 / np.where(ok, d, 1.0), 1.0)  # to a unit diagonal
        # LAPACK potrf on the Fortran view of S (its lower triangle is S's upper one): U = L^T.
        # The conditioning is judged on the unit-diagonal diag(scale) S diag(scale), whose
        # factor is U diag(scale): Cholesky's backward error does not depend on a diagonal
        # scaling, so S itself is factorised (not a scaled copy). A NaN gives a NaN rcond.
        Lt, info = _POTRF(S.T, lower=1, clean=1)
        diag_u = np.diagonal(Lt) * scale
        rcond = (diag_u.min() / diag_u.max()) ** 2 if info == 0 else 0.0
        if not rcond > RANK_TOLERANCE:
            Ss = S * scale[:, None] * scale[None, :]
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
        self.U = Lt.T  # U^T kept Fortran-ordered: LAPACK reads it without a copy

    # ------------------------------------------------------------------ solves
    def _solve_S(self, b: FloatArray) -> FloatArray:
        if self.U.shape[0] == 0:
            return b
        x, info = _POTRS(self.U.T, b, lower=1)  # U^-1 U^-T b: the two triangular solves
        if info != 0:  # pragma: no cover - only for a malformed argument
            raise EstimationError(f"LAPACK potrs failed on the reduced system ({info})")
        return x

    def solve(self, b: FloatArray, rows: np.ndarray | None = None) -> FloatArray:
        """``L^-1 b`` for ``b`` of shape (n,) or (n, k); with ``rows``, only those rows of it
        (the eliminated points back-substituted are those ``rows`` fall on, not all)."""
        vec = b.ndim == 1
        B2 = b[:, None] if vec else b
        k = B2.shape[1]
        npt = self.p_idx.shape[0]
        bR = B2[self.r_idx]
        bP = B2[self.p_idx.ravel()]  # (3 np, k)
        xR = self._solve_S(bR - self.B @ bP)
        if rows is not None:
            out = self._rows_of_solution(np.asarray(rows, dtype=np.int64), xR, bP)
            return out[:, 0] if vec else out
        rhsP = (bP - self.L_RP.T @ xR).reshape(npt, GP_SIZE, k)
        xP = np.matmul(self.Dinv, rhsP).reshape(GP_SIZE * npt, k)
        out = np.empty((self.n, k))
        out[self.r_idx] = xR
        out[self.p_idx.ravel()] = xP
        return out[:, 0] if vec else out

    def _rows_of_solution(self, rows: np.ndarray, xR: FloatArray, bP: FloatArray) -> FloatArray:
        """Rows ``rows`` of ``L^-1 b`` given its kept part ``xR`` and ``b``'s eliminated rows
        ``bP``: ``x_p = D_p^-1 (b_p - L_Rp^T x_R)`` for the points ``rows`` fall on."""
        rpos, ppos = self._positions()
        k = xR.shape[1]
        out = np.empty((rows.size, k))
        in_r = rpos[rows] >= 0
        out[in_r] = xR[rpos[rows[in_r]]]
        jp = np.flatnonzero(~in_r)
        if jp.size:
            q = ppos[rows[jp]]
            pts, at = np.unique(q // GP_SIZE, return_inverse=True)
            cols3 = (pts[:, None] * GP_SIZE + np.arange(GP_SIZE)).ravel()
            if scipy.sparse.issparse(self.L_RP):  # its columns' few non-zeros: O(nnz k)
                rhs = bP[cols3] - self._by_columns("L_RP")[:, cols3].T @ xR
            else:
                rhs = bP[cols3] - self.L_RP[:, cols3].T @ xR
            x_p = np.matmul(self.Dinv[pts], rhs.reshape(pts.size, GP_SIZE, k))
            out[jp] = x_p[at, q % GP_SIZE]
        return out

    def columns(self, idx: np.ndarray) -> FloatArray:
        """Columns ``Q[:, idx]`` of the cofactor ``Q = L^-1``, (n, len(idx))."""
        E = np.zeros((self.n, idx.size))
        E[idx, np.arange(idx.size)] = 1.0
        return self.solve(E)

    # ------------------------------------------------------------------ marginals
    def _v(self) -> FloatArray:
        """``V = U^-1`` (r x r, upper triangular): ``Q_RR = S^-1 = V V^T``.

        An update reads the diagonal of ``Q_RR`` and a few of its blocks, never all of it:
        ``diag(Q_RR)`` is the squared norms of ``V``'s rows, ``Q_RR[a, b] = V[a] V[b]^T``
        and ``B^T Q_RR B = (V^T B)^T (V^T B)``. ``U^-1`` is the first half of LAPACK
        ``potri`` (then ``V V^T``, not paid; ``U^-1`` by :func:`seqat.update.lower_inverse`)."""
        if self._V is None:
            if self.U.shape[0] == 0:
                self._V = np.zeros((0, 0))
            else:  # on the Fortran-ordered lower factor U^T: V^T, Fortran-ordered
                self._V = lower_inverse(self.U.T).T
        return self._V

    def _q_rr(self) -> FloatArray:
        """``Q_RR = S^-1 = V V^T``, dense, exactly symmetric (LAPACK ``lauum``: ``potri``'s
        second half): for :meth:`dense` and a large window's :meth:`_point_extra` only."""
        if self._Qrr is None:
            V = self._v()
            low, info = _LAUUM(V.T, lower=1) if V.size else (V, 0)  # V V^T, lower triangle
            if info != 0:  # pragma: no cover - only for a malformed argument
                raise EstimationError(f"LAPACK lauum failed on the reduced system ({info})")
            Q = np.triu(low.T)
            self._Qrr = Q + np.triu(Q, 1).T
        return self._Qrr

    def _q_rr_block(self, rows: np.ndarray) -> FloatArray:
        """``Q_RR[rows, rows]`` from :meth:`_v`, exactly symmetric."""
        Vr = self._v().take(rows, axis=0)
        M = Vr @ Vr.T
        return 0.5 * (M + M.T)

    def diagonal(self) -> FloatArray:
        """``diag(Q)``: every marginal variance (cofactor units), all > 0."""
        out = np.empty(self.n)
        out[self.r_idx] = self.reduced_diagonal()
        if self.p_idx.shape[0]:
            out[self.p_idx.ravel()] = (np.einsum("pii->pi", self.Dinv)
                                       + self._point_extra()).ravel()
        return out

    def reduced_diagonal(self) -> FloatArray:
        """``diag(Q_RR)``: marginal variances of the kept (not eliminated) parameters, the
        squared norms of :meth:`_v`'s rows (> 0: ``V`` is regular)."""
        V = self._v()
        return np.einsum("ij,ij->i", V, V)

    def _point_extra(self) -> FloatArray:
        """``diag(B_p^T Q_RR B_p)`` (np, 3): what the kept parameters add to each eliminated
        point's variances (``Q_pp = D_p^-1 + B_p^T Q_RR B_p``, ``B_p = L_Rp D_p^-1``).

        ``B_p`` is non-zero only on the rows of the images (and camera) that see the point:
        each point reads its own m x m block of ``Q_RR`` (m = 6 per ray), O(sum m^2) in all,
        instead of the O(nnz(B) r) of ``U^-T B`` (docs/algorithm.md, *Engines*)."""
        r, npt = self.r_idx.size, self.p_idx.shape[0]
        if r == 0:
            return np.zeros((npt, GP_SIZE))
        if not scipy.sparse.issparse(self.B):  # the column norms of V^T B
            W = self._v().T @ np.asarray(self.B)
            return np.einsum("ij,ij->j", W, W).reshape(npt, GP_SIZE)
        return self._sparse_point_quadratic(np.arange(npt), full=False)

    def _sparse_point_quadratic(self, pts: np.ndarray, *, full: bool) -> FloatArray:
        """``B_p^T Q_RR B_p`` of the eliminated points ``pts`` (positions in P) for a sparse
        ``B``: (len(pts), 3, 3), or with ``full`` False its diagonal (len(pts), 3). Each point
        reads the block of ``Q_RR`` on the rows its columns of ``B`` live on
        (:func:`seqat.kernels.point_quadratic`)."""
        B = self._by_columns("B")
        indices = B.indices
        if self._Qrr is None:
            # only the rows B_p lives on: the images' (and the camera's), not the coupled
            # GPs' (of a block's 909 kept parameters, 615 were): the points' variances of
            # F1's updates with r > 600 took 12.7 ms each with all of Q_RR, 6.9 ms so
            pts = np.asarray(pts, dtype=np.int64)
            on = np.zeros(self.r_idx.size, dtype=bool)
            if pts.size == self.p_idx.shape[0]:  # every point: every entry
                on[indices] = True
            else:
                cols = (pts[:, None] * GP_SIZE + np.arange(GP_SIZE)).ravel()
                on[indices[_csc_ranges(B.indptr, cols)]] = True
            sub = np.flatnonzero(on)
            if 2 * sub.size <= self.r_idx.size:
                remap = np.zeros(self.r_idx.size, dtype=np.int64)
                remap[sub] = np.arange(sub.size)
                extra = kernels.point_quadratic(B.indptr, remap[indices], B.data,
                                                self._q_rr_block(sub), pts)
                return extra if full else np.einsum("pii->pi", extra)
        extra = kernels.point_quadratic(B.indptr, indices, B.data, self._q_rr(), pts)
        return extra if full else np.einsum("pii->pi", extra)

    def block(self, idx: np.ndarray) -> FloatArray:
        """``Q[idx, idx]``, (k, k), exactly symmetric, from the block of ``Q_RR`` on the rows
        it reads: ``idx``'s kept parameters ``R`` and the rows ``e`` its eliminated points'
        columns of ``B = L_RP D^-1`` live on (their images'), as
        ``Q_Rp = -Q_RR B_p`` and ``Q_pp' = D_p^-1 [p = p'] + B_p^T Q_RR B_p'``.

        ``Q_RR`` on those ``t = |R u e|`` rows is ``V_t V_t^T`` when :meth:`_v` is at hand
        (the sigmas formed it: O(t^2 r)), else ``t`` columns of ``S^-1`` by one ``potrs``
        (O(r^2 t)); a small window reads all of ``V`` (:meth:`_block_from_v`). An update's
        touched block on a block flight's returning strip had k ~ 450 columns (a hundred
        points, three each) on ~150 such rows: the points' columns were solved for one by
        one, O(r^2 k) (docs/algorithm.md, *Engines*)."""
        idx = np.asarray(idx, dtype=np.int64)
        rpos, ppos = self._positions()
        in_r = rpos[idx] >= 0
        jr, jp = np.flatnonzero(in_r), np.flatnonzero(~in_r)
        R = rpos[idx[jr]]
        q = ppos[idx[jp]]  # positions in P of the eliminated entries asked for
        if self._small():
            return self._block_from_v(jr, jp, R, q)
        Bq = self._columns_of("B", q)  # (r, |jp|)
        e = np.flatnonzero(np.any(Bq != 0.0, axis=1))
        T = np.union1d(R, e)  # the rows of Q_RR read, sorted
        if self._V is not None:
            QT = self._q_rr_block(T)
        else:
            E = np.zeros((self.r_idx.size, T.size))
            E[T, np.arange(T.size)] = 1.0
            QT = self._solve_S(E)[T]
            QT = 0.5 * (QT + QT.T)
        aR = np.searchsorted(T, R)
        QRR = QT[np.ix_(aR, aR)]
        if not jp.size:
            return QRR
        Be, ae = Bq[e], np.searchsorted(T, e)
        QB = QT[:, ae] @ Be  # Q_RR B_q on the rows T
        PP = Be.T @ QB[ae]
        return self._assemble_block(jr, jp, QRR, -QB[aR], PP, q)

    def _block_from_v(self, jr: np.ndarray, jp: np.ndarray, R: np.ndarray,
                      q: np.ndarray) -> FloatArray:
        """:meth:`block` of a small window (dense ``B``) from ``V`` on all its rows: one BLAS
        product ``V^T B_q`` beats the selection of the rows read (0.50 against 0.74 ms per
        block on the paper strip's r ~ 190, k ~ 54)."""
        V = self._v()
        QRR = self._q_rr_block(R)
        if not jp.size:
            return QRR
        W = V.T @ np.asarray(self.B)[:, q]  # (r, |jp|): Q_RR B_q = V W
        return self._assemble_block(jr, jp, QRR, -(V.take(R, axis=0) @ W), W.T @ W, q)

    def _assemble_block(self, jr: np.ndarray, jp: np.ndarray, QRR: FloatArray,
                        QRP: FloatArray, PP: FloatArray, q: np.ndarray) -> FloatArray:
        """``Q[idx, idx]`` from its kept (``jr``) and eliminated (``jp``, at positions ``q``
        of P) parts: ``PP`` is ``B_q^T Q_RR B_q``, to which each point's ``D_p^-1`` adds."""
        blk, comp = q // GP_SIZE, q % GP_SIZE
        a, b = np.nonzero(blk[:, None] == blk[None, :])  # the same point's entries
        PP[a, b] += self.Dinv[blk[a], comp[a], comp[b]]
        nr = jr.size  # kept entries first, then the eliminated ones; idx's order after
        out = np.empty((jr.size + jp.size,) * 2)
        out[:nr, :nr] = QRR
        out[:nr, nr:] = QRP
        out[nr:, :nr] = QRP.T
        out[nr:, nr:] = 0.5 * (PP + PP.T)
        order = np.argsort(np.concatenate([jr, jp]))
        return out.take(order, axis=0)[:, order]

    def diagonal_blocks(self, idx: np.ndarray, sizes: np.ndarray) -> list[FloatArray]:
        """The diagonal blocks of ``Q[idx, idx]``: ``idx`` is consecutive groups of
        ``sizes`` parameters (one key each: an image's 6, a point's 3), each group's
        ``Q[g, g]`` returned, none of the off-diagonal ones :meth:`block` would form
        (O(k^2) of them for k parameters; a departure of 40 images and their points asked
        for 2500 x 2500 to keep 3 x 3 and 6 x 6 blocks).

        A group of kept parameters reads ``Q_RR`` (from :meth:`_v`); an eliminated point's
        is ``D_p^-1 + B_p^T Q_RR B_p`` (``B_p = L_Rp D_p^-1``), one product ``V^T B`` on the
        columns of the points asked for."""
        idx = np.asarray(idx, dtype=np.int64)
        sizes = np.asarray(sizes, dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        rpos, ppos = self._positions()
        V = self._v()
        out: list[FloatArray] = [np.zeros((0, 0))] * sizes.size
        elim: list[int] = []  # groups that are one eliminated point, whole
        for g, (a, m) in enumerate(zip(starts, sizes, strict=True)):
            gi = idx[a:a + m]
            r = rpos[gi]
            if np.all(r >= 0):
                out[g] = self._q_rr_block(r)
            elif (m == GP_SIZE and np.all(ppos[gi] >= 0) and ppos[gi[0]] % GP_SIZE == 0
                  and np.array_equal(ppos[gi], ppos[gi[0]] + np.arange(GP_SIZE))):
                elim.append(g)
            else:  # a group across R and P (no key is): the general block
                out[g] = self.block(gi)
        r = V.shape[0]
        elim_g = np.asarray(elim, dtype=np.int64)
        if r and elim_g.size and scipy.sparse.issparse(self.B):
            # a large window: each point's block of Q_RR (a departure of 40 images and 1100
            # points: V^T B was r x r x 3 np, 6 Gflop, 0.3 s of the update)
            blk = ppos[idx[starts[elim_g]]] // GP_SIZE
            Qpp = self.Dinv[blk] + self._sparse_point_quadratic(blk, full=True)
            Qpp = 0.5 * (Qpp + np.swapaxes(Qpp, 1, 2))
            for g, q in zip(elim_g, Qpp, strict=True):
                out[g] = q
            return out
        # in chunks of bounded memory (r x 3 columns per point, twice)
        for part in np.array_split(elim_g, max(1, r * GP_SIZE * len(elim) // 4_000_000)):
            if not part.size:
                continue
            blk = ppos[idx[starts[part]]] // GP_SIZE
            Qpp = self.Dinv[blk].copy()
            if r:
                cols = (blk[:, None] * GP_SIZE + np.arange(GP_SIZE)).ravel()
                Bc = self._columns_of("B", cols).reshape(r, blk.size, GP_SIZE)
                VB = np.tensordot(V, Bc, axes=(0, 0))  # V^T B: (r, points, 3)
                Qpp += np.einsum("rpi,rpj->pij", VB, VB)
            Qpp = 0.5 * (Qpp + np.swapaxes(Qpp, 1, 2))
            for g, q in zip(part, Qpp, strict=True):
                out[g] = q
        return out

    def entries(self, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
        """``Q[rows, cols]`` (outer). Kept (not eliminated) rows and columns, the EOPs
        among them, come from ``Q_RR = S^-1``: rows of :meth:`_v` in a small window, one
        LAPACK ``potrs`` on the columns asked for in a large one; no back-substitution of the
        eliminated GPs. Otherwise from :meth:`columns`."""
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        rpos = self._positions()[0]
        rr, rc = rpos[rows], rpos[cols]
        if rows.size and cols.size and (rr.min() < 0 or rc.min() < 0):
            return self.columns(cols)[rows]
        if self._small():
            V = self._v()
            return V.take(rr, axis=0) @ V.take(rc, axis=0).T
        E = np.zeros((self.r_idx.size, cols.size))
        E[rc, np.arange(cols.size)] = 1.0
        return self._solve_S(E)[rr]

    def _positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Position of each window parameter in ``R`` and in ``P`` (-1 where it is not)."""
        pos = self._pos
        if pos is None:
            rpos = np.full(self.n, -1, dtype=np.int64)
            rpos[self.r_idx] = np.arange(self.r_idx.size)
            ppos = np.full(self.n, -1, dtype=np.int64)
            ppos[self.p_idx.ravel()] = np.arange(self.p_idx.size)
            pos = self._pos = (rpos, ppos)
        return pos

    def _small(self) -> bool:
        """A window whose ``L`` is dense (:data:`DENSE_UP_TO`): its cofactor blocks come
        from ``V = U^-1`` formed once (:meth:`_v`), cheaper there than a solve per request."""
        return self.n <= DENSE_UP_TO and not scipy.sparse.issparse(self.B)

    def _by_columns(self, name: str) -> scipy.sparse.csc_array:
        """``B`` or ``L_RP`` (sparse: a large window's) by columns, rows sorted: as kept."""
        M = getattr(self, name)
        if isinstance(M, scipy.sparse.csc_array) and M.has_canonical_format:
            return M
        return _canonical_csc(M)

    def _columns_of(self, name: str, cols: np.ndarray) -> FloatArray:
        """``B[:, cols]`` or ``L_RP[:, cols]`` (``name``) as a dense array."""
        M = getattr(self, name)
        if scipy.sparse.issparse(M):
            return self._by_columns(name)[:, cols].toarray()
        return np.asarray(M)[:, cols]

    def dense(self) -> FloatArray:
        """The whole cofactor ``Q = L^-1``, dense, by blocks: ``Q_RR = S^-1``,
        ``Q_RP = -Q_RR B``, ``Q_PP = D^-1 + B^T Q_RR B`` (``D^-1`` per point), O(r^2 p +
        r p^2) for p eliminated parameters, not the O(n^3) of a dense inverse (a departure's
        conditional, :func:`seqat.departures.leaving_conditional`)."""
        Qrr = self._q_rr()
        npt = self.p_idx.shape[0]
        B = self.B.toarray() if scipy.sparse.issparse(self.B) else np.asarray(self.B)
        Qrp = -(Qrr @ B)  # dense BLAS: a sparse B times many columns is slower
        Qpp = -(B.T @ Qrp)
        blocks = np.arange(npt)[:, None] * GP_SIZE + np.arange(GP_SIZE)
        Qpp[blocks[:, :, None], blocks[:, None, :]] += self.Dinv
        Qpp = 0.5 * (Qpp + Qpp.T)
        blocked = np.block([[Qrr, Qrp], [Qrp.T, Qpp]])  # R first, then P
        order = np.argsort(np.concatenate([self.r_idx, self.p_idx.ravel()]))
        return blocked.take(order, axis=0)[:, order]
