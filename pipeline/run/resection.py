"""Initial attitude of a new image from known directions (robust Wahba resection).

Seed 003 §3: a new image is oriented by resection before it joins the sequential
adjustment. The INS of a light UAV is often 10-20° off (Seneca); the sequential update
linearises the new image around its initial value, and a few iterations from such a start
do not converge (there sigma0 jumped from 1.2 to 116 at the first image of a reverse leg).

A full 6-DoF resection on a flat, narrow patch of ground points trades position against
tilt (22 m against 22° at 70 m height, seen on Seneca), so the camera position is taken from
the GPS, which is good to metres, and only the rotation is solved: the rotation that best
turns the image rays into the directions from the GPS position to the points (Wahba's
problem, solved by SVD), inside RANSAC on 2-point samples. The result is only an
initial value (:attr:`seqat.types.Frame.initial_eop`), never an observation. Its outliers
are tie-point observations that disagree with every consistent rotation by more than the
threshold (degrees: far beyond image noise and terrain relief): wrong matches, which the
caller leaves out of the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqat.geometry import angles_from_rotation, rays_world
from seqat.types import EOP_SIZE, FloatArray, PinholeCamera

#: Fewest points to try a resection.
MIN_POINTS = 6
#: A resection is used when at least this many and this fraction of the points agree.
MIN_INLIERS = 6
MIN_INLIER_FRACTION = 0.5
#: RANSAC samples (2 points each) and the seed of their generator (reproducible runs).
SAMPLES = 100
SEED = 0


@dataclass(frozen=True, kw_only=True, eq=False)
class Resection:
    """Result of :func:`resect_attitude`.

    Attributes
    ----------
    eop : (6,) float or None
        ``[X, Y, Z]`` of the nav and the resected ``[omega, phi, kappa]``; ``None`` when no
        reliable rotation exists (too few points or too few agree).
    inliers : (k,) bool
        Points whose ray agrees with the resected rotation (all ``True`` without one).
    n_points, n_inliers : int
    """

    eop: FloatArray | None
    inliers: np.ndarray
    n_points: int
    n_inliers: int


def _wahba(cam: FloatArray, world: FloatArray) -> FloatArray:
    """Rotation ``R`` (camera -> world) minimising ``sum |world_i - R cam_i|^2``."""
    U, _, Vt = np.linalg.svd(world.T @ cam)
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt


def resect_attitude(xyz_m: FloatArray, uv_px: FloatArray, camera: PinholeCamera,
                    nav_eop: FloatArray, threshold_deg: float) -> Resection:
    """Rotation of an image at its GPS position from points of known (approximate) position.

    Parameters
    ----------
    xyz_m : (k, 3) float
        Points, world metres.
    uv_px : (k, 2) float
        Their pixels in the image (of ``camera``, whose distortion the rays take out).
    camera : PinholeCamera
    nav_eop : (6,) float
        GPS/INS EOP; its position is kept.
    threshold_deg : float
        Angle between a ray and the direction to its point within which they agree.

    Returns
    -------
    Resection
    """
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    k = len(xyz)
    if k < MIN_POINTS:
        return Resection(eop=None, inliers=np.ones(k, dtype=bool), n_points=k, n_inliers=0)
    cam = rays_world(np.zeros((k, EOP_SIZE)), uv, camera)  # camera frame: no rotation
    world = xyz - np.asarray(nav_eop[:3], dtype=np.float64)
    world /= np.linalg.norm(world, axis=1, keepdims=True)
    cos_thr = np.cos(np.radians(threshold_deg))
    rng = np.random.default_rng(SEED)
    best = np.zeros(k, dtype=bool)
    for _ in range(SAMPLES):
        pick = rng.choice(k, size=2, replace=False)
        R = _wahba(cam[pick], world[pick])
        agree = np.einsum("ij,ij->i", world, cam @ R.T) >= cos_thr
        if agree.sum() > best.sum():
            best = agree
    n_in = int(best.sum())
    if n_in < max(MIN_INLIERS, MIN_INLIER_FRACTION * k):
        return Resection(eop=None, inliers=np.ones(k, dtype=bool), n_points=k, n_inliers=n_in)
    R = _wahba(cam[best], world[best])
    agree = np.einsum("ij,ij->i", world, cam @ R.T) >= cos_thr  # of the refitted rotation
    eop = np.concatenate([np.asarray(nav_eop[:3], dtype=np.float64), angles_from_rotation(R)])
    return Resection(eop=eop, inliers=agree, n_points=k, n_inliers=int(agree.sum()))
