"""Data snooping of :class:`seqat.simultaneous.SimultaneousAT` (Baarda's w-test after each
adjustment, when ``SimOptions.snooping_critical`` is set): image points rejected and taken
back, GPS/INS groups down-weighted (docs/algorithm.md, *Robust loss*)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from seqat import snooping
from seqat.geometry import project_with_jacobians
from seqat.normals import eop_residual
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray

if TYPE_CHECKING:
    from seqat.normals import BlockData
    from seqat.simultaneous import SimResult


class SnoopingMixin:
    """Data snooping of :class:`seqat.simultaneous.SimultaneousAT`."""

    def _snoop(self, res: SimResult, data: BlockData, sel: np.ndarray, cat_idx: np.ndarray,
               critical: float) -> bool:
        """One round of data snooping (seqat.snooping); True when something was rejected or
        down-weighted (the block is then adjusted again)."""
        full = res.full_cofactor
        assert full is not None
        n = data.n_images
        img, pt = data.obs_image, data.obs_point
        uv, J, cols = self._design(res, img, pt, n)
        worst = snooping.point_w(J,
                                 full[cols[:, :, None], cols[:, None, :]],
                                 data.obs_uv - uv, data.obs_sigma_px)
        cat = self._cat
        changed = False
        for q in snooping.select(worst, critical, img, pt):
            self._rejected.add(int(cat_idx[q]))
            self._gp_est[int(pt[q])] = np.nan  # intersect again from the remaining rays
            self.rejections.append((cat.image_ids[int(img[q])],
                                    cat.point_ids[int(sel[int(pt[q])])], float(worst[q])))
            changed = True
        if changed:
            return True  # image blunders first: they distort the GPS/INS residuals
        if self._readmit(res, sel, full, critical):
            return True
        q_diag = np.diagonal(full)
        res_nav = eop_residual(data.nav_eop, res.eop)
        done = set(self.nav_downweighted)
        for i in range(n):
            groups = snooping.nav_groups(res_nav[i], data.nav_sigma[i],
                                         q_diag[EOP_SIZE * i : EOP_SIZE * (i + 1)], critical)
            for group in groups:
                if (cat.image_ids[i], group) in done:
                    continue  # once per image and group
                sl = slice(0, 3) if group == "position" else slice(3, 6)
                sigma = cat.nav_sigma[i].copy()
                sigma[sl] *= snooping.NAV_DOWNWEIGHT
                cat.nav_sigma[i] = sigma
                self.nav_downweighted.append((cat.image_ids[i], group))
                changed = True
        return changed

    def _readmit(self, res: SimResult, sel: np.ndarray, full: FloatArray,
                 critical: float) -> bool:
        """Take back rejected observations that the clean solution predicts within
        ``critical`` (w of the prediction, variance ``sigma^2 + a Q a^T``): in a young
        block a blunder spreads to good observations, which then fail too. True when any
        came back (the block is then adjusted again)."""
        if not self._rejected:
            return False
        cat = self._cat
        idx = np.fromiter(self._rejected, dtype=np.int64)
        oi, op = cat.rays()
        img = oi[idx]
        remap = np.full(len(cat.point_ids), -1)
        remap[sel] = np.arange(sel.size)
        pt = remap[op[idx]]
        ok = pt >= 0
        if not np.any(ok):
            return False
        idx, img, pt = idx[ok], img[ok], pt[ok]
        n = res.eop.shape[0]
        uv = np.asarray(cat.obs_uv, dtype=np.float64).reshape(-1, 2)[idx]
        sigma = np.asarray(cat.obs_sigma, dtype=np.float64)[idx]
        proj, J, cols = self._design(res, img, pt, n)
        w = snooping.predicted_w(J,
                                 full[cols[:, :, None], cols[:, None, :]], uv - proj, sigma)
        back = idx[w < critical]
        if back.size == 0:
            return False
        self._rejected.difference_update(int(q) for q in back)
        gone = {(cat.image_ids[int(i)], cat.point_ids[int(sel[int(p)])])
                for i, p in zip(img[w < critical], pt[w < critical], strict=True)}
        self.rejections = [r for r in self.rejections if (r[0], r[1]) not in gone]
        return True

    def _design(self, res: SimResult, img: np.ndarray, pt: np.ndarray,
                n: int) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """Projections (k, 2), Jacobians (k, 2, 6 + c + 3) of the observations ``(img, pt)``
        and their columns in the full cofactor ``[EOPs, camera, GPs]``."""
        cal = self._calibration
        c = len(cal.free) if cal is not None and res.camera_cofactor is not None else 0
        uv, Je, Jp, Jc = project_with_jacobians(res.eop[img], res.gp[pt], self.camera_now,
                                                intrinsics=True)
        parts = [Je, Jc[:, :, cal.index]] if c and cal is not None else [Je]
        cols = np.concatenate([EOP_SIZE * img[:, None] + np.arange(EOP_SIZE),
                               np.broadcast_to(EOP_SIZE * n + np.arange(c), (img.size, c)),
                               EOP_SIZE * n + c + GP_SIZE * pt[:, None] + np.arange(GP_SIZE)],
                              axis=1)
        return uv, np.concatenate([*parts, Jp], axis=2), cols
