"""Sim's normal equations: one linearisation of a block, GP-reduced, and its cofactors.

The reduced EOP normal matrix ``N_r = N_ee + N_z - N_ep N_pp^-1 N_ep^T`` (sparse, banded along
a strip) is factorised by sparse LU; GP corrections follow by back-substitution (seed 000
Eq. 5-6). Used by :func:`seqat.simultaneous.adjust_block`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from seqat.errors import EstimationError
from seqat.geometry import depth, project, project_with_jacobians, wrap_angle
from seqat.robust import cauchy_cost, cauchy_weight
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray, PinholeCamera

#: Columns of the reduced inverse solved at once when extracting cofactor blocks.
COVARIANCE_CHUNK_IMAGES = 200


@dataclass(frozen=True, kw_only=True, eq=False)
class BlockData:
    """Observations of a block in local coordinates.

    Attributes
    ----------
    nav_eop : (n, 6) float
        GPS/INS EOP constraints (local metres, radians).
    nav_sigma : (n, 6) float
    obs_image : (k,) int
    obs_point : (k,) int
        Indices into the point arrays, ``[0, m)``.
    obs_uv : (k, 2) float
        Pixels.
    obs_sigma_px : (k,) float
    n_points : int
    """

    nav_eop: FloatArray
    nav_sigma: FloatArray
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_uv: FloatArray
    obs_sigma_px: FloatArray
    n_points: int

    @property
    def n_images(self) -> int:
        return int(self.nav_eop.shape[0])


@dataclass(eq=False)
class Normals:
    """Normal equations of one linearisation, GP-reduced."""

    lu: spla.SuperLU
    N_ep: sp.csr_matrix  # (6n, 3m)
    Nep_blocks: FloatArray  # (k, 6, 3) the block of each observation
    Npp_inv: FloatArray  # (m, 3, 3)
    b_p: FloatArray  # (3m,)
    size: int
    Nee: FloatArray  # (n, 6, 6) EOP diagonal blocks (nav included)
    Npp: FloatArray  # (m, 3, 3)
    undetermined: np.ndarray  # (m,) bool: points out of this linearisation


def eop_residual(nav_eop: FloatArray, eop: FloatArray) -> FloatArray:
    """``nav - eop`` with the angle differences wrapped."""
    r = nav_eop - eop
    r[:, 3:] = wrap_angle(r[:, 3:])
    return r


def linearise(
    camera: PinholeCamera, data: BlockData, eop: FloatArray, gp: FloatArray,
    damping: float = 0.0, robust_scale: float | None = None,
) -> tuple[Normals, FloatArray, FloatArray]:
    """Build and factorise the reduced normal equations at ``(eop, gp)``.

    ``damping`` > 0 adds Marquardt's ``damping * diag(N)`` to the normal matrix (a
    Levenberg-Marquardt step); 0 is the Gauss-Newton system.

    Returns the factorisation and the reduced right-hand side, plus the right-hand side of
    the points.
    """
    n, m = data.n_images, data.n_points
    img, pt = data.obs_image, data.obs_point
    uv, Je, Jp = project_with_jacobians(eop[img], gp[pt], camera)
    ell = data.obs_uv - uv  # (k, 2)
    w = cauchy_weight(ell, data.obs_sigma_px, robust_scale) / data.obs_sigma_px**2
    # Points the data do not determine here (parallel rays, an iterate sent far off by a
    # blunder): their rows get no weight in this linearisation and their block is the
    # identity (no step), instead of a singular system that rounding decides.
    Npp = np.zeros((m, GP_SIZE, GP_SIZE))
    np.add.at(Npp, pt, np.einsum("kri,krj->kij", Jp * w[:, None, None], Jp))
    undetermined = np.zeros(m, dtype=bool)
    if m:
        ev = np.linalg.eigvalsh(Npp)
        undetermined = ~(ev[:, 0] > 1e-12 * np.maximum(ev[:, -1], 1e-300)) | ~np.isfinite(
            ev[:, 0])
        if undetermined.any():
            w = np.where(undetermined[pt], 0.0, w)
    wJe = Je * w[:, None, None]
    wJp = Jp * w[:, None, None]
    Nee = np.zeros((n, EOP_SIZE, EOP_SIZE))
    np.add.at(Nee, img, np.einsum("kri,krj->kij", wJe, Je))
    Nee[:, np.arange(EOP_SIZE), np.arange(EOP_SIZE)] += 1.0 / data.nav_sigma**2
    b_e = np.zeros((n, EOP_SIZE))
    np.add.at(b_e, img, np.einsum("kri,kr->ki", wJe, ell))
    b_e += eop_residual(data.nav_eop, eop) / data.nav_sigma**2
    Npp[undetermined] = np.eye(GP_SIZE)  # the other blocks keep their rows' weights
    b_p = np.zeros((m, GP_SIZE))
    np.add.at(b_p, pt, np.einsum("kri,kr->ki", wJp, ell))
    if damping > 0.0:
        diag3, diag6 = np.arange(GP_SIZE), np.arange(EOP_SIZE)
        Npp[:, diag3, diag3] *= 1.0 + damping
        Nee[:, diag6, diag6] *= 1.0 + damping
    Nep_blocks = np.einsum("kri,krj->kij", wJe, Jp)  # (k, 6, 3)
    try:
        Npp_inv = np.linalg.inv(Npp)
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"singular 3x3 ground point normal block ({m} points)") from err
    rows = (EOP_SIZE * img[:, None, None] + np.arange(EOP_SIZE)[None, :, None]).repeat(GP_SIZE, 2)
    cols = (GP_SIZE * pt[:, None, None] + np.arange(GP_SIZE)[None, None, :]).repeat(EOP_SIZE, 1)
    N_ep = sp.csr_matrix(
        (Nep_blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(EOP_SIZE * n, GP_SIZE * m)
    )
    Npp_inv_sp = sp.bsr_matrix(
        (Npp_inv, np.arange(m), np.arange(m + 1)), shape=(GP_SIZE * m, GP_SIZE * m)
    ).tocsr()
    U1 = N_ep @ Npp_inv_sp  # N_ep N_pp^-1  (Eq. 5, U_1)
    Nee_sp = sp.bsr_matrix(
        (Nee, np.arange(n), np.arange(n + 1)), shape=(EOP_SIZE * n, EOP_SIZE * n)
    ).tocsr()
    N_r = (Nee_sp - U1 @ N_ep.T).tocsc()
    rhs = b_e.ravel() - U1 @ b_p.ravel()
    try:
        lu = spla.splu(N_r)
    except RuntimeError as err:
        raise EstimationError(f"reduced EOP normal matrix ({N_r.shape[0]}) is singular") from err
    return (
        Normals(
            lu=lu,
            N_ep=N_ep,
            Nep_blocks=Nep_blocks,
            Npp_inv=Npp_inv,
            b_p=b_p.ravel(),
            size=N_r.shape[0],
            Nee=Nee,
            Npp=Npp,
            undetermined=undetermined,
        ),
        rhs,
        ell,
    )


def weighted_ssr(camera: PinholeCamera, data: BlockData, eop: FloatArray,
                  gp: FloatArray, robust_scale: float | None = None) -> float:
    """Weighted sum of squared residuals (image points and nav) at ``(eop, gp)``; with a
    ``robust_scale`` the image points' Cauchy cost (:mod:`seqat.robust`)."""
    img, pt = data.obs_image, data.obs_point
    if np.any(depth(eop[img], gp[pt]) <= 0.0):
        return math.inf  # a point behind a camera that sees it: not a solution
    res = data.obs_uv - project(eop[img], gp[pt], camera)
    ssr = cauchy_cost(res, data.obs_sigma_px, robust_scale)
    ssr += float(np.sum(eop_residual(data.nav_eop, eop) ** 2 / data.nav_sigma**2))
    return ssr if np.isfinite(ssr) else math.inf


def back_substitute(nrm: Normals, delta_e: FloatArray) -> FloatArray:
    """GP corrections ``N_pp^-1 (b_p - N_ep^T delta_e)`` (Eq. 6)."""
    r = (nrm.b_p - nrm.N_ep.T @ delta_e).reshape(-1, GP_SIZE)
    return np.einsum("mij,mj->mi", nrm.Npp_inv, r)


def eop_cofactor_blocks(
    nrm: Normals, n: int, pairs: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[FloatArray, FloatArray]:
    """Diagonal 6x6 blocks of ``N_r^-1`` and, optionally, its blocks ``(a[k], b[k])``.

    ``N_r^-1`` is solved ``COVARIANCE_CHUNK_IMAGES`` images (columns) at a time, so memory stays
    ``O(n * chunk)``.

    Returns
    -------
    diag : (n, 6, 6) float
    pair_blocks : (len(a), 6, 6) float
    """
    diag = np.empty((n, EOP_SIZE, EOP_SIZE))
    a, b = pairs if pairs is not None else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    pair_blocks = np.empty((a.size, EOP_SIZE, EOP_SIZE))
    for start in range(0, n, COVARIANCE_CHUNK_IMAGES):
        stop = min(n, start + COVARIANCE_CHUNK_IMAGES)
        cols = np.arange(EOP_SIZE * start, EOP_SIZE * stop)
        rhs = np.zeros((EOP_SIZE * n, cols.size))
        rhs[cols, np.arange(cols.size)] = 1.0
        X = nrm.lu.solve(rhs)  # (6n, 6c) columns of N_r^-1
        Xb = X.reshape(n, EOP_SIZE, stop - start, EOP_SIZE)
        idx = np.arange(start, stop)
        diag[start:stop] = Xb[idx, :, idx - start, :]
        sel = (b >= start) & (b < stop)
        pair_blocks[sel] = Xb[a[sel], :, b[sel] - start, :]
    return diag, pair_blocks


def gp_cofactors(nrm: Normals, data: BlockData) -> FloatArray:
    """3x3 cofactor of every GP (Eq. 5, ``U_3``).

    ``N_pp^-1 + V^T N_r^-1 V`` with ``V = N_ep N_pp^-1``.
    """
    n, m = data.n_images, data.n_points
    img, pt = data.obs_image, data.obs_point
    U = nrm.Nep_blocks @ nrm.Npp_inv[pt]  # 6x3 block N_ep(i, p) N_pp^-1(p) per observation
    # All ordered pairs (o1, o2) of observations of the same point.
    order = np.argsort(pt, kind="stable")
    counts = np.bincount(pt, minlength=m)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rep = counts[pt[order]]
    o1 = np.repeat(order, rep)
    within = np.arange(o1.size) - np.repeat(np.cumsum(rep) - rep, rep)
    o2 = order[np.repeat(starts[pt[order]], rep) + within]
    _, Qpairs = eop_cofactor_blocks(nrm, n, (img[o1], img[o2]))
    contrib = np.einsum("kia,kij,kjb->kab", U[o1], Qpairs, U[o2])
    Qp = nrm.Npp_inv.copy()
    np.add.at(Qp, pt[o1], contrib)
    return Qp


def full_normal(nrm: Normals, n: int, m: int) -> FloatArray:
    """Dense normal matrix over ``[EOPs, GPs]``: its GP-GP part is exactly block diagonal
    (the sequential information engine eliminates those blocks)."""
    ne = EOP_SIZE * n
    N = np.zeros((ne + GP_SIZE * m, ne + GP_SIZE * m))
    for i in range(n):
        N[EOP_SIZE * i : EOP_SIZE * (i + 1), EOP_SIZE * i : EOP_SIZE * (i + 1)] = nrm.Nee[i]
    for j in range(m):
        o = ne + GP_SIZE * j
        N[o : o + GP_SIZE, o : o + GP_SIZE] = nrm.Npp[j]
    Nep = nrm.N_ep.toarray()
    N[:ne, ne:] = Nep
    N[ne:, :ne] = Nep.T
    return N


def full_cofactor(nrm: Normals, n: int, m: int) -> FloatArray:
    """Dense inverse normal matrix over ``[EOPs, GPs]`` (Eq. 5)."""
    Qee = nrm.lu.solve(np.eye(EOP_SIZE * n))
    Qee = 0.5 * (Qee + Qee.T)
    Npp_inv_sp = sp.bsr_matrix(
        (nrm.Npp_inv, np.arange(m), np.arange(m + 1)), shape=(GP_SIZE * m, GP_SIZE * m)
    ).tocsr()
    U1 = (nrm.N_ep @ Npp_inv_sp).toarray()  # N_ep N_pp^-1
    Qep = -Qee @ U1  # U_2
    Qpp = Npp_inv_sp.toarray() + U1.T @ Qee @ U1  # U_3
    Qpp = 0.5 * (Qpp + Qpp.T)
    return np.block([[Qee, Qep], [Qep.T, Qpp]])
