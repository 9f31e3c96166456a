"""Occlusion of the orthorectifier: a z-buffer of DSM cells and facades (default), or rays cast
through the DSM's triangle mesh with open3d (``occlusion_method: raycast``), hides what the
camera cannot see (docs/benchmarks.md, *Occlusion: z-buffer or open3d ray casting*)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from pipeline.ortho.base import BLOCK_ROWS, MAX_FACADE_PX, OCCLUSION_SUBSAMPLE, OUTSIDE_PX
from pipeline.ortho.projection import Projection
from pipeline.ortho.raycast import DsmMesh
from seqat.types import FloatArray


class OcclusionMixin:
    """Hidden-cell masking (part of :class:`~pipeline.ortho.orthorectifier.Orthorectifier`)."""

    def _facade_points(self, Z: np.ndarray, stride: int, col0: int, row0: int,
                       eop: FloatArray, k: FloatArray, step_px: float, min_jump_m: float) -> (
            tuple[np.ndarray, np.ndarray]):
        """Samples of the vertical walls a 2.5D DSM implies, for the z-buffer.

        ``Z`` holds every ``stride``-th cell of the grid in each direction (the grid's top-left
        cell is ``(col0, row0)``). A wall faces the camera where a cell stands more than
        ``min_jump_m`` above its neighbours towards the nadir point (the lowest of the two
        axis neighbours and the diagonal one on that side); the segment from that neighbour's
        height to the cell's is sampled every ``step_px`` image pixels (from its projected
        length). Walls facing away are hidden by their roofs and need no samples.

        Returns
        -------
        uv : (m, 2) float32
        depth : (m,) float32
        """
        p = self.pixel_m
        assert p is not None
        rows, cols = Z.shape
        filled = np.where(np.isnan(Z), np.float32(np.inf), Z)
        # Candidates: above their lowest 8-neighbour (one fast minimum filter) ...
        lowest8 = cv2.erode(filled, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        with np.errstate(invalid="ignore"):
            r, c = np.nonzero(Z - lowest8 > min_jump_m)
        # ... then the neighbours towards the nadir point (columns east, rows south).
        x_cells = (col0 + stride * np.arange(cols) + 0.5) * p - eop[0]
        y_cells = -(row0 + stride * np.arange(rows) + 0.5) * p - eop[1]
        dc = ((x_cells < 0).astype(np.intp) - (x_cells > 0))[c]
        dr = ((y_cells > 0).astype(np.intp) - (y_cells < 0))[r]
        rn, cn = np.clip(r + dr, 0, rows - 1), np.clip(c + dc, 0, cols - 1)
        lowest = np.minimum(np.minimum(filled[rn, c], filled[r, cn]), filled[rn, cn])
        with np.errstate(invalid="ignore"):
            facing = Z[r, c] - lowest > min_jump_m
        r, c, lowest = r[facing], c[facing], lowest[facing]
        empty = (np.empty((0, 2), np.float32), np.empty(0, np.float32))
        if r.size == 0:
            return empty
        x, y = x_cells[c], y_cells[r]
        top, bottom = Z[r, c].astype(np.float64), lowest.astype(np.float64)
        uv_top, _ = self._project_points(k, np.column_stack([x, y, top - eop[2]]))
        uv_bot, _ = self._project_points(k, np.column_stack([x, y, bottom - eop[2]]))
        length = np.linalg.norm(uv_top - uv_bot, axis=1)
        length[~np.isfinite(length) | (length > MAX_FACADE_PX)] = MAX_FACADE_PX
        n = np.ceil(length / step_px).astype(np.int64) + 1
        seg = np.repeat(np.arange(r.size), n)
        first = np.repeat(np.cumsum(n) - n, n)
        t = (np.arange(seg.size) - first) / np.maximum(n[seg] - 1, 1)
        z = bottom[seg] + t * (top[seg] - bottom[seg])
        uv, depth = self._project_points(k, np.column_stack([x[seg], y[seg], z - eop[2]]))
        return uv, depth

    def _hide_occluded(self, proj: Projection, eop: FloatArray, R: FloatArray,
                       col0: int, row0: int,
                       window: tuple[float, float, float, float]) -> int:
        """Mark cells hidden by nearer surfaces as unseen (z-buffer); the number hidden.

        Skipped (0) when the relief under the window is within the tolerance. The buffer is
        filled from every ``OCCLUSION_SUBSAMPLE``-th cell in each direction (``np.minimum.at``)
        and from the camera-facing walls (:meth:`_facade_points`), with buckets of the image
        spacing of those cells on the highest surface, widened by a 3 x 3 minimum filter. The
        same sub-sampled cells then read their bucket (``cv2.remap``, nearest) and are hidden
        when they lie farther than the tolerance behind it; every cell of a k x k block takes
        its sampled cell's verdict (occlusion edges are exact to k cells).
        """
        z_lo, z_hi = self.dsm.height_range(window)
        p = self.pixel_m
        assert p is not None
        if not math.isfinite(z_lo) or z_hi - z_lo <= self.options.occlusion_tolerance_cells * p:
            return 0
        fx = self.camera.fx_px
        k = OCCLUSION_SUBSAMPLE
        # Integer bucket: pixel (i, j) (nearest to an observed position) lies in bucket
        # (i // b, j // b), so the buffer blown up by b reads back with one nearest remap.
        b = max(1, math.ceil(k * p * fx / max(eop[2] - z_hi, 1e-6)))
        tol = np.float32(self.options.occlusion_tolerance_cells * b * (eop[2] - z_lo) / fx)
        width, height = self.camera.width_px, self.camera.height_px
        nbu, nbv = -(-width // b), -(-height // b)
        uv_s, seen_s, depth_s = proj.uv_s, proj.seen_s, proj.depth_s
        # Bucket of the nearest pixel: floor((u + 0.5) / b); as a map coordinate read with
        # nearest-neighbour rounding: (u + 0.5) / b - 0.5.
        uv_b = cv2.addWeighted(uv_s, 1.0 / b, uv_s, 0.0, 0.5 / b - 0.5)
        pix = (uv_b + np.float32(0.5)).astype(np.int32)
        index = pix[:, :, 1] * nbu + pix[:, :, 0]
        index[~seen_s] = nbu * nbv  # unseen cells go to a spare slot
        zbuf = np.full(nbu * nbv + 1, np.inf, dtype=np.float32)
        with np.errstate(invalid="ignore"):  # unseen cells (spare slot) may have NaN depth
            np.minimum.at(zbuf, index.ravel(), depth_s.ravel())
        # Walls between cells of very different height (facades) hide what lies behind them.
        # Wall samples 2 buckets apart: the 3 x 3 minimum filter closes the gaps between them.
        uv_f, depth_f = self._facade_points(proj.z_s, k, col0, row0, eop,
                                            self._lut_coefficients(R), 2.0 * b, float(tol))
        if len(depth_f):
            pf = np.floor((uv_f + 0.5) / b).astype(np.int64)
            inside = (pf[:, 0] >= 0) & (pf[:, 0] < nbu) & (pf[:, 1] >= 0) & (pf[:, 1] < nbv)
            np.minimum.at(zbuf, pf[inside, 1] * nbu + pf[inside, 0], depth_f[inside])
        zbuf = cv2.erode(zbuf[:-1].reshape(nbv, nbu), np.ones((3, 3), np.uint8))
        zbuf[~np.isfinite(zbuf)] = np.float32(3.0e38)
        # The test runs on the same sub-sampled cells; each full cell takes its k x k block's.
        nearest = cv2.remap(zbuf, uv_b, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        nearest += tol
        hidden_s = (seen_s & (depth_s > nearest)).view(np.uint8)
        return self._apply_hidden(proj, hidden_s)

    def _hide_occluded_raycast(self, proj: Projection, eop: FloatArray, col0: int, row0: int,
                               window: tuple[float, float, float, float]) -> int:
        """As :meth:`_hide_occluded`, by ray casting (``occlusion_method: raycast``).

        The same sub-sampled cells each cast one ray from the camera towards their ground
        point through the DSM's triangle mesh (:class:`~pipeline.ortho.raycast.DsmMesh`,
        open3d's ``RaycastingScene``, built once); a cell is hidden when the ray meets the
        surface more than the tolerance (``occlusion_tolerance_cells`` ground cells) before
        it. Exact visibility of the triangulated DSM: no buckets, no facade samples.
        """
        z_lo, z_hi = self.dsm.height_range(window)
        p = self.pixel_m
        assert p is not None
        if not math.isfinite(z_lo) or z_hi - z_lo <= self.options.occlusion_tolerance_cells * p:
            return 0
        if self._mesh is None:
            self._mesh = DsmMesh(self.dsm)
        k = OCCLUSION_SUBSAMPLE
        seen_s = proj.seen_s
        r, c = np.nonzero(seen_s)
        if r.size == 0:
            return 0
        ground = np.column_stack([(col0 + k * c + 0.5) * p, -(row0 + k * r + 0.5) * p,
                                  proj.z_s[r, c].astype(np.float64)])
        ray = ground - eop[:3]
        distance = np.linalg.norm(ray, axis=1)
        t_hit = self._mesh.first_hit_m(eop[:3], ray / distance[:, None])
        hidden = t_hit < distance - self.options.occlusion_tolerance_cells * p
        hidden_s = np.zeros(seen_s.shape, np.uint8)
        hidden_s[r[hidden], c[hidden]] = 1
        return self._apply_hidden(proj, hidden_s)

    def _apply_hidden(self, proj: Projection, hidden_s: np.ndarray) -> int:
        """Unsee every cell of the k x k blocks whose sampled cell is hidden (uint8 mask of
        the sub-sampled grid); the number of cells hidden."""
        k = OCCLUSION_SUBSAMPLE
        rows, cols = proj.seen.shape
        if not hidden_s.any():
            return 0
        hidden_full = cv2.resize(hidden_s, (hidden_s.shape[1] * k, hidden_s.shape[0] * k),
                                 interpolation=cv2.INTER_NEAREST)
        hidden_counts: list[int] = []

        def block(r0: int) -> None:
            rs = slice(r0, min(r0 + BLOCK_ROWS, rows))
            seen = proj.seen[rs]
            hidden = seen & hidden_full[rs, :cols].view(bool)
            seen &= ~hidden
            proj.uv[rs][hidden] = OUTSIDE_PX
            hidden_counts.append(int(np.count_nonzero(hidden)))

        list(self._pool.map(block, range(0, proj.seen.shape[0], BLOCK_ROWS)))
        return sum(hidden_counts)
