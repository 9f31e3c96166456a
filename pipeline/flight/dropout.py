"""GNSS dropouts: images without a GPS/INS fix, bridged by a 6-DoF space resection.

A dropout image reaches the estimator with ``nav_sigma = inf`` for its missing components
(no constraint) and ``initial_eop`` from a resection on the ground points the estimator
currently holds (its window): OpenCV's ``solvePnPRansac`` with the camera's distortion, refined by
Levenberg-Marquardt on the inliers (``solvePnPRefineLM``). The resection is only the start
value of the linearisation; the image's EOP and its σ come from the adjustment (issue 7).

Conventions: OpenCV's camera frame is ours with y and z negated (``seqat.cvframe``), so
``cam_from_world`` of OpenCV maps to EOPs with :func:`seqat.cvframe.eop_from_cv_pose`; the
pixels of seqat's camera are OpenCV pixels of ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]``
with its distortion coefficients ``(k1, k2, p1, p2, k3)`` (docs/conventions.md).

Start values of the missing components (:func:`predict_missing`) come from the past only
(no look-ahead): the last fix moved on at the velocity of the last two fixes, the last
attitude. They feed the tracker's footprint prediction and the estimator when nothing better
is known; they are never observations.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from seqat.cvframe import cv_pose_from_eop, eop_from_cv_pose
from seqat.geometry import depth, project
from seqat.types import EOP_SIZE, FloatArray, PinholeCamera

#: Fewest known ground points to try a resection (6 DoF; OpenCV needs >= 4, RANSAC more).
MIN_POINTS = 6
#: A resection is used when at least this many and this fraction of the points agree.
MIN_INLIERS = 6
MIN_INLIER_FRACTION = 0.5
#: RANSAC reprojection threshold: this many image sigmas, at least ``MIN_THRESHOLD_PX``.
THRESHOLD_SIGMAS = 5.0
MIN_THRESHOLD_PX = 2.0
#: RANSAC iterations and confidence (OpenCV's defaults are 100 / 0.99).
RANSAC_ITERATIONS = 500
RANSAC_CONFIDENCE = 0.999
#: OpenCV's RNG seed before each RANSAC (reproducible runs).
RANSAC_SEED = 0


@dataclass(frozen=True, kw_only=True, eq=False)
class PoseResection:
    """Result of :func:`resect_pose`.

    Attributes
    ----------
    eop : (6,) float or None
        World ``[X, Y, Z, omega, phi, kappa]`` (metres, radians); ``None`` when no reliable
        pose exists (``reason`` says why).
    inliers : (k,) bool
        Points within the RANSAC threshold of the refined pose (all ``False`` without one).
    n_points, n_inliers : int
    rms_px : float
        Reprojection r.m.s. of the inliers (NaN without a pose).
    reason : str
        Empty when ``eop`` is given.
    """

    eop: FloatArray | None
    inliers: np.ndarray
    n_points: int
    n_inliers: int
    rms_px: float
    reason: str = ""


def _failed(k: int, reason: str, n_inliers: int = 0) -> PoseResection:
    return PoseResection(eop=None, inliers=np.zeros(k, dtype=bool), n_points=k,
                         n_inliers=n_inliers, rms_px=float("nan"), reason=reason)


def resect_pose(xyz_m: FloatArray, uv_px: FloatArray, camera: PinholeCamera, *,
                sigma_px: float = 1.0, start_eop: FloatArray | None = None) -> PoseResection:
    """6-DoF pose of an image from points of known position (robust PnP, then LM).

    Parameters
    ----------
    xyz_m : (k, 3) float
        Ground points, world metres.
    uv_px : (k, 2) float
        Their pixels in the image, of ``camera`` (with its distortion).
    camera : PinholeCamera
    sigma_px : float
        Image point σ; the RANSAC threshold is ``max(5 σ, 2 px)``.
    start_eop : (6,) float, optional
        A guess (e.g. the predicted nav); used only when RANSAC alone finds nothing.

    Returns
    -------
    PoseResection
    """
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    k = len(xyz)
    if k < MIN_POINTS:
        return _failed(k, f"{k} known ground point(s) in the image, at least {MIN_POINTS} "
                          "are needed to resect it")
    origin = xyz.mean(axis=0)  # conditioning: OpenCV works in float64, but not in UTM metres
    obj = xyz - origin
    K = np.array([[camera.f_px, 0.0, camera.cx_px], [0.0, camera.f_px, camera.cy_px],
                  [0.0, 0.0, 1.0]])
    dist = (np.array([camera.k1, camera.k2, camera.p1, camera.p2, camera.k3])
            if camera.has_distortion else None)
    threshold = max(THRESHOLD_SIGMAS * sigma_px, MIN_THRESHOLD_PX)
    cv2.setRNGSeed(RANSAC_SEED)
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        obj, uv, K, dist, iterationsCount=RANSAC_ITERATIONS, reprojectionError=threshold,
        confidence=RANSAC_CONFIDENCE, flags=cv2.SOLVEPNP_SQPNP)
    if (not ok or idx is None) and start_eop is not None:
        guess = np.asarray(start_eop, dtype=np.float64).copy()
        guess[:3] -= origin
        R_cv, t = cv_pose_from_eop(guess[None])
        rvec, _ = cv2.Rodrigues(R_cv[0])
        ok, rvec, tvec, idx = cv2.solvePnPRansac(
            obj, uv, K, dist, rvec=rvec, tvec=t[0].reshape(3, 1).copy(),
            useExtrinsicGuess=True, iterationsCount=RANSAC_ITERATIONS,
            reprojectionError=threshold, confidence=RANSAC_CONFIDENCE,
            flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or idx is None:
        return _failed(k, f"no consistent pose from {k} known ground points (RANSAC)")
    inl = np.zeros(k, dtype=bool)
    inl[np.asarray(idx).ravel()] = True
    if inl.sum() >= 4:
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], uv[inl], K, dist, rvec, tvec)
    R_cv, _ = cv2.Rodrigues(rvec)
    eop = eop_from_cv_pose(R_cv[None], np.asarray(tvec, dtype=np.float64).reshape(1, 3))[0]
    eop[:3] += origin
    res = np.linalg.norm(project(np.broadcast_to(eop, (k, EOP_SIZE)), xyz, camera) - uv, axis=1)
    front = depth(np.broadcast_to(eop, (k, EOP_SIZE)), xyz) > 0
    inl = (res <= threshold) & front
    n_in = int(inl.sum())
    if n_in < max(MIN_INLIERS, MIN_INLIER_FRACTION * k):
        return _failed(k, f"resection: {n_in} of {k} known ground points agree with the pose "
                          f"(at least {max(MIN_INLIERS, int(np.ceil(MIN_INLIER_FRACTION * k)))} "
                          "needed)", n_in)
    return PoseResection(eop=eop, inliers=inl, n_points=k, n_inliers=n_in,
                         rms_px=float(np.sqrt(np.mean(res[inl] ** 2))))


def resect_from_known(point_ids: Sequence[str], uv_px: FloatArray,
                      known_xyz_m: Mapping[str, FloatArray], camera: PinholeCamera, *,
                      sigma_px: float = 1.0,
                      start_eop: FloatArray | None = None) -> tuple[PoseResection, np.ndarray]:
    """:func:`resect_pose` on the observations of an image whose point is known.

    Returns
    -------
    resection : PoseResection
    used : (m,) int
        Index into ``point_ids`` of each point given to the resection (``resection.inliers``
        is over these).
    """
    used = np.asarray([k for k, p in enumerate(point_ids) if p in known_xyz_m], dtype=np.int64)
    xyz = np.asarray([known_xyz_m[point_ids[k]] for k in used], dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)[used]
    return resect_pose(xyz, uv, camera, sigma_px=sigma_px, start_eop=start_eop), used


def predict_missing(eop: FloatArray, times_s: FloatArray) -> FloatArray:
    """Start values for the missing (NaN) components of a nav table, from earlier rows only.

    A missing position is the last known one moved on at the velocity between the last two
    known positions (per second where both times are finite, else per row); a missing
    attitude is the last known one. Before the first known value: the first known value.

    Parameters
    ----------
    eop : (n, 6) float
        NaN where a component is missing (positions and attitudes as groups of 3).
    times_s : (n,) float
        May hold NaN (rows without a time).

    Returns
    -------
    (n, 6) float
        Finite wherever any row of that group is known.
    """
    out = np.asarray(eop, dtype=np.float64).copy()
    t = np.asarray(times_s, dtype=np.float64)
    n = out.shape[0]
    for sl in (slice(0, 3), slice(3, 6)):
        known = np.flatnonzero(np.all(np.isfinite(out[:, sl]), axis=1))
        if known.size == 0:
            continue
        for i in range(n):
            if np.all(np.isfinite(eop[i, sl])):
                continue
            before = known[known < i]
            if before.size == 0:
                out[i, sl] = eop[known[0], sl]
                continue
            a = before[-1]
            out[i, sl] = eop[a, sl]
            if sl.start == 0 and before.size >= 2:
                b = before[-2]
                if np.isfinite(t[[a, b, i]]).all() and t[a] > t[b]:
                    step = (t[i] - t[a]) / (t[a] - t[b])
                else:
                    step = float(i - a) / float(a - b)
                out[i, sl] = eop[a, sl] + step * (eop[a, sl] - eop[b, sl])
    return out


def dropout_sigma(nav_sigma: FloatArray, missing: np.ndarray) -> FloatArray:
    """``nav_sigma`` with ``inf`` (no constraint) for the missing components.

    Parameters
    ----------
    nav_sigma : (6,) float
    missing : (6,) bool
    """
    return np.where(np.asarray(missing, dtype=bool), np.inf,
                    np.asarray(nav_sigma, dtype=np.float64))
