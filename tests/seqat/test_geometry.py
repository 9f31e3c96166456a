"""Collinearity model: conventions, analytic Jacobians, project -> intersect round trip."""

from __future__ import annotations

import numpy as np
import pytest

from seqat.geometry import (
    angles_from_rotation,
    depth,
    distort_normalized,
    intersect_rays,
    inverse_distortion,
    project,
    project_with_jacobians,
    rotation_matrix,
    undistort_normalized,
)
from seqat.types import PinholeCamera

CAM = PinholeCamera(f_px=4927.5, cx_px=1227.5, cy_px=1028.5, width_px=2456, height_px=2058)
#: Central differences with these steps agree with the analytic derivatives to ~1e-6 relative.
STEP_M = 1e-4
STEP_RAD = 1e-7
JACOBIAN_RTOL = 1e-5


def _random_pose(rng: np.random.Generator, n: int) -> np.ndarray:
    eop = np.zeros((n, 6))
    eop[:, :2] = rng.uniform(-50, 50, (n, 2))
    eop[:, 2] = rng.uniform(150, 250, n)
    eop[:, 3:5] = rng.normal(0, 0.05, (n, 2))
    eop[:, 5] = rng.uniform(-np.pi, np.pi, n)
    return eop


def test_nadir_camera_image_top_is_north() -> None:
    eop = np.array([[0.0, 0.0, 100.0, 0.0, 0.0, 0.0]])
    north = project(eop, np.array([[0.0, 10.0, 0.0]]), CAM)[0]
    east = project(eop, np.array([[10.0, 0.0, 0.0]]), CAM)[0]
    assert north[0] == pytest.approx(CAM.cx_px) and north[1] < CAM.cy_px  # up in the image
    assert east[0] > CAM.cx_px and east[1] == pytest.approx(CAM.cy_px)  # to the right
    # 10 m at 100 m distance: f * 0.1 pixels off the principal point.
    assert CAM.cy_px - north[1] == pytest.approx(0.1 * CAM.f_px)


def test_kappa_90_turns_image_top_to_west() -> None:
    # R = Rz(90deg): the camera's y axis (image top) points to world -x (west).
    R = rotation_matrix(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(R[:, 1], [-1.0, 0.0, 0.0], atol=1e-15)
    eop = np.array([[0.0, 0.0, 100.0, 0.0, 0.0, np.pi / 2]])
    west = project(eop, np.array([[-10.0, 0.0, 0.0]]), CAM)[0]
    assert west[1] < CAM.cy_px and west[0] == pytest.approx(CAM.cx_px)


def test_rotation_angle_round_trip() -> None:
    rng = np.random.default_rng(3)
    ang = np.column_stack(
        [rng.uniform(-np.pi, np.pi, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-np.pi, np.pi, 50)]
    )
    R = rotation_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14
    )
    np.testing.assert_allclose(angles_from_rotation(R), ang, atol=1e-12)


def _check_eop_and_point_jacobians(eop: np.ndarray, X: np.ndarray, cam: PinholeCamera,
                                   Je: np.ndarray, Jp: np.ndarray) -> None:
    """``Je``, ``Jp`` against central differences of :func:`project` with ``cam``."""
    for k in range(6):
        h = STEP_M if k < 3 else STEP_RAD
        d = np.zeros(6)
        d[k] = h
        fd = (project(eop + d, X, cam) - project(eop - d, X, cam)) / (2 * h)
        np.testing.assert_allclose(Je[:, :, k], fd, rtol=JACOBIAN_RTOL, atol=1e-3)
    for k in range(3):
        d = np.zeros(3)
        d[k] = STEP_M
        fd = (project(eop, X + d, cam) - project(eop, X - d, cam)) / (2 * STEP_M)
        np.testing.assert_allclose(Jp[:, :, k], fd, rtol=JACOBIAN_RTOL, atol=1e-3)


def test_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(5)
    eop = _random_pose(rng, 20)
    X = np.column_stack([eop[:, :2] + rng.normal(0, 30, (20, 2)), rng.uniform(-10, 20, 20)])
    _, Je, Jp = project_with_jacobians(eop, X, CAM)
    _check_eop_and_point_jacobians(eop, X, CAM, Je, Jp)


def _round_trip_scene(rng: np.random.Generator, half_m: float, n_pts: int = 30,
                      n_img: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Five cameras along x, points within ``half_m`` of the centre, every point in every
    image: EOPs, points and the image and point index of each observation."""
    eop = _random_pose(rng, n_img)
    eop[:, :2] = np.column_stack([np.linspace(-40, 40, n_img), np.zeros(n_img)])
    X = np.column_stack([rng.uniform(-half_m, half_m, (n_pts, 2)), rng.uniform(-5, 5, n_pts)])
    return eop, X, np.repeat(np.arange(n_img), n_pts), np.tile(np.arange(n_pts), n_img)


def test_project_intersect_round_trip() -> None:
    rng = np.random.default_rng(9)
    n_pts = 30
    eop, X, img, pt = _round_trip_scene(rng, 30.0, n_pts)
    uv = project(eop[img], X[pt], CAM)
    assert np.all(depth(eop[img], X[pt]) > 0)
    X_hat, spread = intersect_rays(eop[img], uv, pt, n_pts, CAM)
    np.testing.assert_allclose(X_hat, X, atol=1e-7)  # metres
    assert np.all(spread > np.radians(10))


def test_intersection_of_single_ray_is_undefined() -> None:
    eop = np.array([[0.0, 0.0, 100.0, 0.0, 0.0, 0.0]])
    X, spread = intersect_rays(eop, np.array([[100.0, 200.0]]), np.array([0]), 1, CAM)
    assert np.all(np.isnan(X)) and spread[0] == 0.0


#: A strongly distorted camera (a consumer wide angle: 3 % barrel at the corners, decentring).
DISTORTED = PinholeCamera(f_px=2500.0, cx_px=1810.0, cy_px=1340.0, width_px=3600,
                          height_px=2700, k1=-0.08, k2=0.03, p1=4e-4, p2=-6e-4, k3=-0.01)


def _points_in_view(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    eop = _random_pose(rng, n)
    X = np.column_stack([eop[:, :2] + rng.normal(0, 60, (n, 2)), rng.uniform(-10, 20, n)])
    return eop, X


def test_distorted_projection_equals_opencv() -> None:
    import cv2

    rng = np.random.default_rng(11)
    eop, X = _points_in_view(rng, 40)
    uv = project(eop, X, DISTORTED)
    R = rotation_matrix(eop[:, 3], eop[:, 4], eop[:, 5])
    cv_from_cam = np.diag([1.0, -1.0, -1.0])
    c = DISTORTED
    K = np.array([[c.f_px, 0, c.cx_px], [0, c.f_px, c.cy_px], [0, 0, 1.0]])
    dist = np.array([c.k1, c.k2, c.p1, c.p2, c.k3])
    for i in range(len(X)):
        Rcv = cv_from_cam @ R[i].T
        rvec, _ = cv2.Rodrigues(Rcv)
        tvec = -Rcv @ eop[i, :3]
        ref, _ = cv2.projectPoints(X[i : i + 1], rvec, tvec, K, dist)
        np.testing.assert_allclose(uv[i], ref.reshape(2), atol=1e-6)


def test_distorted_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(12)
    eop, X = _points_in_view(rng, 30)
    _, Je, Jp, Jc = project_with_jacobians(eop, X, DISTORTED, intrinsics=True)
    _, Je0, Jp0 = project_with_jacobians(eop, X, DISTORTED)
    np.testing.assert_array_equal(Je, Je0)
    np.testing.assert_array_equal(Jp, Jp0)
    _check_eop_and_point_jacobians(eop, X, DISTORTED, Je, Jp)
    base = DISTORTED.intrinsics
    for k, h in enumerate([1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-8, 1e-8, 1e-7]):
        d = np.zeros(8)
        d[k] = h
        fd = (project(eop, X, DISTORTED.with_intrinsics(base + d))
              - project(eop, X, DISTORTED.with_intrinsics(base - d))) / (2 * h)
        np.testing.assert_allclose(Jc[:, :, k], fd, rtol=JACOBIAN_RTOL, atol=1e-3)


def test_distorted_project_intersect_round_trip() -> None:
    rng = np.random.default_rng(13)
    n_pts = 30
    eop, X, img, pt = _round_trip_scene(rng, 60.0, n_pts)
    uv = project(eop[img], X[pt], DISTORTED)
    X_hat, _ = intersect_rays(eop[img], uv, pt, n_pts, DISTORTED)
    np.testing.assert_allclose(X_hat, X, atol=1e-7)
    # the same pixels through the undistorted camera miss by metres: distortion is applied
    X_bad, _ = intersect_rays(eop[img], uv, pt, n_pts, DISTORTED.with_intrinsics(
        np.r_[DISTORTED.intrinsics[:3], np.zeros(5)]))
    assert np.max(np.abs(X_bad - X)) > 0.5


#: Strong lenses at f 400 px, 640 x 480 px that flight.yaml's fold check accepts: a barrel
#: lens whose corners sit where the polynomial's derivative nears zero (8 plain Newton steps
#: left 0.12 px there, OpenCV's undistortPoints 1.3 px), and one on which Newton from the
#: distorted point landed on a root beyond the fold (482 px off).
STRONG_BARREL = PinholeCamera(f_px=400.0, cx_px=319.5, cy_px=239.5, width_px=640,
                              height_px=480, k1=-0.6, k2=0.2, p1=0.01)
OTHER_BRANCH = PinholeCamera(f_px=400.0, cx_px=319.5, cy_px=239.5, width_px=640,
                             height_px=480, k1=-0.785, k2=0.398, k3=-0.0445, p1=0.0134,
                             p2=-0.0102)


def _image_grid(camera: PinholeCamera, n: int) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(0.0, camera.width_px - 1.0, n),
                       np.linspace(0.0, camera.height_px - 1.0, n))
    return (u.ravel() - camera.cx_px) / camera.f_px, (v.ravel() - camera.cy_px) / camera.f_px


def _continuation(xd: np.ndarray, yd: np.ndarray, camera: PinholeCamera,
                  steps: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Reference: plain Newton along the straight segment of distorted points from the
    principal point, in small steps (stays on the principal point's branch), polished at
    the end (near a fold 4 iterations a step leave ~1e-4 px)."""
    x, y = np.zeros_like(xd), np.zeros_like(yd)
    for t in np.arange(1, steps + 1) / steps:
        for _ in range(4 if t < 1.0 else 30):
            fx, fy, D, _ = distort_normalized(x, y, camera, jacobians=True)
            rx, ry = t * xd - fx, t * yd - fy
            det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
            x = x + (D[:, 1, 1] * rx - D[:, 0, 1] * ry) / det
            y = y + (D[:, 0, 0] * ry - D[:, 1, 0] * rx) / det
    return x, y


@pytest.mark.parametrize("camera", [DISTORTED, STRONG_BARREL, OTHER_BRANCH])
def test_inverse_distortion_solves_every_pixel_on_the_principal_points_branch(
        camera: PinholeCamera) -> None:
    xd, yd = _image_grid(camera, 81)
    xn, yn, found = inverse_distortion(xd, yd, camera)
    assert found.all()
    bx, by = distort_normalized(xn, yn, camera)
    assert np.max(np.hypot(bx - xd, by - yd)) * camera.f_px < 1e-9  # pixels
    # the root of the principal point's branch, the one a ray through the lens has
    rx, ry = _continuation(xd, yd, camera)
    np.testing.assert_allclose(xn, rx, rtol=0, atol=1e-10)
    np.testing.assert_allclose(yn, ry, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(np.column_stack(undistort_normalized(xd, yd, camera)),
                                  np.column_stack([xn, yn]))


def test_inverse_distortion_keeps_the_input_shape_and_passes_a_pinhole_through() -> None:
    xd, yd = np.array([[0.1, -0.2], [0.3, 0.0]]), np.array([[0.0, 0.1], [-0.2, 0.25]])
    xn, yn, found = inverse_distortion(xd, yd, STRONG_BARREL)
    assert xn.shape == yn.shape == found.shape == (2, 2) and found.all()
    xp, yp, found = inverse_distortion(xd, yd, CAM)
    np.testing.assert_array_equal(xp, xd)
    np.testing.assert_array_equal(yp, yd)
    assert found.all()


def test_a_pixel_beyond_the_fold_is_not_found() -> None:
    """With these tangential terms the part of the image plane before the fold stops 10.7 px
    short of the image's lower right corner (a polar grid of 20 million ideal points up to
    the fold comes no closer): that pixel has no ray; the centre's pixels have."""
    camera = PinholeCamera(f_px=400.0, cx_px=319.5, cy_px=239.5, width_px=640,
                           height_px=480, k1=0.203, k2=-0.112, k3=-0.0756, p1=-0.0098,
                           p2=-0.0177)
    corner = np.array([(639.0 - 319.5) / 400.0]), np.array([(479.0 - 239.5) / 400.0])
    _, _, found = inverse_distortion(*corner, camera)
    assert not found.any()
    _, _, found = inverse_distortion(*_image_grid(
        PinholeCamera(f_px=400.0, cx_px=319.5, cy_px=239.5, width_px=400, height_px=300), 21),
        camera)
    assert found.all()


@pytest.mark.parametrize("camera", [DISTORTED, STRONG_BARREL, OTHER_BRANCH])
def test_the_branch_checks_determinant_is_distort_normalizeds(camera: PinholeCamera) -> None:
    """The inverse's branch check evaluates the Jacobian's determinant in closed form (7x
    faster than forming ``D``): it must be the determinant of :func:`distort_normalized`'s
    ``D``, everywhere in and around the image."""
    from seqat.geometry import _jacobian_det

    x, y = _image_grid(camera, 41)
    x, y = 1.3 * x, 1.3 * y
    _, _, D, _ = distort_normalized(x, y, camera, jacobians=True)
    det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
    np.testing.assert_allclose(_jacobian_det(x, y, camera), det, rtol=1e-12, atol=1e-14)
