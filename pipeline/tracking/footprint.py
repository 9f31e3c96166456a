"""Predicted ground footprints of the tracker's images (:mod:`pipeline.tracking.tracker`):
which held images a new one may overlap, from the nav EOPs alone, before any pixel is read.

The footprint is the four image corners intersected with the plane ``Z = plane_z`` (ideal
pinhole). An image whose corner rays point near or above the horizon has none. When no
footprint overlaps, the nav attitude may be far off (an INS glitch, a gimbal still
turning) while its position is right: :func:`near_in_plan` says whether two images' *nadir*
footprints at their positions would overlap.
"""

from __future__ import annotations

import math

import numpy as np

from seqat.geometry import rays_world
from seqat.types import FloatArray, PinholeCamera

#: A corner ray must point at least this much below the horizon to give a footprint (radians);
#: flatter rays count as "horizon" and the image falls back to recency-based candidates.
MIN_RAY_DEPRESSION_RAD = math.radians(5.0)
#: A footprint corner farther than this multiple of the height above the plane counts as
#: horizon too (an oblique corner would otherwise span kilometres).
MAX_FOOTPRINT_RANGE_FACTOR = 20.0


def ground_footprint(nav: FloatArray, plane_z: float, camera: PinholeCamera
                     ) -> FloatArray | None:
    """World XY (4, 2) of the image corners on ``Z = plane_z`` (in corner order), or None
    (below the plane, or a corner at the horizon)."""
    corners = np.array([[0.0, 0.0], [camera.width_px - 1.0, 0.0],
                        [camera.width_px - 1.0, camera.height_px - 1.0],
                        [0.0, camera.height_px - 1.0]])
    rays = rays_world(np.tile(nav, (4, 1)), corners, camera)
    height = nav[2] - plane_z
    if height <= 0 or np.any(rays[:, 2] > -math.sin(MIN_RAY_DEPRESSION_RAD)):
        return None
    t = -height / rays[:, 2]
    if np.any(t > MAX_FOOTPRINT_RANGE_FACTOR * height):
        return None
    return nav[:2] + t[:, None] * rays[:, :2]


def near_in_plan(nav_a: FloatArray, nav_b: FloatArray, plane_z: float,
                 camera: PinholeCamera) -> bool:
    """The nadir footprints of two images at their nav positions overlap: their plan
    distance is below the sum of the footprints' half diagonals (each at its own height
    above ``Z = plane_z``). Attitude-free, for images whose predicted footprints miss."""
    half_diagonal = math.hypot(camera.width_px, camera.height_px) / (2.0 * camera.f_px)
    reach = half_diagonal * (max(nav_a[2] - plane_z, 0.0) + max(nav_b[2] - plane_z, 0.0))
    return bool(math.hypot(nav_a[0] - nav_b[0], nav_a[1] - nav_b[1]) < reach)
