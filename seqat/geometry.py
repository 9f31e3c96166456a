"""Collinearity model: rotation, projection, analytic Jacobians, multi-ray intersection.

Conventions (DESIGN.md, docs/conventions.md)
--------------------------------------------
* World frame: east, north, up (metres). Camera frame: x right, y to the image top, z towards
  the viewer; the camera looks along -z.
* ``R_world_from_cam = Rx(omega) @ Ry(phi) @ Rz(kappa)`` (active, right-handed). A nadir camera
  with omega = phi = kappa = 0 has the image top to the north.
* A world point ``X`` maps to ``p = R^T (X - X0)``, photo coordinates ``x = -f p_x / p_z``,
  ``y = -f p_y / p_z`` and OpenCV pixels ``u = cx + x``, ``v = cy - y``. With lens
  distortion the normalised OpenCV coordinates ``xn = -p_x / p_z``, ``yn = p_y / p_z`` are
  distorted first (:class:`seqat.types.PinholeCamera`): ``u = cx + f xd``, ``v = cy + f yd``.
* EOP vector: ``[X0_m, Y0_m, Z0_m, omega_rad, phi_rad, kappa_rad]``.

All functions are vectorised over a leading axis; shapes are given in the docstrings.
"""

from __future__ import annotations

import numpy as np

from seqat.types import INTRINSICS, FloatArray, PinholeCamera

#: Rays whose largest pairwise angle is below this are treated as parallel (radians).
MIN_INTERSECTION_ANGLE_RAD = 1e-6
#: The inverse distortion (:func:`inverse_distortion`): damped Newton, each point until its
#: residual is below the tolerance (normalised image units, ~1e-10 px at f = 1000 px), at
#: most this many iterations. A fixed count of 8 plain Newton steps from the distorted point
#: (before 2026-12-07) left 0.12 px in the corners of k1 -0.6 / k2 0.2 / p1 0.01, where the
#: polynomial's derivative nears zero, and could land on a root beyond the lens's fold.
UNDISTORT_MAX_ITERATIONS = 50
UNDISTORT_TOLERANCE = 1e-13
#: Samples of the Jacobian's determinant on the segment from the principal point to each
#: solution: a root with a fold (determinant <= 0) on its way is another branch's.
UNDISTORT_BRANCH_SAMPLES = 16
#: Steps of the continuation from the principal point (for the points Newton did not solve
#: on the principal point's branch) and Newton iterations per step.
UNDISTORT_CONTINUATION_STEPS = 64
UNDISTORT_STEP_ITERATIONS = 8


def wrap_angle(angle_rad: FloatArray | float) -> FloatArray:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


def nearest_branch(angles_rad: FloatArray, reference_rad: FloatArray) -> FloatArray:
    """``(omega, phi, kappa)`` (k, 3) as the same rotations, each on the Euler branch
    nearest its ``reference`` (k, 3; the largest wrapped difference of the three angles),
    wrapped to ``[-pi, pi)``. ``Rx(omega + pi) Ry(pi - phi) Rz(kappa + pi)`` is
    ``Rx(omega) Ry(phi) Rz(kappa)``: an adjustment can reach either, and a GPS/INS prior
    compared angle by angle must see the one on its own branch. A reference with a NaN
    (no attitude) takes the branch with ``|phi| <= pi / 2``."""
    a = np.asarray(angles_rad, dtype=np.float64)
    a = np.where((a >= -np.pi) & (a < np.pi), a, wrap_angle(a))  # in range: not rounded
    b = wrap_angle(a * np.array([1.0, -1.0, 1.0]) + np.pi)
    ref = np.asarray(reference_rad, dtype=np.float64)
    known = np.all(np.isfinite(ref), axis=1)
    ref = np.where(known[:, None], ref, 0.0)
    da = np.where(known, np.max(np.abs(wrap_angle(a - ref)), axis=1), np.abs(a[:, 1]))
    db = np.where(known, np.max(np.abs(wrap_angle(b - ref)), axis=1), np.abs(b[:, 1]))
    return np.where((db < da)[:, None], b, a)


def rotation_matrix(
    omega_rad: FloatArray | float, phi_rad: FloatArray | float, kappa_rad: FloatArray | float
) -> FloatArray:
    """Camera-to-world rotation ``Rx(omega) Ry(phi) Rz(kappa)``.

    Parameters
    ----------
    omega_rad, phi_rad, kappa_rad : (...) float
        Angles in radians (broadcast together).

    Returns
    -------
    (..., 3, 3) float
        ``R_world_from_cam``.
    """
    o, p, k = (np.asarray(a, dtype=np.float64) for a in (omega_rad, phi_rad, kappa_rad))
    if not o.shape == p.shape == k.shape:
        o, p, k = np.broadcast_arrays(o, p, k)
    co, so, cp, sp, ck, sk = np.cos(o), np.sin(o), np.cos(p), np.sin(p), np.cos(k), np.sin(k)
    R = np.empty(o.shape + (3, 3))
    R[..., 0, 0] = cp * ck
    R[..., 0, 1] = -cp * sk
    R[..., 0, 2] = sp
    R[..., 1, 0] = co * sk + so * sp * ck
    R[..., 1, 1] = co * ck - so * sp * sk
    R[..., 1, 2] = -so * cp
    R[..., 2, 0] = so * sk - co * sp * ck
    R[..., 2, 1] = so * ck + co * sp * sk
    R[..., 2, 2] = co * cp
    return R


def angles_from_rotation(R_world_from_cam: FloatArray) -> FloatArray:
    """Inverse of :func:`rotation_matrix`.

    Parameters
    ----------
    R_world_from_cam : (..., 3, 3) float

    Returns
    -------
    (..., 3) float
        ``[omega, phi, kappa]`` in radians, ``phi`` in ``[-pi/2, pi/2]``.
    """
    R = np.asarray(R_world_from_cam, dtype=np.float64)
    phi = np.arcsin(np.clip(R[..., 0, 2], -1.0, 1.0))
    omega = np.arctan2(-R[..., 1, 2], R[..., 2, 2])
    kappa = np.arctan2(-R[..., 0, 1], R[..., 0, 0])
    return np.stack([omega, phi, kappa], axis=-1)


def _rotation_axes(eop: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation matrices and the world axes ``a_k`` of the three angle rotations.

    ``dR/d theta_k = [a_k]x R`` with ``a_omega = e_x``, ``a_phi = Rx e_y``,
    ``a_kappa = Rx Ry e_z``.

    Returns
    -------
    R : (n, 3, 3) float
    axes : (n, 3, 3) float
        ``axes[:, k]`` is ``a_k`` for angle ``k`` (omega, phi, kappa).
    """
    omega, phi = eop[:, 3], eop[:, 4]
    R = rotation_matrix(omega, phi, eop[:, 5])
    n = eop.shape[0]
    axes = np.zeros((n, 3, 3))
    axes[:, 0, 0] = 1.0
    co, so, cp, sp = np.cos(omega), np.sin(omega), np.cos(phi), np.sin(phi)
    axes[:, 1] = np.stack([np.zeros(n), co, so], axis=-1)  # Rx e_y
    axes[:, 2] = np.stack([sp, -so * cp, co * cp], axis=-1)  # Rx Ry e_z
    return R, axes


def distort_normalized(
    xn: FloatArray, yn: FloatArray, camera: PinholeCamera, *, jacobians: bool = False
) -> tuple[FloatArray, ...]:
    """OpenCV distortion of normalised camera coordinates (:class:`PinholeCamera`).

    Parameters
    ----------
    xn, yn : (n,) float
        Normalised coordinates in the OpenCV camera frame.
    camera : PinholeCamera
    jacobians : bool
        Also return ``D`` (n, 2, 2), ``d[xd, yd]/d[xn, yn]``, and ``K`` (n, 2, 5),
        ``d[xd, yd]/d[k1, k2, p1, p2, k3]``.

    Returns
    -------
    xd, yd : (n,) float
    """
    k1, k2, p1, p2, k3 = camera.k1, camera.k2, camera.p1, camera.p2, camera.k3
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2.0 * xn * yn
    xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
    if not jacobians:
        return xd, yd
    dr = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # d radial / d r2, times 2
    D = np.empty(xn.shape + (2, 2))
    D[..., 0, 0] = radial + xn * xn * dr + 2.0 * p1 * yn + 6.0 * p2 * xn
    D[..., 0, 1] = xn * yn * dr + 2.0 * p1 * xn + 2.0 * p2 * yn
    D[..., 1, 0] = xn * yn * dr + 2.0 * p1 * xn + 2.0 * p2 * yn
    D[..., 1, 1] = radial + yn * yn * dr + 6.0 * p1 * yn + 2.0 * p2 * xn
    K = np.empty(xn.shape + (2, 5))
    K[..., 0, :] = np.stack([xn * r2, xn * r2 * r2, xy2, r2 + 2.0 * xn * xn, xn * r2**3], -1)
    K[..., 1, :] = np.stack([yn * r2, yn * r2 * r2, r2 + 2.0 * yn * yn, xy2, yn * r2**3], -1)
    return xd, yd, D, K


def undistort_normalized(xd: FloatArray, yd: FloatArray,
                         camera: PinholeCamera) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`distort_normalized` (:func:`inverse_distortion` without its flags)."""
    xn, yn, _ = inverse_distortion(xd, yd, camera)
    return xn, yn


def inverse_distortion(xd: FloatArray, yd: FloatArray,
                       camera: PinholeCamera) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """The ideal normalised coordinates that :func:`distort_normalized` maps to ``(xd, yd)``,
    on the branch of the principal point (no fold between it and them), and whether each was
    found (arrays of the input's shape).

    Damped Newton from the principal point, its first trial the distorted point (a step
    that neither lowers the residual nor keeps the Jacobian's determinant > 0 is halved),
    until the residual is within :data:`UNDISTORT_TOLERANCE`; a solution with a fold on its
    segment from the principal point, or none, is sought again by continuation along the
    distorted segment (:data:`UNDISTORT_CONTINUATION_STEPS`). A point with no preimage on
    that branch (a pixel beyond where the lens folds back) is not found and keeps the
    continuation's last iterate."""
    shape = np.shape(xd)
    xd = np.asarray(xd, dtype=np.float64).ravel()
    yd = np.asarray(yd, dtype=np.float64).ravel()
    if not camera.has_distortion:
        return xd.reshape(shape), yd.reshape(shape), np.ones(shape, dtype=bool)
    xn, yn, found = _damped_newton(xd, yd, np.zeros_like(xd), np.zeros_like(yd), camera,
                                   UNDISTORT_MAX_ITERATIONS)
    s = np.arange(1, UNDISTORT_BRANCH_SAMPLES + 1)[:, None] / UNDISTORT_BRANCH_SAMPLES
    found &= np.all(_jacobian_det(s * xn, s * yn, camera) > 0.0, axis=0)
    again = np.flatnonzero(~found)
    if again.size:
        tx, ty = xd[again], yd[again]
        x, y = np.zeros(again.size), np.zeros(again.size)
        ok = np.ones(again.size, dtype=bool)
        for step in range(1, UNDISTORT_CONTINUATION_STEPS + 1):
            t = step / UNDISTORT_CONTINUATION_STEPS
            x, y, ok_t = _damped_newton(t * tx, t * ty, x, y, camera,
                                        UNDISTORT_STEP_ITERATIONS)
            ok &= ok_t
        xn[again], yn[again], found[again] = x, y, ok
    return xn.reshape(shape), yn.reshape(shape), found.reshape(shape)


def _jacobian_det(x: FloatArray, y: FloatArray, camera: PinholeCamera) -> FloatArray:
    """Determinant of ``d[xd, yd]/d[xn, yn]`` (any shape; the terms of
    :func:`distort_normalized`'s ``D``)."""
    k1, k2, p1, p2, k3 = camera.k1, camera.k2, camera.p1, camera.p2, camera.k3
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dr = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))
    off = x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
    return ((radial + x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x)
            * (radial + y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x) - off * off)


def _damped_newton(tx: FloatArray, ty: FloatArray, x0: FloatArray, y0: FloatArray,
                   camera: PinholeCamera, iterations: int
                   ) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Newton from ``(x0, y0)`` (determinant > 0 there) towards ``distort(x) = (tx, ty)``:
    a trial is accepted when its residual is lower and the determinant still > 0, else the
    step from the last accepted iterate is halved. Returns the last accepted iterates and
    which are within :data:`UNDISTORT_TOLERANCE`, after at most ``iterations`` trials."""
    x0, y0 = x0.copy(), y0.copy()
    fx, fy, D, _ = distort_normalized(x0, y0, camera, jacobians=True)
    rx, ry = tx - fx, ty - fy
    norm0 = np.hypot(rx, ry)
    done = np.maximum(np.abs(rx), np.abs(ry)) <= UNDISTORT_TOLERANCE
    det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
    dx = (D[:, 1, 1] * rx - D[:, 0, 1] * ry) / det
    dy = (D[:, 0, 0] * ry - D[:, 1, 0] * rx) / det
    active = np.flatnonzero(~done)
    for _ in range(iterations):
        if not active.size:
            break
        x, y = x0[active] + dx[active], y0[active] + dy[active]
        fx, fy, D, _ = distort_normalized(x, y, camera, jacobians=True)
        rx, ry = tx[active] - fx, ty[active] - fy
        norm = np.hypot(rx, ry)
        det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
        ok = (norm < norm0[active]) & (det > 0.0)
        halve = active[~ok]
        dx[halve] *= 0.5
        dy[halve] *= 0.5
        a = active[ok]
        x0[a], y0[a], norm0[a] = x[ok], y[ok], norm[ok]
        fin = np.maximum(np.abs(rx[ok]), np.abs(ry[ok])) <= UNDISTORT_TOLERANCE
        done[a[fin]] = True
        go, D, rx, ry, det = a[~fin], D[ok][~fin], rx[ok][~fin], ry[ok][~fin], det[ok][~fin]
        dx[go] = (D[:, 1, 1] * rx - D[:, 0, 1] * ry) / det
        dy[go] = (D[:, 0, 0] * ry - D[:, 1, 0] * rx) / det
        active = np.concatenate([go, halve])
    return x0, y0, done


def project(eop: FloatArray, X_world_m: FloatArray, camera: PinholeCamera) -> FloatArray:
    """Project world points into pixels.

    Parameters
    ----------
    eop : (n, 6) float
        Exterior orientation per point (one row per observation).
    X_world_m : (n, 3) float
    camera : PinholeCamera

    Returns
    -------
    (n, 2) float
        ``[u, v]`` OpenCV pixels. Points behind the camera give values but are meaningless;
        check :func:`depth` where it matters.
    """
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    X = np.atleast_2d(np.asarray(X_world_m, dtype=np.float64))
    R = rotation_matrix(eop[:, 3], eop[:, 4], eop[:, 5])
    p = np.einsum("nji,nj->ni", R, X - eop[:, :3])
    xn, yn = -p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    if camera.has_distortion:
        xn, yn = distort_normalized(xn, yn, camera)
    f = camera.f_px
    return np.stack([camera.cx_px + f * xn, camera.cy_px + f * yn], axis=-1)


def depth(eop: FloatArray, X_world_m: FloatArray) -> FloatArray:
    """Distance of each point in front of its camera along the viewing axis (``-p_z``), metres.

    Parameters
    ----------
    eop : (n, 6) float
    X_world_m : (n, 3) float

    Returns
    -------
    (n,) float
        Positive in front of the camera.
    """
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    return np.einsum("nj,nj->n", viewing_axes(eop), eop[:, :3] - np.atleast_2d(X_world_m))


def viewing_axes(eop: FloatArray) -> FloatArray:
    """The camera z axis in the world frame, ``R[:, :, 2]`` (n, 3): depends on omega and phi
    only (``Rx(omega) Ry(phi) e_z``); the camera looks along its negative."""
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    co, so = np.cos(eop[:, 3]), np.sin(eop[:, 3])
    cp, sp = np.cos(eop[:, 4]), np.sin(eop[:, 4])
    return np.stack([sp, -so * cp, co * cp], axis=-1)


def project_with_jacobians(
    eop: FloatArray, X_world_m: FloatArray, camera: PinholeCamera, *,
    intrinsics: bool = False,
) -> tuple[FloatArray, ...]:
    """Project world points and return the analytic Jacobians of ``[u, v]``.

    Parameters
    ----------
    eop : (n, 6) float
    X_world_m : (n, 3) float
    camera : PinholeCamera
    intrinsics : bool
        Also return ``J_camera``.

    Returns
    -------
    uv_px : (n, 2) float
    J_eop : (n, 2, 6) float
        ``d[u, v] / d[X0, Y0, Z0, omega, phi, kappa]`` (pixels per metre / per radian).
    J_point : (n, 2, 3) float
        ``d[u, v] / d[X, Y, Z]`` (pixels per metre).
    J_camera : (n, 2, 8) float, with ``intrinsics``
        ``d[u, v] / d`` :data:`seqat.types.INTRINSICS`.
    """
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    X = np.atleast_2d(np.asarray(X_world_m, dtype=np.float64))
    n = eop.shape[0]
    omega, phi = eop[:, 3], eop[:, 4]
    R = rotation_matrix(omega, phi, eop[:, 5])
    d = X - eop[:, :3]
    p = np.einsum("nji,nj->ni", R, d)  # R^T d
    f = camera.f_px
    inv_z = 1.0 / p[:, 2]
    xn, yn = -p[:, 0] * inv_z, p[:, 1] * inv_z
    # d[xn, yn]/dp: xn = -px/pz, yn = py/pz
    dn_dp = np.zeros((n, 2, 3))
    dn_dp[:, 0, 0] = -inv_z
    dn_dp[:, 0, 2] = -xn * inv_z
    dn_dp[:, 1, 1] = inv_z
    dn_dp[:, 1, 2] = -yn * inv_z
    if camera.has_distortion or intrinsics:
        xd, yd, D, K = distort_normalized(xn, yn, camera, jacobians=True)
        duv_dp = f * (D @ dn_dp)
    else:
        xd, yd = xn, yn
        duv_dp = f * dn_dp  # (n, 2, 3)
    J_eop = np.empty((n, 2, 6))
    J_point = np.matmul(duv_dp, np.swapaxes(R, 1, 2))  # dp/dX = R^T
    J_eop[:, :, :3] = -J_point
    # dp/dtheta_k = -R^T (a_k x d) with the world axes a_k of the three angle rotations
    # (a_omega = e_x, a_phi = Rx e_y, a_kappa = Rx Ry e_z): d[u, v]/dtheta = -J_point C,
    # C[:, :, k] = a_k x d, written out (np.cross is slow on short stacks)
    co, so, cp, sp = np.cos(omega), np.sin(omega), np.cos(phi), np.sin(phi)
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    ky, kz = -so * cp, co * cp  # a_kappa = [sp, ky, kz]
    C = np.empty((n, 3, 3))
    C[:, 0, 0] = 0.0
    C[:, 1, 0] = -dz
    C[:, 2, 0] = dy
    C[:, 0, 1] = co * dz - so * dy
    C[:, 1, 1] = so * dx
    C[:, 2, 1] = -co * dx
    C[:, 0, 2] = ky * dz - kz * dy
    C[:, 1, 2] = kz * dx - sp * dz
    C[:, 2, 2] = sp * dy - ky * dx
    J_eop[:, :, 3:] = np.matmul(J_eop[:, :, :3], C)
    uv = np.stack([camera.cx_px + f * xd, camera.cy_px + f * yd], axis=-1)
    if not intrinsics:
        return uv, J_eop, J_point
    J_cam = np.zeros((n, 2, len(INTRINSICS)))
    J_cam[:, 0, 0], J_cam[:, 1, 0] = xd, yd
    J_cam[:, 0, 1] = 1.0
    J_cam[:, 1, 2] = 1.0
    J_cam[:, :, 3:] = f * K
    return uv, J_eop, J_point, J_cam


def rays_world(eop: FloatArray, uv_px: FloatArray, camera: PinholeCamera) -> FloatArray:
    """Unit viewing rays in the world frame through the given pixels.

    Parameters
    ----------
    eop : (n, 6) float
    uv_px : (n, 2) float

    Returns
    -------
    (n, 3) float
    """
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    uv = np.atleast_2d(np.asarray(uv_px, dtype=np.float64))
    R = rotation_matrix(eop[:, 3], eop[:, 4], eop[:, 5])
    ray_cam = np.empty((uv.shape[0], 3))
    xn, yn = (uv[:, 0] - camera.cx_px) / camera.f_px, (uv[:, 1] - camera.cy_px) / camera.f_px
    if camera.has_distortion:
        xn, yn = undistort_normalized(xn, yn, camera)
    ray_cam[:, 0], ray_cam[:, 1], ray_cam[:, 2] = xn, -yn, -1.0
    ray = np.einsum("nij,nj->ni", R, ray_cam)
    return ray / np.sqrt(np.einsum("ni,ni->n", ray, ray))[:, None]


def intersect_rays(
    eop: FloatArray,
    uv_px: FloatArray,
    point_index: FloatArray,
    n_points: int,
    camera: PinholeCamera,
) -> tuple[FloatArray, FloatArray]:
    """Least-squares multi-ray intersection of many points at once.

    Minimises, per point, the sum of squared perpendicular distances to its rays:
    ``sum_i (I - d_i d_i^T)(X - C_i) = 0``.

    Parameters
    ----------
    eop : (k, 6) float
        EOP of the image of each observation.
    uv_px : (k, 2) float
    point_index : (k,) int
        Point of each observation, in ``[0, n_points)``.
    n_points : int
    camera : PinholeCamera

    Returns
    -------
    X_world_m : (n_points, 3) float
        NaN for points with fewer than two rays or (near-)parallel rays.
    max_angle_rad : (n_points,) float
        Largest angle between the point's rays (a measure of intersection strength).
    """
    eop = np.atleast_2d(np.asarray(eop, dtype=np.float64))
    idx = np.asarray(point_index, dtype=np.int64)
    d = rays_world(eop, uv_px, camera)
    C = eop[:, :3]
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    # the per-point sums of the normal equations and of the rays in one scatter (a birth
    # intersects a few points from a few dozen rays: numpy's per-call cost dominates)
    sums = np.zeros((n_points, 15))
    np.add.at(sums, idx, np.concatenate([proj.reshape(-1, 9),
                                         np.einsum("kij,kj->ki", proj, C), d], axis=1))
    A, b = sums[:, :9].reshape(n_points, 3, 3), sums[:, 9:12]
    # Largest ray angle per point: angle of each ray to the point's mean ray, doubled bound.
    mean_dir = sums[:, 12:]
    norm = np.linalg.norm(mean_dir, axis=1, keepdims=True)
    mean_dir = np.divide(mean_dir, norm, out=np.zeros_like(mean_dir), where=norm > 0)
    ang = np.arccos(np.clip(np.einsum("ki,ki->k", d, mean_dir[idx]), -1.0, 1.0))
    max_angle = np.zeros(n_points)
    np.maximum.at(max_angle, idx, 2.0 * ang)
    X = np.full((n_points, 3), np.nan)
    ok = max_angle > MIN_INTERSECTION_ANGLE_RAD
    if np.any(ok):
        X[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    return X, max_angle


def attitude_axes(eop: FloatArray) -> FloatArray:
    """World axes of the three angle rotations, ``dR = [A dtheta]x R``.

    Parameters
    ----------
    eop : (n, 6) float

    Returns
    -------
    (n, 3, 3) float
        ``A`` with columns ``a_omega = e_x``, ``a_phi = Rx e_y``, ``a_kappa = Rx Ry e_z``, so a
        small change ``dtheta`` of ``[omega, phi, kappa]`` rotates the camera by the world
        rotation vector ``A dtheta``.
    """
    _, axes = _rotation_axes(np.atleast_2d(np.asarray(eop, dtype=np.float64)))
    return np.swapaxes(axes, 1, 2)


def resect(eop0: FloatArray, X_world_m: FloatArray, uv_px: FloatArray, sigma_px: FloatArray,
           camera: PinholeCamera, *, iterations: int = 30) -> FloatArray | None:
    """Least-squares space resection: the EOP (6,) of one image from its rays to points of
    known position, by Gauss-Newton from ``eop0`` (no prior, no robust loss; a step that
    raises the cost is halved).

    Returns None with fewer than 4 points, a singular system, a point behind the camera at
    the end, or no convergence in ``iterations`` steps.
    """
    X = np.asarray(X_world_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    w = np.repeat(1.0 / np.asarray(sigma_px, dtype=np.float64).reshape(-1) ** 2, 2)
    k = X.shape[0]
    if k < 4:
        return None
    eop = np.asarray(eop0, dtype=np.float64).copy()

    def cost(e: FloatArray) -> float:
        with np.errstate(all="ignore"):
            r = (uv - project(np.broadcast_to(e, (k, 6)), X, camera)).ravel()
        c = float(np.sum(w * r**2))
        return c if np.isfinite(c) else np.inf

    c = cost(eop)
    for _ in range(iterations):
        uv_hat, Je, _ = project_with_jacobians(np.broadcast_to(eop, (k, 6)), X, camera)
        J = Je.reshape(2 * k, 6)
        r = (uv - uv_hat).ravel()
        try:
            step = np.linalg.solve(J.T @ (w[:, None] * J), J.T @ (w * r))
        except np.linalg.LinAlgError:
            return None
        for _ in range(30):
            c_new = cost(eop + step)
            if c_new <= c:
                break
            step = 0.5 * step
        else:
            return None
        eop, c = eop + step, c_new
        if np.max(np.abs(step[:3])) < 1e-6 and np.max(np.abs(step[3:])) < 1e-9:
            return eop if np.all(depth(np.broadcast_to(eop, (k, 6)), X) > 0) else None
    return None
