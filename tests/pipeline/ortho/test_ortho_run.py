"""``seqat ortho`` on a synthetic run folder: orthos, mosaic, cameras.gpkg, fallbacks, errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import laspy
import numpy as np
import pyogrio
import pyproj
import pytest
import rasterio
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.common.tables import NavTable
from pipeline.flight.inputs import RunInputs
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.dsm import DSM_NODATA
from pipeline.ortho.raster import cog_problems, write_cog
from pipeline.ortho.stage import orthorectify_run
from pipeline.run.store import (
    RunRecord,
    RunTotals,
    TimingStats,
    format_observation_lines,
    write_run_outputs,
)
from seqat.errors import ConfigError, InputDataError
from seqat.types import EopEstimate, PointEstimate, Solution

from ..synthetic_ortho import CRS, E0_M, N0_M, TEXTURE_MAX, Scene, render, small_camera, texture

#: Nadir points of the strip (metres east of E0), 52 m high over the plane at 12 m.
STRIP_EAST_M = (-15.0, 0.0, 15.0)
Z_PLANE_M = 12.0
#: 8-bit images: texture / TEXTURE_SCALE; agreement allowed after JPEG and 8-bit rounding.
TEXTURE_SCALE = TEXTURE_MAX / 250.0
JPEG_TOL = 8.0


def write_run(tmp_path: Path, *, with_images: bool = True, missing: str | None = None) -> Path:
    """A run folder of three images of the flat textured scene, and its images folder."""
    cam, scene = small_camera(), Scene(a=Z_PLANE_M)
    images = tmp_path / "images"
    images.mkdir(parents=True)
    eops = []
    for i, de in enumerate(STRIP_EAST_M):
        eop = np.array([E0_M + de, N0_M, 52.0, 0.0, 0.0, np.radians(90.0)])
        image_id = f"img_{i:04d}"
        eops.append(EopEstimate(image_id=image_id, eop=eop, sigma=np.full(6, 0.01)))
        if image_id != missing:
            grey = np.clip(render(scene, cam, eop) / TEXTURE_SCALE, 0, 255).astype(np.uint8)
            suffix = ".JPG" if i == 1 else ".jpg"  # any case
            cv2.imwrite(str(images / f"{image_id}{suffix}"), np.dstack([grey] * 3),
                        [cv2.IMWRITE_JPEG_QUALITY, 98])
    points = [PointEstimate(point_id=f"p{j}", xyz_m=np.array([E0_M + j, N0_M, Z_PLANE_M]),
                            sigma_m=np.full(3, 0.02), n_obs=3) for j in range(5)]
    nav = NavTable(image_ids=tuple(e.image_id for e in eops), times_s=np.arange(3.0),
                   eop=np.array([e.eop for e in eops]))
    inputs = RunInputs(crs=CRS, camera=cam, camera_approximate=False, nav=nav,
                       nav_sigma=np.array([1.0, 1.0, 1.0, 0.01, 0.01, 0.01]),
                       sigma_image_px=1.0, images_dir=images if with_images else None,
                       skipped=(), warnings=())
    stats = TimingStats.from_samples([1.0])
    totals = RunTotals(images=3, points=5, observations=0, update_ms=stats,
                       sequential_update_ms=stats, wall_s=0.1, sigma0=1.0, redundancy=1)
    record = RunRecord(method="seq-r", flight=str(tmp_path / "flight"), inputs=inputs,
                       options=stats, final_only=False, images=(), totals=totals)
    out = tmp_path / "out"
    write_run_outputs(out, Solution(eops=tuple(eops), points=tuple(points), sigma0=1.0,
                                    redundancy=1), record,
                      format_observation_lines("img_0000", (), np.zeros((0, 2))))
    return out


def write_scene_dsm(path: Path) -> Path:
    dsm = Scene(a=Z_PLANE_M).dsm(cell_m=1.0)
    return write_cog(path, dsm.heights_m[None], transform=dsm.transform, crs=CRS,
                     nodata=DSM_NODATA)


def mosaic_matches_texture(path: Path) -> None:
    with rasterio.open(path) as src:
        for de in (-20.0, -7.3, 0.4, 8.1, 21.0):
            x, y = E0_M + de, N0_M + 3.3
            row, col = src.index(x, y)
            cx, cy = src.xy(row, col)
            r, g, b, a = (int(v) for v in next(src.sample([(cx, cy)])))
            assert a == 255
            expected = texture(np.array(cx), np.array(cy)) / TEXTURE_SCALE
            assert r == g == b or abs(r - g) <= 2
            assert abs(r - expected) < JPEG_TOL, (de, r, expected)


def test_ortho_run_writes_orthos_mosaic_and_gpkg(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    dsm = write_scene_dsm(tmp_path / "scene_dsm.tif")
    summary = orthorectify_run(out, dsm_path=dsm, options=OrthoOptions(pixel_m=0.1),
                               progress=False)
    assert [r.image for r in summary.images] == ["img_0000", "img_0001", "img_0002"]
    assert summary.skipped == () and summary.warnings == ()
    for record in summary.images:
        assert record.path is not None and cog_problems(record.path) == ()
    assert cog_problems(out / "mosaic.tif") == ()
    mosaic_matches_texture(out / "mosaic.tif")
    layers = dict(pyogrio.list_layers(out / "cameras.gpkg"))
    assert layers == {"cameras": "Point Z", "footprints": "Polygon", "tie_points": "Point Z"}
    info = pyogrio.read_info(out / "cameras.gpkg", layer="cameras")
    assert info["features"] == 3 and pyproj.CRS(info["crs"]).to_epsg() == 32652
    assert "kappa_deg" in list(info["fields"]) and "sx_m" in list(info["fields"])
    cams = pyogrio.raw.read(out / "cameras.gpkg", layer="cameras")
    assert list(cams[3][0]) == ["img_0000", "img_0001", "img_0002"]
    np.testing.assert_allclose(cams[3][list(info["fields"]).index("kappa_deg")], 90.0)
    assert pyogrio.read_info(out / "cameras.gpkg", layer="tie_points")["features"] == 5
    doc = json.loads((out / "ortho.json").read_text())
    assert doc["pixel_m"] == 0.1 and len(doc["images"]) == 3
    assert doc["compute_ms"]["median_ms"] > 0


def test_ortho_run_without_dsm_uses_the_tie_point_plane(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    summary = orthorectify_run(out, options=OrthoOptions(pixel_m=0.1), progress=False)
    assert any("flat plane" in w and f"{Z_PLANE_M:.2f}" in w for w in summary.warnings)
    mosaic_matches_texture(out / "mosaic.tif")


@pytest.mark.parametrize("lidar", ["dsm", "las"])
def test_ortho_run_uses_the_flights_lidar(tmp_path: Path, lidar: str) -> None:
    out = write_run(tmp_path)
    flight = tmp_path / "flight"  # the run's flight folder (run.json "flight")
    flight.mkdir()
    if lidar == "dsm":
        write_scene_dsm(flight / "scene_dsm.tif")
        name = "scene_dsm.tif"
    else:  # a LiDAR cloud of the textured plane, gridded into OUT/dsm.tif
        g = np.arange(-40.0, 40.0, 0.5)
        x, y = np.meshgrid(E0_M + g, N0_M + g)
        header = laspy.LasHeader(point_format=3, version="1.4")
        header.scales, header.offsets = np.full(3, 0.001), np.array([E0_M, N0_M, 0.0])
        header.add_crs(CRS)
        las = laspy.LasData(header)
        las.x, las.y, las.z = x.ravel(), y.ravel(), np.full(x.size, Z_PLANE_M)
        las.write(flight / "cloud.las")
        name = "cloud.las"
    (flight / "flight.yaml").write_text(
        "crs: EPSG:32652\n"
        "camera: {model: PINHOLE, width_px: 400, height_px: 300, fx_px: 400, fy_px: 400,"
        " cx_px: 199.5, cy_px: 149.5}\n"
        "nav: {sigma_position_m: 1, sigma_attitude_deg: 1}\n"
        f"lidar: {name}\n")
    summary = orthorectify_run(out, options=OrthoOptions(pixel_m=0.1), progress=False)
    assert summary.warnings == ()
    assert summary.dsm_source == str(flight / name if lidar == "dsm" else out / "dsm.tif")
    mosaic_matches_texture(out / "mosaic.tif")


def test_ortho_run_skips_a_missing_image_with_a_warning(tmp_path: Path) -> None:
    out = write_run(tmp_path, missing="img_0001")
    summary = orthorectify_run(out, dsm_path=write_scene_dsm(tmp_path / "d.tif"),
                               options=OrthoOptions(pixel_m=0.1), progress=False)
    assert summary.skipped == ("img_0001",)
    assert any("img_0001" in w for w in summary.warnings)
    assert not (out / "ortho" / "img_0001.tif").exists()


def test_ortho_run_errors(tmp_path: Path) -> None:
    out = write_run(tmp_path / "a", with_images=False)
    with pytest.raises(InputDataError, match="no images"):
        orthorectify_run(out, progress=False)
    out = write_run(tmp_path / "b")
    with pytest.raises(InputDataError, match="reference"):
        orthorectify_run(out, eop_source="reference", progress=False)
    far = tmp_path / "far_dsm.tif"
    dsm = Scene(a=Z_PLANE_M).dsm(cell_m=1.0)
    shifted = rasterio.transform.from_origin(E0_M + 5000, N0_M + 60, 1.0, 1.0)  # 5 km east
    write_cog(far, dsm.heights_m[None], transform=shifted, crs=CRS, nodata=DSM_NODATA)
    with pytest.raises(InputDataError, match="no image could be orthorectified.*does not cover"):
        orthorectify_run(out, dsm_path=far, progress=False)
    assert not (out / "mosaic.tif").exists()


def test_ortho_run_in_another_crs(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    summary = orthorectify_run(out, dsm_path=write_scene_dsm(tmp_path / "d.tif"),
                               options=OrthoOptions(pixel_m=0.2), out_crs="EPSG:4326",
                               progress=False)
    assert summary.crs == "WGS 84"
    lon, lat = pyproj.Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(
        E0_M, N0_M)
    for path in (out / "mosaic.tif", Path(summary.images[0].path or "")):
        assert cog_problems(path) == ()
        with rasterio.open(path) as src:
            assert src.crs.to_epsg() == 4326
            west, south, east, north = src.bounds
            assert west < lon < east and south < lat < north
    with pytest.raises(ConfigError, match="--crs"):
        orthorectify_run(out, out_crs="EPSG:0", progress=False)


def test_cli_ortho(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    options = tmp_path / "opts.yaml"
    options.write_text("ortho:\n  pixel_m: 0.2\nmosaic:\n  feather_px: 4\n")
    result = CliRunner().invoke(app, ["ortho", str(out), "--dsm",
                                      str(write_scene_dsm(tmp_path / "d.tif")), "--options",
                                      str(options), "--no-progress"])
    assert result.exit_code == 0, result.output
    with rasterio.open(out / "mosaic.tif") as src:
        assert src.transform.a == 0.2
    bad = CliRunner().invoke(app, ["ortho", str(out), "--eop", "colmap"])
    assert bad.exit_code == 2 and "--eop" in bad.output
    options.write_text("ortho:\n  pixel_mm: 0.2\n")
    bad = CliRunner().invoke(app, ["ortho", str(out), "--options", str(options)])
    assert bad.exit_code == 2 and "ortho.pixel_mm: unknown key" in bad.output
