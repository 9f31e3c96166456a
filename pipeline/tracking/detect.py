"""Feature detection of one image: the part of tracking that depends on the image alone.

:class:`FeatureDetector` turns an image into keypoints (working resolution), descriptors and
responses (:class:`Features`). The :class:`pipeline.tracking.tracker.Tracker` holds one; a
live watch holds a second one in its read-ahead thread (``pipeline/run/sources.py``
:class:`ReadAhead`), so that the next image is read and detected while the estimator adjusts
the current one: detection needs nothing of the tracker's or the estimator's state, so the
result is the same as detecting in turn (docs/architecture.md, *Live watch*).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.tracking.options import TrackerOptions
from seqat.types import FloatArray

#: OpenCV's SIFT defaults (Lowe 2004): layers per octave, edge threshold, base blur.
SIFT_OCTAVE_LAYERS = 3
SIFT_EDGE_THRESHOLD = 10.0
SIFT_SIGMA = 1.6
#: ORB pyramid scale factor (OpenCV's default).
ORB_SCALE_FACTOR = 1.2


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints (n, 2) float32 at working resolution, descriptors (n, d) uint8, responses (n,),
    and the milliseconds the detection took."""

    keypoints: NDArray[np.float32]
    descriptors: NDArray[np.uint8]
    response: FloatArray
    detect_ms: float


class FeatureDetector:
    """SIFT or ORB (``options.detector``) on the gray working copy of ``working_size_px``.

    One instance per thread: OpenCV's detectors are not documented as thread-safe.
    """

    def __init__(self, options: TrackerOptions, working_size_px: tuple[int, int]) -> None:
        self.options = options
        self.working_size_px = working_size_px
        if options.detector == "sift":
            # precise upscale: without it OpenCV's SIFT keypoints are 0.25 px (working
            # resolution) right of and below the true position (its doubled first octave is
            # resampled centre-aligned, then halved corner-aligned).
            self._detector = cv2.SIFT_create(
                options.max_features, SIFT_OCTAVE_LAYERS, options.sift_contrast_threshold,
                SIFT_EDGE_THRESHOLD, SIFT_SIGMA, cv2.CV_8U, True)
        else:
            self._detector = cv2.ORB_create(nfeatures=options.max_features,
                                            scaleFactor=ORB_SCALE_FACTOR)

    def detect(self, image: NDArray[np.uint8]) -> Features:
        """Gray or BGR image (checked by the tracker) -> its :class:`Features`."""
        t0 = time.perf_counter()
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.working_size_px != (gray.shape[1], gray.shape[0]):
            gray = cv2.resize(gray, self.working_size_px, interpolation=cv2.INTER_AREA)
        keypoints, desc = self._detector.detectAndCompute(gray, None)
        n_bytes = 128 if self.options.detector == "sift" else 32
        if desc is None or len(keypoints) == 0:
            return Features(np.zeros((0, 2), np.float32), np.zeros((0, n_bytes), np.uint8),
                            np.zeros(0), 1e3 * (time.perf_counter() - t0))
        kp = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
        response = np.array([k.response for k in keypoints], dtype=np.float64)
        if self.options.detector == "orb":
            # ORB reports a level-l corner at x_l * s_l; the level was resampled centre-aligned
            # (cv2.resize), so the pixel is (x_l + 0.5) s_l - 0.5: add 0.5 (s_l - 1).
            level = np.array([k.octave for k in keypoints], dtype=np.float64)
            kp += 0.5 * (ORB_SCALE_FACTOR**level - 1.0)[:, None]
        return Features(kp.astype(np.float32), np.ascontiguousarray(desc, dtype=np.uint8),
                        response, 1e3 * (time.perf_counter() - t0))
