"""Reading flight folders: frames in acquisition order, and every kind of bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pyproj.exceptions import CRSError
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.folder import read_flight, read_truth
from seqat.errors import ConfigError, InputDataError, SeqatError
from seqat.geometry import rays_world
from seqat.simulate import SimulatedFlight

from ..sample_flight import FLIGHT_FILES, FlightMaker

#: Tolerance of values that went through a degrees <-> radians conversion (radians).
ANGLE_TOL_RAD = 1e-15


def test_frames_follow_nav_order_with_nav_sigmas(make_flight: FlightMaker) -> None:
    flight = read_flight(make_flight())
    assert flight.crs.to_epsg() == 32652
    assert flight.camera.f_px == 1000.0 and flight.camera.cx_px == 319.5
    frames = list(flight.frames())
    assert [f.image_id for f in frames] == ["img_1", "img_2", "img_3", "img_4"]
    assert [f.point_ids for f in frames] == [("p1", "p2"), ("p1", "p2", "p3"), (), ("p3", "p4")]
    np.testing.assert_array_equal(frames[0].uv_px, [[100.0, 200.0], [300.5, 250.25]])
    assert frames[2].uv_px.shape == (0, 2)  # an image without observations still has nav
    np.testing.assert_allclose(frames[0].nav_eop[:3], [500000.0, 4090000.0, 300.0], rtol=0,
                               atol=0)
    np.testing.assert_allclose(frames[0].nav_eop[3:], np.radians([0.5, -0.25, 90.0]), rtol=0,
                               atol=ANGLE_TOL_RAD)
    np.testing.assert_allclose(frames[1].nav_sigma, [0.3, 0.3, 0.3,
                                                     *np.radians([0.1, 0.1, 0.2])],
                               rtol=0, atol=ANGLE_TOL_RAD)
    assert all(f.sigma_px == 1.5 for f in frames)
    stats = flight.frames().validate()
    assert (stats.n_observations, stats.n_points, stats.n_images_observed) == (7, 4, 3)
    assert len(flight.frames()) == 4
    assert read_truth(flight.path) is None


def test_observations_are_streamed(make_flight: FlightMaker) -> None:
    """A bad row late in observations.csv surfaces only when the stream reaches it."""
    bad = FLIGHT_FILES["observations.csv"].replace("img_4,p4,10.0,11.0", "img_4,p4,10.0,oops")
    frames = iter(read_flight(make_flight(**{"observations.csv": bad})).frames())
    assert next(frames).image_id == "img_1"
    assert next(frames).image_id == "img_2"
    with pytest.raises(InputDataError, match=r"observations\.csv:8: field 'y_px'"):
        list(frames)


# (file, text to replace, replacement, exception type, expected message fragment)
BAD_INPUTS = [
    ("nav.csv", "500005.0", "abc", InputDataError,
     "nav.csv:3: field 'x_m': expected a finite number, got 'abc'"),
    ("nav.csv", "300.2", "inf", InputDataError,  # nan / empty: a GNSS dropout (test_dropout)
     "nav.csv:3: field 'z_m': expected a finite number, got 'inf'"),
    ("nav.csv", "time_s", "time", InputDataError,
     "nav.csv:1: wrong columns (missing time_s; unexpected time)"),
    ("nav.csv", "img_2,0.5,500005.0,", "img_2,0.5,", InputDataError,
     "nav.csv:3: expected 8 fields"),
    ("nav.csv", "img_3,", "img_2,", InputDataError,
     "nav.csv:4: duplicate nav row for image 'img_2' (first at line 3)"),
    ("nav.csv", "img_3,1.0,", "img_3,0.25,", InputDataError,
     "nav.csv:4: nav out of time order: time_s 0.25 of image 'img_3' is not after 0.5"),
    ("nav.csv", FLIGHT_FILES["nav.csv"], "image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg\n"
     "img_1,0.0,500000.0,4090000.0,300.0,0.5,-0.25,90.0\n", InputDataError,
     "nav.csv: 1 image(s); at least 2 are needed"),
    ("nav.csv", FLIGHT_FILES["nav.csv"], "image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg\n"
     "img_1,0.0,500000.0,4090000.0,300.0,,,\nimg_2,0.5,500005.0,4090000.0,300.2,nan,nan,nan\n",
     InputDataError, "nav.csv: no row has an attitude (omega_deg, phi_deg, kappa_deg empty in "
     "every row); at least one is needed"),
    ("nav.csv", "img_1,0.0", "img 1,0.0", InputDataError,
     "nav.csv:2: field 'image': expected an id (non-empty, no spaces, commas or quotes), "
     "got 'img 1'"),
    ("observations.csv", "img_2,p1,80.0", "img_2,p1,inf", InputDataError,
     "observations.csv:4: field 'x_px': expected a finite number, got 'inf'"),
    ("observations.csv", "img_2,p1,", "img_9,p1,", InputDataError,
     "observations.csv:4: field 'image': unknown image 'img_9' (not in nav.csv)"),
    ("observations.csv", "img_2,p3,", "img_1,p3,", InputDataError,
     "observations.csv:6: rows of image 'img_1' are not contiguous (its earlier rows end at "
     "line 3)"),
    ("observations.csv", "img_1,p2,", "img_1,p1,", InputDataError,
     "observations.csv:3: duplicate observation of point 'p1' in image 'img_1' (first at "
     "line 2)"),
    ("observations.csv", "img_1,", "img_3,", InputDataError,
     "observations.csv:3: image 'img_1' comes after image 'img_3' but was acquired before it"),
    ("flight.yaml", "width_px: 640", "width_px: 64", InputDataError,  # mostly outside
     "observations.csv: 6 of 7 observations lie outside the image (first: "),
    ("observations.csv", "image,point,x_px,y_px", "image,point,u_px,v_px", InputDataError,
     "observations.csv:1: wrong columns (missing x_px, y_px; unexpected u_px, v_px)"),
    ("observations.csv", "img_4,p4,10.0,11.0", 'img_4,"p4,10.0,11.0', InputDataError,
     "observations.csv:8: malformed CSV"),
    ("flight.yaml", "EPSG:32652", "EPSG:99999999", InputDataError,
     "flight.yaml: crs: unknown CRS 'EPSG:99999999'"),
    ("flight.yaml", "EPSG:32652", "EPSG:4326", InputDataError,
     "flight.yaml: crs: 'EPSG:4326' (WGS 84) is not a projected CRS"),
    ("flight.yaml", "EPSG:32652", "EPSG:2992", InputDataError, "a metre CRS is needed"),
    ("flight.yaml", "frame: projected", "frame: geodetic", InputDataError,
     "nav.csv:1: wrong columns"),
    ("flight.yaml", "sigma_image_px: 1.5", "sigma_image_px: 1.5\nsigma_image: 2", ConfigError,
     "flight.yaml: sigma_image: unknown key"),
    ("flight.yaml", "observations: observations.csv", "observations: obs.csv", InputDataError,
     "obs.csv: no such file (observations in"),
    # k1 -3 where -0.3 was meant: the polynomial folds back before the corners (f 1000 px)
    ("flight.yaml", "model: PINHOLE", "model: OPENCV\n  k1: -3.0", ConfigError,
     "flight.yaml: camera: the distortion (k1 -3, k2 0, p1 0, p2 0, k3 0) folds back inside "
     "the 640 x 480 px image, 222 px from the principal point"),
]


def broken_flight(make_flight: FlightMaker, name: str, old: str, new: str) -> Path:
    text = FLIGHT_FILES[name]
    assert old in text, f"test case does not apply to {name}: {old!r}"
    return make_flight(**{name: text.replace(old, new, 1)})


@pytest.mark.parametrize(("name", "old", "new", "error", "message"), BAD_INPUTS)
def test_bad_input_raises_with_file_and_line(make_flight: FlightMaker, name: str, old: str,
                                             new: str, error: type[SeqatError],
                                             message: str) -> None:
    folder = broken_flight(make_flight, name, old, new)
    with pytest.raises(error) as info:
        read_flight(folder).frames().validate()
    text = str(info.value)
    assert text.startswith(str(folder)), text  # the message names the file by its path
    assert message in text
    if "unknown CRS" in message:
        assert isinstance(info.value.__cause__, CRSError)


@pytest.mark.parametrize(("name", "old", "new", "error", "message"), BAD_INPUTS)
def test_bad_input_exits_2_and_writes_nothing(make_flight: FlightMaker, tmp_path: Path,
                                              name: str, old: str, new: str,
                                              error: type[SeqatError], message: str) -> None:
    folder = broken_flight(make_flight, name, old, new)
    out = tmp_path / "out" / "run"
    result = CliRunner().invoke(app, ["run", str(folder), "--out", str(out), "--no-progress"])
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("seqat: error: ")
    assert message.split(": ", 1)[-1] in lines[0]
    assert not (tmp_path / "out").exists()


def test_missing_flight_folder(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="no such flight folder"):
        read_flight(tmp_path / "nowhere")
    with pytest.raises(InputDataError, match=r"flight\.yaml: no such file, and no JPEG images"):
        read_flight(tmp_path)


def test_flight_without_observations_or_images(make_flight: FlightMaker) -> None:
    text = FLIGHT_FILES["flight.yaml"].replace("observations: observations.csv\n", "")
    with pytest.raises(ConfigError, match=r"give observations: \(image points\) or images:"):
        read_flight(make_flight(**{"flight.yaml": text}))


def test_opencv_flight_frames_carry_observed_pixels_and_the_camera_the_distortion(
        make_flight: FlightMaker) -> None:
    """A fixed OPENCV camera: the frames carry the observed pixels (the image points'
    noise is in them: docs/architecture.md, *Distortion is in the model*) and seqat's camera
    the distortion; their rays are those of the undistorted (ideal) pixels through the
    pinhole camera."""
    text = FLIGHT_FILES["flight.yaml"].replace("PINHOLE", "OPENCV").replace(
        "cy_px: 239.5", "cy_px: 239.5\n  k1: -0.2\n  p1: 0.001")
    flight = read_flight(make_flight(**{"flight.yaml": text}))
    assert flight.calibration is None
    assert (flight.camera.k1, flight.camera.p1) == (-0.2, 0.001)
    frame = next(iter(flight.frames()))
    raw = np.array([[100.0, 200.0], [300.5, 250.25]])
    np.testing.assert_array_equal(frame.uv_px, raw)
    ideal = PixelCorrector(camera=flight.camera_config).ideal_pixels(raw)
    assert np.linalg.norm(ideal[0] - raw[0]) > 1.0  # the distortion moves them
    level = np.zeros((2, 6))
    np.testing.assert_allclose(rays_world(level, frame.uv_px, flight.camera),
                               rays_world(level, ideal, pinhole_camera(flight.camera_config)),
                               rtol=0, atol=1e-12)


def test_truth_of_simulated_flight(small_sim: SimulatedFlight, small_sim_dir: Path) -> None:
    truth = read_truth(small_sim_dir)
    assert truth is not None
    assert truth.eop.image_ids == small_sim.image_ids
    np.testing.assert_array_equal(truth.eop.eop[:, :3], small_sim.truth_eop[:, :3])
    np.testing.assert_allclose(truth.eop.eop[:, 3:], small_sim.truth_eop[:, 3:], rtol=0,
                               atol=ANGLE_TOL_RAD)
    assert truth.points.point_ids == small_sim.point_ids
    np.testing.assert_array_equal(truth.points.xyz_m, small_sim.truth_xyz)


@pytest.mark.shared
def test_real_feet_crs_is_rejected_with_its_name(shared_data: Path,
                                                 make_flight: FlightMaker) -> None:
    """The Autzen survey's WKT (Oregon Lambert, international feet) is not a metre CRS."""
    wkt = " ".join((shared_data / "autzen" / "autzen-srs.wkt").read_text().split())
    text = FLIGHT_FILES["flight.yaml"].replace("crs: EPSG:32652", f"crs: '{wkt}'")
    with pytest.raises(InputDataError, match=r"\(NAD_1983_HARN_Lambert_Conformal_Conic\) has "
                                             r"axes in foot; a metre CRS is needed"):
        read_flight(make_flight(**{"flight.yaml": text}))


@pytest.mark.parametrize(("k1", "k2", "folds"), [
    (-0.25, 0.06, False), (-0.08, 0.02, False), (0.5, 0.0, False),  # lenses
    (-0.3, 0.0, True),  # folds 281 px from the principal point, the corners at 400 px
    (-0.9, 0.06, True)])
def test_a_distortion_that_folds_inside_the_image_is_no_lens(k1: float, k2: float,
                                                             folds: bool) -> None:
    """Known answers at f 400 px, 640 x 480 px: k1 alone folds where 1 + 3 k1 r² = 0, at
    r_d = (2/3) / sqrt(-3 k1) normalised (281 px for k1 -0.3, inside the 400 px corners)."""
    from pipeline.flight.schema import CameraConfig

    cam = CameraConfig(model="OPENCV", width_px=640, height_px=480, fx_px=400.0, fy_px=400.0,
                       cx_px=319.5, cy_px=239.5, k1=k1, k2=k2)
    fold = cam.fold()
    assert (fold is not None) is folds
    if k1 == -0.3:
        assert fold is not None and "281 px from the principal point" in fold


def test_a_distortion_that_leaves_a_corner_without_a_ray_is_no_lens() -> None:
    """Every direction from the principal point reaches the border unfolded, but with these
    tangential terms the unfolded part stops short of the lower right corner (1.3 px: a
    polar grid of ideal points up to the fold comes no closer)."""
    from pipeline.flight.schema import CameraConfig

    cam = CameraConfig(model="OPENCV", width_px=640, height_px=480, fx_px=400.0, fy_px=404.0,
                       cx_px=319.5, cy_px=239.5, k1=0.203, k2=-0.112, k3=-0.0756, p1=-0.0098,
                       p2=-0.0177)
    assert cam.fold() == (
        "the distortion (k1 0.203, k2 -0.112, p1 -0.0098, p2 -0.0177, k3 -0.0756) folds back "
        "before the border of the 640 x 480 px image: no ray reaches the pixel (629, 479) "
        "(check the coefficients' signs and that they are OpenCV's, on normalised "
        "coordinates)")
