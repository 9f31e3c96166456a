"""Observed OpenCV pixels -> ideal pinhole pixels."""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.flight.camera import (
    DistortionTable,
    PixelCorrector,
    distort_normalized,
    pinhole_camera,
)
from pipeline.flight.schema import CameraConfig

#: Agreement required between undistorted and exact ideal pixels.
UNDISTORT_TOL_PX = 1e-8


def opencv_camera(fy_px: float) -> CameraConfig:
    return CameraConfig(model="OPENCV", width_px=2456, height_px=2058, fx_px=3000.0,
                        fy_px=fy_px, cx_px=1230.2, cy_px=1025.7, k1=-0.12, k2=0.08, p1=1e-3,
                        p2=-5e-4, k3=-0.01)


def test_undistortion_inverts_opencv_projection() -> None:
    cam = opencv_camera(fy_px=3012.0)
    rng = np.random.default_rng(3)
    # Points in the OpenCV camera frame (z forward) filling the image.
    X = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.33, 0.33, 200),
                         np.ones(200)])
    K = np.array([[cam.fx_px, 0, cam.cx_px], [0, cam.fy_px, cam.cy_px], [0, 0, 1]])
    observed, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, cam.distortion)
    ideal = PixelCorrector(camera=cam).ideal_pixels(np.asarray(observed, dtype=np.float64)
                                                    .reshape(-1, 2))
    # Ideal square-pixel camera: f_px = fx_px on both axes.
    pin = pinhole_camera(cam)
    expected = X[:, :2] / X[:, 2:] * pin.f_px + [pin.cx_px, pin.cy_px]
    np.testing.assert_allclose(ideal, expected, rtol=0, atol=UNDISTORT_TOL_PX)


def test_pinhole_camera_pixels_pass_through() -> None:
    cam = CameraConfig(model="PINHOLE", width_px=640, height_px=480, fx_px=800.0, fy_px=800.0,
                       cx_px=319.5, cy_px=239.5)
    corrector = PixelCorrector(camera=cam)
    uv = np.array([[1.0, 2.0], [600.5, 470.25]])
    assert corrector.is_identity
    np.testing.assert_array_equal(corrector.ideal_pixels(uv), uv)
    pin = pinhole_camera(cam)
    assert (pin.f_px, pin.cx_px, pin.cy_px, pin.width_px) == (800.0, 319.5, 239.5, 640)


def test_empty_observations_stay_empty() -> None:
    out = PixelCorrector(camera=opencv_camera(fy_px=3000.0)).ideal_pixels(np.zeros((0, 2)))
    assert out.shape == (0, 2)


#: Agreement required between the closed-form distortion and OpenCV's projectPoints.
DISTORT_TOL_PX = 1e-9


def test_distortion_matches_opencv_project_points() -> None:
    cam = opencv_camera(fy_px=3012.0)
    rng = np.random.default_rng(4)
    X = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.33, 0.33, 200),
                         np.ones(200)])
    K = np.array([[cam.fx_px, 0, cam.cx_px], [0, cam.fy_px, cam.cy_px], [0, 0, 1]])
    expected, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, cam.distortion)
    u, v = distort_normalized(X[:, 0] / X[:, 2], X[:, 1] / X[:, 2], cam)
    np.testing.assert_allclose(np.column_stack([u, v]), np.asarray(expected).reshape(-1, 2),
                               rtol=0, atol=DISTORT_TOL_PX)


def test_observed_pixels_round_trip_through_ideal_pixels() -> None:
    corrector = PixelCorrector(camera=opencv_camera(fy_px=3012.0))
    rng = np.random.default_rng(5)
    observed = np.column_stack([rng.uniform(0, 2455, 100), rng.uniform(0, 2057, 100)])
    back = corrector.observed_pixels(corrector.ideal_pixels(observed))
    np.testing.assert_allclose(back, observed, rtol=0, atol=UNDISTORT_TOL_PX)


def test_ideal_pixels_of_a_strong_barrel_lens_reach_the_corners() -> None:
    """k1 -0.6, k2 0.2, p1 0.01 at f 400 px: OpenCV's undistortPoints stopped 1.3 px short
    of these corners; the Newton inverse meets the closed form to 1e-8 px everywhere."""
    cam = CameraConfig(model="OPENCV", width_px=640, height_px=480, fx_px=400.0, fy_px=404.0,
                       cx_px=319.5, cy_px=239.5, k1=-0.6, k2=0.2, p1=0.01)
    assert cam.fold() is None
    corrector = PixelCorrector(camera=cam)
    u, v = np.meshgrid(np.linspace(0.0, 639.0, 33), np.linspace(0.0, 479.0, 25))
    observed = np.column_stack([u.ravel(), v.ravel()])
    back = corrector.observed_pixels(corrector.ideal_pixels(observed))
    np.testing.assert_allclose(back, observed, rtol=0, atol=UNDISTORT_TOL_PX)


#: Largest error of the distortion table against the closed form, pixels.
TABLE_TOL_PX = 0.01


def test_distortion_table_matches_the_closed_form() -> None:
    cam = opencv_camera(fy_px=3012.0)
    table = DistortionTable.for_camera(cam)
    corrector = PixelCorrector(camera=cam)
    rng = np.random.default_rng(6)
    observed = np.column_stack([rng.uniform(-0.5, 2455.5, 2000), rng.uniform(-0.5, 2057.5, 2000)])
    ideal = corrector.ideal_pixels(observed)
    coords = ((ideal - [table.u0, table.v0]) / table.step_px).astype(np.float32)
    delta = cv2.remap(table.table, coords.reshape(1, -1, 2), None, cv2.INTER_LINEAR)
    looked_up = coords * table.step_px + delta.reshape(-1, 2)
    np.testing.assert_allclose(looked_up, observed, rtol=0, atol=TABLE_TOL_PX)
