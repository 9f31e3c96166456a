"""The OpenCV / COLMAP camera frame: poses, GPS/INS prior covariances, posterior covariances.

COLMAP's camera frame is OpenCV's (x right, y down, z forward) = ours (docs/conventions.md:
x right, y up, z towards the viewer) with y and z negated, and COLMAP stores
``cam_from_world``: ``p_cv = R_cv_from_world X + t``. Pure numpy, used by the COLMAP
reference (``pipeline/reference.py``).
"""

from __future__ import annotations

import numpy as np

from seqat.geometry import angles_from_rotation, attitude_axes, rotation_matrix
from seqat.types import EOP_SIZE, FloatArray

#: Rotation vector per unit of Ceres' quaternion tangent (it turns by twice the step norm).
QUATERNION_TANGENT_TO_ROTATION = 2.0

#: ``R_cv_from_cam``: the OpenCV camera frame is ours with y and z negated.
CV_FROM_CAM = np.diag([1.0, -1.0, -1.0])


def cv_pose_from_eop(eop: FloatArray) -> tuple[FloatArray, FloatArray]:
    """COLMAP's ``cam_from_world`` (OpenCV camera frame) of EOPs.

    ``R_cv_from_world = diag(1, -1, -1) R^T`` and ``t = -R_cv_from_world X0``, so that
    ``p_cv = R_cv_from_world X + t`` (docs/conventions.md).

    Parameters
    ----------
    eop : (n, 6) float

    Returns
    -------
    R_cv_from_world : (n, 3, 3) float
    t_cv_m : (n, 3) float
    """
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    R = rotation_matrix(eop[:, 3], eop[:, 4], eop[:, 5])
    R_cv = CV_FROM_CAM @ np.swapaxes(R, 1, 2)
    t = -np.einsum("nij,nj->ni", R_cv, eop[:, :3])
    return R_cv, t


def eop_from_cv_pose(R_cv_from_world: FloatArray, t_cv_m: FloatArray) -> FloatArray:
    """Inverse of :func:`cv_pose_from_eop`.

    Parameters
    ----------
    R_cv_from_world : (n, 3, 3) float
    t_cv_m : (n, 3) float

    Returns
    -------
    (n, 6) float
        ``[X0, Y0, Z0, omega, phi, kappa]``.
    """
    R_cv = np.asarray(R_cv_from_world, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t_cv_m, dtype=np.float64).reshape(-1, 3)
    Rt = np.swapaxes(R_cv, 1, 2)
    X0 = -np.einsum("nij,nj->ni", Rt, t)
    R_world_from_cam = Rt @ CV_FROM_CAM
    return np.concatenate([X0, angles_from_rotation(R_world_from_cam)], axis=1)


def pose_prior_covariance(nav_eop: FloatArray, nav_sigma: FloatArray) -> FloatArray:
    """Covariance of COLMAP's 6-DoF prior residual ``[rotation, translation]`` (see module).

    Parameters
    ----------
    nav_eop : (n, 6) float
        Prior EOPs (metres, radians).
    nav_sigma : (6,) or (n, 6) float
        Standard deviations of ``[X0, Y0, Z0, omega, phi, kappa]``.

    Returns
    -------
    (n, 6, 6) float
        ``J diag(sigma^2) J^T`` with ``J = [[0, -R_cv A], [-R_cv, 0]]``.
    """
    nav = np.atleast_2d(np.asarray(nav_eop, dtype=np.float64))
    n = nav.shape[0]
    var = np.broadcast_to(np.asarray(nav_sigma, dtype=np.float64) ** 2, (n, EOP_SIZE))
    R_cv, _ = cv_pose_from_eop(nav)
    J = np.zeros((n, 6, 6))
    J[:, :3, 3:] = -R_cv @ attitude_axes(nav)
    J[:, 3:, :3] = -R_cv
    return np.einsum("nij,nj,nkj->nik", J, var, J)


def eop_covariance_from_tangent(eop: FloatArray, cov_tangent: FloatArray) -> FloatArray:
    """Covariance of ``[X0, Y0, Z0, omega, phi, kappa]`` from COLMAP's pose covariance.

    COLMAP's tangent space of ``cam_from_world`` is ``[dq, dt]``: Ceres' quaternion manifold
    ``q' = [cos|dq|, sin|dq| dq/|dq|] q`` turns by ``2|dq|``, so the rotation vector is
    ``drho = 2 dq`` with ``R_cv' = Exp(drho) R_cv``, and ``t' = t + dt``. Then
    ``dC = -R_cv^T ([t]x drho + dt)`` and ``dtheta = -A^-1 R_cv^T drho``.

    Parameters
    ----------
    eop : (6,) float
        The adjusted EOP (local or world coordinates, as ``cov_tangent``'s ``t``).
    cov_tangent : (6, 6) float

    Returns
    -------
    (6, 6) float
    """
    R_cv, t = cv_pose_from_eop(np.asarray(eop, dtype=np.float64)[None])
    Rt = R_cv[0].T
    tx = np.array([[0.0, -t[0, 2], t[0, 1]], [t[0, 2], 0.0, -t[0, 0]],
                   [-t[0, 1], t[0, 0], 0.0]])
    J = np.zeros((6, 6))
    J[:3, :3] = -Rt @ tx * QUATERNION_TANGENT_TO_ROTATION
    J[:3, 3:] = -Rt
    J[3:, :3] = -np.linalg.solve(attitude_axes(np.asarray(eop)[None])[0], Rt)
    J[3:, :3] *= QUATERNION_TANGENT_TO_ROTATION
    return J @ cov_tangent @ J.T
