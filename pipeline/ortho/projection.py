"""Projection of DSM cells into one image: the remap tables of the orthorectifier."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.ortho.base import BLOCK_ROWS, OCCLUSION_SUBSAMPLE, OUTSIDE_PX, POINTS_PER_ROW
from seqat.types import FloatArray


@dataclass(kw_only=True, eq=False)
class Projection:
    """Per-cell work arrays of one image (float32 / bool, the ortho grid's shape)."""

    uv: np.ndarray  # (rows, cols, 2) observed pixels, OUTSIDE_PX where unseen
    off_nadir: np.ndarray
    seen: np.ndarray
    off_dsm: list[int]
    # Every OCCLUSION_SUBSAMPLE-th cell in each direction (z-buffer): observed pixels, depth
    # (NaN behind the camera, inf outside the footprint), seen, and the DSM heights there.
    uv_s: np.ndarray
    depth_s: np.ndarray
    seen_s: np.ndarray
    z_s: np.ndarray


def _hull_columns(hull: FloatArray, col0: int, grow0: int, grow1: int, pixel_m: float,
                  cols: int) -> tuple[int, int]:
    """Columns ``[c_lo, c_hi)`` of the grid that the convex polygon ``hull`` reaches in the
    global rows ``[grow0, grow1)`` (one cell of margin); ``(0, 0)`` when none.

    The x range of a convex polygon within a horizontal band: its vertices inside the band
    and its edges' crossings of the band's two lines.
    """
    y_hi, y_lo = -grow0 * pixel_m, -grow1 * pixel_m
    a, b = hull, np.roll(hull, -1, axis=0)
    xs = [a[(a[:, 1] >= y_lo) & (a[:, 1] <= y_hi), 0]]
    for y in (y_lo, y_hi):
        crosses = (a[:, 1] - y) * (b[:, 1] - y) < 0
        t = (y - a[crosses, 1]) / (b[crosses, 1] - a[crosses, 1])
        xs.append(a[crosses, 0] + t * (b[crosses, 0] - a[crosses, 0]))
    x = np.concatenate(xs)
    if x.size == 0:
        return 0, 0
    c_lo = int(math.floor(x.min() / pixel_m)) - col0 - 1
    c_hi = int(math.ceil(x.max() / pixel_m)) - col0 + 1
    return max(c_lo, 0), min(max(c_hi, 0), cols)


class ProjectionMixin:
    """DSM cells -> image pixels (part of
    :class:`~pipeline.ortho.orthorectifier.Orthorectifier`)."""

    def _project(self, eop: FloatArray, R: FloatArray, col0: int, row0: int, Z: np.ndarray,
                 z_ground: float, hull: FloatArray) -> Projection:
        """Observed pixel, depth and off-nadir tangent of every cell (float32, row blocks).

        With ``d = -p_z`` (the depth) the ideal pixel is ``u = (cx d + f p_x) / d``,
        ``v = (cy d - f p_y) / d``: numerators and depth are affine in the cell's offset from
        the projection centre, so each is an outer sum over the grid's rows and columns plus
        a multiple of the height. The distortion is added from the camera's lookup table
        (:class:`pipeline.flight.camera.DistortionTable`, one ``cv2.remap``). Cells without DSM
        height are projected at ``z_ground`` only to count those inside the image
        (``off_dsm``); they stay unseen.
        In each row block only the columns inside ``hull`` (the footprint's convex hull over
        the DSM's heights, east/north metres) are projected.
        """
        rows, cols = Z.shape
        p = self.pixel_m
        assert p is not None
        f32 = np.float32
        dx = (col0 + np.arange(cols) + 0.5) * p - eop[0]
        dy = -(row0 + np.arange(rows) + 0.5) * p - eop[1]
        k = self._lut_coefficients(R)
        col_terms = (k[:, 0:1] * dx[None, :]).astype(f32)  # (3, cols)
        row_terms = (k[:, 1:2] * dy[None, :]).astype(f32)  # (3, rows)
        k_f32 = k[:, 2].astype(f32)
        dxy2 = ((dx**2).astype(f32), (dy**2).astype(f32))  # squared horizontal offsets
        ks = OCCLUSION_SUBSAMPLE
        sub_shape = (-(-rows // ks), -(-cols // ks))
        out = Projection(uv=self._buffer("uv", (rows, cols, 2)),
                          off_nadir=np.empty((rows, cols), f32),
                          seen=np.empty((rows, cols), bool), off_dsm=[],
                          uv_s=self._buffer("uv_s", sub_shape + (2,)),
                          depth_s=self._buffer("depth_s", sub_shape),
                          seen_s=np.empty(sub_shape, bool), z_s=self._buffer("z_s", sub_shape))
        z0, z_fill = f32(eop[2]), f32(z_ground)
        margin = 1.0 if self.options.resampling == "cubic" else 0.0  # kernel inside the image
        lo = (margin, margin)
        hi = (self.camera.width_px - 1 - margin, self.camera.height_px - 1 - margin)
        has_holes = bool(np.isnan(Z).any())

        def block(r0: int) -> None:
            rs = slice(r0, min(r0 + BLOCK_ROWS, rows))
            # Only the columns the footprint can reach in these rows are projected.
            c_lo, c_hi = _hull_columns(hull, col0, row0 + rs.start, row0 + rs.stop, p, cols)
            ss = slice(rs.start // ks, -(-rs.stop // ks))
            for part in (slice(0, c_lo), slice(c_hi, cols)):
                out.seen[rs, part] = False
                out.uv[rs, part] = OUTSIDE_PX
                out.off_nadir[rs, part] = np.inf
                out.depth_s[ss, -(-part.start // ks):-(-part.stop // ks)] = np.inf
            cs = slice(c_lo, c_hi)
            if c_lo < c_hi:
                self._project_block(out, rs, cs, Z, k_f32, row_terms, col_terms, dxy2,
                                    z0, z_fill, has_holes, lo, hi)
            # Every ks-th cell for the z-buffer, copied while the block is in the cache.
            out.uv_s[ss] = out.uv[rs][::ks, ::ks]
            out.seen_s[ss] = out.seen[rs][::ks, ::ks]
            out.z_s[ss] = Z[rs][::ks, ::ks]

        list(self._pool.map(block, range(0, rows, BLOCK_ROWS)))
        return out

    def _project_block(self, out: Projection, rs: slice, cs: slice, Z: np.ndarray,
                       kz: np.ndarray, row_terms: np.ndarray, col_terms: np.ndarray,
                       dxy2: tuple[np.ndarray, np.ndarray], z0: np.float32, z_fill: np.float32,
                       has_holes: bool, lo: tuple[float, float],
                       hi: tuple[float, float]) -> None:
        """Project the cells ``[rs, cs]`` into ``out`` (see :meth:`_project`)."""
        f32 = np.float32
        lut = self._lut
        dz = Z[rs, cs] - z0
        no_height = np.isnan(dz) if has_holes else None
        if no_height is not None:
            dz[no_height] = z_fill - z0
        depth = kz[2] * dz
        depth += row_terms[2, rs, None]
        depth += col_terms[2, cs]
        behind = depth <= 0
        any_behind = bool(behind.any())
        uv_obs = out.uv[rs, cs]  # written in place (OpenCV takes the strided view)
        uv = np.empty(depth.shape + (2,), f32) if self._distorted else uv_obs
        for c in (0, 1):
            num = kz[c] * dz
            num += row_terms[c, rs, None]
            num += col_terms[c, cs]
            np.divide(num, depth, out=uv[:, :, c])
        if any_behind:
            uv[behind] = OUTSIDE_PX
            depth[behind] = np.nan
        if self._distorted:
            delta = cv2.remap(lut.table, uv, None, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=(OUTSIDE_PX,) * 4)
            cv2.scaleAdd(uv, lut.step_px, delta, dst=uv_obs)
        seen = out.seen[rs, cs]
        np.greater(cv2.inRange(uv_obs, lo, hi), 0, out=seen)
        if no_height is not None:
            out.off_dsm.append(int(np.count_nonzero(seen & no_height)))
            seen &= ~no_height
            uv_obs[~seen] = OUTSIDE_PX
        ks = OCCLUSION_SUBSAMPLE  # the z-buffer needs the depth of every ks-th cell only
        out.depth_s[rs.start // ks:-(-rs.stop // ks), -(-cs.start // ks):-(-cs.stop // ks)] = (
            depth[(-rs.start) % ks::ks, (-cs.start) % ks::ks])
        hdist = np.sqrt(dxy2[0][cs] + dxy2[1][rs, None])
        np.divide(hdist, dz, out=hdist)
        np.negative(hdist, out=out.off_nadir[rs, cs])

    def _lut_coefficients(self, R: FloatArray) -> FloatArray:
        """(3, 3) map from ``(X - X0, Y - Y0, Z - Z0)`` to (numerator u, numerator v, depth).

        ``depth = -p_z``; ``u = (cx d + f p_x) / d``, ``v = (cy d - f p_y) / d`` with the
        distortion table's origin and step folded in: ``num_u / d = (u - u0) / step``
        (an ideal camera: ``num_u / d = u``).
        """
        lut = self._lut
        u0, v0, step = (lut.u0, lut.v0, lut.step_px) if self._distorted else (0.0, 0.0, 1.0)
        f, cx, cy = self._pinhole.f_px, self._pinhole.cx_px, self._pinhole.cy_px
        Rt = R.T  # rows: camera axes in world coordinates
        k = np.vstack([f * Rt[0] - (cx - u0) * Rt[2],
                       -f * Rt[1] - (cy - v0) * Rt[2],
                       -Rt[2]])
        k[:2] /= step
        return k

    def _project_points(self, k: FloatArray, offsets_m: FloatArray) -> (
            tuple[np.ndarray, np.ndarray]):
        """Observed pixels (OUTSIDE_PX where not seeable) and depths of scattered points.

        Parameters
        ----------
        k : (3, 3) float
            :meth:`_lut_coefficients`.
        offsets_m : (n, 3) float
            Points minus the projection centre.
        """
        x, y, z = (np.ascontiguousarray(offsets_m[:, i], dtype=np.float32) for i in range(3))
        kf = k.astype(np.float32)
        num_u, num_v, depth = (kf[i, 0] * x + kf[i, 1] * y + kf[i, 2] * z for i in range(3))
        uv = np.empty((len(x), 2), np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(num_u, depth, out=uv[:, 0])
            np.divide(num_v, depth, out=uv[:, 1])
        uv[~(depth > 0)] = OUTSIDE_PX
        if not self._distorted:
            return uv, depth
        n = len(uv)
        # cv2.remap needs maps under 32767 x 32767: lay the points out in rows.
        rows = -(-n // POINTS_PER_ROW)
        grid = np.full((rows * POINTS_PER_ROW, 2), OUTSIDE_PX, np.float32)
        grid[:n] = uv
        delta = cv2.remap(self._lut.table, grid.reshape(rows, POINTS_PER_ROW, 2), None,
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(OUTSIDE_PX,) * 4)
        return uv * np.float32(self._lut.step_px) + delta.reshape(-1, 2)[:n], depth
