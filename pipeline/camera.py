"""From the ``flight.yaml`` camera to seqat's ideal pinhole camera.

seqat works with an ideal pinhole camera with square pixels (:class:`seqat.types.PinholeCamera`).
A ``PINHOLE`` camera maps 1:1 (``f_px = fx_px = fy_px``). For an ``OPENCV`` camera, observed
pixels are mapped to *ideal pixels* with ``cv2.undistortPoints`` using the new camera matrix
``P = [[fx, 0, cx], [0, fx, cy], [0, 0, 1]]``: this is ``P = K`` when ``fx = fy``, and
otherwise also rescales ``v`` so that the ideal camera has square pixels with ``f_px = fx``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.config import CameraConfig
from seqat.types import FloatArray, PinholeCamera

#: Iterations of OpenCV's iterative undistortion (its default of 5 leaves ~1e-5 px errors).
UNDISTORT_MAX_ITERATIONS = 100
#: Convergence threshold of the iterative undistortion, normalised image units.
UNDISTORT_EPS = 1e-14


def pinhole_camera(camera: CameraConfig) -> PinholeCamera:
    """The ideal pinhole camera seqat uses for ``camera`` (``f_px = fx_px``)."""
    return PinholeCamera(f_px=camera.fx_px, cx_px=camera.cx_px, cy_px=camera.cy_px,
                         width_px=camera.width_px, height_px=camera.height_px)


@dataclass(frozen=True, kw_only=True, eq=False)
class PixelCorrector:
    """Maps observed pixels of a configured camera to ideal pinhole pixels.

    Parameters
    ----------
    camera : CameraConfig
    """

    camera: CameraConfig

    @property
    def is_identity(self) -> bool:
        """True when observed pixels already are ideal pixels (no distortion, square pixels)."""
        return not self.camera.has_distortion and self.camera.fx_px == self.camera.fy_px

    def ideal_pixels(self, uv_px: FloatArray) -> FloatArray:
        """Remove lens distortion (and pixel aspect) from observed pixel coordinates.

        Parameters
        ----------
        uv_px : (k, 2) float
            Observed OpenCV pixels (u right, v down, origin at the centre of the top-left pixel).

        Returns
        -------
        (k, 2) float
            Pixels of the ideal camera :func:`pinhole_camera`.
        """
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        if self.is_identity or uv.shape[0] == 0:
            return uv.copy()
        cam = self.camera
        K = np.array([[cam.fx_px, 0.0, cam.cx_px], [0.0, cam.fy_px, cam.cy_px], [0.0, 0.0, 1.0]])
        P = np.array([[cam.fx_px, 0.0, cam.cx_px], [0.0, cam.fx_px, cam.cy_px], [0.0, 0.0, 1.0]])
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, UNDISTORT_MAX_ITERATIONS,
                    UNDISTORT_EPS)
        out = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, cam.distortion, P=P, criteria=criteria)
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)
