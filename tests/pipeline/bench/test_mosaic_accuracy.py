"""Mosaic check-point accuracy: a mosaic shifted by a known amount is measured as such."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pyproj
import pytest
from rasterio.transform import from_origin

from pipeline.bench.mosaic_accuracy import mosaic_shifts
from pipeline.ortho.raster import write_cog
from pipeline.simulate.render import Texture, affine_texture_map

CRS = pyproj.CRS.from_epsg(32610)
X0, Y0, PIXEL = 500000.0, 4877000.0, 0.25  # texture: pixel (0, 0) centred at (X0, Y0)


@pytest.mark.parametrize("dxy_m", [(0.0, 0.0), (0.4, -0.3), (-0.7, 0.55)])
def test_known_shift_of_the_mosaic_is_measured(tmp_path: Path, dxy_m: tuple[float, float]
                                               ) -> None:
    rng = np.random.default_rng(4)
    noise = rng.uniform(0, 255, (900, 900)).astype(np.float32)
    image = cv2.GaussianBlur(noise, (0, 0), 3.0)
    image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    texture = Texture(image=cv2.cvtColor(image, cv2.COLOR_GRAY2BGR),
                      to_pixel=affine_texture_map(X0, Y0, PIXEL, -PIXEL))
    # the mosaic (0.3 m cells) shows at ground (x, y) what lies at (x - dx, y - dy)
    cell, n = 0.3, 600
    west, north = X0 + 10.0, Y0 - 10.0
    cc, rr = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    gx, gy = west + cc * cell - dxy_m[0], north - rr * cell - dxy_m[1]
    tx, ty = texture.to_pixel(gx, gy)
    gray = cv2.remap(image, tx.astype(np.float32), ty.astype(np.float32), cv2.INTER_LINEAR)
    alpha = np.full_like(gray, 255)
    path = write_cog(tmp_path / "mosaic.tif", np.stack([gray, gray, gray, alpha]),
                     transform=from_origin(west, north, cell, cell), crs=CRS, alpha=True)
    xy = np.array([[west + 40.0, north - 40.0], [west + 90.0, north - 120.0],
                   [west + 150.0, north - 60.0], [west + 500.0, north - 60.0]])
    r = mosaic_shifts(path, ("a", "b", "c", "outside"), xy, texture)
    assert r.point_ids == ("a", "b", "c") and r.skipped == ("outside",)
    np.testing.assert_allclose(r.dxy_m, np.tile(dxy_m, (3, 1)), atol=0.03)  # 0.1 cell
    assert r.rmse_h_m == pytest.approx(float(np.hypot(*dxy_m)), abs=0.03)
