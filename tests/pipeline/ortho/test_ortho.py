"""Orthorectification on synthetic scenes with known ground texture, occlusion, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from pipeline.ortho.base import OrthoOptions, OrthoRaster
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.ortho.raster import cog_problems
from seqat.errors import InputDataError

from ..synthetic_ortho import (
    CRS,
    E0_M,
    N0_M,
    ROOF_VALUE,
    TEXTURE_MAX,
    Scene,
    hidden_by_box,
    render,
    small_camera,
    texture,
)

#: Ortho pixel of the synthetic tests, metres (the camera's GSD is ~0.1 m).
PIXEL_M = 0.1
#: Largest allowed shift of the ortho against the ground texture, ortho cells.
SHIFT_TOL_CELLS = 0.02
#: Largest allowed RMS of ortho - texture (bilinear interpolation of a smooth texture), as a
#: fraction of the texture's range.
RMS_TOL = 2e-3
#: Cells next to a box edge where the DSM's bilinear ramp and the bucket size blur visibility.
EDGE_MARGIN_CELLS = 3
#: At most this fraction of the truly hidden cells (edges excluded) may be filled.
HIDDEN_FILLED_TOL = 0.005
#: At most this fraction of the truly visible cells may be marked hidden.
FALSE_HIDDEN_TOL = 0.005


def cell_centres(raster: OrthoRaster) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = raster.shape
    x = (raster.col0 + np.arange(cols) + 0.5) * raster.pixel_m
    y = -(raster.row0 + np.arange(rows) + 0.5) * raster.pixel_m
    return np.meshgrid(x, y)


def texture_shift_m(raster: OrthoRaster) -> tuple[np.ndarray, float]:
    """Least-squares shift (east, north) of the ortho against the texture, and the RMS."""
    X, Y = cell_centres(raster)
    m = raster.seen
    diff = raster.pixels[:, :, 0].astype(np.float64) - texture(X, Y)
    eps = 1e-3
    gx = (texture(X + eps, Y) - texture(X - eps, Y)) / (2 * eps)
    gy = (texture(X, Y + eps) - texture(X, Y - eps)) / (2 * eps)
    A = np.column_stack([gx[m], gy[m], np.ones(m.sum())])
    sol, *_ = np.linalg.lstsq(A, diff[m], rcond=None)
    return sol[:2], float(np.sqrt(np.mean(diff[m] ** 2)))


def eop_deg(de: float, dn: float, z: float, omega: float, phi: float, kappa: float) -> np.ndarray:
    return np.array([E0_M + de, N0_M + dn, z, *np.radians([omega, phi, kappa])])


@pytest.mark.parametrize(("scene", "eop", "distorted"), [
    (Scene(a=12.0), eop_deg(1.0, -2.0, 52.0, 0.0, 0.0, 0.0), False),
    (Scene(a=12.0), eop_deg(3.0, -2.0, 52.0, 3.0, -4.0, 30.0), True),
    (Scene(a=12.0, b=0.05, c=-0.03), eop_deg(3.0, -2.0, 52.0, -2.0, 5.0, -120.0), True),
], ids=["flat-nadir-pinhole", "flat-tilted-distorted", "sloped-tilted-distorted"])
def test_ortho_reproduces_ground_texture(scene: Scene, eop: np.ndarray, distorted: bool) -> None:
    cam = small_camera(distorted)
    image = render(scene, cam, eop)
    with Orthorectifier(scene.dsm(), cam, CRS, None, OrthoOptions(pixel_m=PIXEL_M)) as ortho:
        result = ortho.add_image("img", image, eop)
    shift_m, rms = texture_shift_m(result.raster)
    assert np.all(np.abs(shift_m) < SHIFT_TOL_CELLS * PIXEL_M), shift_m
    assert rms < RMS_TOL * 65535
    assert result.warnings == ()
    assert result.occluded_cells == 0  # a plane hides nothing
    # The seen area is the image footprint: ground cells of pixel_m ~ image pixels (GSD).
    assert result.seen_cells == pytest.approx(cam.width_px * cam.height_px, rel=0.3)


def test_ortho_cubic_resampling_is_as_accurate() -> None:
    cam, scene = small_camera(), Scene(a=5.0)
    eop = eop_deg(0.0, 0.0, 45.0, 2.0, 1.0, 45.0)
    with Orthorectifier(scene.dsm(), cam, CRS, None,
                        OrthoOptions(pixel_m=PIXEL_M, resampling="cubic")) as ortho:
        result = ortho.add_image("img", render(scene, cam, eop), eop)
    shift_m, rms = texture_shift_m(result.raster)
    assert np.all(np.abs(shift_m) < SHIFT_TOL_CELLS * PIXEL_M)
    assert rms < RMS_TOL * 65535


def box_scene() -> tuple[Scene, np.ndarray]:
    """A 6 x 6 m, 12 m high building east of an oblique-looking camera."""
    scene = Scene(a=10.0, box=(E0_M + 4, N0_M - 3, E0_M + 10, N0_M + 3, 12.0))
    return scene, eop_deg(-6.0, -1.0, 50.0, 2.0, -3.0, 10.0)


@pytest.mark.parametrize("method", ["zbuffer", "raycast"])
@pytest.mark.parametrize("distorted", [True, False], ids=["distorted", "ideal-camera"])
def test_occluded_ground_is_not_filled_from_the_roof(distorted: bool, method: str) -> None:
    scene, eop = box_scene()
    cam = small_camera(distorted)  # an ideal camera skips the distortion table
    image = render(scene, cam, eop)
    rasters = {}
    for occlusion in (True, False):
        with Orthorectifier(scene.dsm(), cam, CRS, None,
                            OrthoOptions(pixel_m=PIXEL_M, occlusion=occlusion,
                                         occlusion_method=method)) as ortho:
            rasters[occlusion] = ortho.add_image("img", image, eop)
    with_occ, without = rasters[True].raster, rasters[False].raster
    assert with_occ.shape == without.shape and with_occ.col0 == without.col0
    X, Y = cell_centres(with_occ)
    hidden = hidden_by_box(scene, eop, X.ravel(), Y.ravel()).reshape(X.shape)
    bw, bs, be, bn, _ = scene.box  # type: ignore[misc]
    margin = EDGE_MARGIN_CELLS * PIXEL_M
    near_box = (X >= bw - margin) & (X <= be + margin) & (Y >= bs - margin) & (Y <= bn + margin)
    kernel = np.ones((2 * EDGE_MARGIN_CELLS + 1,) * 2, np.uint8)
    hidden_core = cv2.erode(hidden.astype(np.uint8), kernel).astype(bool) & ~near_box
    visible_core = ~cv2.dilate(hidden.astype(np.uint8), kernel).astype(bool) & ~near_box
    in_image = without.seen
    assert hidden_core.sum() > 1000  # the building hides a real area
    # Without the z-buffer the roof smears over the hidden ground ...
    assert np.mean(without.pixels[hidden_core, 0] == ROOF_VALUE) > 0.9
    # ... with it those cells stay empty, and visible ground keeps its texture.
    assert np.mean(with_occ.seen[hidden_core]) < HIDDEN_FILLED_TOL
    false_hidden = in_image & visible_core & ~with_occ.seen
    assert false_hidden.sum() < FALSE_HIDDEN_TOL * (in_image & visible_core).sum()
    roof_like = with_occ.pixels[:, :, 0] > (ROOF_VALUE + TEXTURE_MAX) / 2
    assert not np.any(roof_like & with_occ.seen & visible_core)
    # Only a thin band along the hidden area's outline may mix roof and ground.
    assert np.sum(roof_like & with_occ.seen & ~near_box) < 0.05 * hidden_core.sum()
    assert rasters[True].occluded_cells >= hidden_core.sum()


def test_ortho_cog_has_crs_geotransform_and_alpha(tmp_path: Path) -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eop = eop_deg(0.0, 0.0, 52.0, 0.0, 0.0, 0.0)
    with Orthorectifier(scene.dsm(), cam, CRS, tmp_path / "ortho",
                        OrthoOptions(pixel_m=PIXEL_M)) as ortho:
        result = ortho.add_image("img_0001", render(scene, cam, eop), eop)
    assert result.path == tmp_path / "ortho" / "img_0001.tif"
    assert cog_problems(result.path) == ()
    raster = result.raster
    with rasterio.open(result.path) as src:
        assert src.crs.to_epsg() == 32652
        assert src.transform.a == PIXEL_M and src.transform.e == -PIXEL_M
        # The outer corner of the top-left cell sits on the global grid (multiples of PIXEL_M).
        assert src.transform.c == pytest.approx(raster.col0 * PIXEL_M, abs=1e-6)
        assert src.transform.f == pytest.approx(-raster.row0 * PIXEL_M, abs=1e-6)
        assert src.colorinterp[-1] == rasterio.enums.ColorInterp.alpha
        band, alpha = src.read(1), src.read(2)
        # Known coordinates: the cell holding the nadir point carries the texture there.
        row, col = src.index(E0_M + 0.05, N0_M + 0.05)
        x, y = src.xy(row, col)  # cell centre (pixel-is-area)
        assert alpha[row, col] == 65535
        assert band[row, col] == pytest.approx(texture(np.array(x), np.array(y)), abs=80)
        assert src.profile["tiled"] and src.block_shapes[0] == (512, 512)


def test_background_writes_give_the_same_files(tmp_path: Path) -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eops = [eop_deg(de, 0.0, 52.0, 0.0, 0.0, 0.0) for de in (0.0, 10.0, 20.0)]
    images = [render(scene, cam, e) for e in eops]
    for background in (True, False):
        options = OrthoOptions(pixel_m=PIXEL_M, background_writes=background)
        with Orthorectifier(scene.dsm(), cam, CRS, tmp_path / str(background), options) as o:
            for i, (image, eop) in enumerate(zip(images, eops, strict=True)):
                o.add_image(f"img_{i}", image, eop)
    for i in range(3):
        with rasterio.open(tmp_path / "True" / f"img_{i}.tif") as a, \
                rasterio.open(tmp_path / "False" / f"img_{i}.tif") as b:
            np.testing.assert_array_equal(a.read(), b.read())
            assert a.transform == b.transform


def test_pixel_size_defaults_to_the_gsd_of_the_first_image() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eop = eop_deg(0.0, 0.0, 52.0, 0.0, 0.0, 0.0)  # 40 m above ground, fx 400 px: GSD 0.1 m
    with Orthorectifier(scene.dsm(), cam, CRS, None) as ortho:
        ortho.add_image("a", render(scene, cam, eop), eop)
        assert ortho.pixel_m == pytest.approx(0.1)
        higher = eop_deg(1.0, 0.0, 72.0, 0.0, 0.0, 0.0)
        result = ortho.add_image("b", render(scene, cam, higher), higher)
        assert result.raster.pixel_m == pytest.approx(0.1)  # fixed for the flight


def test_eop_above_the_horizon_is_an_error() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eop = eop_deg(0.0, 0.0, 52.0, 95.0, 0.0, 0.0)
    image = np.zeros((cam.height_px, cam.width_px), np.uint8)
    with Orthorectifier(scene.dsm(), cam, CRS, None) as ortho, \
            pytest.raises(InputDataError, match="horizon"):
        ortho.add_image("img_9", image, eop)


def test_oblique_image_reaching_the_horizon_gives_a_partial_ortho() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eop = eop_deg(0.0, 0.0, 22.0, 60.0, 0.0, 0.0)  # upper image edge above the horizon
    with Orthorectifier(scene.dsm(half_size_m=80.0), cam, CRS, None,
                        OrthoOptions(pixel_m=PIXEL_M)) as ortho:
        result = ortho.add_image("img", render(scene, cam, eop), eop)
    assert any("beyond" in w for w in result.warnings)
    shift_m, _ = texture_shift_m(result.raster)
    assert np.all(np.abs(shift_m) < SHIFT_TOL_CELLS * PIXEL_M)


def test_dsm_not_covering_the_image_is_an_error() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eop = eop_deg(500.0, 0.0, 52.0, 0.0, 0.0, 0.0)
    image = np.zeros((cam.height_px, cam.width_px), np.uint8)
    with Orthorectifier(scene.dsm(), cam, CRS, None) as ortho, \
            pytest.raises(InputDataError, match="does not cover"):
        ortho.add_image("img", image, eop)


def test_dsm_partly_covering_the_image_gives_a_partial_ortho_and_a_warning() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    eop = eop_deg(55.0, 0.0, 52.0, 0.0, 0.0, 0.0)  # DSM ends 5 m east of the nadir point
    with Orthorectifier(scene.dsm(), cam, CRS, None, OrthoOptions(pixel_m=PIXEL_M)) as ortho:
        result = ortho.add_image("img", render(scene, cam, eop), eop)
    _, _, east, _ = result.raster.bounds
    assert east <= E0_M + 60.0 + 1e-6  # nothing past the DSM's east edge
    assert result.seen_cells > 0.3 * cam.width_px * cam.height_px
    assert any("beyond the DSM" in w for w in result.warnings)


def test_wrong_image_size_is_an_error() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    with Orthorectifier(scene.dsm(), cam, CRS, None) as ortho, \
            pytest.raises(InputDataError, match="differs from the camera"):
        ortho.add_image("img", np.zeros((10, 10), np.uint8), eop_deg(0, 0, 52, 0, 0, 0))


def test_camera_below_the_surface_is_an_error() -> None:
    cam, scene = small_camera(), Scene(a=12.0)
    image = np.zeros((cam.height_px, cam.width_px), np.uint8)
    with Orthorectifier(scene.dsm(), cam, CRS, None) as ortho, \
            pytest.raises(InputDataError, match="not above the DSM"):
        ortho.add_image("img", image, eop_deg(0, 0, 5.0, 0, 0, 0))


def test_bilinear_is_the_default_resampling() -> None:
    assert OrthoOptions().resampling == "bilinear"
    assert math.isclose(OrthoOptions().max_range_factor, 3.0)
