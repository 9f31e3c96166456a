"""Ground footprint of one image on the DSM: the window the orthorectifier fills."""

from __future__ import annotations

import math

import cv2
import numpy as np

from pipeline.flight.camera import border_pixels
from pipeline.ortho.base import MIN_DEPRESSION_SIN
from seqat.errors import InputDataError
from seqat.geometry import rays_world
from seqat.types import FloatArray


class FootprintMixin:
    """Footprint of an image on the DSM (part of
    :class:`~pipeline.ortho.orthorectifier.Orthorectifier`)."""

    def _ground_height(self, image_id: str, eop: FloatArray) -> float:
        """DSM height under the camera (the median of the DSM when that cell is empty)."""
        z = float(self.dsm.sample(eop[:1], eop[1:2])[0])
        if not math.isfinite(z):
            z = float(np.nanmedian(self.dsm.heights_m))
        if eop[2] <= z:
            raise InputDataError(f"image {image_id!r}: the camera (Z0 = {eop[2]:.2f} m) is not "
                                 f"above the DSM ({z:.2f} m under it)")
        return z

    def _ground_points(self, eop: FloatArray, rays: FloatArray, z_m: float, range_m: float) -> (
            tuple[FloatArray, bool]):
        """Rays meet the plane ``Z = z_m``, at most ``range_m`` from the nadir point."""
        down = rays[:, 2] < -MIN_DEPRESSION_SIN
        t = np.where(down, (z_m - eop[2]) / np.where(down, rays[:, 2], -1.0), np.inf)
        horiz = np.linalg.norm(rays[:, :2], axis=1)
        t_max = range_m / np.maximum(horiz, 1e-12)
        partial = bool(np.any(t > t_max))
        t = np.minimum(t, t_max)
        return eop[:2] + t[:, None] * rays[:, :2], partial

    def _footprint(self, image_id: str, eop: FloatArray, R: FloatArray, z_ground: float,
                   height_agl: float) -> tuple[FloatArray, FloatArray,
                                               tuple[float, float, float, float],
                                               tuple[str, ...]]:
        """Footprint ring on the nadir plane, its convex hull over the DSM's heights, the
        ground window (clipped to the DSM) and warnings."""
        ideal = self._corrector.ideal_pixels(border_pixels(self.camera.width_px,
                                                           self.camera.height_px))
        rays = rays_world(np.tile(eop, (len(ideal), 1)), ideal, self._pinhole)
        range_m = self.options.max_range_factor * height_agl
        ring, partial = self._ground_points(eop, rays, z_ground, range_m)
        box = (ring[:, 0].min(), ring[:, 1].min(), ring[:, 0].max(), ring[:, 1].max())
        z_lo, z_hi = self.dsm.height_range(box)
        if not math.isfinite(z_lo):
            z_lo = z_hi = z_ground
        z_hi = min(z_hi, eop[2] - 1e-3 * height_agl)
        pts = [ring]
        for z in (min(z_lo, z_ground), max(z_hi, z_ground)):
            ground, part = self._ground_points(eop, rays, z, range_m * (eop[2] - z) / height_agl)
            pts.append(ground)
            partial |= part
        allp = np.vstack(pts)
        dw, ds, de, dn = self.dsm.bounds
        window = (max(allp[:, 0].min(), dw), max(allp[:, 1].min(), ds),
                  min(allp[:, 0].max(), de), min(allp[:, 1].max(), dn))
        if window[0] >= window[2] or window[1] >= window[3]:
            raise InputDataError(
                f"image {image_id!r}: the DSM ({self.dsm.source}, bounds "
                f"{tuple(round(b, 1) for b in self.dsm.bounds)}) does not cover the image "
                f"footprint {tuple(round(float(b), 1) for b in box)}")
        notes = []
        if partial:
            notes.append(f"image {image_id!r}: part of the image looks beyond "
                         f"{self.options.max_range_factor:g} x the height above ground (or "
                         "above the horizon); that part is not orthorectified")
        if not np.all((ring[:, 0] >= dw) & (ring[:, 0] <= de) & (ring[:, 1] >= ds)
                      & (ring[:, 1] <= dn)):
            notes.append(f"image {image_id!r}: the footprint reaches beyond the DSM "
                         f"({self.dsm.source}); the ortho stops at its edge")
        hull = cv2.convexHull(allp.astype(np.float32)).reshape(-1, 2).astype(np.float64)
        return np.vstack([ring, ring[:1]]), hull, window, tuple(notes)
