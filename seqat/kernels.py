"""Compiled point-by-point kernels of the ground points' elimination (numba).

A window's eliminated ground point couples to the few images (and the camera) that see it:
its three columns of ``L_RP`` hold ``m`` non-zero rows (6 per ray), so the Schur product
``L_RP D^-1 L_PR`` and the points' marginals ``B_p^T Q_RR B_p`` cost ``O(sum m^2)`` taken
point by point, as a bundle adjuster's Schur eliminator takes them (Ceres'
``SchurEliminator``). In numpy a point costs some ten calls of microseconds each, which is
why the large windows went through sparse or grouped BLAS products instead, at the price of
products over zeros (points of different strips share no rows); compiled, the per-point loop
costs its flops (docs/algorithm.md, *Engines*). Sim's small blocks are reduced the same
way (:func:`eliminate_points`, from each ray's block; docs/algorithm.md, *Sim*), the rays'
weighted products summed by :func:`ray_products` and other per-image and per-point sums by
:func:`scatter_add`.

The loops add in a fixed order (points in turn, rows in storage order) and without
``fastmath`` (no reassociation, no fused multiply-add): the results do not depend on the CPU
or on a BLAS kernel. Each kernel is compiled once for int64 indices and float64 values, at
import (cached on disk beside this file, so only the first import compiles: ~1 s).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from seqat.types import FloatArray

_INDEX = "int64[::1]"
_VALUES = "float64[::1]"


@njit(f"int64({_INDEX}, {_INDEX}, {_VALUES}, int64, int64[::1], int64[::1], float64[:, ::1])",
      cache=True, nogil=True)
def _gather(indptr, indices, data, p, pos, rows, Lp):  # noqa: ANN001, ANN202
    """Point ``p``'s three columns of a CSC matrix made dense on their rows: ``Lp[:m]``
    (m, 3), ``rows[:m]`` the row numbers, in order of first appearance; ``pos`` maps row ->
    local index (-1: not gathered) and is left set for the caller to reset."""
    m = 0
    for c in range(3):
        col = 3 * p + c
        for k in range(indptr[col], indptr[col + 1]):
            i = indices[k]
            a = pos[i]
            if a < 0:
                a = m
                pos[i] = m
                rows[m] = i
                Lp[m, 0] = 0.0
                Lp[m, 1] = 0.0
                Lp[m, 2] = 0.0
                m += 1
            Lp[a, c] += data[k]
    return m


@njit(f"void({_INDEX}, {_INDEX}, {_VALUES}, float64[:, :, ::1], float64[:, ::1])",
      cache=True, nogil=True)
def _schur(indptr, indices, data, Dinv, out):  # noqa: ANN001, ANN202
    r = out.shape[0]
    npt = Dinv.shape[0]
    most = 0  # the most rows a point can have: its three columns' entries
    for p in range(npt):
        most = max(most, indptr[3 * p + 3] - indptr[3 * p])
    pos = np.full(r, -1, np.int64)
    rows = np.empty(r, np.int64)
    Lp = np.empty((r, 3))
    Bp = np.empty((r, 3))
    V = np.empty((most, most))
    run_at = np.empty(most, np.int64)
    run_len = np.empty(most, np.int64)
    for p in range(npt):
        m = _gather(indptr, indices, data, p, pos, rows, Lp)
        D = Dinv[p]
        for a in range(m):  # B_p = L_p D_p^-1
            for j in range(3):
                Bp[a, j] = Lp[a, 0] * D[0, j] + Lp[a, 1] * D[1, j] + Lp[a, 2] * D[2, j]
        for a in range(m):  # V = B_p L_p^T: the upper triangle by rows
            b0, b1, b2 = Bp[a, 0], Bp[a, 1], Bp[a, 2]
            Va = V[a]
            for b in range(a, m):
                Va[b] = b0 * Lp[b, 0] + b1 * Lp[b, 1] + b2 * Lp[b, 2]
        for a in range(m):  # ... mirrored: exactly symmetric
            for b in range(a):
                V[a, b] = V[b, a]
        nrun = 0  # the rows in runs of consecutive numbers (an image's six EOPs at least)
        b = 0
        while b < m:
            e = b + 1
            while e < m and rows[e] == rows[e - 1] + 1:
                e += 1
            run_at[nrun] = b
            run_len[nrun] = e - b
            nrun += 1
            b = e
        for a in range(m):  # added row by row, run by run (slices: vector instructions)
            out_a = out[rows[a]]
            Va = V[a]
            for k in range(nrun):
                at, n = run_at[k], run_len[k]
                seg = out_a[rows[at]:rows[at] + n]  # a view: added in place, no temporary
                seg += Va[at:at + n]
        for a in range(m):
            pos[rows[a]] = -1


@njit(f"void({_INDEX}, {_INDEX}, {_VALUES}, float64[:, ::1], {_INDEX}, float64[:, :, ::1])",
      cache=True, nogil=True)
def _quadratic(indptr, indices, data, Q, pts, out):  # noqa: ANN001, ANN202
    r = Q.shape[0]
    pos = np.full(r, -1, np.int64)
    rows = np.empty(r, np.int64)
    Bp = np.empty((r, 3))
    for t in range(pts.shape[0]):
        m = _gather(indptr, indices, data, pts[t], pos, rows, Bp)
        # sum over a, b of B[a, i] Q[a, b] B[b, j]: the diagonal terms, then each pair a < b
        # once (Q symmetric) for both of its orders
        s00 = s01 = s02 = s11 = s12 = s22 = 0.0
        for a in range(m):
            Qa = Q[rows[a]]
            a0, a1, a2 = Bp[a, 0], Bp[a, 1], Bp[a, 2]
            q = Qa[rows[a]]
            s00 += q * a0 * a0
            s01 += q * a0 * a1
            s02 += q * a0 * a2
            s11 += q * a1 * a1
            s12 += q * a1 * a2
            s22 += q * a2 * a2
            # w = sum over b > a of Q[a, b] B[b], in two interleaved partial sums (two
            # chains of dependent adds run at once; still a fixed order)
            w0 = w1 = w2 = u0 = u1 = u2 = 0.0
            b = a + 1
            while b + 1 < m:
                q = Qa[rows[b]]
                w0 += q * Bp[b, 0]
                w1 += q * Bp[b, 1]
                w2 += q * Bp[b, 2]
                q = Qa[rows[b + 1]]
                u0 += q * Bp[b + 1, 0]
                u1 += q * Bp[b + 1, 1]
                u2 += q * Bp[b + 1, 2]
                b += 2
            if b < m:
                q = Qa[rows[b]]
                w0 += q * Bp[b, 0]
                w1 += q * Bp[b, 1]
                w2 += q * Bp[b, 2]
            w0 += u0
            w1 += u1
            w2 += u2
            s00 += 2.0 * a0 * w0
            s11 += 2.0 * a1 * w1
            s22 += 2.0 * a2 * w2
            s01 += a0 * w1 + a1 * w0
            s02 += a0 * w2 + a2 * w0
            s12 += a1 * w2 + a2 * w1
        out[t, 0, 0] = s00
        out[t, 1, 1] = s11
        out[t, 2, 2] = s22
        out[t, 0, 1] = out[t, 1, 0] = s01
        out[t, 0, 2] = out[t, 2, 0] = s02
        out[t, 1, 2] = out[t, 2, 1] = s12
        for a in range(m):
            pos[rows[a]] = -1


def _csc(indptr: np.ndarray, indices: np.ndarray,
         data: FloatArray) -> tuple[np.ndarray, np.ndarray, FloatArray]:
    """The CSC arrays as the kernels take them (scipy's int32 indices widened)."""
    return (np.ascontiguousarray(indptr, dtype=np.int64),
            np.ascontiguousarray(indices, dtype=np.int64),
            np.ascontiguousarray(data, dtype=np.float64))


def schur_product(indptr: np.ndarray, indices: np.ndarray, data: FloatArray,
                  Dinv: FloatArray, r: int) -> FloatArray:
    """``L_RP D^-1 L_PR`` (r, r), exactly symmetric, of ``L_RP`` (r, 3 np) given by its CSC
    arrays (no duplicate entries) and the points' ``D_p^-1`` (np, 3, 3, symmetric)."""
    out = np.zeros((r, r))
    _schur(*_csc(indptr, indices, data), np.ascontiguousarray(Dinv, dtype=np.float64), out)
    return out


def point_quadratic(indptr: np.ndarray, indices: np.ndarray, data: FloatArray,
                    Q: FloatArray, pts: np.ndarray) -> FloatArray:
    """``B_p^T Q B_p`` (len(pts), 3, 3), exactly symmetric, of the points ``pts`` (positions
    in P) of ``B`` (r, 3 np) given by its CSC arrays (no duplicate entries); ``Q`` (r, r)
    symmetric (only its rows are read, one per row of ``B_p``)."""
    out = np.empty((np.size(pts), 3, 3))
    _quadratic(*_csc(indptr, indices, data), np.ascontiguousarray(Q, dtype=np.float64),
               np.ascontiguousarray(pts, dtype=np.int64), out)
    return out


@njit("void(float64[:, ::1], int64[::1], float64[:, ::1])", cache=True, nogil=True)
def _scatter_add(out, idx, vals):  # noqa: ANN001, ANN202
    for k in range(idx.shape[0]):
        i = idx[k]
        for j in range(vals.shape[1]):
            out[i, j] += vals[k, j]


def scatter_add(out: FloatArray, idx: np.ndarray, vals: FloatArray) -> None:
    """``out[idx[k]] += vals[k]`` for every ``k`` in turn (``np.add.at``'s sums, in its
    order); ``out`` (g, ...) C-contiguous, ``vals`` (len(idx), ...) of the same trailing
    shape."""
    k = np.size(idx)
    if k == 0:
        return
    assert out.flags.c_contiguous, "scatter_add: out must be C-contiguous"
    flat = out.reshape(out.shape[0], -1)
    _scatter_add(flat, np.ascontiguousarray(idx, dtype=np.int64),
                 np.ascontiguousarray(vals, dtype=np.float64).reshape(k, flat.shape[1]))


@njit("void(int64[::1], int64[::1], int64[::1], float64[:, :, ::1], float64[:, :, ::1], "
      "float64[:, ::1], int64, float64[:, ::1], float64[::1])", cache=True, nogil=True)
def _eliminate_points(order, start, img, blocks, Dinv, bp, c, N, rhs):  # noqa: ANN001, ANN202
    npt = Dinv.shape[0]
    cam0 = N.shape[0] - c
    most = 0
    for p in range(npt):
        most = max(most, start[p + 1] - start[p])
    rows = np.empty(6 * most + c, np.int64)
    M = np.empty((6 * most + c, 3))
    B = np.empty((6 * most + c, 3))
    for p in range(npt):
        t = start[p + 1] - start[p]
        if t == 0:
            continue
        size = 6 * t + c
        for a in range(c):  # the camera's rows: every ray of the point adds to them
            rows[6 * t + a] = cam0 + a
            M[6 * t + a, 0] = 0.0
            M[6 * t + a, 1] = 0.0
            M[6 * t + a, 2] = 0.0
        for s in range(t):
            o = order[start[p] + s]
            e0 = 6 * img[o]
            for a in range(6):
                rows[6 * s + a] = e0 + a
                M[6 * s + a, 0] = blocks[o, a, 0]
                M[6 * s + a, 1] = blocks[o, a, 1]
                M[6 * s + a, 2] = blocks[o, a, 2]
            for a in range(c):
                M[6 * t + a, 0] += blocks[o, 6 + a, 0]
                M[6 * t + a, 1] += blocks[o, 6 + a, 1]
                M[6 * t + a, 2] += blocks[o, 6 + a, 2]
        D = Dinv[p]
        z0 = D[0, 0] * bp[p, 0] + D[0, 1] * bp[p, 1] + D[0, 2] * bp[p, 2]
        z1 = D[1, 0] * bp[p, 0] + D[1, 1] * bp[p, 1] + D[1, 2] * bp[p, 2]
        z2 = D[2, 0] * bp[p, 0] + D[2, 1] * bp[p, 1] + D[2, 2] * bp[p, 2]
        for a in range(size):
            m0, m1, m2 = M[a, 0], M[a, 1], M[a, 2]
            B[a, 0] = m0 * D[0, 0] + m1 * D[1, 0] + m2 * D[2, 0]
            B[a, 1] = m0 * D[0, 1] + m1 * D[1, 1] + m2 * D[2, 1]
            B[a, 2] = m0 * D[0, 2] + m1 * D[1, 2] + m2 * D[2, 2]
            rhs[rows[a]] -= m0 * z0 + m1 * z1 + m2 * z2
        for a in range(size):  # the upper triangle, added to both halves: exactly symmetric
            ra = rows[a]
            b0, b1, b2 = B[a, 0], B[a, 1], B[a, 2]
            N[ra, ra] -= b0 * M[a, 0] + b1 * M[a, 1] + b2 * M[a, 2]
            for b in range(a + 1, size):
                v = b0 * M[b, 0] + b1 * M[b, 1] + b2 * M[b, 2]
                rb = rows[b]
                N[ra, rb] -= v
                N[rb, ra] -= v


def eliminate_points(obs_point: np.ndarray, obs_image: np.ndarray, blocks: FloatArray,
                     Dinv: FloatArray, b_p: FloatArray, c: int, N: FloatArray,
                     rhs: FloatArray) -> None:
    """Eliminate the points of a block from its normal equations, in place: ``N -= sum_p
    M_p D_p^-1 M_p^T`` and ``rhs -= sum_p M_p D_p^-1 b_p`` (Eq. 5), point by point in
    order of their number, their rays in storage order. ``M_p`` gathers the rays'
    ``blocks`` (k, 6 + c, 3) ``N_Rp`` blocks: a ray's first six rows at its image's EOP
    rows (``6 obs_image``), its last ``c`` (the camera's) added at ``N``'s last ``c``
    rows. ``Dinv`` (m, 3, 3) and ``b_p`` (m, 3) are the points'; ``N`` (r, r) C-contiguous
    keeps exact symmetry."""
    pt = np.ascontiguousarray(obs_point, dtype=np.int64)
    order = np.argsort(pt, kind="stable")
    start = np.zeros(Dinv.shape[0] + 1, dtype=np.int64)
    np.cumsum(np.bincount(pt, minlength=Dinv.shape[0]), out=start[1:])
    _eliminate_points(order, start, np.ascontiguousarray(obs_image, dtype=np.int64),
                      np.ascontiguousarray(blocks, dtype=np.float64),
                      np.ascontiguousarray(Dinv, dtype=np.float64),
                      np.ascontiguousarray(b_p, dtype=np.float64), int(c), N, rhs)


@njit("void(int64[::1], int64[::1], float64[:, :, ::1], float64[:, :, ::1], float64[::1], "
      "float64[:, ::1], float64[:, :, ::1], float64[:, ::1], float64[:, :, ::1], "
      "float64[:, ::1], float64[::1], float64[:, ::1], float64[:, :, ::1])",
      cache=True, nogil=True)
def _ray_products(img, pt, JR, Jp, w, ell, Nee, be, Nce, Ncc, bc, bp, NRp):  # noqa: ANN001, ANN202
    q = JR.shape[2]
    for o in range(img.shape[0]):
        wo = w[o]
        if wo == 0.0:
            continue
        i = img[o]
        p = pt[o]
        for r in range(2):
            e = ell[o, r]
            for a in range(q):
                wa = wo * JR[o, r, a]
                if a < 6:
                    for b in range(6):
                        Nee[i, a, b] += wa * JR[o, r, b]
                    be[i, a] += wa * e
                else:
                    for b in range(6):
                        Nce[i, a - 6, b] += wa * JR[o, r, b]
                    for b in range(6, q):
                        Ncc[a - 6, b - 6] += wa * JR[o, r, b]
                    bc[a - 6] += wa * e
                NRp[o, a, 0] += wa * Jp[o, r, 0]
                NRp[o, a, 1] += wa * Jp[o, r, 1]
                NRp[o, a, 2] += wa * Jp[o, r, 2]
            we = wo * e
            bp[p, 0] += we * Jp[o, r, 0]
            bp[p, 1] += we * Jp[o, r, 1]
            bp[p, 2] += we * Jp[o, r, 2]


def ray_products(img: np.ndarray, pt: np.ndarray, JR: FloatArray, Jp: FloatArray,
                 w: FloatArray, ell: FloatArray, n: int,
                 m: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray,
                                  FloatArray, FloatArray]:
    """The weighted products of a block's rays, summed per image and per point: ``w A^T A``
    and ``w A^T ell`` of each ray's two rows ``A = [JR | Jp]`` (``JR`` (k, 2, 6 + c): its
    EOP and camera columns, ``Jp`` (k, 2, 3) its point's; ``w`` (k,) its weight, ``ell``
    (k, 2) its residual). Returns ``N_ee`` (n, 6, 6) and ``b_e`` (n, 6) per image, ``N_ce``
    (n, c, 6), ``N_cc`` (c, c) and ``b_c`` (c,) of the camera, ``b_p`` (m, 3) per point and
    each ray's ``N_Rp`` block ``w JR^T Jp`` (k, 6 + c, 3), rays of weight 0 left out."""
    k, _, q = JR.shape
    c = q - 6
    out = (np.zeros((n, 6, 6)), np.zeros((n, 6)), np.zeros((n, c, 6)), np.zeros((c, c)),
           np.zeros(c), np.zeros((m, 3)), np.zeros((k, q, 3)))
    if k:
        _ray_products(np.ascontiguousarray(img, dtype=np.int64),
                      np.ascontiguousarray(pt, dtype=np.int64),
                      np.ascontiguousarray(JR, dtype=np.float64),
                      np.ascontiguousarray(Jp, dtype=np.float64),
                      np.ascontiguousarray(w, dtype=np.float64),
                      np.ascontiguousarray(ell, dtype=np.float64), *out)
    return out
