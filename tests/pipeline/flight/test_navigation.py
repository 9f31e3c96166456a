"""pipeline.flight.image_metadata and pipeline.flight.navigation: EXIF/XMP reading, CRS, attitude
-> OPK."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyproj
import pytest
from PIL import ExifTags, Image

from pipeline.flight.image_metadata import read_image_metadata, require_position
from pipeline.flight.navigation import (
    BoresightConfig,
    GeodeticToProjected,
    grid_convergence_rad,
    opk_from_attitude,
    read_image_folder_nav,
    resolve_working_crs,
    utm_epsg,
    world_from_cam,
)
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import rotation_matrix

#: Exactness of closed-form rotations (radians / unit vectors).
ANGLE_TOL_RAD = 1e-12
#: Agreement of our grid convergence sign check with a finite-difference azimuth (radians).
CONVERGENCE_TOL_RAD = 1e-6
NADIR = BoresightConfig().R_body_from_cam()
EAST, NORTH, UP = np.eye(3)
#: UTM 17N: central meridian 81 W.
UTM17N = pyproj.CRS.from_epsg(32617)
CM_17_DEG = -81.0

SENSEFLY_XMP = """<x:xmpmeta xmlns:x='adobe:ns:meta/'>
<rdf:RDF xmlns:rdf='http://www.w3.org/1999/02/22-rdf-syntax-ns#'>
 <rdf:Description rdf:about='' xmlns:sensefly='http://ns.sensefly.com/sensefly/1.0/'>
  <sensefly:Heading>61.5</sensefly:Heading>
  <sensefly:PitchAngle>-0.25</sensefly:PitchAngle>
  <sensefly:RollAngle>-1.5</sensefly:RollAngle>
  <sensefly:UTCTime>2013-06-04T17:39:35</sensefly:UTCTime>
 </rdf:Description>
</rdf:RDF>
</x:xmpmeta>"""

DJI_XMP = """<x:xmpmeta xmlns:x="adobe:ns:meta/">
<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">
 <rdf:Description rdf:about="" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"
   drone-dji:GimbalRollDegree="+0.00" drone-dji:GimbalYawDegree="-12.30"
   drone-dji:GimbalPitchDegree="-89.90" drone-dji:FlightRollDegree="+1.00"
   drone-dji:FlightYawDegree="-10.00" drone-dji:FlightPitchDegree="-2.00"/>
</rdf:RDF>
</x:xmpmeta>"""


def _rational_dms(deg: float) -> tuple[float, float, float]:
    d = math.floor(deg)
    m = math.floor((deg - d) * 60.0)
    return (float(d), float(m), (deg - d - m / 60.0) * 3600.0)


def write_jpeg(path: Path, *, lat: float | None = 41.0351924, lon: float = -83.3065655,
               alt: float = 285.12, alt_below: bool = False, xmp: str | None = SENSEFLY_XMP,
               size: tuple[int, int] = (64, 48), make: str = "Canon",
               gps_time: bool = False) -> Path:
    """A small JPEG with EXIF GPS and optional XMP, written by Pillow."""
    exif = Image.Exif()
    exif[ExifTags.Base.Make] = make
    exif[ExifTags.Base.Model] = "Test Camera"
    exif_ifd = exif.get_ifd(ExifTags.IFD.Exif)
    exif_ifd[ExifTags.Base.DateTimeOriginal] = "2013:06:04 13:39:01"
    exif_ifd[ExifTags.Base.FocalLength] = 4.3
    if lat is not None:
        gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
        gps[ExifTags.GPS.GPSLatitudeRef] = "N" if lat >= 0 else "S"
        gps[ExifTags.GPS.GPSLatitude] = _rational_dms(abs(lat))
        gps[ExifTags.GPS.GPSLongitudeRef] = "E" if lon >= 0 else "W"
        gps[ExifTags.GPS.GPSLongitude] = _rational_dms(abs(lon))
        gps[ExifTags.GPS.GPSAltitudeRef] = 1 if alt_below else 0
        gps[ExifTags.GPS.GPSAltitude] = alt
        if gps_time:
            gps[ExifTags.GPS.GPSDateStamp] = "2013:06:04"
            gps[ExifTags.GPS.GPSTimeStamp] = (17.0, 39.0, 36.5)
    kwargs = {"xmp": xmp.encode()} if xmp is not None else {}
    Image.new("RGB", size, (90, 120, 60)).save(path, "JPEG", exif=exif, **kwargs)
    return path


# --------------------------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------------------------


def test_reads_exif_gps_and_sensefly_xmp(tmp_path: Path) -> None:
    meta = read_image_metadata(write_jpeg(tmp_path / "a.jpg"))
    assert (meta.width_px, meta.height_px) == (64, 48)
    assert meta.lat_deg == pytest.approx(41.0351924, abs=1e-9)
    assert meta.lon_deg == pytest.approx(-83.3065655, abs=1e-9)
    assert meta.h_m == pytest.approx(285.12)
    assert meta.height_kind == "ellipsoidal"
    assert (meta.roll_deg, meta.pitch_deg, meta.yaw_deg) == (-1.5, -0.25, 61.5)
    assert (meta.attitude_frame, meta.attitude_source) == ("body", "sensefly")
    assert meta.time_source == "xmp-utc"
    assert meta.time_s == pytest.approx(1370367575.0)  # 2013-06-04T17:39:35Z
    assert meta.focal_mm == pytest.approx(4.3)
    assert meta.make == "Canon"


def test_gps_time_wins_and_altitude_ref_below(tmp_path: Path) -> None:
    meta = read_image_metadata(write_jpeg(tmp_path / "a.jpg", alt=12.0, alt_below=True,
                                          gps_time=True, lat=-33.5, lon=151.2))
    assert meta.h_m == pytest.approx(-12.0)
    assert meta.lat_deg == pytest.approx(-33.5) and meta.lon_deg == pytest.approx(151.2)
    assert meta.time_source == "gps-utc"
    assert meta.time_s == pytest.approx(1370367576.5)


def test_dji_gimbal_attitude_and_orthometric_height(tmp_path: Path) -> None:
    meta = read_image_metadata(write_jpeg(tmp_path / "d.jpg", xmp=DJI_XMP, make="DJI"))
    assert (meta.roll_deg, meta.pitch_deg, meta.yaw_deg) == (0.0, -89.9, -12.3)
    assert (meta.attitude_frame, meta.attitude_source) == ("gimbal", "dji-gimbal")
    assert meta.height_kind == "orthometric"
    assert meta.time_source == "camera-clock"


def test_no_xmp_no_attitude_unknown_height(tmp_path: Path) -> None:
    meta = read_image_metadata(write_jpeg(tmp_path / "p.jpg", xmp=None, make="Sony"))
    assert meta.attitude_source is None and not meta.has_attitude
    assert meta.height_kind == "unknown"


def test_no_gps_names_file_and_found_tags(tmp_path: Path) -> None:
    meta = read_image_metadata(write_jpeg(tmp_path / "IMG_0460.JPG", lat=None, xmp=None))
    with pytest.raises(InputDataError, match=r"IMG_0460.JPG: no GPS position in EXIF "
                       r"\(found: Make, Model, time, FocalLength\)"):
        require_position(meta)


@pytest.mark.parametrize("keep_bytes", [1, 20, 300, -200])
def test_truncated_jpeg_is_input_data_error(tmp_path: Path, keep_bytes: int) -> None:
    data = write_jpeg(tmp_path / "full.jpg", size=(256, 192)).read_bytes()
    bad = tmp_path / "cut.jpg"
    bad.write_bytes(data[:keep_bytes])
    with pytest.raises(InputDataError, match="cut.jpg"):
        read_image_metadata(bad)


def test_not_an_image_and_bad_xmp(tmp_path: Path) -> None:
    text = tmp_path / "t.jpg"
    text.write_text("hello", encoding="utf-8")
    with pytest.raises(InputDataError, match="t.jpg"):
        read_image_metadata(text)
    bad = write_jpeg(tmp_path / "x.jpg", xmp=SENSEFLY_XMP.replace("</sensefly:Heading>", ""))
    with pytest.raises(InputDataError, match="x.jpg: malformed XMP"):
        read_image_metadata(bad)


# --------------------------------------------------------------------------------------------
# CRS and heights
# --------------------------------------------------------------------------------------------


def test_auto_crs_is_utm_zone_of_first_fix() -> None:
    assert resolve_working_crs("auto", -83.3, 41.0).to_epsg() == 32617
    assert resolve_working_crs("auto", 151.2, -33.9).to_epsg() == 32756
    assert utm_epsg(-180.0, 0.0) == 32601 and utm_epsg(179.9, 1.0) == 32660
    assert resolve_working_crs("EPSG:32617+5773", 0.0, 0.0).is_compound


@pytest.mark.parametrize("crs", ["EPSG:4326", "EPSG:2994", "EPSG:99999999"])
def test_unsuitable_crs_is_input_data_error(crs: str) -> None:
    with pytest.raises(InputDataError, match="flight.yaml: crs:"):
        resolve_working_crs(crs, -83.3, 41.0)


def test_ellipsoidal_heights_pass_unchanged_into_2d_utm() -> None:
    xyz = GeodeticToProjected(UTM17N)(np.array([CM_17_DEG]), np.array([0.0]),
                                      np.array([285.0]))
    # On the central meridian at the equator: false easting, zero northing.
    np.testing.assert_allclose(xyz, [[500000.0, 0.0, 285.0]], rtol=0, atol=1e-6)


def test_geoid_heights_need_the_grid() -> None:
    """EGM96 heights: converted when PROJ has the grid, else a ConfigError naming it."""
    crs = pyproj.CRS.from_user_input("EPSG:32617+5773")
    try:
        convert = GeodeticToProjected(crs, "ellipsoidal")
    except ConfigError as err:
        assert "egm96" in str(err).lower()
        return
    z = convert(np.array([-83.3]), np.array([41.03]), np.array([285.0]))[0, 2]
    assert 310.0 < z < 325.0  # geoid ~33 m below the ellipsoid in Ohio


# --------------------------------------------------------------------------------------------
# Attitude
# --------------------------------------------------------------------------------------------


def test_level_north_nadir_is_zero() -> None:
    np.testing.assert_allclose(opk_from_attitude(0.0, 0.0, 0.0, NADIR, 0.0), [0.0, 0.0, 0.0],
                               atol=ANGLE_TOL_RAD)


def test_heading_east_turns_image_top_east() -> None:
    opk = opk_from_attitude(0.0, 0.0, math.pi / 2, NADIR, 0.0)
    np.testing.assert_allclose(opk, [0.0, 0.0, -math.pi / 2], atol=ANGLE_TOL_RAD)
    R = rotation_matrix(*opk)
    np.testing.assert_allclose(R[:, 1], EAST, atol=ANGLE_TOL_RAD)   # image top
    np.testing.assert_allclose(R[:, 0], -NORTH, atol=ANGLE_TOL_RAD)  # image right = south


def test_roll_tilts_view_to_right_wing_pitch_tilts_forward() -> None:
    small = math.radians(5.0)
    view_roll = -world_from_cam(small, 0.0, 0.0, NADIR, 0.0)[:, 2]
    view_pitch = -world_from_cam(0.0, small, 0.0, NADIR, 0.0)[:, 2]
    # Heading north: right wing = east. Right wing down (roll +) tilts the belly axis left,
    # i.e. west; nose up (pitch +) tilts it forward (north).
    np.testing.assert_allclose(view_roll, [-math.sin(small), 0.0, -math.cos(small)],
                               atol=ANGLE_TOL_RAD)
    np.testing.assert_allclose(view_pitch, [0.0, math.sin(small), -math.cos(small)],
                               atol=ANGLE_TOL_RAD)
    # seqat's angles reproduce the same rotation.
    R = world_from_cam(small, small, 0.3, NADIR, 0.0)
    np.testing.assert_allclose(rotation_matrix(*opk_from_attitude(small, small, 0.3, NADIR, 0.0)),
                               R, atol=ANGLE_TOL_RAD)


def test_grid_convergence_sign_east_of_central_meridian() -> None:
    lon, lat = CM_17_DEG + 1.0, 41.0
    gamma = grid_convergence_rad(UTM17N, lon, lat)
    # Grid azimuth of true north from two projected points one arc-second apart.
    t = pyproj.Transformer.from_crs("EPSG:4326", UTM17N, always_xy=True)
    (x0, x1), (y0, y1) = t.transform([lon, lon], [lat, lat + 1.0 / 3600.0])
    true_north_grid_azimuth = math.atan2(x1 - x0, y1 - y0)
    assert gamma > 0.0
    assert true_north_grid_azimuth == pytest.approx(-gamma, abs=CONVERGENCE_TOL_RAD)
    assert math.degrees(gamma) == pytest.approx(math.sin(math.radians(lat)), rel=0.01)
    # Heading true north: image top on the meridian, turned counter-clockwise by gamma.
    opk = opk_from_attitude(0.0, 0.0, 0.0, NADIR, gamma)
    np.testing.assert_allclose(opk, [0.0, 0.0, gamma], atol=ANGLE_TOL_RAD)
    top = rotation_matrix(*opk)[:, 1]
    assert math.atan2(top[0], top[1]) == pytest.approx(true_north_grid_azimuth,
                                                       abs=CONVERGENCE_TOL_RAD)
    assert grid_convergence_rad(UTM17N, CM_17_DEG, lat) == pytest.approx(0.0, abs=1e-12)


def test_gimbal_nadir_matches_body_nadir() -> None:
    from pipeline.flight.navigation import mount_for

    yaw = math.radians(30.0)
    gimbal = world_from_cam(0.0, -math.pi / 2, yaw, mount_for("gimbal", BoresightConfig()), 0.0)
    body = world_from_cam(0.0, 0.0, yaw, NADIR, 0.0)
    np.testing.assert_allclose(gimbal, body, atol=ANGLE_TOL_RAD)


def test_boresight_misalignment_composes() -> None:
    tilted = BoresightConfig(yaw_deg=90.0).R_body_from_cam()
    # A camera yawed 90 deg on a north-heading aircraft looks like the aircraft heading east.
    np.testing.assert_allclose(world_from_cam(0.0, 0.0, 0.0, tilted, 0.0),
                               world_from_cam(0.0, 0.0, math.pi / 2, NADIR, 0.0),
                               atol=ANGLE_TOL_RAD)


# --------------------------------------------------------------------------------------------
# Image folders
# --------------------------------------------------------------------------------------------


def test_folder_warnings_and_table(tmp_path: Path) -> None:
    folder = tmp_path / "imgs"
    folder.mkdir()
    write_jpeg(folder / "b.jpg", lat=41.0352, size=(64, 48))
    later = SENSEFLY_XMP.replace("17:39:35", "17:39:39")
    write_jpeg(folder / "a.jpg", lat=41.0354, xmp=later, size=(32, 24))
    nav = read_image_folder_nav(folder)
    assert nav.crs.to_epsg() == 32617
    assert [r.image for r in nav.records] == ["b", "a"]  # time order, not name order
    # sizes are the camera's business (pipeline.flight.folder), not the navigation's
    assert not any("size" in w for w in nav.warnings)
    table = nav.to_nav_table()
    assert table.eop.shape == (2, 6)
    assert table.eop[1, 1] - table.eop[0, 1] == pytest.approx(22.2, abs=0.5)  # 0.0002 deg lat


def test_folder_without_gps_or_images(tmp_path: Path) -> None:
    folder = tmp_path / "imgs"
    folder.mkdir()
    with pytest.raises(InputDataError, match="0 usable JPEG image"):
        read_image_folder_nav(folder)
    write_jpeg(folder / "a.jpg")
    write_jpeg(folder / "IMG_0460.JPG", lat=None, xmp=None)
    with pytest.raises(InputDataError, match="IMG_0460.JPG: no GPS position"):
        read_image_folder_nav(folder)
    # skip_bad leaves the image out and says why; one usable image is still too few
    with pytest.raises(InputDataError, match=r"1 usable JPEG image.*of 2.* \(left out: "
                                             r"IMG_0460.JPG: no GPS position"):
        read_image_folder_nav(folder, skip_bad=True)
    later = SENSEFLY_XMP.replace("17:39:35", "17:39:39")
    write_jpeg(folder / "c.jpg", lat=41.0354, xmp=later)
    nav = read_image_folder_nav(folder, skip_bad=True)
    assert [r.image for r in nav.records] == ["a", "c"]
    assert len(nav.skipped) == 1
    assert nav.skipped[0][0] == "IMG_0460"
    assert nav.skipped[0][1].startswith("IMG_0460.JPG: no GPS position in EXIF")


@pytest.mark.shared
def test_seneca_images(shared_data: Path) -> None:
    """The shared Seneca folder: 70 images, IMG_0446 to IMG_0515 (IMG_0460-0494 before)."""
    nav = read_image_folder_nav(shared_data / "seneca" / "images")
    assert nav.crs.to_epsg() == 32617
    ids = [r.image for r in nav.records]
    assert ids == [f"IMG_{n:04d}" for n in range(446, 516)] and nav.skipped == ()
    # IMG_0446 is 3240 x 2430 px, the other 69 images 3600 x 2700 px (same aspect ratio):
    # sizes are checked against the camera when the images are read, not here
    assert nav.warnings == ()
    assert all(r.kappa_rad is not None for r in nav.records)
    xyz = np.array([[r.x_m, r.y_m, r.z_m] for r in nav.records])
    assert np.all((xyz[:, 0] > 300000) & (xyz[:, 0] < 320000))  # west of the 81 W meridian
    assert np.all((xyz[:, 1] > 4.54e6) & (xyz[:, 1] < 4.55e6))
    steps_m = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
    assert 25.0 < np.median(steps_m) < 35.0
    assert np.mean((steps_m > 25.0) & (steps_m < 37.0)) > 0.55  # turns make the rest longer
    yaw_deg = np.array([r.metadata.yaw_deg for r in nav.records]) % 360.0
    strips = ((yaw_deg > 20) & (yaw_deg < 90)) | ((yaw_deg > 200) & (yaw_deg < 270))
    last_leg = ids.index("IMG_0509")
    assert np.all(strips[:last_leg])  # NE / SW strips
    assert np.all((yaw_deg[last_leg:] > 120) & (yaw_deg[last_leg:] < 180))  # then SE
    # Kappa = -(yaw - gamma) for a near-level nadir camera (gamma < 0 west of the CM).
    r0 = nav.records[0]
    gamma = grid_convergence_rad(nav.crs, r0.metadata.lon_deg, r0.metadata.lat_deg)
    assert gamma < 0.0
    assert math.degrees(r0.kappa_rad) == pytest.approx(-(70.06 - math.degrees(gamma)), abs=2.0)
