"""COG writing and the layout check (GDAL's validate_cloud_optimized_geotiff rules)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyproj
import pytest
import rasterio
from rasterio.enums import Resampling
from rasterio.transform import from_origin

from pipeline.ortho.raster import cog_problems, reproject_cog, write_cog
from seqat.errors import InputDataError

CRS = pyproj.CRS.from_epsg(32652)
#: Larger than two 512 px tiles, so the COG has overviews.
SIZE = (3, 1200, 1100)


def sample() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 255, SIZE, dtype=np.uint8)


def test_write_cog_passes_the_layout_check_with_known_georeferencing(tmp_path: Path) -> None:
    path = write_cog(tmp_path / "a.tif", sample(), transform=from_origin(500000, 4090000, 0.5, 0.5),
                     crs=CRS, alpha=True)
    assert cog_problems(path) == ()
    with rasterio.open(path) as src:
        assert src.overviews(1) == [2, 4]
        assert src.block_shapes[0] == (512, 512)
        assert src.crs.to_epsg() == 32652
        # Pixel-is-area: the outer corner of the top-left pixel; centre half a pixel in.
        assert src.tags()["AREA_OR_POINT"] == "Area"
        assert src.xy(0, 0) == (500000.25, 4089999.75)
        assert src.bounds == (500000.0, 4090000.0 - 600.0, 500000.0 + 550.0, 4090000.0)
    assert not list(tmp_path.glob(".*"))  # no temporary file left
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # readable like any other output


def test_plain_and_badly_ordered_geotiffs_fail_the_check(tmp_path: Path) -> None:
    profile = {"driver": "GTiff", "width": SIZE[2], "height": SIZE[1], "count": SIZE[0],
               "dtype": "uint8", "crs": "EPSG:32652",
               "transform": from_origin(500000, 4090000, 0.5, 0.5)}
    with rasterio.open(tmp_path / "strips.tif", "w", **profile) as dst:
        dst.write(sample())
    problems = cog_problems(tmp_path / "strips.tif")
    assert any("not tiled" in p for p in problems)
    assert any("LAYOUT=COG" in p for p in problems)
    assert any("no overviews" in p for p in problems)
    # Tiled, overviews added afterwards: their IFDs and data come after the full resolution.
    with rasterio.open(tmp_path / "late.tif", "w", tiled=True, blockxsize=256, blockysize=256,
                       **profile) as dst:
        dst.write(sample())
    with rasterio.open(tmp_path / "late.tif", "r+") as dst:
        dst.build_overviews([2, 4], Resampling.average)
    problems = cog_problems(tmp_path / "late.tif")
    assert any("ordered" in p or "IFD" in p for p in problems), problems


def test_reproject_cog_keeps_a_valid_cog(tmp_path: Path) -> None:
    path = write_cog(tmp_path / "a.tif", sample(), transform=from_origin(500000, 4090000, 0.5, 0.5),
                     crs=CRS, alpha=True)
    reproject_cog(path, pyproj.CRS.from_epsg(4326))
    assert cog_problems(path) == ()
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 4326
        assert 128.9 < src.bounds.left < 129.1  # UTM 52N: central meridian 129 E


def test_cog_check_of_a_missing_file_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="cannot open raster"):
        cog_problems(tmp_path / "none.tif")
