"""Streaming mosaic: most-nadir choice, feathered seams, tiles on disk, COG output."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import rasterio

from pipeline.ortho.base import OrthoOptions, OrthoResult
from pipeline.ortho.mosaic import MosaicBuilder
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.ortho.raster import cog_problems
from seqat.errors import InputDataError

from ..synthetic_ortho import CRS, E0_M, N0_M, Scene, render, small_camera, texture

PIXEL_M = 0.1
#: Brightness offset of every second image (uint16 units): tells the images apart in the mosaic.
EXPOSURE_STEP = 4000
#: Nadir points of the strip, metres east of E0 (15 m apart: half overlap of a 40 m footprint).
STRIP_EAST_M = (-22.5, -7.5, 7.5, 22.5)
FEATHER_PX = 6


@pytest.fixture(scope="module")
def strip_orthos() -> list[OrthoResult]:
    cam, scene = small_camera(), Scene(a=12.0)
    results = []
    with Orthorectifier(scene.dsm(), cam, CRS, None, OrthoOptions(pixel_m=PIXEL_M)) as ortho:
        for i, de in enumerate(STRIP_EAST_M):
            eop = np.array([E0_M + de, N0_M, 52.0, 0.0, 0.0, np.radians(90.0)])
            image = render(scene, cam, eop).astype(np.int64) + (i % 2) * EXPOSURE_STEP
            results.append(ortho.add_image(f"img_{i}", image.astype(np.uint16), eop))
    return results


def test_mosaic_picks_the_most_nadir_image_with_a_short_feather(
        tmp_path: Path, strip_orthos: list[OrthoResult]) -> None:
    builder = MosaicBuilder(tmp_path / "mosaic.tif", CRS, feather_px=FEATHER_PX)
    updates = [builder.add(o) for o in strip_orthos]
    result = builder.finish()
    assert not builder.work_dir.exists()  # tile store removed
    assert cog_problems(result.path) == ()
    with rasterio.open(result.path) as src:
        assert src.crs.to_epsg() == 32652
        assert src.overviews(1)  # larger than one tile
        # On the global grid (cell edges at multiples of the pixel), cropped to the data:
        # the union of the orthos' seen cells, not the 512 px tiles they fall in.
        assert src.transform.c / PIXEL_M == pytest.approx(round(src.transform.c / PIXEL_M),
                                                          abs=1e-6)
        west = min(o.raster.transform.c + PIXEL_M * np.flatnonzero(o.raster.seen.any(0))[0]
                   for o in strip_orthos)
        north = max(o.raster.transform.f - PIXEL_M * np.flatnonzero(o.raster.seen.any(1))[0]
                    for o in strip_orthos)
        east = max(o.raster.transform.c + PIXEL_M * (np.flatnonzero(o.raster.seen.any(0))[-1]
                                                     + 1) for o in strip_orthos)
        south = min(o.raster.transform.f - PIXEL_M * (np.flatnonzero(o.raster.seen.any(1))[-1]
                                                      + 1) for o in strip_orthos)
        assert tuple(src.bounds) == pytest.approx((west, south, east, north), abs=1e-6)
        assert result.bounds == pytest.approx((west, south, east, north), abs=1e-6)
        full = src.read(src.count)
        assert full[0].any() and full[-1].any() and full[:, 0].any() and full[:, -1].any()
        # Along the strip's centre line: offset of each cell against the texture.
        row, _ = src.index(E0_M, N0_M)
        band = src.read(1, window=rasterio.windows.Window(0, row, src.width, 1))[0]
        alpha = src.read(2, window=rasterio.windows.Window(0, row, src.width, 1))[0]
        x, y = (np.asarray(c) for c in src.xy(np.full(src.width, row), np.arange(src.width)))
    seen = alpha > 0
    offset = band[seen].astype(np.float64) - texture(x[seen], y[seen])
    xs = x[seen] - E0_M
    # Far from seams each cell comes from the image whose nadir point is nearest.
    nadir = np.asarray(STRIP_EAST_M)
    nearest = np.argmin(np.abs(xs[:, None] - nadir[None, :]), axis=1)
    seams = (nadir[:-1] + nadir[1:]) / 2
    far = np.min(np.abs(xs[:, None] - seams[None, :]), axis=1) > FEATHER_PX * PIXEL_M
    far &= (xs > xs.min() + 2 * PIXEL_M) & (xs < xs.max() - 2 * PIXEL_M)  # image borders
    expected = (nearest % 2) * EXPOSURE_STEP
    assert np.all(np.abs(offset[far] - expected[far]) < 200)
    # Across a seam the offset ramps over about FEATHER_PX cells (not a step, not wider).
    ramp = (offset > 0.1 * EXPOSURE_STEP) & (offset < 0.9 * EXPOSURE_STEP)
    ramp_cells = ramp.sum() / len(seams)
    assert 0.5 * FEATHER_PX <= ramp_cells <= 1.5 * FEATHER_PX
    # Flat memory: an update touches only the tiles under its ortho.
    assert max(u.tiles_touched for u in updates) <= 4
    assert result.images == len(strip_orthos)


def test_tiles_evicted_to_disk_give_the_same_mosaic(tmp_path: Path,
                                                   strip_orthos: list[OrthoResult]) -> None:
    paths = []
    for cache in (1, None):
        builder = MosaicBuilder(tmp_path / f"m{cache}.tif", CRS, cache_tiles=cache)
        for ortho in strip_orthos:
            builder.add(ortho)
        paths.append(builder.finish().path)
    with rasterio.open(paths[0]) as a, rasterio.open(paths[1]) as b:
        np.testing.assert_array_equal(a.read(), b.read())


def test_8bit_orthos_blend_like_16bit(tmp_path: Path, strip_orthos: list[OrthoResult]) -> None:
    results = {}
    for dtype in (np.uint8, np.uint16):
        builder = MosaicBuilder(tmp_path / f"{np.dtype(dtype).name}.tif", CRS)
        for o in strip_orthos:
            pixels = (o.raster.pixels // 256).astype(dtype)
            builder.add(dataclasses.replace(o, raster=dataclasses.replace(o.raster,
                                                                          pixels=pixels)))
        with rasterio.open(builder.finish().path) as src:
            results[dtype] = src.read(1).astype(np.int64)
    assert np.abs(results[np.uint8] - results[np.uint16]).max() <= 1


def test_mosaic_of_nothing_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="no ortho"):
        MosaicBuilder(tmp_path / "mosaic.tif", CRS).finish()


def test_mosaic_rejects_a_different_pixel_size(tmp_path: Path,
                                                strip_orthos: list[OrthoResult]) -> None:
    builder = MosaicBuilder(tmp_path / "mosaic.tif", CRS)
    builder.add(strip_orthos[0])
    cam, scene = small_camera(), Scene(a=12.0)
    eop = np.array([E0_M, N0_M, 52.0, 0.0, 0.0, 0.0])
    with Orthorectifier(scene.dsm(), cam, CRS, None, OrthoOptions(pixel_m=0.2)) as ortho:
        other = ortho.add_image("x", render(scene, cam, eop), eop)
    with pytest.raises(InputDataError, match="does not match the mosaic"):
        builder.add(other)
