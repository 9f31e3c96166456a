"""The sequential update of the estimates and of the inverse normal matrix (seed 000 Eq. 10-14).

Notation of seed 000 §2.2 (derivation in docs/algorithm.md):

* ``xi_1`` existing parameters with cofactor ``Q = N11^-1`` (the *window*); ``xi_2`` new ones.
* ``y_2 = A21 xi_1 + A22 xi_2 + e_2`` rows touching existing parameters (y12 and y21 of the
  paper; weights ``P2``), ``y_3 = A32 xi_2 + e_3`` rows touching only new parameters (y22 and
  the GPS/INS constraints z2; weights ``P3``).
* ``D = M22 + L22 = A22^T P2 A22 + A32^T P3 A32``,
  ``P2bar = P2 - P2 A22 D^-1 A22^T P2``, ``P23bar = -P2 A22 D^-1 A32^T P3``,
  ``S = I + P2bar A21 N11^-1 A21^T``.
* Eq. 13 (corrected): ``xi_1 += N11^-1 A21^T S^-1 {P2bar (y2 - A21 xi_1) + P23bar y3}``;
  Eq. 14: ``xi_2 = D^-1 {A22^T P2 (y2 - A21 xi_1_new) + A32^T P3 y3}``.
* Eq. 11-12: ``N_r^-1 = N11^-1 - N11^-1 A21^T S^-1 P2bar A21 N11^-1``,
  ``W1 = M12 D^-1``, ``Q12 = -N_r^-1 W1``, ``Q22 = D^-1 + W1^T N_r^-1 W1``.

Only ``S`` (order m2 = rows of y2) and ``D`` (order n2 = new parameters) are inverted.

Everything here is written in *corrections* from a linearisation point: ``xi_1 = x1 + d1``
with prior ``d1 ~ (0, Q)``, ``xi_2 = x2_0 + d2``; ``l2``, ``l3`` are the reduced observations
(observed minus computed at the linearisation point, plus ``A * d_lin`` when iterating).
``A21`` is given only on the *touched* existing parameters (indices ``touched``); the other
columns of ``A21`` are zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse

from seqat.errors import EstimationError
from seqat.types import FloatArray

#: Updates whose ``A21`` has more entries than this form their products sparse (the paper
#: strip's ~80 x 250 stays dense: there numpy beats scipy.sparse's per-call cost).
SPARSE_ROWS_FROM = 50_000

_POTRF = scipy.linalg.lapack.dpotrf
_POTRI = scipy.linalg.lapack.dpotri
_GESV = scipy.linalg.lapack.dgesv
_TRTRI = scipy.linalg.lapack.dtrtri
_TRMM = scipy.linalg.blas.dtrmm
#: :func:`lower_inverse` splits triangles from this order on (below it one ``trtri`` call).
SPLIT_TRIANGLE_FROM = 128


@dataclass(frozen=True, kw_only=True, eq=False)
class LinearRows:
    """New observation rows, linearised.

    Attributes
    ----------
    A21 : (m2, t) float
        Design of the y2 rows on the touched existing parameters.
    A22 : (m2, n2) float
        Design of the y2 rows on the new parameters.
    w2 : (m2,) float
        Weights (diagonal of ``P2``).
    l2 : (m2,) float
    A32 : (m3, n2) float
    w3 : (m3,) float
    l3 : (m3,) float
    """

    A21: FloatArray
    A22: FloatArray
    w2: FloatArray
    l2: FloatArray
    A32: FloatArray
    w3: FloatArray
    l3: FloatArray


@dataclass(frozen=True, kw_only=True, eq=False)
class UpdateSolution:
    """Corrections and the intermediate matrices reused by :func:`update_cofactor`.

    ``delta1_touched`` is ``d1`` on the touched parameters only; the full ``d1`` is
    ``N11^-1[:, touched] kappa1`` (see :meth:`delta1`). ``G = N11^-1 A21^T`` is formed on the
    touched rows only (``Gt``): over the whole window (n1 rows) it would cost ``n1 t m2`` per
    iteration, the most expensive product of a large window's update (Seneca: n1 ~ 4000,
    84 of 116 ms); ``d1`` needs one product with ``kappa1 = A21^T kappa``, which the
    information engine forms as one solve (:meth:`seqat.window.Window.q_apply`).
    """

    Qt: FloatArray | None  # (n1, t)  N11^-1 on the touched columns (None: given as a block)
    # the observation-space terms; None when solved in the parameter space (``terms``)
    Gt: FloatArray | None  # (t, m2)  N11^-1 A21^T on the touched rows
    H: FloatArray | None  # (m2, m2)  A21 N11^-1 A21^T
    P2bar: FloatArray | None  # (m2, m2)
    S: FloatArray | None  # (m2, m2)  I + P2bar H
    D_inv: FloatArray  # (n2, n2)  (M22 + L22)^-1
    kappa: FloatArray | None  # (m2,)  S^-1 {P2bar l2 + P23bar l3}
    delta1_touched: FloatArray  # (t,)
    delta2: FloatArray  # (n2,)
    ssr_increment: float  # increase of the weighted sum of squared residuals

    kappa1: FloatArray  # (t,)  A21^T kappa: d1 = N11^-1[:, touched] kappa1

    def delta1(self) -> FloatArray:
        """Correction of every existing parameter, (n1,) (``Q`` given with its columns)."""
        if self.Qt is None:
            raise ValueError("solve_update was given Q[touched, touched] only: "
                             "d1 = Q[:, touched] @ kappa1")
        return self.Qt @ self.kappa1


def spd_inverse(M: FloatArray, what: str) -> FloatArray:
    """Inverse of a symmetric positive definite matrix, or :class:`EstimationError`.

    LAPACK ``potrf`` (which fails unless ``M`` is positive definite) and ``potri`` on its
    factor: two calls, the result exactly symmetric (the matrices are small: an update's new
    parameters, a departure's leaving ones, where numpy's per-call overhead is the cost)."""
    M = np.asarray(M, dtype=np.float64)
    if M.shape[0] == 0:
        return np.zeros((0, 0))
    U, info = _POTRF(M, lower=0, clean=1)
    if info == 0 and np.isfinite(U).all():
        inv, info = _POTRI(U, lower=0)
    else:
        info = info or -1
    if info != 0:
        ev = np.linalg.eigvalsh(np.nan_to_num(M))
        raise EstimationError(
            f"{what} ({M.shape[0]}x{M.shape[0]}) is not positive definite: "
            f"eigenvalues from {ev[0]:.3g} to {ev[-1]:.3g}"
        )
    # potri writes the upper triangle; below it stand U's zeros (clean): mirror it
    out = inv + inv.T
    out.flat[:: M.shape[0] + 1] = np.diagonal(inv)
    return out


def lower_inverse(L: FloatArray) -> FloatArray:
    """``L^-1`` of a regular lower triangular ``L`` (Fortran-ordered, zeros above the
    diagonal: a ``potrf`` factor with ``clean``), lower triangular and Fortran-ordered, by
    halves::

        [[A, 0], [B, C]]^-1 = [[A^-1, 0], [-C^-1 B A^-1, C^-1]]

    LAPACK ``trtri`` on the two halves, BLAS ``trmm`` for the corner: OpenBLAS's ``trtri``
    runs at half the rate of ``potrf`` at the paper strip's r ~ 190 (0.37-0.43 ms against
    0.27-0.30 ms by halves, measured 2026-12-03), ``trmm`` at the full rate."""
    n = L.shape[0]
    h = n // 2 if n >= SPLIT_TRIANGLE_FROM else n
    out = np.zeros((n, n), order="F")
    for a, b in ((0, h), (h, n)):
        if b > a:
            inv, info = _TRTRI(L[a:b, a:b], lower=1)
            if info != 0:
                raise EstimationError(f"LAPACK trtri: a singular triangle ({info})")
            out[a:b, a:b] = inv
    if h < n:  # -C^-1 B A^-1
        out[h:, :h] = _TRMM(1.0, out[:h, :h], _TRMM(-1.0, out[h:, h:], L[h:, :h], lower=1),
                            lower=1, side=1)
    return out


def solve_update(Q: FloatArray, touched: np.ndarray, rows: LinearRows, *,
                 columns: bool = False, block: bool = False,
                 terms: bool = True) -> UpdateSolution:
    """Estimate the corrections of existing and new parameters (Eq. 13-14).

    Parameters
    ----------
    Q : (n1, n1) float, (n1, t) with ``columns``, (t, t) with ``block``
        Cofactor (inverse normal matrix) of the existing parameters, only its columns
        ``Q[:, touched]``, or only its block ``Q[touched, touched]`` (all the update needs;
        :meth:`UpdateSolution.delta1` then needs the caller's ``Q[:, touched] kappa1``).
    touched : (t,) int
        Indices of the existing parameters that the y2 rows involve.
    rows : LinearRows
    terms : bool
        ``False``: the caller needs the corrections only (not :func:`update_cofactor` nor
        data snooping): a large update with more rows than touched parameters is then
        solved in the parameter space (:func:`_solve_in_parameter_space`), its
        observation-space terms left ``None``.

    Returns
    -------
    UpdateSolution
    """
    A21, A22, A32 = rows.A21, rows.A22, rows.A32
    w2, w3 = rows.w2, rows.w3
    P2A22 = w2[:, None] * A22
    # A row touches one point and one image (and the camera): A21 and A22 have a few
    # non-zeros per row. A large update forms G, H and P2bar as sparse products, O(m2 t)
    # instead of O(t^2 m2 + m2 t m2) (docs/algorithm.md, *Engines*); the same numbers.
    sparse = A21.size > SPARSE_ROWS_FROM
    if sparse:
        A21s, P2A22s = scipy.sparse.csr_array(A21), scipy.sparse.csr_array(P2A22)
        A22s = scipy.sparse.csr_array(A22)
        D = (A22s.T @ P2A22s).toarray() + A32.T @ (w3[:, None] * A32)  # M22 + L22
    else:
        D = A22.T @ P2A22 + A32.T @ (w3[:, None] * A32)
    D_inv = spd_inverse(D, "(M22 + L22)")
    b3 = A32.T @ (w3 * rows.l3)
    if sparse and block and not terms and A21.shape[0] > A21.shape[1]:
        return _solve_in_parameter_space(Q, rows, A21s, P2A22s, D_inv, b3)
    if sparse:
        P2bar = -(P2A22s @ (P2A22s @ D_inv).T)
    else:
        P2bar = -(P2A22 @ D_inv @ P2A22.T)
    P2bar.flat[:: P2bar.shape[0] + 1] += w2
    P23bar_l3 = -P2A22 @ (D_inv @ b3)
    Qt = None if block else Q if columns else Q[:, touched]
    Q_tt = Q if block else Qt[touched]  # type: ignore[index]
    if sparse:
        Gt = (A21s @ Q_tt).T  # Q_tt symmetric
        H = A21s @ Gt
        H = 0.5 * (H + H.T)
    else:
        Gt = Q_tt @ A21.T
        H = A21 @ Gt
    m2 = A21.shape[0]
    if sparse:  # P2bar = P2 - P2 A22 D^-1 A22^T P2 of rank n2 << m2: O(m2^2 n2), not O(m2^3)
        S = w2[:, None] * H - P2A22s @ (D_inv @ (P2A22s.T @ H))
    else:
        S = P2bar @ H
    S.flat[:: m2 + 1] += 1.0
    kappa = P2bar @ rows.l2 + P23bar_l3
    if m2:
        _, _, kappa, info = _GESV(S, kappa)  # LU with partial pivoting, as np.linalg.solve
        if info != 0:
            raise EstimationError(f"[I + P2bar A21 N11^-1 A21^T] ({m2}x{m2}) is singular")
    d1t = Gt @ kappa
    d2 = D_inv @ (P2A22.T @ (rows.l2 - A21 @ d1t) + b3)
    v2 = rows.l2 - A21 @ d1t - A22 @ d2
    v3 = rows.l3 - A32 @ d2
    # Omega grows by the new rows' weighted residuals plus d1^T N11 d1 = kappa^T H kappa.
    ssr = float(kappa @ H @ kappa + np.sum(w2 * v2**2) + np.sum(w3 * v3**2))
    return UpdateSolution(
        Qt=Qt,
        Gt=Gt,
        H=H,
        P2bar=P2bar,
        S=S,
        D_inv=D_inv,
        kappa=kappa,
        kappa1=A21.T @ kappa,
        delta1_touched=d1t,
        delta2=d2,
        ssr_increment=ssr,
    )


def _solve_in_parameter_space(Q_tt: FloatArray, rows: LinearRows,
                              A21s: scipy.sparse.csr_array, P2A22s: scipy.sparse.csr_array,
                              D_inv: FloatArray, b3: FloatArray) -> UpdateSolution:
    """:func:`solve_update` of a large update with more rows (m2) than touched parameters
    (t): the same corrections from a t x t system instead of the m2 x m2 one.

    With the new parameters eliminated (``P2bar``, as in Eq. 13) and ``r = P2bar l2 +
    P23bar l3 = P2 (l2 - A22 D^-1 (A22^T P2 l2 + b3))``, Eq. 13's ``kappa = S^-1 r`` is only
    needed as ``kappa1 = A21^T kappa``; by ``A21^T (I + P2bar A21 Q A21^T)^-1 = (I + C Q)^-1
    A21^T`` (push-through) with ``C = A21^T P2bar A21 = A21^T P2 A21 - E D^-1 E^T``, ``E =
    A21^T P2 A22``::

        kappa1 = (I + C Q_tt)^-1 A21^T r,   d1_t = Q_tt kappa1,   kappa^T H kappa = kappa1^T d1_t

    All products sparse but ``E D^-1`` (t x n2): O(m2 t) instead of the O(m2^3) of forming
    and solving ``S`` (a block's first image of a strip: 272 points born at once, m2 = 1210,
    t = 465: 278 -> 30 ms)."""
    w2, l2 = rows.w2, rows.l2
    E = (A21s.T @ P2A22s).toarray()  # (t, n2)
    ED = E @ D_inv
    # C Q_tt with C's sparse part (a row touches one point and one image) and its rank-n2
    # part apart: O(nnz t + t^2 n2) instead of the O(t^3) of a dense C times Q_tt
    C_s = scipy.sparse.csr_array(A21s.T @ A21s.multiply(w2[:, None]))
    r = w2 * l2 - P2A22s @ (D_inv @ (P2A22s.T @ l2 + b3))
    M = C_s @ Q_tt - ED @ (E.T @ Q_tt)
    M.flat[:: M.shape[0] + 1] += 1.0
    kappa1 = A21s.T @ r
    if kappa1.size:
        _, _, kappa1, info = _GESV(M, kappa1)
        if info != 0:
            raise EstimationError(f"[I + A21^T P2bar A21 N11^-1] ({M.shape[0]}) is singular")
    d1t = Q_tt @ kappa1
    d2 = D_inv @ (P2A22s.T @ (l2 - A21s @ d1t) + b3)
    v2 = l2 - A21s @ d1t - rows.A22 @ d2
    v3 = rows.l3 - rows.A32 @ d2
    ssr = float(kappa1 @ d1t + np.sum(w2 * v2**2) + np.sum(rows.w3 * v3**2))
    return UpdateSolution(Qt=None, Gt=None, H=None, P2bar=None, S=None, D_inv=D_inv,
                          kappa=None, kappa1=kappa1, delta1_touched=d1t, delta2=d2,
                          ssr_increment=ssr)


def update_cofactor(
    Q: FloatArray, touched: np.ndarray, rows: LinearRows, sol: UpdateSolution
) -> FloatArray:
    """New cofactor of ``[xi_1, xi_2]`` (Eq. 11-12); ``Q`` is overwritten with ``N_r^-1``.

    Parameters
    ----------
    Q : (n1, n1) float
        Cofactor of the existing parameters; modified in place.
    touched : (t,) int
    rows : LinearRows
    sol : UpdateSolution
        From :func:`solve_update` with the same ``Q`` and ``rows``.

    Returns
    -------
    (n1 + n2, n1 + n2) float
    """
    assert sol.S is not None and sol.P2bar is not None  # solve_update(terms=True)
    T = np.linalg.solve(sol.S, sol.P2bar)  # S^-1 P2bar (symmetric)
    T = 0.5 * (T + T.T)
    G = Q[:, touched] @ rows.A21.T  # N11^-1 A21^T
    Q -= (G @ T) @ G.T  # Eq. 12: N_r^-1
    W1t = (rows.A21.T @ (rows.w2[:, None] * rows.A22)) @ sol.D_inv  # M12 D^-1 on touched rows
    Q12 = -Q[:, touched] @ W1t
    Q22 = sol.D_inv + W1t.T @ Q[np.ix_(touched, touched)] @ W1t
    n1, n2 = Q.shape[0], Q22.shape[0]
    out = np.empty((n1 + n2, n1 + n2))
    out[:n1, :n1] = Q
    out[:n1, n1:] = Q12
    out[n1:, :n1] = Q12.T
    out[n1:, n1:] = 0.5 * (Q22 + Q22.T)
    return out
