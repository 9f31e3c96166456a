"""Collinearity model: conventions, analytic Jacobians, project -> intersect round trip."""

from __future__ import annotations

import numpy as np
import pytest

from seqat.geometry import (
    angles_from_rotation,
    depth,
    intersect_rays,
    project,
    project_with_jacobians,
    rotation_matrix,
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


def test_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(5)
    eop = _random_pose(rng, 20)
    X = np.column_stack([eop[:, :2] + rng.normal(0, 30, (20, 2)), rng.uniform(-10, 20, 20)])
    _, Je, Jp = project_with_jacobians(eop, X, CAM)
    for k in range(6):
        h = STEP_M if k < 3 else STEP_RAD
        d = np.zeros(6)
        d[k] = h
        fd = (project(eop + d, X, CAM) - project(eop - d, X, CAM)) / (2 * h)
        np.testing.assert_allclose(Je[:, :, k], fd, rtol=JACOBIAN_RTOL, atol=1e-3)
    for k in range(3):
        d = np.zeros(3)
        d[k] = STEP_M
        fd = (project(eop, X + d, CAM) - project(eop, X - d, CAM)) / (2 * STEP_M)
        np.testing.assert_allclose(Jp[:, :, k], fd, rtol=JACOBIAN_RTOL, atol=1e-3)


def test_project_intersect_round_trip() -> None:
    rng = np.random.default_rng(9)
    n_pts, n_img = 30, 5
    eop = _random_pose(rng, n_img)
    eop[:, :2] = np.column_stack([np.linspace(-40, 40, n_img), np.zeros(n_img)])
    X = np.column_stack([rng.uniform(-30, 30, (n_pts, 2)), rng.uniform(-5, 5, n_pts)])
    img = np.repeat(np.arange(n_img), n_pts)
    pt = np.tile(np.arange(n_pts), n_img)
    uv = project(eop[img], X[pt], CAM)
    assert np.all(depth(eop[img], X[pt]) > 0)
    X_hat, spread = intersect_rays(eop[img], uv, pt, n_pts, CAM)
    np.testing.assert_allclose(X_hat, X, atol=1e-7)  # metres
    assert np.all(spread > np.radians(10))


def test_intersection_of_single_ray_is_undefined() -> None:
    eop = np.array([[0.0, 0.0, 100.0, 0.0, 0.0, 0.0]])
    X, spread = intersect_rays(eop, np.array([[100.0, 200.0]]), np.array([0]), 1, CAM)
    assert np.all(np.isnan(X)) and spread[0] == 0.0
