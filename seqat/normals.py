"""Sim's normal equations: one linearisation of a block, GP-reduced, and its cofactors.

The reduced normal matrix ``N_r = N_RR + N_z - N_Rp N_pp^-1 N_Rp^T`` of a block of up to
:data:`DENSE_REDUCED_MAX` parameters is formed dense, its points eliminated one by one
(:func:`seqat.kernels.eliminate_points`), and factorised by dense LU; a larger one's is
sparse (banded along a strip) and factorised by sparse LU. GP corrections follow by
back-substitution (seed 000 Eq. 5-6). ``R`` are the parameters kept in the reduced
system: the EOPs (``6 n``, image by image) and, with self-calibration, the free interior
parameters of the camera (``c``, last; :mod:`seqat.calibration`). Used by
:func:`seqat.adjustment.adjust_block`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from seqat.errors import EstimationError
from seqat.geometry import depth, nearest_branch, project, project_with_jacobians, wrap_angle
from seqat.kernels import eliminate_points, ray_products, scatter_add
from seqat.robust import (
    cauchy_cost,
    cauchy_weight,
    nav_cost,
    nav_tail_curvature,
    nav_weight,
    ray_u2,
)
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray, PinholeCamera

#: A point's block with the loss's own curvature is used while its smallest eigenvalue is
#: above this fraction of its largest (positive definite, not near singular); IRLS's else
#: (:func:`_tail_rays`, :mod:`seqat.tail_points`).
MIN_EIGENVALUE_RATIO = 1e-6

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
    control_point : (g,) int
        Ground control (:class:`seqat.types.ControlPoint`): the points whose coordinates
        are observed, each once, ...
    control_xyz : (g, 3) float
        ... their surveyed coordinates (local metres) ...
    control_weight : (g, 3) float
        ... and the weights ``1 / sigma^2`` of those observations (0: a free coordinate).
    """

    nav_eop: FloatArray
    nav_sigma: FloatArray
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_uv: FloatArray
    obs_sigma_px: FloatArray
    n_points: int
    control_point: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    control_xyz: FloatArray = field(default_factory=lambda: np.zeros((0, GP_SIZE)))
    control_weight: FloatArray = field(default_factory=lambda: np.zeros((0, GP_SIZE)))

    def control_ssr(self, gp: FloatArray) -> float:
        """Weighted sum of squared residuals of the control points' coordinates at ``gp``."""
        if not self.control_point.size:
            return 0.0
        return float(np.sum(self.control_weight * (self.control_xyz - gp[self.control_point])**2))

    @property
    def n_images(self) -> int:
        return int(self.nav_eop.shape[0])


@dataclass(frozen=True, kw_only=True, eq=False)
class CameraBlock:
    """The free interior parameters of a self-calibrating block: their positions in
    :data:`seqat.types.INTRINSICS` and their prior (stochastic constraint)."""

    index: np.ndarray  # (c,) int
    prior: FloatArray  # (c,) prior values
    sigma: FloatArray  # (c,) prior standard deviations

    @property
    def size(self) -> int:
        return int(self.index.size)

    def residual(self, camera: PinholeCamera) -> FloatArray:
        """``prior - current`` of the free parameters."""
        return self.prior - camera.intrinsics[self.index]


#: Reduced systems up to this order (150 images) are formed and factorised dense; larger
#: ones sparse (a strip's banded system: dense and sparse cost the same at ~1100).
DENSE_REDUCED_MAX = 900


class DenseLU:
    """LU factors (partial pivoting) of a dense reduced normal matrix, solved as
    :class:`scipy.sparse.linalg.SuperLU` is; an exactly singular matrix is an
    :class:`~seqat.errors.EstimationError`, as for the sparse factorisation."""

    def __init__(self, a: FloatArray) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", sla.LinAlgWarning)  # singular: checked below
            self._lu, self._piv = sla.lu_factor(a, check_finite=False)
        if np.any(np.diagonal(self._lu) == 0.0):
            raise EstimationError(f"reduced EOP normal matrix ({a.shape[0]}) is singular")

    def solve(self, rhs: FloatArray) -> FloatArray:
        return np.asarray(sla.lu_solve((self._lu, self._piv), rhs, check_finite=False))


Factor = spla.SuperLU | DenseLU


@dataclass(eq=False)
class Normals:
    """Normal equations of one linearisation, GP-reduced.

    ``N_Rp`` (r, 3m) is kept as its rays' blocks (``obs_blocks`` at rows ``obs_rows``,
    columns of point ``obs_point``) and made a sparse matrix only when asked for (the
    cofactors): a step's back-substitution takes the blocks themselves."""

    lu: Factor
    N_RR: sp.csr_matrix | FloatArray  # (r, r) EOPs and camera (nav and camera prior included)
    Npp_inv: FloatArray  # (m, 3, 3)
    b_p: FloatArray  # (3m,)
    size: int  # r = 6 n + c
    n_camera: int  # c: free interior parameters (last in R)
    Npp: FloatArray  # (m, 3, 3)
    undetermined: np.ndarray  # (m,) bool: points out of this linearisation
    obs_blocks: FloatArray  # (k, 6 + c, 3) each ray's block of N_Rp
    obs_rows: np.ndarray  # (k, 6 + c) its rows in R
    obs_point: np.ndarray  # (k,) its point
    _N_Rp: sp.csr_matrix | None = None

    @property
    def N_Rp(self) -> sp.csr_matrix:
        """(r, 3m) sparse, the rays' blocks summed (the camera's rows of a point's rays)."""
        if self._N_Rp is None:
            self._N_Rp = _sparse_N_Rp(self.obs_blocks, self.obs_rows, self.obs_point,
                                      self.size, self.Npp.shape[0])
        return self._N_Rp

    def dense_N_RR(self) -> FloatArray:
        """``N_RR`` as a dense (r, r) array, whichever way it was formed."""
        return self.N_RR.toarray() if sp.issparse(self.N_RR) else np.array(self.N_RR)


def _sparse_N_Rp(blocks: FloatArray, rows: np.ndarray, point: np.ndarray, r: int,
                 m: int) -> sp.csr_matrix:
    """(r, 3m) sparse of the rays' ``blocks`` (k, q, 3) at ``rows`` (k, q), in the columns
    of their ``point`` (k,), the duplicates (the camera's rows of a point's rays) summed."""
    cols = GP_SIZE * point[:, None, None] + np.arange(GP_SIZE)[None, None, :]
    return sp.csr_matrix((blocks.ravel(), (np.repeat(rows[:, :, None], GP_SIZE, axis=2).ravel(),
                                           np.repeat(cols, rows.shape[1], axis=1).ravel())),
                         shape=(r, GP_SIZE * m))


def on_nav_branch(eop: FloatArray, nav_eop: FloatArray) -> bool:
    """Put the angles of ``eop`` (n, 6, in place) on the Euler branch of the GPS/INS
    attitude ``nav_eop``, the same rotations (:func:`seqat.geometry.nearest_branch`),
    wrapped; True: an image changed branch. An adjustment's step can reach the other branch
    (a turn of a weak-GPS block: omega -182, phi 182, kappa 855 degrees), where the prior,
    compared angle by angle (:func:`eop_residual`), is ~180 degrees off: the robust loss
    then drops it and the angles are published as they are."""
    angles = nearest_branch(eop[:, 3:], nav_eop[:, 3:])
    turned = bool(np.any(np.abs(wrap_angle(angles - eop[:, 3:])) > 0.5 * np.pi))
    eop[:, 3:] = angles
    return turned


def eop_residual(nav_eop: FloatArray, eop: FloatArray) -> FloatArray:
    """``nav - eop`` with the angle differences wrapped."""
    r = nav_eop - eop
    r[:, 3:] = wrap_angle(r[:, 3:])
    return r


def linearise(
    camera: PinholeCamera, data: BlockData, eop: FloatArray, gp: FloatArray,
    damping: float = 0.0, robust_scale: float | None = None,
    calib: CameraBlock | None = None, nav_robust_scale: float | None = None,
    newton: bool = False,
) -> tuple[Normals, FloatArray, FloatArray]:
    """Build and factorise the reduced normal equations at ``(eop, gp, camera)``.

    ``damping`` > 0 adds Marquardt's ``damping * diag(N)`` to the normal matrix (a
    Levenberg-Marquardt step); 0 is the Gauss-Newton system. ``calib``: the camera's free
    interior parameters are unknowns too (columns ``6 n ...`` of the reduced system).
    ``nav_robust_scale``: the GPS/INS groups weighted by their robust loss at ``eop``.
    ``newton``: beyond the losses' cores their own curvature too, not IRLS's alone — the
    GPS/INS groups' (:func:`seqat.robust.nav_tail_curvature`) and the rays' of each point
    whose block stays positive definite with it (:func:`_tail_rays`): Newton's method on
    the robust cost. The matrix may then be indefinite: a step for the line search to
    judge, never a covariance.

    Returns the factorisation and the reduced right-hand side, plus the image residuals.
    """
    n, m = data.n_images, data.n_points
    img, pt = data.obs_image, data.obs_point
    k = img.size
    c = calib.size if calib is not None else 0
    if c:
        uv, Je, Jp, Jc = project_with_jacobians(eop[img], gp[pt], camera, intrinsics=True)
        JR = np.concatenate([Je, Jc[:, :, calib.index]], axis=2)  # type: ignore[union-attr]
    else:
        uv, JR, Jp = project_with_jacobians(eop[img], gp[pt], camera)
    ne = EOP_SIZE * n
    r = ne + c
    rcol = np.concatenate([EOP_SIZE * img[:, None] + np.arange(EOP_SIZE),
                           np.broadcast_to(ne + np.arange(c), (k, c))], axis=1)
    ell = data.obs_uv - uv  # (k, 2)
    w = cauchy_weight(ell, data.obs_sigma_px, robust_scale) / data.obs_sigma_px**2
    # Points the data do not determine here (parallel rays, an iterate sent far off by a
    # blunder): their rows get no weight in this linearisation and their block is the
    # identity (no step), instead of a singular system that rounding decides.
    Npp = np.zeros((m, GP_SIZE, GP_SIZE))
    scatter_add(Npp, pt, np.einsum("kri,krj->kij", Jp * w[:, None, None], Jp))
    cp = data.control_point
    diag3 = np.arange(GP_SIZE)
    Npp[cp[:, None], diag3, diag3] += data.control_weight  # surveyed coordinates (A = I)
    undetermined = np.zeros(m, dtype=bool)
    if m:
        ev = np.linalg.eigvalsh(Npp)
        undetermined = ~(ev[:, 0] > 1e-12 * np.maximum(ev[:, -1], 1e-300)) | ~np.isfinite(
            ev[:, 0])
        if undetermined.any():
            w = np.where(undetermined[pt], 0.0, w)
    # the rays' weighted products, summed per image (N_ee, b_e), over the camera (N_ce,
    # N_cc, b_c) and per point (b_p), and each ray's N_Rp block (seqat.kernels)
    Nee, be, Nce, Ncc, bc, b_p, NRp_blocks = ray_products(img, pt, JR, Jp, w, ell, n, m)
    if newton and robust_scale is not None:
        _tail_rays(Npp, Nee, Nce, Ncc, NRp_blocks, img, pt, JR, Jp, w, ell,
                   data.obs_sigma_px, robust_scale, undetermined)
    res_nav = eop_residual(data.nav_eop, eop)
    w_nav = nav_weight(res_nav, data.nav_sigma, nav_robust_scale) / data.nav_sigma**2
    Nee[:, np.arange(EOP_SIZE), np.arange(EOP_SIZE)] += w_nav
    if newton:
        Nee += nav_tail_curvature(res_nav, data.nav_sigma, nav_robust_scale)
    b_R = np.zeros(r)
    b_R[:ne] = (be + w_nav * res_nav).ravel()
    dense = r <= DENSE_REDUCED_MAX
    N_RR: sp.csr_matrix | FloatArray
    if dense:
        N_RR = np.zeros((r, r))
        at = EOP_SIZE * np.arange(n)[:, None, None]
        N_RR[at + np.arange(EOP_SIZE)[None, :, None],
             at + np.arange(EOP_SIZE)[None, None, :]] = Nee
    else:
        N_RR = sp.bsr_matrix((Nee, np.arange(n), np.arange(n + 1)), shape=(ne, ne)).tocsr()
    if c:
        assert calib is not None
        Ncc[np.arange(c), np.arange(c)] += 1.0 / calib.sigma**2
        Nce_flat = Nce.transpose(1, 0, 2).reshape(c, ne)
        if dense:
            N_RR[ne:, :ne] = Nce_flat
            N_RR[:ne, ne:] = Nce_flat.T
            N_RR[ne:, ne:] = Ncc
        else:
            N_RR = sp.bmat([[N_RR, sp.csr_matrix(Nce_flat.T)],
                            [sp.csr_matrix(Nce_flat), sp.csr_matrix(Ncc)]], format="csr")
        b_R[ne:] = bc + calib.residual(camera) / calib.sigma**2
    Npp[undetermined] = np.eye(GP_SIZE)  # the other blocks keep their rows' weights
    b_p[cp] += data.control_weight * (data.control_xyz - gp[cp])
    if damping > 0.0:
        Npp[:, diag3, diag3] *= 1.0 + damping
        if dense:
            N_RR[np.arange(r), np.arange(r)] *= 1.0 + damping
        else:
            N_RR = N_RR + sp.diags(damping * N_RR.diagonal())
    try:
        Npp_inv = np.linalg.inv(Npp)
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"singular 3x3 ground point normal block ({m} points)") from err
    lu: Factor
    N_Rp: sp.csr_matrix | None = None
    if dense:
        # a small block (the initial one, a short flight): the points eliminated one by one
        # into a dense matrix and a dense LU (seqat.kernels), not sparse products whose
        # bookkeeping costs more than their flops (docs/algorithm.md, *Sim*)
        N_r = np.array(N_RR)
        rhs = b_R.copy()
        eliminate_points(pt, img, NRp_blocks, Npp_inv, b_p, c, N_r, rhs)
        lu = DenseLU(N_r)
    else:
        N_Rp = _sparse_N_Rp(NRp_blocks, rcol, pt, r, m)
        U1 = N_Rp @ _block_diagonal(Npp_inv)  # N_Rp N_pp^-1  (Eq. 5, U_1)
        rhs = b_R - U1 @ b_p.ravel()
        try:
            lu = spla.splu((N_RR - U1 @ N_Rp.T).tocsc())
        except RuntimeError as err:
            raise EstimationError(f"reduced EOP normal matrix ({r}) is singular") from err
    return Normals(lu=lu, N_RR=N_RR, Npp_inv=Npp_inv, b_p=b_p.ravel(), size=r, n_camera=c,
                   Npp=Npp, undetermined=undetermined, obs_blocks=NRp_blocks, obs_rows=rcol,
                   obs_point=pt, _N_Rp=N_Rp), rhs, ell


def tail_ray_curvature(Jp: FloatArray, ell: FloatArray, u2: FloatArray, sigma_px: FloatArray,
                       w: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rays beyond the loss's core, their point's part of what IRLS leaves out of their
    curvature: ``v = Jpᵀ r̂`` (k, 3), ``r̂`` the residual ``ell``'s direction (its norm
    ``sqrt(u2) σ``), and ``-2 w v vᵀ`` (k, 3, 3), ``w = ρ'/σ²`` the ray's weight. The Cauchy
    tail is concave along the residual: curvature ``-ρ'`` where IRLS takes ``+ρ'``."""
    v = np.einsum("kai,ka->ki", Jp, ell) / np.sqrt(u2 * sigma_px**2)[:, None]
    return v, -2.0 * w[:, None, None] * v[:, :, None] * v[:, None, :]


def definite_enough(blocks: FloatArray) -> np.ndarray:
    """(m,) bool: each 3x3 block's smallest eigenvalue above :data:`MIN_EIGENVALUE_RATIO` of
    its largest (positive definite, not near singular): a point's block that may take the
    loss's own curvature."""
    ev = np.linalg.eigvalsh(blocks)
    return ev[:, 0] > MIN_EIGENVALUE_RATIO * np.abs(ev[:, -1])


def _tail_rays(Npp: FloatArray, Nee: FloatArray, Nce: FloatArray, Ncc: FloatArray,
               NRp_blocks: FloatArray, img: np.ndarray, pt: np.ndarray, JR: FloatArray,
               Jp: FloatArray, w: FloatArray, ell: FloatArray, sigma_px: FloatArray,
               scale: float, undetermined: np.ndarray) -> None:
    """Add to the rays' normal blocks, in place, what IRLS leaves out of the curvature of
    each ray beyond the loss's core: ``-2 w (Aᵀ r̂)(Aᵀ r̂)ᵀ``, ``A = [JR | Jp]`` its rows,
    ``r̂`` its residual's direction, ``w = ρ'/σ²`` its weight (:func:`tail_ray_curvature`).
    Only the rays of points whose 3x3 block stays positive definite with them
    (:func:`definite_enough`) and that are determined; the others keep IRLS's."""
    u2 = ray_u2(ell, sigma_px)
    tail = np.flatnonzero((u2 > scale**2) & (w > 0.0) & ~undetermined[pt])
    if tail.size == 0:
        return
    vp, corr = tail_ray_curvature(Jp[tail], ell[tail], u2[tail], sigma_px[tail], w[tail])
    exact = Npp.copy()
    scatter_add(exact, pt[tail], corr)
    keep = definite_enough(exact)[pt[tail]]
    tail, vp, corr = tail[keep], vp[keep], corr[keep]
    if tail.size == 0:
        return
    direction = ell[tail] / np.linalg.norm(ell[tail], axis=1)[:, None]
    scatter_add(Npp, pt[tail], corr)
    # each ray as one row r̂ᵀ A of weight -2 w (the kernel's products of a rank-one ray)
    rows_R = np.zeros((tail.size, 2, JR.shape[2]))
    rows_p = np.zeros((tail.size, 2, GP_SIZE))
    rows_R[:, 0] = np.einsum("ka,kai->ki", direction, JR[tail])
    rows_p[:, 0] = vp
    dNee, _, dNce, dNcc, _, _, dNRp = ray_products(img[tail], pt[tail], rows_R, rows_p,
                                                   -2.0 * w[tail], np.zeros((tail.size, 2)),
                                                   Nee.shape[0], Npp.shape[0])
    Nee += dNee
    Nce += dNce
    Ncc += dNcc
    NRp_blocks[tail] += dNRp


def _block_diagonal(blocks: FloatArray) -> sp.csr_matrix:
    """(m, 3, 3) blocks as a sparse block-diagonal matrix."""
    m = blocks.shape[0]
    return sp.bsr_matrix((blocks, np.arange(m), np.arange(m + 1)),
                         shape=(GP_SIZE * m, GP_SIZE * m)).tocsr()


def weighted_ssr(camera: PinholeCamera, data: BlockData, eop: FloatArray,
                  gp: FloatArray, robust_scale: float | None = None,
                  calib: CameraBlock | None = None,
                  nav_robust_scale: float | None = None) -> float:
    """Weighted sum of squared residuals (image points, nav, control, camera prior) at ``(eop, gp,
    camera)``; with a ``robust_scale`` the image points' Cauchy cost, with a
    ``nav_robust_scale`` the GPS/INS groups' (:mod:`seqat.robust`)."""
    img, pt = data.obs_image, data.obs_point
    if np.any(depth(eop[img], gp[pt]) <= 0.0):
        return math.inf  # a point behind a camera that sees it: not a solution
    res = data.obs_uv - project(eop[img], gp[pt], camera)
    ssr = cauchy_cost(res, data.obs_sigma_px, robust_scale)
    ssr += nav_cost(eop_residual(data.nav_eop, eop), data.nav_sigma, nav_robust_scale)
    ssr += data.control_ssr(gp)
    if calib is not None:
        ssr += float(np.sum((calib.residual(camera) / calib.sigma) ** 2))
    return ssr if np.isfinite(ssr) else math.inf


def back_substitute(nrm: Normals, delta_r: FloatArray) -> FloatArray:
    """GP corrections ``N_pp^-1 (b_p - N_Rp^T delta_R)`` (Eq. 6)."""
    coupled = np.zeros((nrm.Npp.shape[0], GP_SIZE))
    scatter_add(coupled, nrm.obs_point,
                np.einsum("kqi,kq->ki", nrm.obs_blocks, delta_r[nrm.obs_rows]))
    return np.einsum("mij,mj->mi", nrm.Npp_inv, nrm.b_p.reshape(-1, GP_SIZE) - coupled)


def eop_cofactor_blocks(nrm: Normals, n: int) -> FloatArray:
    """Diagonal 6x6 blocks of ``N_r^-1``, (n, 6, 6).

    ``N_r^-1`` is solved ``COVARIANCE_CHUNK_IMAGES`` images (columns) at a time, so memory stays
    ``O(n * chunk)``.
    """
    diag = np.empty((n, EOP_SIZE, EOP_SIZE))
    for start in range(0, n, COVARIANCE_CHUNK_IMAGES):
        stop = min(n, start + COVARIANCE_CHUNK_IMAGES)
        cols = np.arange(EOP_SIZE * start, EOP_SIZE * stop)
        rhs = np.zeros((nrm.size, cols.size))
        rhs[cols, np.arange(cols.size)] = 1.0
        X = nrm.lu.solve(rhs)[: EOP_SIZE * n]  # (6n, 6c) columns of N_r^-1
        Xb = X.reshape(n, EOP_SIZE, stop - start, EOP_SIZE)
        idx = np.arange(start, stop)
        diag[start:stop] = Xb[idx, :, idx - start, :]
    return diag


def camera_cofactor(nrm: Normals) -> FloatArray:
    """(c, c) cofactor of the free interior parameters (the last ``c`` columns of
    ``N_r^-1``)."""
    c = nrm.n_camera
    rhs = np.zeros((nrm.size, c))
    rhs[nrm.size - c + np.arange(c), np.arange(c)] = 1.0
    Q = nrm.lu.solve(rhs)[nrm.size - c :]
    return 0.5 * (Q + Q.T)


#: Points whose cofactors are solved at once by :func:`gp_cofactors`.
GP_COFACTOR_CHUNK = 1000


def gp_cofactors(nrm: Normals, data: BlockData) -> FloatArray:
    """3x3 cofactor of every GP (Eq. 5, ``U_3``): the diagonal blocks of
    ``N_pp^-1 + V^T N_r^-1 V`` with ``V = N_Rp N_pp^-1``, solved for
    :data:`GP_COFACTOR_CHUNK` points at a time."""
    m = data.n_points
    V = (nrm.N_Rp @ _block_diagonal(nrm.Npp_inv)).tocsc()
    Qp = nrm.Npp_inv.copy()
    r = nrm.size
    for start in range(0, m, GP_COFACTOR_CHUNK):
        stop = min(m, start + GP_COFACTOR_CHUNK)
        Vc = V[:, GP_SIZE * start : GP_SIZE * stop].toarray()
        Y = nrm.lu.solve(Vc)
        Qp[start:stop] += np.einsum("rca,rcb->cab", Vc.reshape(r, -1, GP_SIZE),
                                    Y.reshape(r, -1, GP_SIZE))
    return Qp


def full_normal(nrm: Normals, n: int, m: int) -> FloatArray:
    """Dense normal matrix over ``[EOPs, camera, GPs]``, exactly symmetric: its GP-GP part is
    exactly block diagonal (the sequential information engine eliminates those blocks).
    Only its diagonal blocks are symmetrised (the dense path forms them symmetric: then a
    no-op), not the whole matrix: a pass over 1000+ squared entries cost the hand-over
    ~10 ms."""
    r = nrm.size
    N = np.zeros((r + GP_SIZE * m, r + GP_SIZE * m))
    N_RR = nrm.dense_N_RR()
    N[:r, :r] = 0.5 * (N_RR + N_RR.T)
    Npp = 0.5 * (nrm.Npp + np.swapaxes(nrm.Npp, 1, 2))
    for j in range(m):
        o = r + GP_SIZE * j
        N[o : o + GP_SIZE, o : o + GP_SIZE] = Npp[j]
    NRp = nrm.N_Rp.toarray()
    N[:r, r:] = NRp
    N[r:, :r] = NRp.T
    return N


def full_cofactor(nrm: Normals, n: int, m: int) -> FloatArray:
    """Dense inverse normal matrix over ``[EOPs, camera, GPs]`` (Eq. 5)."""
    Qrr = nrm.lu.solve(np.eye(nrm.size))
    Qrr = 0.5 * (Qrr + Qrr.T)
    Npp_inv_sp = _block_diagonal(nrm.Npp_inv)
    U1 = (nrm.N_Rp @ Npp_inv_sp).toarray()  # N_Rp N_pp^-1
    Qrp = -Qrr @ U1  # U_2
    Qpp = Npp_inv_sp.toarray() + U1.T @ Qrr @ U1  # U_3
    Qpp = 0.5 * (Qpp + Qpp.T)
    return np.block([[Qrr, Qrp], [Qrp.T, Qpp]])
