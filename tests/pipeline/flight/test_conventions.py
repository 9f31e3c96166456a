"""docs/conventions.md, checked: nadir orientation, pixel axes, kappa sense, degree files."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.flight.folder import read_flight
from seqat.geometry import project, rotation_matrix
from seqat.types import PinholeCamera

from ..sample_flight import FlightMaker

CAMERA = PinholeCamera(f_px=1000.0, cx_px=319.5, cy_px=239.5, width_px=640, height_px=480)
#: A nadir camera 100 m above the origin.
NADIR = np.array([0.0, 0.0, 100.0, 0.0, 0.0, 0.0])
#: Exactness of the closed-form checks (pixels).
PX_TOL = 1e-9


def uv_of(eop: np.ndarray, X: list[float]) -> np.ndarray:
    return project(eop[None], np.asarray([X], dtype=np.float64), CAMERA)[0]


def test_nadir_camera_image_top_is_north_right_is_east() -> None:
    north = uv_of(NADIR, [0.0, 10.0, 0.0])
    east = uv_of(NADIR, [10.0, 0.0, 0.0])
    # x = -f p_x / p_z with p_z = -100: 10 m at 100 m is 100 px.
    np.testing.assert_allclose(north, [CAMERA.cx_px, CAMERA.cy_px - 100.0], atol=PX_TOL)
    np.testing.assert_allclose(east, [CAMERA.cx_px + 100.0, CAMERA.cy_px], atol=PX_TOL)


def test_kappa_90_turns_image_top_to_west() -> None:
    eop = NADIR.copy()
    eop[5] = np.pi / 2
    west = uv_of(eop, [-10.0, 0.0, 0.0])
    np.testing.assert_allclose(west, [CAMERA.cx_px, CAMERA.cy_px - 100.0], atol=PX_TOL)


def test_rotation_is_rx_ry_rz_camera_to_world() -> None:
    o, p, k = 0.1, -0.2, 0.3
    Rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    np.testing.assert_allclose(rotation_matrix(o, p, k), Rx @ Ry @ Rz, rtol=0, atol=1e-15)


def test_files_hold_degrees_frames_hold_radians(make_flight: FlightMaker, tmp_path: Path) -> None:
    frame = next(iter(read_flight(make_flight()).frames()))
    np.testing.assert_allclose(frame.nav_eop[3:], np.radians([0.5, -0.25, 90.0]), rtol=0,
                               atol=1e-15)
