"""Exports of a run for other tools (docs/formats.md, *Exports*): shots.geojson, the OPK table,
the tie points as LAZ; each read back with the tools users have (json + pyproj, csv, laspy)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
from scipy.spatial.transform import Rotation

from pipeline.common.tables import EopTable
from pipeline.run.exports import (
    CAMERAS_OPK_CSV,
    CAMERAS_OPK_PRJ,
    OPK_COLUMNS,
    SHOTS_GEOJSON,
    TIE_POINTS_LAZ,
    format_shots_geojson,
)
from pipeline.run.store import read_run
from seqat.cvframe import eop_from_cv_pose

#: Round trip through WGS 84 and back: well below a millimetre.
ROUND_TRIP_M = 1e-3


def read_shots(path: Path) -> dict[str, dict]:
    doc = json.loads(path.read_text())
    assert doc["type"] == "FeatureCollection" and "crs" not in doc  # RFC 7946: no crs member
    return {f["properties"]["image"]: f for f in doc["features"]}


def test_shots_geojson_round_trips_to_the_run_crs(strip_run: Path) -> None:
    run = read_run(strip_run)
    shots = read_shots(strip_run / SHOTS_GEOJSON)
    assert list(shots) == list(run.eop.image_ids)
    lon_lat_h = np.array([shots[i]["geometry"]["coordinates"] for i in run.eop.image_ids])
    assert lon_lat_h.shape == (len(run.eop), 3)
    assert np.all(np.abs(lon_lat_h[:, 0]) <= 180) and np.all(np.abs(lon_lat_h[:, 1]) <= 90)
    back = pyproj.Transformer.from_crs("EPSG:4979", run.crs.to_3d(), always_xy=True)
    xyz = np.column_stack(back.transform(*lon_lat_h.T))
    np.testing.assert_allclose(xyz, run.eop.eop[:, :3], rtol=0, atol=ROUND_TRIP_M)
    # ODM's properties: translation (run CRS), rotation (OpenSfM: world -> OpenCV camera).
    first = shots[run.eop.image_ids[0]]["properties"]
    assert {"filename", "focal", "width", "height", "translation", "rotation"} <= set(first)
    assert first["focal"] == pytest.approx(run.camera.fx_px / max(run.camera.width_px,
                                                                    run.camera.height_px))
    assert first["translation_crs"] == "EPSG:32652"
    for k, iid in enumerate(run.eop.image_ids):
        p = shots[iid]["properties"]
        R_cv = Rotation.from_rotvec(p["rotation"]).as_matrix()
        t = -R_cv @ np.asarray(p["translation"])
        back_eop = eop_from_cv_pose(R_cv[None], t[None])[0]
        np.testing.assert_allclose(back_eop[:3], run.eop.eop[k, :3], rtol=0, atol=1e-6)
        np.testing.assert_allclose(back_eop[3:], run.eop.eop[k, 3:], rtol=0, atol=1e-12)
        np.testing.assert_allclose([p["omega_deg"], p["phi_deg"], p["kappa_deg"]],
                                   np.degrees(run.eop.eop[k, 3:]), rtol=0, atol=1e-12)
        assert p["sx_m"] == run.eop.sigma[k, 0]
        assert p["skappa_deg"] == pytest.approx(np.degrees(run.eop.sigma[k, 5]), rel=1e-15)
        assert p["filename"] == iid  # an observations flight has no image files


def test_exports_write_null_for_nan_and_leave_out_points_without_position() -> None:
    from pipeline.common.tables import PointTable
    from pipeline.flight.schema import CameraConfig
    from pipeline.run.exports import tie_points_laz

    eops = EopTable(image_ids=("a", "b"), eop=np.array([
        [500000.0, 4100000.0, 300.0, 0.1, 0.0, 0.2], [np.nan, 4100000.0, 300.0, 0.1, 0.0, 0.2]]),
                    sigma=np.full((2, 6), np.nan))
    camera = CameraConfig(model="PINHOLE", width_px=100, height_px=80, fx_px=90.0, fy_px=90.0,
                          cx_px=49.5, cy_px=39.5)
    crs = pyproj.CRS.from_epsg(32652)
    features = json.loads(format_shots_geojson(eops, crs, camera, {"a": "a.jpg"}))["features"]
    assert features[0]["properties"]["sx_m"] is None
    assert features[0]["properties"]["filename"] == "a.jpg"
    assert features[1]["geometry"] is None and features[1]["properties"]["translation"][0] is None
    points = PointTable(point_ids=("p", "q"), xyz_m=np.array([[500000.0, 4100000.0, 10.0],
                                                             [np.nan, 0.0, 0.0]]),
                        sigma_m=np.full((2, 3), 0.1), n_obs=np.array([3, 2]))
    import io

    las = laspy.read(io.BytesIO(tie_points_laz(points, crs)))
    assert len(las.points) == 1 and las["n_obs"][0] == 3


def test_tie_points_laz_holds_a_point_thousands_of_km_off() -> None:
    """A wild estimate (a blunder's intersection 5000 km off) must not fail the export
    (laspy: "Values given do not fit after applying offset and scale"): that axis gets a
    coarser scale, every point reads back within half of it; the others keep millimetres."""
    import io

    from pipeline.common.tables import PointTable
    from pipeline.run.exports import LAZ_SCALE_M, tie_points_laz

    xyz = np.array([[500000.123, 4100000.456, 10.789], [500010.0, 4100020.0, 12.0],
                    [500005.0, 9100000.0, 11.0]])
    points = PointTable(point_ids=("a", "b", "c"), xyz_m=xyz, sigma_m=np.full((3, 3), 0.1),
                        n_obs=np.array([3, 2, 2]))
    las = laspy.read(io.BytesIO(tie_points_laz(points, pyproj.CRS.from_epsg(32610))))
    scales = np.asarray(las.header.scales)
    assert scales[0] == LAZ_SCALE_M and scales[2] == LAZ_SCALE_M and scales[1] == 0.01
    got = np.column_stack([las.x, las.y, las.z])
    assert np.all(np.abs(got - xyz) <= scales / 2 + 1e-9)


def test_opk_table_round_trips_against_eop_csv(strip_run: Path) -> None:
    run = read_run(strip_run)
    lines = (strip_run / CAMERAS_OPK_CSV).read_text().splitlines()
    assert lines[0].startswith("# " + ",".join(OPK_COLUMNS) + "; CRS EPSG:32652 ")
    assert not any(line.startswith("#") for line in lines[1:])  # Pix4D: one comment line
    rows = list(csv.reader(lines[1:]))
    assert [r[0] for r in rows] == list(run.eop.image_ids)
    values = np.array([[float(v) for v in r[1:]] for r in rows])
    assert values.shape == (len(run.eop), 8)
    np.testing.assert_array_equal(values[:, :3], run.eop.eop[:, :3])
    np.testing.assert_allclose(np.radians(values[:, 3:6]), run.eop.eop[:, 3:], rtol=0,
                               atol=1e-15)
    s = run.eop.sigma
    np.testing.assert_allclose(values[:, 6], np.sqrt((s[:, 0] ** 2 + s[:, 1] ** 2) / 2))
    np.testing.assert_array_equal(values[:, 7], s[:, 2])
    prj = pyproj.CRS.from_user_input((strip_run / CAMERAS_OPK_PRJ).read_text())
    assert prj.equals(run.crs, ignore_axis_order=True)


def test_tie_points_laz_reads_back_with_crs_and_sigmas(strip_run: Path) -> None:
    run = read_run(strip_run)
    las = laspy.read(strip_run / TIE_POINTS_LAZ)
    assert las.header.are_points_compressed and las.header.version.minor == 4
    assert len(las.points) == len(run.points) > 0
    xyz = np.column_stack([las.x, las.y, las.z])
    np.testing.assert_allclose(xyz, run.points.xyz_m, rtol=0, atol=0.0005 + 1e-9)
    assert las.header.parse_crs().equals(run.crs, ignore_axis_order=True)
    np.testing.assert_allclose(las["sz_m"], run.points.sigma_m[:, 2].astype(np.float32))
    np.testing.assert_array_equal(las["n_obs"], run.points.n_obs)


def test_image_flight_exports_and_colmap_model_carry_file_names(
        autzen_run: Path, tmp_path: Path) -> None:
    """The reference model's images are the image files: pycolmap.undistort_images finds
    them (it failed on ``img_0001`` without its extension)."""
    import pycolmap

    from pipeline.reference.stage import COLMAP_MODEL_DIR, run_reference

    run = read_run(autzen_run)
    shots = read_shots(autzen_run / SHOTS_GEOJSON)
    assert shots["img_0001"]["properties"]["filename"] == "img_0001.jpg"
    assert (autzen_run / CAMERAS_OPK_CSV).read_text().splitlines()[1].startswith(
        "img_0001.jpg,")
    out = tmp_path / "run"
    shutil.copytree(autzen_run, out)
    run_reference(out)
    model = out / "reference" / COLMAP_MODEL_DIR
    rec = pycolmap.Reconstruction(str(model))
    names = sorted(image.name for image in rec.images.values())
    assert names and all((run.images_dir / n).is_file() for n in names)
    assert names[0] == "img_0001.jpg"
    assert "img_0001.jpg" in (model / "images.txt").read_text()
    dense = tmp_path / "dense"
    pycolmap.undistort_images(str(dense), str(model), str(run.images_dir))
    undistorted = sorted(p.name for p in (dense / "images").iterdir())
    assert undistorted == names
