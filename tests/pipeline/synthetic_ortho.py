"""Synthetic scenes for the ortho tests: known ground texture, surfaces and cameras.

An image is rendered by casting the ray of every observed pixel (undistorted with
:class:`pipeline.flight.camera.PixelCorrector`) onto a surface with an analytic intersection (a
plane ``Z = a + b X + c Y``, optionally with a box building) and reading the ground texture there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyproj
from rasterio.transform import from_origin

from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.schema import CameraConfig
from pipeline.ortho.dsm import Dsm
from seqat.geometry import rays_world

#: Working CRS of the synthetic scenes (UTM 52N, where the simulated strips live).
CRS = pyproj.CRS.from_epsg(32652)
#: Scene origin (a round UTM position) and camera height above it.
E0_M, N0_M = 500000.0, 4090000.0
#: Wavelength of the sinusoidal ground texture, metres.
TEXTURE_WAVELENGTH_M = 4.0
#: Texture value on box roofs (uint16), far from any ground value.
ROOF_VALUE = 65000
#: Largest ground texture value (uint16).
TEXTURE_MAX = 50000.0


def small_camera(distorted: bool = True) -> CameraConfig:
    """A 400 x 300 px camera with OpenCV distortion (or an ideal one)."""
    if not distorted:
        return CameraConfig(model="PINHOLE", width_px=400, height_px=300, fx_px=400.0,
                            fy_px=400.0, cx_px=199.5, cy_px=149.5)
    return CameraConfig(model="OPENCV", width_px=400, height_px=300, fx_px=400.0, fy_px=402.0,
                        cx_px=201.3, cy_px=148.2, k1=-0.08, k2=0.02, p1=5e-4, p2=-3e-4)


def texture(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """Smooth ground texture (uint16 scale, float): a product of sines of the local position."""
    k = 2.0 * np.pi / TEXTURE_WAVELENGTH_M
    xl, yl = x_m - E0_M, y_m - N0_M
    return TEXTURE_MAX * (0.5 + 0.25 * np.sin(k * xl + 0.3) * np.cos(k * 0.8 * yl - 0.2)
                          + 0.2 * np.sin(k * 0.35 * (xl + yl)))


@dataclass(frozen=True)
class Scene:
    """Plane ``Z = a + b (X - E0) + c (Y - N0)`` plus an optional box (west, south, east,
    north, height above the plane at its centre)."""

    a: float = 0.0
    b: float = 0.0
    c: float = 0.0
    box: tuple[float, float, float, float, float] | None = None

    def height(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        z = self.a + self.b * (x_m - E0_M) + self.c * (y_m - N0_M)
        if self.box is not None:
            w, s, e, n, h = self.box
            inside = (x_m >= w) & (x_m <= e) & (y_m >= s) & (y_m <= n)
            z = np.where(inside, self.a + h, z)
        return z

    def dsm(self, cell_m: float = 0.25, half_size_m: float = 60.0) -> Dsm:
        """The scene as a DSM raster around the origin."""
        n = int(2 * half_size_m / cell_m)
        west, north = E0_M - half_size_m, N0_M + half_size_m
        xc = west + (np.arange(n) + 0.5) * cell_m
        yc = north - (np.arange(n) + 0.5) * cell_m
        X, Y = np.meshgrid(xc, yc)
        return Dsm(heights_m=self.height(X, Y).astype(np.float32),
                   transform=from_origin(west, north, cell_m, cell_m), crs=CRS, source="scene")


def render(scene: Scene, camera: CameraConfig, eop: np.ndarray) -> np.ndarray:
    """The uint16 image the camera sees (box roofs and walls = ROOF_VALUE).

    The box is treated as flat-topped at ``a + h`` (the scene's plane must be flat when a box
    is present).
    """
    h, w = camera.height_px, camera.width_px
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    observed = np.column_stack([uu.ravel(), vv.ravel()])
    ideal = PixelCorrector(camera=camera).ideal_pixels(observed)
    d = rays_world(np.tile(eop, (len(ideal), 1)), ideal, pinhole_camera(camera))
    C = eop[:3]
    # Plane: C_z + t d_z = a + b (C_x + t d_x - E0) + c (C_y + t d_y - N0)
    num = scene.a + scene.b * (C[0] - E0_M) + scene.c * (C[1] - N0_M) - C[2]
    den = d[:, 2] - scene.b * d[:, 0] - scene.c * d[:, 1]
    t = num / den
    ground = C + t[:, None] * d
    value = texture(ground[:, 0], ground[:, 1])
    if scene.box is not None:
        bw, bs, be, bn, bh = scene.box
        lo = np.array([bw, bs, scene.a])
        hi = np.array([be, bn, scene.a + bh])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - C) / d
            t2 = (hi - C) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_far > 0) & (t_near < t)
        value = np.where(hit, ROOF_VALUE, value)
    return np.clip(np.rint(value), 0, 65535).astype(np.uint16).reshape(h, w)


def hidden_by_box(scene: Scene, eop: np.ndarray, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """Ground points (on the flat plane, outside the box) whose ray to the camera hits the box."""
    assert scene.box is not None
    bw, bs, be, bn, bh = scene.box
    P = np.column_stack([x_m, y_m, np.full(x_m.shape, scene.a)])
    d = eop[:3] - P
    lo = np.array([bw, bs, scene.a])
    hi = np.array([be, bn, scene.a + bh])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - P) / d
        t2 = (hi - P) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    inside = (x_m >= bw) & (x_m <= be) & (y_m >= bs) & (y_m <= bn)
    return (t_near <= t_far) & (t_far > 1e-9) & (t_near < 1.0) & ~inside
