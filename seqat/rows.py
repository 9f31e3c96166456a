"""The rows of one sequential update and the window's image-point factors.

* :class:`RowBuilder` linearises a new image's rows (seed 000 Eq. 7-8) in the corrections
  form :mod:`seqat.update` takes, iterated around the new estimate.
* :func:`snoop_update`: Baarda's data snooping of those rows (:mod:`seqat.snooping`).
* :class:`Factors` / :class:`FactorSet`: every window observation with its linearisation, as
  arrays, for the window re-linearisation (docs/algorithm.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse

from seqat import snooping
from seqat.calibration import FreeCamera
from seqat.dense import add_square
from seqat.geometry import wrap_angle
from seqat.information import (
    WindowMatrix,
    add_block,
    padded,
    sparse_entries,
    window_matrix,
)
from seqat.normals import eop_residual
from seqat.robust import (
    NAV_GROUPS,
    POOR_START_BEYOND,
    cauchy_weight,
    nav_far_beyond,
    nav_groups_of,
    nav_outside,
    nav_weight,
    nav_within_core,
    ray_u2,
    rays_hold,
    unsupported_images,
)
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray
from seqat.update import SPARSE_ROWS_FROM, LinearRows, UpdateSolution

if TYPE_CHECKING:
    from seqat.sequential import Window


@dataclass(frozen=True, kw_only=True, eq=False)
class Verdict:
    """What one round of data snooping rejects: image observations (indices in the row
    builder's order) with their w, and GPS/INS groups to down-weight."""

    observations: list[int]
    w: list[float]
    nav_groups: list[str]


def snoop_update(Q: FloatArray, touched: np.ndarray, rows: LinearRows, sol: UpdateSolution,
           builder: RowBuilder, d1t: FloatArray, d2: FloatArray, critical: float) -> Verdict:
    """Baarda's w-test on the rows of one update (seed 003 §3.1; docs/algorithm.md).

    ``Q`` is the prior cofactor block of the touched parameters, ``Q[touched, touched]``.

    ``w_i = v_i / (sigma_i sqrt(r_i))`` with the residual ``v = l - A d`` of the converged
    update and the redundancy number ``r_i = 1 - (A Q_post A^T)_ii / sigma_i^2``, where
    ``Q_post`` is the cofactor after the update of the parameters the rows touch (Eq. 11-12
    restricted to them: O((t + n2)^2)). An image point fails when either coordinate does;
    observations with ``r < MIN_REDUNDANCY`` cannot be tested (a blunder there is absorbed).
    """
    assert sol.S is not None and sol.P2bar is not None and sol.Gt is not None  # terms=True
    T = np.linalg.solve(sol.S, sol.P2bar)
    T = 0.5 * (T + T.T)
    Gt = sol.Gt
    Qtt = Q - Gt @ T @ Gt.T
    W1t = (rows.A21.T @ (rows.w2[:, None] * rows.A22)) @ sol.D_inv
    Q12 = -Qtt @ W1t
    Q22 = sol.D_inv + W1t.T @ Qtt @ W1t
    Z = np.block([[Qtt, Q12], [Q12.T, Q22]])
    v = builder.residuals(d1t, d2)
    k = builder.k
    observations: list[int] = []
    wq: list[float] = []
    if k:
        _, _, Je, Jp, _ = builder._lin
        cols = np.concatenate([builder.eidx, builder.pidx], axis=1)  # (k, 9)
        worst = snooping.point_w(np.concatenate([Je, Jp], axis=2),
                                 Z[cols[:, :, None], cols[:, None, :]],
                                 v[: 2 * k].reshape(k, 2), builder.sigmas)
        sel = snooping.select(worst, critical, builder.ids[:, 0], builder.ids[:, 1])[:1]
        observations = [int(q) for q in sel]
        wq = [float(worst[q]) for q in sel]
    t = touched.size
    nav = slice(2 * k, 2 * k + EOP_SIZE)
    with np.errstate(divide="ignore"):
        nav_sigma = 1.0 / np.sqrt(builder.w[nav])
    groups = snooping.nav_exceedance(v[nav], nav_sigma, np.diagonal(Z)[t : t + EOP_SIZE],
                                     critical)
    # The worst failure first, image point or GPS/INS group, in units of its own critical
    # value (w² / c² for a point, T / chi² for a group): a 5 m jump then goes before the good
    # rays it drags over the limit, a blunder before the GPS/INS it distorts.
    image_excess = (wq[0] / critical) ** 2 if wq else 0.0
    if groups and groups[0][1] > max(1.0, image_excess):
        return Verdict(observations=[], w=[], nav_groups=[groups[0][0]])
    return Verdict(observations=observations, w=wq, nav_groups=[])


def add_information(L: WindowMatrix, touched: np.ndarray, rows: LinearRows) -> WindowMatrix:
    """Information matrix after adding new parameters and the rows ``y2``, ``y3`` (Eq. 10).

    ``L`` (n1, n1; dense or sparse, :func:`seqat.information.window_matrix`) is extended by
    ``n2`` new parameters; ``A^T P A`` of the rows is added on the touched and new columns
    only (sparse: O(their entries), never O(n1^2)).
    """
    n1, n2 = L.shape[0], rows.A22.shape[1]
    t = touched.size
    cols = np.concatenate([touched, n1 + np.arange(n2)])
    A2 = np.hstack([rows.A21, rows.A22])
    if scipy.sparse.issparse(L) and A2.size > SPARSE_ROWS_FROM:
        # a large update (a strip's first image: hundreds of points born) forms A^T P A
        # from its few non-zeros per row: 216 -> 10 ms at m2 = 1210, t + n2 = 1287
        A2s = scipy.sparse.csr_array(A2)
        Ms = (A2s.T @ A2s.multiply(rows.w2[:, None])).tocoo()
        A32 = rows.A32.T @ (rows.w3[:, None] * rows.A32)
        i3, j3 = np.nonzero(A32)
        r = np.concatenate([cols[Ms.row], cols[t + i3]])
        c = np.concatenate([cols[Ms.col], cols[t + j3]])
        v = 0.5 * np.concatenate([Ms.data, A32[i3, j3]])  # each entry and its mirror: symmetric
        M = sparse_entries(np.concatenate([r, c]), np.concatenate([c, r]),
                           np.concatenate([v, v]), n1 + n2)
        return window_matrix(padded(L, n1 + n2) + M)
    M = A2.T @ (rows.w2[:, None] * A2)
    M[t:, t:] += rows.A32.T @ (rows.w3[:, None] * rows.A32)
    M = 0.5 * (M + M.T)
    if not scipy.sparse.issparse(L):  # one copy, the rows added in place
        out = np.empty((n1 + n2, n1 + n2))
        out[:n1, :n1] = L
        out[:n1, n1:] = 0.0
        out[n1:] = 0.0
        add_square(out, cols, M)
        return window_matrix(out)
    return window_matrix(add_block(padded(L, n1 + n2), cols, M))


#: A sequential update iterates until its GPS/INS groups' robust weights change less than
#: this (IRLS; bounded by SequentialOptions.max_update_iterations).
NAV_WEIGHT_TOLERANCE = 1e-3


class RowBuilder:
    """Linearises one image's new rows around the current iterate (corrections form).

    All image rows are projected in one vectorised call. Parameters are addressed in the
    stacked vector ``z = [x1 (touched existing), x2 (new)]`` of length ``t + n2``; the design
    of every row is scattered into one matrix ``[[A21, A22], [0, A32]]``.

    Parameters
    ----------
    cam : FreeCamera
        The camera; with free interior parameters (self-calibration) their block is at
        column ``cam_col`` of ``z`` and joins every observation's EOP columns.
    t, n2 : int
        Numbers of touched existing and of new parameters.
    obs : list of (eop_col, point_col, uv, sigma_px, in_y2, (image, point))
        One entry per image observation: columns in ``z`` of its EOP and GP blocks, the
        observed pixel, its sigma, whether it belongs to y2 (touches an existing
        parameter) rather than y3, and its image and point indices.
    nav, nav_sigma : (6,) float
        GPS/INS constraint of the new image (local), its sigma.
    robust_scale : float or None
        Robust loss scale of the image rows in sigma (:mod:`seqat.robust`): their weights
        are re-computed from the residuals at every linearisation (IRLS).
    nav_robust_scale : float or None
        Robust loss scale of the GPS/INS groups (sigmas per degree of freedom): their weights
        likewise, from ``nav - estimate`` at every linearisation.
    control : list of (col, xyz, weight)
        Ground control among the new points: the column in ``z`` of the point, its surveyed
        coordinates and their weights (0: free); three linear rows each (``A = I``), after
        the GPS/INS rows.

    The attribute ``robust`` (set by the caller per iteration: the first one is least
    squares) switches the robust losses; ``nav_on`` holds the GPS/INS groups whose loss
    :meth:`settled` or :meth:`nav_loss_at` has turned on, ``nav_wrong`` those of them
    :meth:`nav_loss_at` found wrong before any iterate, ``nav_trial`` those a held
    resection weighs by their loss until it is judged (:meth:`resect_without_far_nav`):
    the loss of these two applies to the least-squares iterates too.
    """

    def __init__(
        self,
        cam: FreeCamera,
        t: int,
        n2: int,
        obs: list[tuple[int, int, FloatArray, float, bool, tuple[int, int]]],
        nav: FloatArray,
        nav_sigma: FloatArray,
        robust_scale: float | None = None,
        nav_robust_scale: float | None = None,
        cam_col: int = 0,
        control: Sequence[tuple[int, FloatArray, FloatArray]] = (),
    ) -> None:
        self.cam, self.t, self.n2 = cam, t, n2
        self.robust_scale = robust_scale
        self.nav_robust_scale = nav_robust_scale
        self.robust = True
        # the GPS/INS loss per group: on once the rows have converged without it (settled)
        self.nav_on = np.zeros(len(NAV_GROUPS), dtype=bool)
        # ... and those found wrong at a start the rays hold (nav_loss_at): on from there
        self.nav_wrong = np.zeros(len(NAV_GROUPS), dtype=bool)
        # ... and those a held resection weighs by their loss until nav_loss_at judges them
        self.nav_trial = np.zeros(len(NAV_GROUPS), dtype=bool)
        self.nav, self.nav_sigma = nav, nav_sigma
        y2 = [o for o in obs if o[4]]
        y3 = [o for o in obs if not o[4]]
        ordered = y2 + y3
        self.m2 = 2 * len(y2)
        self.control = list(control)
        self.m3 = 2 * len(y3) + EOP_SIZE + GP_SIZE * len(self.control)
        ncol = t + n2
        k = len(ordered)
        ecol = np.asarray([o[0] for o in ordered], dtype=np.int64).reshape(k)
        pcol = np.asarray([o[1] for o in ordered], dtype=np.int64).reshape(k)
        self.eidx = np.concatenate([ecol[:, None] + np.arange(EOP_SIZE), np.broadcast_to(
            cam_col + np.arange(cam.size), (k, cam.size))], axis=1)
        self.pidx = pcol[:, None] + np.arange(GP_SIZE)
        rows = np.arange(2 * k).reshape(k, 2)
        # Flat indices of each observation's 2x(6+c) image-block and 2x3 GP Jacobians in the
        # design.
        self.flat_e = (rows[:, :, None] * ncol + self.eidx[:, None, :]).ravel()
        self.flat_p = (rows[:, :, None] * ncol + self.pidx[:, None, :]).ravel()
        self.flat_nav = (2 * k + np.arange(EOP_SIZE)) * ncol + t + np.arange(EOP_SIZE)
        self.obs = np.asarray([o[2] for o in ordered], dtype=np.float64).reshape(2 * k)
        self.ids = np.asarray([o[5] for o in ordered], dtype=np.int64).reshape(k, 2)
        self.sigmas = np.asarray([o[3] for o in ordered], dtype=np.float64).reshape(k)
        w_img = np.repeat(1.0 / np.asarray([o[3] for o in ordered], dtype=np.float64) ** 2, 2)
        self.w = np.concatenate([w_img, 1.0 / nav_sigma**2]
                                + [wc for _, _, wc in self.control])
        self.w0 = self.w.copy()  # least-squares weights; self.w carries the robust factor
        self.k = k
        self.ncol = ncol

    def rows(
        self, x1t: FloatArray, x2_0: FloatArray, d1t: FloatArray, d2: FloatArray
    ) -> LinearRows:
        """Rows linearised at ``(x1t + d1t, x2_0 + d2)``; reduced observations in corrections
        from ``(x1t, x2_0)``: ``l = y - f(x_lin) + A (x_lin - x_prior)``."""
        t, k = self.t, self.k
        z = np.concatenate([x1t + d1t, x2_0 + d2])
        n_rows = 2 * k + EOP_SIZE + GP_SIZE * len(self.control)
        A = np.zeros((n_rows, self.ncol))
        ell = np.empty(n_rows)
        if k:
            ze, zp = z[self.eidx], z[self.pidx]
            uv, Je, Jp = self.cam.project_with_jacobians(ze, zp)
            A.flat[self.flat_e] = Je.ravel()
            A.flat[self.flat_p] = Jp.ravel()
            res = (self.obs - uv.ravel()).reshape(k, 2)
            ell[: 2 * k] = res.ravel()
            self._lin = (ze, zp, Je, Jp, res)
            self.w[: 2 * k] = self.w0[: 2 * k] * np.repeat(
                cauchy_weight(res, self.sigmas, self.robust_scale if self.robust else None), 2)
        # GPS/INS constraint of the new EOP (linear, A = I): nav - e_new, angles wrapped.
        A.flat[self.flat_nav] = 1.0
        dz = self.nav - z[t : t + EOP_SIZE]
        dz[3:] = wrap_angle(dz[3:])
        nav_end = 2 * k + EOP_SIZE
        ell[2 * k : nav_end] = dz
        on = self.nav_on if self.robust else self.nav_wrong | self.nav_trial
        self.w[2 * k : nav_end] = self.w0[2 * k : nav_end] * nav_weight(
            dz, self.nav_sigma, self.nav_robust_scale if on.any() else None, on)[0]
        # ground control: surveyed - current coordinates of each new control point (A = I)
        for q, (col, xyz, _) in enumerate(self.control):
            r = nav_end + GP_SIZE * q + np.arange(GP_SIZE)
            A[r, col + np.arange(GP_SIZE)] = 1.0
            ell[r] = xyz - z[col : col + GP_SIZE]
        ell += A @ np.concatenate([d1t, d2])
        self._A, self._ell = A, ell
        m2 = self.m2
        return LinearRows(
            A21=A[:m2, :t],
            A22=A[:m2, t:],
            w2=self.w[:m2],
            l2=ell[:m2],
            A32=A[m2:, t:],
            w3=self.w[m2:],
            l3=ell[m2:],
        )

    def store_factors(self, factors: Factors) -> None:
        """Keep the image rows as finally linearised (for window re-linearisation)."""
        if self.k == 0:
            return
        e, p, Je, Jp, r = self._lin
        factors.add_linearised(self.ids[:, 0], self.ids[:, 1],
                               self.obs.reshape(self.k, 2), self.sigmas, e, p, Je, Jp, r,
                               robust=self.w[: 2 * self.k : 2] / self.w0[: 2 * self.k : 2])

    def residuals(self, d1t: FloatArray, d2: FloatArray) -> FloatArray:
        """Residuals of the last linearised rows at the corrections ``(d1t, d2)``: image rows
        in builder order (2 per observation), the 6 GPS/INS rows, then 3 per control point."""
        return self._ell - self._A @ np.concatenate([d1t, d2])

    def linearisation_error(
        self, x1t: FloatArray, x2_0: FloatArray, d1t: FloatArray, d2: FloatArray
    ) -> float:
        """Largest difference (px) between the image points projected at ``(d1t, d2)`` and the
        last linearised rows' prediction there; 0 without image rows."""
        k = self.k
        z = np.concatenate([x1t + d1t, x2_0 + d2])
        self._nav_res = self.nav - z[self.t : self.t + EOP_SIZE]
        self._nav_res[3:] = wrap_angle(self._nav_res[3:])
        if k == 0:
            self._true = np.zeros(0)
            return 0.0
        true_resid = self.obs - self.cam.project(z[self.eidx], z[self.pidx]).ravel()
        self._true = true_resid
        lin_resid = self._ell[: 2 * k] - self._A[: 2 * k] @ np.concatenate([d1t, d2])
        return float(np.max(np.abs(true_resid - lin_resid)))

    def within_core(self) -> bool:
        """Every image point and the GPS/INS groups at the estimate of the last
        :meth:`linearisation_error` lie within their robust loss's least-squares core
        (``u² <= k²``; ``k² d`` for a group): their robust weight there is 1, so the
        least-squares solution of these rows is already the robust one (True without
        robust losses)."""
        if not nav_within_core(self._nav_res, self.nav_sigma, self.nav_robust_scale):
            return False
        if self.robust_scale is None:
            return True
        u2 = np.sum(self._true.reshape(-1, 2) ** 2, axis=1) / self.sigmas**2
        return bool(np.all(u2 <= self.robust_scale**2))

    def unsupported(self, image: int, born: Sequence[int] = (),
                    beyond: float = POOR_START_BEYOND) -> bool:
        """Most of ``image``'s rays to points not being ``born`` (points other images
        determine) lie far (``beyond`` times) beyond the robust loss's core at the estimate
        of the last :meth:`linearisation_error` (:func:`seqat.robust.unsupported_images`)."""
        known = ~np.isin(self.ids[:, 1], np.asarray(born, dtype=np.int64))
        mine = (self.ids[:, 0] == image) & known
        if not mine.any():
            return False
        u2 = ray_u2(self._true.reshape(-1, 2)[mine], self.sigmas[mine])
        return unsupported_images(u2, self.ids[mine, 0], self.robust_scale, beyond).size > 0

    def nav_loss_at(self, x1t: FloatArray, x2_0: FloatArray, image: int,
                    born: Sequence[int] = ()) -> None:
        """The GPS/INS loss on, from the next iterate (least squares or not), for the
        groups far beyond its core at the start ``(x1t, x2_0)``
        (:func:`seqat.robust.nav_far_beyond`) when the image's rays hold the start
        (:meth:`rays_hold`; the tracker's resection on known points): that GPS/INS is wrong.
        Left to :meth:`settled`, its least-squares pull (150 deg at a sigma of 0.1 deg) took
        the image from its resection to the GPS/INS as the ray loss down-weighted the rays;
        left to the first robust iterate, the least-squares one before it (90 deg) moved a
        self-calibrated focal length by -2800 px, and ten iterates did not come back (the
        image diverged, carried by its INS). A start its rays do not hold (6 deg off, the
        GPS/INS right) changes nothing."""
        self.nav_trial[:] = False  # a held resection's trial ends here
        far = self._nav_far_beyond(x2_0)
        if far.any() and self.k:
            z = np.concatenate([x1t, x2_0])
            self._true = self.obs - self.cam.project(z[self.eidx], z[self.pidx]).ravel()
            if self.rays_hold(image, born, POOR_START_BEYOND):
                self.nav_on |= far
                self.nav_wrong |= far

    def resect_without_far_nav(self, x2: FloatArray) -> None:
        """A resection with the window held starts at ``x2``: the GPS/INS groups far beyond
        their core there (:func:`seqat.robust.nav_far_beyond`) are weighed by their loss
        until it ends, where :meth:`nav_loss_at` judges them at the resection. A resection
        is the rays' estimate: in least squares, an INS 90 deg off at 0.1 deg (900 sigma)
        outweighed an image's seven rays and held the resection 10 deg from where they put
        it, 70-150 px off each, so that the rays could not be seen to hold it and the image
        was diverged and carried by its INS. A group the rays do not then show wrong is
        weighed as before."""
        self.nav_trial |= self._nav_far_beyond(x2)

    def _nav_far_beyond(self, x2: FloatArray) -> np.ndarray:
        """(g,) bool: the GPS/INS groups far beyond their core with the new image at ``x2``
        (:func:`seqat.robust.nav_far_beyond`)."""
        res = eop_residual(self.nav[None], x2[None, :EOP_SIZE])
        return nav_far_beyond(res, self.nav_sigma, self.nav_robust_scale)[0]

    def rays_hold(self, image: int, born: Sequence[int] = (), beyond: float = 1.0) -> bool:
        """``image``'s rays to points not being ``born``, at the estimate of the last
        :meth:`linearisation_error`, fix it (:func:`seqat.robust.rays_hold`). A start is held
        within :data:`seqat.robust.POOR_START_BEYOND` times the core (the test of
        :func:`seqat.robust.unsupported_images`), an estimate within the core."""
        known = ~np.isin(self.ids[:, 1], np.asarray(born, dtype=np.int64))
        mine = (self.ids[:, 0] == image) & known
        u2 = ray_u2(self._true.reshape(-1, 2)[mine], self.sigmas[mine])
        return rays_hold(u2, self.robust_scale, beyond)

    def settled(self) -> bool:
        """Called once the rows predict the estimate: their robust weights need no other
        iteration. Least-squares rows (the first iterate): when the estimate lies
        :meth:`within_core`. Robust rows: when their GPS/INS weights are those at the
        estimate (within :data:`NAV_WEIGHT_TOLERANCE`; the rows are linear, their
        linearisation error says nothing of their weights) and no group is beyond the core
        with its loss off. The GPS/INS loss is turned on once the rows have converged
        without it (as Sim: with 20 % blunders an early GPS/INS loss let the least-squares
        iterate's pull down-weight good GPS/INS), one group at a time in
        :data:`seqat.robust.NAV_GROUPS` order — the GNSS position first: an update sees
        only the window's data, and a 5 m jump split between position and attitude
        (u² 40 and 47, strip seed 2) otherwise made the attitude the outlier.
        """
        if not self.robust:
            return self.within_core()
        nav = slice(2 * self.k, 2 * self.k + EOP_SIZE)
        used = self.w[nav] / self.w0[nav]
        now = nav_weight(self._nav_res, self.nav_sigma, self.nav_robust_scale, self.nav_on)[0]
        if not np.max(np.abs(now - used)) < NAV_WEIGHT_TOLERANCE:
            return False
        off = nav_outside(self._nav_res, self.nav_sigma, self.nav_robust_scale)[0] & ~self.nav_on
        if off.any():
            self.nav_on[int(np.argmax(off))] = True
            return False
        return True

    def nav_group_weights(self) -> FloatArray:
        """(g,) weight factor of each GPS/INS group in the last
        linearised rows (1: least squares)."""
        nav = slice(2 * self.k, 2 * self.k + EOP_SIZE)
        with np.errstate(invalid="ignore", divide="ignore"):
            f = self.w[nav] / self.w0[nav]
        return nav_groups_of(np.where(np.isfinite(f), f, 1.0))[0]




def factor_blocks(Je: FloatArray, Jp: FloatArray, w: FloatArray) -> FloatArray:
    """``J^T W J`` of each image-point factor, (k, 9, 9) on its [EOP, GP] columns."""
    J = np.concatenate([Je, Jp], axis=2)  # (k, 2, 9)
    return np.einsum("kri,krj->kij", J * w[:, None, None], J)


def gradient_from_factors(Je: FloatArray, Jp: FloatArray, r: FloatArray, w: FloatArray,
                          cols: np.ndarray, n: int) -> FloatArray:
    """``J^T W r`` of image-point factors scattered into ``n`` window columns."""
    J = np.concatenate([Je, Jp], axis=2)
    return np.bincount(cols.ravel(), weights=np.einsum("kri,kr->ki", J * w[:, None, None],
                                                       r).ravel(), minlength=n)


@dataclass(eq=False)
class FactorSet:
    """Image-point factors (one observation each) with their linearisation, as arrays."""

    img: np.ndarray  # (k,) image index
    pt: np.ndarray  # (k,) point index
    uv: FloatArray  # (k, 2) ideal pixels
    w: FloatArray  # (k,) weight: 1/sigma^2 times the robust factor at the linearisation
    w0: FloatArray  # (k,) least-squares weight 1/sigma^2
    e_lin: FloatArray  # (k, 6 + c) image block (EOP, local; camera) where linearised
    p_lin: FloatArray  # (k, 3)
    Je: FloatArray  # (k, 2, 6 + c) Jacobians there
    Jp: FloatArray  # (k, 2, 3)
    r_lin: FloatArray  # (k, 2) residual there
    #: The window offsets of each factor's image and point blocks (Factors.in_window), for
    #: the layout they were read in; None: looked up by :meth:`columns`.
    offsets: tuple[np.ndarray, np.ndarray] | None = None

    def columns(self, w: Window) -> tuple[np.ndarray, np.ndarray]:
        """Window columns of every factor's image block (k, 6 + c: EOP, then the camera's
        free parameters when the window holds them) and GP (k, 3)."""
        if self.offsets is not None:  # found by Factors.in_window for this layout
            e, p = self.offsets
        else:
            e, p = w.offsets_of("e", self.img), w.offsets_of("p", self.pt)
        e_cols = e[:, None] + np.arange(EOP_SIZE)
        cam = [k for k in w.keys if k[0] == "c"]
        if cam:  # self-calibration: the camera's columns join every image block
            cam_cols = w.indices(cam)
            e_cols = np.concatenate([e_cols, np.broadcast_to(cam_cols, (e.size, cam_cols.size))],
                                    axis=1)
        return e_cols, p[:, None] + np.arange(GP_SIZE)

    def predicted(self, e: FloatArray, p: FloatArray) -> FloatArray:
        """Residuals the linearised factors predict at ``(e, p)``."""
        return (self.r_lin - np.einsum("kri,ki->kr", self.Je, e - self.e_lin)
                - np.einsum("kri,ki->kr", self.Jp, p - self.p_lin))

    def evaluate(self, e: FloatArray, p: FloatArray,
                 cam: FreeCamera) -> tuple[FloatArray, FloatArray, FloatArray]:
        uv, Je, Jp = cam.project_with_jacobians(e, p)
        return Je, Jp, self.uv - uv

    def residuals(self, e: FloatArray, p: FloatArray, cam: FreeCamera) -> FloatArray:
        """True residuals ``uv - f(e, p)`` of every factor, (k, 2)."""
        return self.uv - cam.project(e, p)

    def linearisation_error(self, e: FloatArray, p: FloatArray, cam: FreeCamera,
                            true: FloatArray | None = None) -> float:
        if true is None:
            true = self.residuals(e, p, cam)
        return float(np.max(np.abs(true - self.predicted(e, p)), initial=0.0))

    def linearised_ssr(self, e: FloatArray, p: FloatArray) -> float:
        return float(np.sum(self.w[:, None] * self.predicted(e, p) ** 2))

    def relinearised_at(self, e: FloatArray, p: FloatArray, Je: FloatArray, Jp: FloatArray,
                        r: FloatArray) -> None:
        self.e_lin, self.p_lin, self.Je, self.Jp, self.r_lin = e.copy(), p.copy(), Je, Jp, r


class Factors:
    """The image-point factors of the window, as appended array chunks (no per-factor Python
    objects: the check after every update must stay well below the update itself)."""

    _FIELDS = ("img", "pt", "uv", "w", "w0", "e_lin", "p_lin", "Je", "Jp", "r_lin")

    def __init__(self) -> None:
        self._chunks: list[tuple[np.ndarray, ...]] = []
        self._dormant: list[tuple[np.ndarray, ...]] = []

    def add(self, img: np.ndarray, pt: np.ndarray, uv: FloatArray, sigma: FloatArray,
            e_lin: FloatArray, p_lin: FloatArray, cam: FreeCamera,
            robust_scale: float | None = None) -> None:
        if len(img) == 0:
            return
        proj, Je, Jp = cam.project_with_jacobians(e_lin, p_lin)
        r = np.asarray(uv, dtype=np.float64).reshape(-1, 2) - proj
        self.add_linearised(img, pt, uv, sigma, e_lin, p_lin, Je, Jp, r,
                            robust=cauchy_weight(r, sigma, robust_scale))

    def add_linearised(self, img: np.ndarray, pt: np.ndarray, uv: FloatArray,
                       sigma: FloatArray, e_lin: FloatArray, p_lin: FloatArray, Je: FloatArray,
                       Jp: FloatArray, r: FloatArray, *,
                       robust: FloatArray | None = None) -> None:
        """Keep rows linearised at ``(e_lin, p_lin)``. Their weight is ``robust / sigma^2``:
        ``robust`` is the robust loss's factor in [0, 1] (default 1), never a weight. The
        window's information holds the same rows with that weight; a factor kept at another
        one leaves the difference in the kept information, linearised for good (a finish-time
        birth passed ``1 / sigma^2`` twice: at 0.5 px, 3/4 of its rows never re-linearised
        and their robust re-weighting counted them 1.75 times)."""
        if len(img) == 0:
            return
        w0 = 1.0 / np.asarray(sigma, dtype=np.float64).reshape(-1) ** 2
        w = w0.copy()
        if robust is not None:
            factor = np.asarray(robust, dtype=np.float64).reshape(-1)
            if not np.all((factor >= 0.0) & (factor <= 1.0 + 1e-12)):
                raise ValueError("robust factors must lie in [0, 1]")
            w *= factor
        self._chunks.append((np.asarray(img, dtype=np.int64).copy(),
                             np.asarray(pt, dtype=np.int64).copy(),
                             np.asarray(uv, dtype=np.float64).reshape(-1, 2).copy(), w, w0,
                             np.array(e_lin, dtype=np.float64), np.array(p_lin, dtype=np.float64),
                             np.array(Je, dtype=np.float64), np.array(Jp, dtype=np.float64),
                             np.array(r, dtype=np.float64)))

    def in_window(self, w: Window, keep_leaving: bool = False) -> FactorSet | None:
        """The factors whose image and point are both in the window.

        The others — their image or point has left the window — are dropped, or, with
        ``keep_leaving`` (departure records kept: the keys may re-open), set aside as
        *dormant* until :meth:`wake` brings back those of re-opened keys: a re-opened key's
        rows are then re-linearised with the window's (its information is restored exactly
        by the re-opening's conditional prior: docs/algorithm.md). Dormant factors are not
        touched here: the cost stays that of the window's own factors."""
        if not self._chunks:
            return None
        parts = self._concat(self._chunks)
        e_off, p_off = w.offsets_of("e", parts[0]), w.offsets_of("p", parts[1])
        keep = (e_off >= 0) & (p_off >= 0)
        if keep.all():
            self._chunks = [tuple(parts)]
        else:
            if keep_leaving:
                self._dormant.append(tuple(a[~keep] for a in parts))
            self._chunks = [tuple(a[keep] for a in parts)] if keep.any() else []
            if not keep.any():
                return None
            e_off, p_off = e_off[keep], p_off[keep]
        return FactorSet(**dict(zip(self._FIELDS, self._chunks[0], strict=True)),
                         offsets=(e_off, p_off))

    def wake(self, w: Window) -> None:
        """Dormant factors whose image and point are both in the window again (after a
        re-opening) become window factors: O(dormant factors), at re-openings only."""
        if not self._dormant:
            return
        parts = self._concat(self._dormant)
        back = self._inside(parts, w)
        if back.any():
            self._chunks.append(tuple(a[back] for a in parts))
        self._dormant = [tuple(a[~back] for a in parts)] if not back.all() else []

    def prune_dormant(self, w: Window, images: np.ndarray, points: np.ndarray) -> None:
        """Keep the dormant factors whose image and point are each in the window or among
        ``images`` / ``points`` (the departed keys that may still re-open); drop the rest."""
        if not self._dormant:
            return
        parts = self._concat(self._dormant)
        keep = (np.isin(parts[0], np.concatenate([w.ids("e"), images]))
                & np.isin(parts[1], np.concatenate([w.ids("p"), points])))
        self._dormant = [tuple(a[keep] for a in parts)] if keep.any() else []

    def forget(self, points: set[int]) -> None:
        """Drop every factor of ``points``, in the window or dormant (taken out of the
        solution; a later observation starts the point anew)."""
        if not points:
            return
        gone = np.fromiter(points, dtype=np.int64)
        for name in ("_chunks", "_dormant"):
            chunks = getattr(self, name)
            if chunks:
                parts = self._concat(chunks)
                keep = ~np.isin(parts[1], gone)
                setattr(self, name, [tuple(a[keep] for a in parts)] if keep.any() else [])

    def replace(self, f: FactorSet) -> None:
        """``f``: the window's factors, re-linearised."""
        self._chunks = [tuple(getattr(f, name) for name in self._FIELDS)]

    @staticmethod
    def _concat(chunks: list[tuple[np.ndarray, ...]]) -> list[np.ndarray]:
        if len(chunks) == 1:
            return list(chunks[0])
        return [np.concatenate(col) for col in zip(*chunks, strict=True)]

    @staticmethod
    def _inside(parts: list[np.ndarray], w: Window) -> np.ndarray:
        return (w.offsets_of("e", parts[0]) >= 0) & (w.offsets_of("p", parts[1]) >= 0)

