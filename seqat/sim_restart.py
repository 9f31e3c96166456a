"""Images of :class:`seqat.simultaneous.SimultaneousAT` most of whose rays reject the
solution: named, started again at a resection, or carried by their GPS/INS
(docs/algorithm.md, *A poor start*)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from seqat import robust as rloss
from seqat.geometry import project, resect
from seqat.types import GP_SIZE

if TYPE_CHECKING:
    from seqat.normals import BlockData
    from seqat.simultaneous import Covariance, SimResult


class RestartMixin:
    """Unsupported images of :class:`seqat.simultaneous.SimultaneousAT` (its state lives
    there)."""

    def _note_unsupported(self, res: SimResult, data: BlockData) -> None:
        """Images most of whose rays lie beyond the loss's core at ``res``
        (:func:`seqat.robust.unsupported_images`: the loss kept a poor GPS/INS start, or
        most of the rays are wrong matches) are noted in ``_unsupported``
        (docs/algorithm.md, *A poor start*)."""
        img, pt = data.obs_image, data.obs_point
        u2 = rloss.ray_u2(data.obs_uv - project(res.eop[img], res.gp[pt], self.camera_now),
                          data.obs_sigma_px)
        bad = rloss.unsupported_images(u2, img, self.options.robust_scale)
        self._unsupported = [self._cat.image_ids[j] for j in bad]

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
        if cat.image_ids[i] not in self._unsupported:
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
