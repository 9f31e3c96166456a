"""Ground control files (pipeline/flight/gcp.py): ODM ``gcp_list.txt``, Metashape markers XML
(+ reference CSV), CRS transforms, pixel conventions, the frames they go into, bad input."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pyproj
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.flight.folder import read_flight, with_ground_control
from pipeline.flight.gcp import (
    ImageFrame,
    read_metashape_markers,
    read_odm_gcp_list,
)
from pipeline.run.sources import ObservationSource
from seqat.errors import InputDataError

from ..sample_runs import STRIP

UTM10 = pyproj.CRS.from_epsg(32610)
IDS = ("img_0001", "img_0002", "img_0003")
P1 = (494239.78, 4877550.08, 124.65)
P2 = (494269.91, 4877562.33, 134.21)


def frame(size: tuple[int, int] = (640, 480), file_size: tuple[int, int] | None = None
          ) -> ImageFrame:
    return ImageFrame(ids=IDS, names={f"{i}.jpg": i for i in IDS}, camera_size=size,
                      file_size=lambda _: file_size or size)


def write(tmp_path: Path, text: str, name: str = "gcp_list.txt") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def odm(header: str, rows: list[str]) -> str:
    return "\n".join([header, *rows]) + "\n"


def test_odm_list_in_the_run_crs(tmp_path: Path) -> None:
    text = odm("# survey 2026\nEPSG:32610", [
        f"{P1[0]} {P1[1]} {P1[2]} 547.6 203.8 img_0001.jpg g1 extra",
        f"{P1[0]}\t{P1[1]}\t{P1[2]}\t500.0\t100.0\timg_0002 g1",
        "",
        f"{P2[0]} {P2[1]} {P2[2]} 10 20 img_0001.jpg g2",
        f"{P2[0]} {P2[1]} {P2[2]} 11 21 other.jpg g2"])
    c = read_odm_gcp_list(write(tmp_path, text), UTM10, frame(),
                          sigma_horizontal_m=0.01, sigma_vertical_m=0.05)
    assert [p.point_id for p in c.points] == ["gcp:g1", "gcp:g2"]
    np.testing.assert_array_equal(c.points[0].xyz_m, P1)  # same CRS: exact
    np.testing.assert_array_equal(c.points[0].sigma_m, [0.01, 0.01, 0.05])
    ids, uv = c.for_image("img_0001")
    assert ids == ("gcp:g1", "gcp:g2")
    np.testing.assert_array_equal(uv, [[547.6, 203.8], [10, 20]])  # OpenSfM: OpenCV pixels
    assert c.for_image("img_0002")[0] == ("gcp:g1",)
    assert c.n_observations == 3
    assert "other.jpg" in c.warnings[0]  # an image not in the flight: left out, said


def test_odm_unnamed_points_by_coordinates_and_nan_height(tmp_path: Path) -> None:
    text = odm("WGS84 UTM 10N", [f"{P1[0]} {P1[1]} {P1[2]} 1 2 img_0001.jpg",
                                 f"{P1[0]} {P1[1]} {P1[2]} 3 4 img_0002.jpg",
                                 f"{P2[0]} {P2[1]} NaN 5 6 img_0001.jpg"])
    c = read_odm_gcp_list(write(tmp_path, text), UTM10, frame())
    assert [p.name for p in c.points] == ["unnamed-1", "unnamed-2"]
    assert c.points[1].sigma_m[2] == np.inf and c.points[1].xyz_m[2] == pytest.approx(P1[2])


def test_crs_round_trip_geographic_and_proj_strings(tmp_path: Path) -> None:
    to_geo = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True)
    lon, lat = to_geo.transform(P1[0], P1[1])
    for header in ("EPSG:4326", "WGS84",
                   "+proj=utm +zone=10 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"):
        x, y = (lon, lat) if "proj=utm" not in header else P1[:2]
        c = read_odm_gcp_list(write(tmp_path, odm(header, [
            f"{x!r} {y!r} {P1[2]} 1 2 img_0001.jpg g"])), UTM10, frame())
        np.testing.assert_allclose(c.points[0].xyz_m, P1, rtol=0, atol=1e-6, err_msg=header)


def test_pixels_of_a_resized_file_scale_to_the_camera(tmp_path: Path) -> None:
    text = odm("EPSG:32610", [f"{P1[0]} {P1[1]} {P1[2]} 159.5 119.5 img_0001.jpg g"])
    c = read_odm_gcp_list(write(tmp_path, text), UTM10, frame((640, 480), (320, 240)))
    np.testing.assert_allclose(c.for_image("img_0001")[1], [[319.5, 239.5]])  # centre


def metashape_xml(reference: str = "") -> str:
    wkt = UTM10.to_wkt("WKT1_GDAL")
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="1.2.0"><chunk>
 <sensors><sensor id="0" label="cam" type="frame"><resolution width="640" height="480"/>
 </sensor></sensors>
 <cameras><camera id="0" label="img_0001.JPG" sensor_id="0"/>
  <group label="g"><camera id="1" label="img_0002" sensor_id="0"/></group></cameras>
 <markers>
  <marker id="5" label="point 1"><reference x="{P1[0]}" y="{P1[1]}" z="{P1[2]}"
     sx="0.01" sy="0.01" sz="0.02" enabled="true"/></marker>
  <marker id="6" label="chk"><reference x="{P2[0]}" y="{P2[1]}" z="{P2[2]}"
     enabled="false"/></marker>
 </markers>
 <frames><frame id="0"><markers>
  <marker marker_id="5">
   <location camera_id="0" pinned="true" x="100.5" y="200.5"/>
   <location camera_id="1" pinned="false" x="300" y="300"/>
  </marker>
  <marker marker_id="6"><location camera_id="1" pinned="true" x="5" y="5"/></marker>
 </markers></frame></frames>
 {reference or f"<reference>{wkt}</reference>"}
</chunk></document>
"""


def test_metashape_markers_xml(tmp_path: Path) -> None:
    path = write(tmp_path, metashape_xml(), "markers.xml")
    c = read_metashape_markers(path, UTM10, frame())
    assert [p.point_id for p in c.points] == ["gcp:point_1"]  # whitespace as _
    np.testing.assert_allclose(c.points[0].xyz_m, P1, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(c.points[0].sigma_m, [0.01, 0.01, 0.02])
    # pinned only; Metashape's (0.5, 0.5) pixel centre -> OpenCV's (0, 0)
    assert list(c.observations) == ["img_0001"]
    np.testing.assert_allclose(c.for_image("img_0001")[1], [[100.0, 200.0]])
    assert "chk" in c.warnings[0]  # disabled: Metashape's check point, not control


def test_metashape_reference_csv_replaces_coordinates(tmp_path: Path) -> None:
    path = write(tmp_path, metashape_xml(), "markers.xml")
    ref = write(tmp_path, "#Label,X,Y,Z,Accuracy\npoint 1,494000,4877000,100,0.05\n",
                "ref.csv")
    c = read_metashape_markers(path, UTM10, frame(), reference=ref)
    np.testing.assert_allclose(c.points[0].xyz_m, [494000, 4877000, 100])
    np.testing.assert_array_equal(c.points[0].sigma_m, [0.05, 0.05, 0.05])


@pytest.mark.parametrize(("row", "pattern"), [
    (f"{P1[0]} {P1[1]} 1 2 img_0001.jpg", r"gcp_list.txt:2: expected at least 6 fields"),
    (f"{P1[0]} {P1[1]} abc 1 2 img_0001.jpg g", r"gcp_list.txt:2: field 'geo_z': expected a "
                                                 r"finite number or NaN, got 'abc'"),
    (f"1e300 {P1[1]} 1 1 2 img_0001.jpg g", r"gcp_list.txt:2: field 'geo_x': '1e300' is not "
                                            r"plausible"),
    (f"{P1[0]} {P1[1]} 1 900 2 img_0001.jpg g", r"gcp_list.txt:2: field 'im_x': pixel "
                                                r"\(900, 2\) lies outside the 640 x 480 px"),
    (f"{P1[0]} {P1[1]} 1 9 2 img_0001.jpg g,h", r"gcp_list.txt:2: field 'gcp_name'"),
])
def test_bad_odm_lines_name_file_line_and_field(tmp_path: Path, row: str, pattern: str
                                                ) -> None:
    with pytest.raises(InputDataError, match=pattern):
        read_odm_gcp_list(write(tmp_path, odm("EPSG:32610", [row])), UTM10, frame())


def test_bad_odm_crs_and_repeated_points(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match=r"gcp_list.txt:1: CRS line: expected"):
        read_odm_gcp_list(write(tmp_path, odm("EPSG:99999999", [])), UTM10, frame())
    twice = [f"{P1[0]} {P1[1]} 1 1 2 img_0001.jpg g", f"{P1[0]} {P1[1]} 1 3 4 img_0001.jpg g"]
    with pytest.raises(InputDataError, match=r":3: GCP 'g' is observed twice in image "
                                             r"'img_0001' \(first at .*:2\)"):
        read_odm_gcp_list(write(tmp_path, odm("EPSG:32610", twice)), UTM10, frame())
    moved = [f"{P1[0]} {P1[1]} 1 1 2 img_0001.jpg g", f"{P1[0]} {P1[1]} 2 3 4 img_0002.jpg g"]
    with pytest.raises(InputDataError, match=r":3: field 'gcp_name': GCP 'g' has other "
                                             r"coordinates than at .*:2"):
        read_odm_gcp_list(write(tmp_path, odm("EPSG:32610", moved)), UTM10, frame())


def strip_gcp(tmp_path: Path, rows: list[str]) -> Path:
    """A GCP list on the strip_demo flight (its CRS, camera and image ids)."""
    crs = read_flight(STRIP).crs.to_string()
    return write(tmp_path, odm(crs, rows))


def test_gcp_observations_join_the_frames(tmp_path: Path) -> None:
    path = strip_gcp(tmp_path, ["500 600 10 1000 1000 img_0001 g1",
                                "500 600 10 1200.5 900 img_0002 g1"])
    flight = with_ground_control(read_flight(STRIP), path)
    frames = ObservationSource(flight).frames()
    first = next(frames)
    assert first.frame.point_ids[-1] == "gcp:g1"
    np.testing.assert_allclose(first.observed_px[-1], [1000, 1000])
    np.testing.assert_allclose(first.frame.uv_px[-1], [1000, 1000])  # PINHOLE: ideal = observed
    assert len(set(first.frame.point_ids)) == len(first.frame.point_ids)


def test_bad_gcp_file_through_the_cli_exits_2_with_one_line(tmp_path: Path) -> None:
    path = strip_gcp(tmp_path, ["500 600 ten 1000 1000 img_0001 g1"])
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", str(STRIP), "--out", str(out), "--gcp", str(path),
                                      "--no-progress"])
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and re.search(r"seqat: error: .*gcp_list.txt:2: field 'geo_z'",
                                         lines[0]), lines
    assert not out.exists()
    result = CliRunner().invoke(app, ["run", str(STRIP), "--out", str(out), "--gcp", str(path),
                                      "--gcp-sigma-m", "0,1"])
    assert result.exit_code == 2 and "--gcp-sigma-m" in result.stderr


def test_gcp_list_in_the_folder_is_found_and_gcp_option_replaces_it(tmp_path: Path) -> None:
    flight = tmp_path / "flight"
    flight.mkdir()
    for item in STRIP.iterdir():
        (flight / item.name).symlink_to(item)
    crs = read_flight(STRIP).crs.to_string()
    write(flight, odm(crs, ["500 600 10 1000 1000 img_0001 g1"]))  # auto-detected
    assert [p.name for p in read_flight(flight).control.points] == ["g1"]  # type: ignore[union-attr]
    write(flight, odm(crs, ["500 600 ten 1000 1000 img_0001 g1"]))  # broken, but replaced
    other = write(tmp_path, odm(crs, ["500 600 10 1000 1000 img_0002 g2"]), "other.txt")
    got = read_flight(flight, gcp_file=other, gcp_sigma_m=(0.5, 0.7)).control
    assert got is not None and [p.name for p in got.points] == ["g2"]
    np.testing.assert_array_equal(got.points[0].sigma_m, [0.5, 0.5, 0.7])


def test_metashape_pixels_of_another_sensor_resolution_scale(tmp_path: Path) -> None:
    path = write(tmp_path, metashape_xml().replace('width="640" height="480"',
                                                   'width="1280" height="960"'), "markers.xml")
    c = read_metashape_markers(path, UTM10, frame())
    # corner origin: (100.5, 200.5) of 1280 x 960 is (50.25, 100.25) of 640 x 480, - 0.5
    np.testing.assert_allclose(c.for_image("img_0001")[1], [[49.75, 99.75]])
