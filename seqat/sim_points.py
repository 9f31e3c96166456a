"""The tie points :class:`seqat.simultaneous.SimultaneousAT` takes out of its block or does
not publish: their rays fit two places, disagree or barely spread, or they have two rays
in a flight whose other points show many wrong matches (docs/algorithm.md, *Points whose
rays disagree* and the paragraphs after it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from seqat import robust as rloss
from seqat.geometry import project

if TYPE_CHECKING:
    from seqat.normals import BlockData
    from seqat.simultaneous import SimResult


class PointChecksMixin:
    """Tie points left out by :class:`seqat.simultaneous.SimultaneousAT`."""

    def _block_u2(self, res: SimResult, data: BlockData,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The block's rays but ground control's: image, point (block positions), pixels,
        σ and squared normalised residual at ``res``."""
        img, pt = data.obs_image, data.obs_point
        use = ~np.isin(pt, data.control_point)
        img, pt, uv, sg = img[use], pt[use], data.obs_uv[use], data.obs_sigma_px[use]
        u2 = rloss.ray_u2(uv - project(res.eop[img], res.gp[pt], self.camera_now), sg)
        return img, pt, uv, sg, u2

    def _not_control(self, op: np.ndarray) -> np.ndarray:
        """Mask of the rays (their catalogue points ``op``) of points not ground control."""
        if not self.control:
            return np.ones(op.size, dtype=bool)
        ids = self._cat.point_ids
        return np.fromiter((ids[j] not in self.control for j in op), bool, op.size)

    def _ambiguous_points(self, res: SimResult, data: BlockData, sel: np.ndarray) -> set[int]:
        """Catalogue indices of the block's points (``sel``) whose rays disagree or fit two
        places as well at ``res`` (:func:`seqat.robust.uninformative_points`; ground
        control exempt)."""
        k = self.options.robust_scale
        if k is None or not data.obs_point.size:
            return set()
        img, pt, uv, sg, u2 = self._block_u2(res, data)
        found = rloss.uninformative_points(u2, pt, res.eop[img], uv, sg, self.camera_now, k,
                                           res.sigma0)
        return {int(sel[j]) for j in found}

    def _untrusted_pairs(self, res: SimResult, data: BlockData, sel: np.ndarray) -> set[int]:
        """Catalogue indices of the two-ray tie points the block leaves out at ``res``: every
        one (of the block's and of those left out before) but an image's that has few other
        ties, when the block's points of three rays or more show more wrong matches than
        :data:`seqat.robust.MAX_CONTAMINATION` (:func:`seqat.robust.untrusted_two_ray_points`;
        ground control exempt), else none.
        Not in Seq-R's initial block (``SimOptions.untrust_pairs``): its finish() judges
        them with the rest. The contamination is :attr:`contamination`."""
        k = self._scale  # the configured scale: the contamination judges the data
        self.contamination = float("nan")
        if k is None or not self.options.untrust_pairs or not data.obs_point.size:
            return set()
        # the block's rays and those of the points left out before (their squared
        # residuals are not read: two-ray points do not count in the contamination)
        _, oi, op, uv, sg = self._observations()
        pos = np.full(len(self._cat.point_ids), -1)
        pos[sel] = np.arange(sel.size)
        mine = (pos[op] >= 0) | np.isin(op, np.fromiter(self._untrusted, np.int64))
        mine &= self._not_control(op)
        oi, op, uv, sg = oi[mine], op[mine], uv[mine], sg[mine]
        u2 = np.zeros(op.size)
        inb = pos[op] >= 0
        img, pt = oi[inb], pos[op[inb]]
        u2[inb] = rloss.ray_u2(uv[inb] - project(res.eop[img], res.gp[pt], self.camera_now),
                               sg[inb])
        found, self.contamination = rloss.untrusted_two_ray_points(u2, op, oi, k, res.sigma0)
        return {int(j) for j in found}

    def _disagreeing_points(self, res: SimResult) -> set[int]:
        """Block points (positions in the selection) not published at ``res``: their rays
        disagree (:func:`seqat.robust.withheld_points`) or barely spread
        (:func:`seqat.robust.narrow_points`); control exempt; :attr:`disagreeing`."""
        _, oi, op, uv, sg = self._observations()
        pos = np.full(len(self._cat.point_ids), -1)
        pos[self._point_sel] = np.arange(self._point_sel.size)
        ids = self._cat.point_ids
        use = (pos[op] >= 0) & self._not_control(op)  # ground control is exempt
        if res.undetermined is not None and res.undetermined.any():  # left out already
            use &= ~res.undetermined[np.maximum(pos[op], 0)]
        oi, pt, uv, sg = oi[use], pos[op[use]], uv[use], sg[use]
        u2 = rloss.ray_u2(uv - project(res.eop[oi], res.gp[pt], self.camera_now), sg)
        off = np.union1d(rloss.withheld_points(u2, pt, res.eop[oi], uv, sg, self.camera_now,
                                               self.options.robust_scale, res.sigma0),
                         rloss.narrow_points(pt, res.eop[oi], uv, self.camera_now))
        held = sorted(self._ambiguous)  # out of the block already (_solve)
        self.disagreeing = [ids[int(j)] for j in sorted(held + self._point_sel[off].tolist())]
        return set(off.tolist())

    @property
    def untrusted(self) -> list[str]:
        """Two-ray tie points out of the block at the last solution (:meth:`_untrusted_pairs`)."""
        return [self._cat.point_ids[j] for j in sorted(self._untrusted)]
