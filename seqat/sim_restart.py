"""Images of :class:`seqat.simultaneous.SimultaneousAT` most of whose rays reject the
solution: named, started again at a resection, or carried by their GPS/INS
(docs/algorithm.md, *A poor start*)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from seqat import robust as rloss
from seqat.errors import EstimationError
from seqat.geometry import project, resect
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray, PinholeCamera

if TYPE_CHECKING:
    from seqat.simultaneous import Covariance


class RestartMixin:
    """Unsupported images of :class:`seqat.simultaneous.SimultaneousAT` (its state lives
    there)."""

    def _rejected_by_rays(self, i: int) -> bool:
        """Most of image ``i``'s rays in the last solution's block lie far beyond the loss's
        core (:func:`seqat.robust.unsupported_images`): the loss kept a poor GPS/INS start,
        or most of the rays are wrong matches (docs/algorithm.md, *A poor start*)."""
        return self._rays_reject(i, self._point_sel, self._eop_est[i], self._gp_est,
                                 self.camera_now)

    def _rays_reject(self, i: int, sel: np.ndarray, eop: FloatArray, gp: FloatArray,
                     camera: PinholeCamera) -> bool:
        """:meth:`_rejected_by_rays` at a solution: image ``i`` at ``eop``, the points
        ``sel`` (catalogue indices, sorted) at ``gp``."""
        if sel.size == 0:
            return False
        _, oi, op, uv, sg = self._observations()
        pos = np.minimum(np.searchsorted(sel, op), sel.size - 1)  # sel is sorted
        mine = (oi == i) & (sel[pos] == op)
        n = int(np.count_nonzero(mine))
        u2 = rloss.ray_u2(uv[mine] - project(np.broadcast_to(eop, (n, EOP_SIZE)),
                                             gp[pos[mine]], camera), sg[mine])
        return rloss.unsupported_images(u2, oi[mine], self.options.robust_scale).size > 0

    def _held_camera_start(self, i: int) -> bool:
        """Self-calibrating: solve the block with image ``i`` (just added) and the camera
        held at its last estimate, and start the free solve there. Returns True when most
        of ``i``'s rays reject that solution (a poor start: :meth:`_start_again`).

        The free interior parameters can absorb a poor start in a small block: a heading
        150 deg off at the fourth image of the initial block ended 4.7 m and 1.3 deg off, a
        focal length that then drifted from 4928 to 5479 px over six images, and a flight
        lost (88 m r.m.s., or a singular window); with the camera held the same image ends
        within 1 m and 0.3 deg. Where the held solve fails, the free solve starts where it
        would have (its own guards decide)."""
        cal = self._calibration
        if cal is None or not cal.free:
            return False
        from seqat.simultaneous import Covariance, adjust_block  # (it imports this module)

        data, sel, eop0, gp0, _ = self._block()
        try:
            res = adjust_block(self.camera_now, data, eop0, gp0, self.options,
                               Covariance.NONE, None)
        except EstimationError:
            return False
        self._eop_est, self._gp_est, self._point_sel = res.eop.copy(), res.gp.copy(), sel
        return self._rays_reject(i, sel, res.eop[i], res.gp, self.camera_now)

    def _start_again(self, i: int, cov: Covariance) -> int:
        """Image ``i``, just added, is one most of whose rays reject the solution: the
        block is solved again with ``i`` started at its least-squares resection on the
        points the other images determine (:func:`seqat.geometry.resect`), as a sequential
        update starts again with the window held (:mod:`seqat.iteration`). If most rays
        reject that solution too, or no resection exists, ``i`` is carried by its GPS/INS
        (:meth:`_leave_out`). Returns the iterations of the solves."""
        cat = self._cat
        oi = np.asarray(cat.obs_image, dtype=np.int64)
        op = np.asarray(cat.obs_point, dtype=np.int64)
        at = {int(j): k for k, j in enumerate(self._point_sel)}
        others = np.bincount(op[oi != i], minlength=len(cat.point_ids))
        mine = np.flatnonzero((oi == i) & (others[op] >= 2)
                              & np.isin(op, self._point_sel))
        if self._rejected:
            mine = np.setdiff1d(mine, np.fromiter(self._rejected, dtype=np.int64))
        X = self._gp_est[[at[int(j)] for j in op[mine]]].reshape(-1, GP_SIZE)
        uv = np.asarray(cat.obs_uv, dtype=np.float64).reshape(-1, 2)[mine]
        sigma = np.asarray(cat.obs_sigma, dtype=np.float64)[mine]
        eop = resect(self._eop_est[i], X, uv, sigma, self.camera_now)
        if eop is None:
            self._leave_out([i])
            return self._solve(cov).iterations
        self._eop_est[i] = eop
        self._dirty = True
        iterations = self._solve(cov).iterations
        if not self._rejected_by_rays(i):
            return iterations
        self._leave_out([i])
        return iterations + self._solve(cov).iterations

    def _leave_out(self, images: list[int]) -> None:
        """The ``images`` (catalogue indices) diverged: their rays left out, started again
        at their GPS/INS, named in :attr:`diverged`."""
        self._diverged |= set(images)
        self.diverged += [self._cat.image_ids[j] for j in images]
        self._eop_est[images] = np.asarray(self._cat.nav_eop)[images]
        self._dirty = True
