"""Rendered flight folders (``seqat simulate`` with ``kind: rendered``, issue 6)."""

from __future__ import annotations

from pathlib import Path

import cv2
import laspy
import numpy as np
import pyproj
import pytest

from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.folder import read_flight, read_truth
from pipeline.flight.nav_files import read_ground_points
from pipeline.flight.navigation import BoresightConfig, geodetic_to_eop
from pipeline.flight.schema import CameraConfig
from pipeline.ortho.dsm import read_las, to_working_crs
from pipeline.reference.stage import read_observations
from pipeline.simulate.config import (
    FlightPlanConfig,
    RenderSimulateConfig,
    RenderSourceConfig,
    load_simulate_config,
)
from pipeline.simulate.rendered import geodetic_nav, plan_poses
from pipeline.simulate.stage import simulate_to_folder
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import project

CRS = "EPSG:32610"
#: Round trips through geodetic coordinates (PROJ) and back.
POSITION_TOL_M = 1e-6
ANGLE_TOL_RAD = 1e-9
#: Synthetic source area (UTM 10N) and texel size.
WEST, SOUTH, SIZE_M, TEXEL_M = 494000.0, 4877000.0, 400.0, 0.2
LEVER_M = (0.3, -0.1, -0.2)


def _hills(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 130.0 + 5.0 * np.sin((x - WEST) / 31.0) * np.cos((y - SOUTH) / 43.0)


def _camera(width: int = 160, height: int = 120, f: float = 100.0) -> CameraConfig:
    return CameraConfig(model="OPENCV", width_px=width, height_px=height, fx_px=f, fy_px=f,
                        cx_px=(width - 1) / 2, cy_px=(height - 1) / 2, k1=-0.05, k2=0.01)


def write_sources(folder: Path) -> None:
    """A textured hill in UTM 10N: ``tex.png`` + ``tex.wld`` and ``hill.las``."""
    rng = np.random.default_rng(3)
    n = int(SIZE_M / TEXEL_M)
    noise = rng.uniform(0, 255, (n // 8, n // 8)).astype(np.float32)
    image = cv2.resize(noise, (n, n), interpolation=cv2.INTER_CUBIC)
    image = np.clip(image, 0, 255).astype(np.uint8)
    cv2.imwrite(str(folder / "tex.png"), cv2.merge([image, 255 - image, image]))
    (folder / "tex.wld").write_text(
        f"{TEXEL_M}\n0\n0\n{-TEXEL_M}\n{WEST + TEXEL_M / 2}\n{SOUTH + SIZE_M - TEXEL_M / 2}\n")
    x = rng.uniform(WEST, WEST + SIZE_M, 200_000)
    y = rng.uniform(SOUTH, SOUTH + SIZE_M, 200_000)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = np.array([WEST, SOUTH, 0.0])
    header.scales = np.array([0.001, 0.001, 0.001])
    header.add_crs(pyproj.CRS(CRS))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, _hills(x, y)
    las.write(str(folder / "hill.las"))


def write_config(folder: Path, *, noise: bool = True, extra: str = "") -> Path:
    nav = "" if noise else ("  sigma_position_m: 0\n  position_drift_m_per_sqrt_s: 0\n"
                            "  sigma_attitude_deg: 0\n  attitude_drift_deg_per_sqrt_s: 0\n")
    text = f"""kind: rendered
crs: {CRS}
source:
  texture: tex.png
  texture_crs: {CRS}
  lidar: [hill.las]
camera: {{model: OPENCV, width_px: 160, height_px: 120, fx_px: 100.0, fy_px: 100.0,
          cx_px: 79.5, cy_px: 59.5, k1: -0.05, k2: 0.01}}
plan:
  strips: 2
  strip_spacing_m: 19.2
  strip_length_m: 40.0
  height_m: 30.0
  speed_m_s: 5.0
  frame_rate_hz: 0.6944444444444444
nav:
  lever_arm_m: [{LEVER_M[0]}, {LEVER_M[1]}, {LEVER_M[2]}]
{nav}output:
  lidar_density_per_m2: 2.0
{extra}"""
    path = folder / "render.yaml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("sources")
    write_sources(folder)
    return folder


@pytest.fixture(scope="module")
def exact_flight(sources: Path) -> Path:
    out = sources.parent / "exact_flight"
    simulate_to_folder(write_config(sources, noise=False), out, seed=11)
    return out


def test_geodetic_nav_round_trip_with_lever_arm() -> None:
    config = RenderSimulateConfig(
        kind="rendered", crs=CRS, camera=_camera(),
        source=RenderSourceConfig(texture="t", texture_crs=CRS, lidar=("l",)),
        plan=FlightPlanConfig(strips=3, direction_deg=30.0, attitude_wander_deg=3.0))
    crs = pyproj.CRS(CRS)
    flight = plan_poses(config, (480000.0, 4877000.0), 130.0, np.random.default_rng(0))
    n = len(flight.image_ids)
    rows = geodetic_nav(flight, crs, np.array(LEVER_M), np.zeros((n, 3)), np.zeros((n, 3)))
    eop = geodetic_to_eop(rows[:, 1], rows[:, 0], rows[:, 2], rows[:, 3:], ["body"] * n,
                          ["ellipsoidal"] * n, crs, BoresightConfig(), np.array(LEVER_M))
    np.testing.assert_allclose(eop[:, :3], flight.eop[:, :3], atol=POSITION_TOL_M, rtol=0)
    dang = (eop[:, 3:] - flight.eop[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    assert np.max(np.abs(dang)) < ANGLE_TOL_RAD
    # 2.4 km west of the central meridian (123° W): the convergence matters
    assert abs(rows[0, 5] - (np.degrees(flight.body_rpy_rad[0, 2]) % 360)) > 0.01


def test_rendered_folder_reads_back_as_truth(exact_flight: Path) -> None:
    flight = read_flight(exact_flight)
    truth = read_truth(exact_flight)
    assert truth is not None and flight.kind == "images" and not flight.skipped
    assert flight.nav.image_ids == truth.eop.image_ids
    np.testing.assert_allclose(flight.nav.eop[:, :3], truth.eop.eop[:, :3],
                               atol=POSITION_TOL_M, rtol=0)
    np.testing.assert_allclose(flight.nav.eop[:, 3:], truth.eop.eop[:, 3:], atol=1e-9, rtol=0)
    assert flight.camera_config.k1 == pytest.approx(-0.05)


def test_checkpoints_are_projections_of_truth(exact_flight: Path) -> None:
    flight = read_flight(exact_flight)
    truth = read_truth(exact_flight)
    assert truth is not None
    known = read_ground_points(exact_flight / "checkpoints.csv")
    assert len(known.point_ids) >= 30
    np.testing.assert_allclose(_hills(known.xyz_m[:, 0], known.xyz_m[:, 1]), known.xyz_m[:, 2],
                               atol=0.05)  # on the surface gridded at 1 m (curvature)
    obs_image, point_ids, obs_point, uv = read_observations(
        exact_flight / "checkpoint_obs.csv", {i: k for k, i in enumerate(flight.nav.image_ids)})
    assert np.all(np.bincount(obs_point) >= 2)
    pid = {p: k for k, p in enumerate(known.point_ids)}
    X = known.xyz_m[[pid[point_ids[j]] for j in obs_point]]
    ideal = np.array([project(truth.eop.eop[i], x[None, :], pinhole_camera(flight.camera_config))[0]
                      for i, x in zip(obs_image, X, strict=True)])
    observed = PixelCorrector(camera=flight.camera_config).observed_pixels(ideal)
    np.testing.assert_allclose(uv, observed, atol=1e-6)


def test_lidar_in_source_crs_on_the_surface(exact_flight: Path) -> None:
    cloud = read_las(exact_flight / "lidar" / "surface.laz")
    assert cloud.crs.equals(pyproj.CRS(CRS))
    xyz, _ = to_working_crs(cloud, pyproj.CRS(CRS))
    residual = xyz[:, 2] - _hills(xyz[:, 0], xyz[:, 1])
    assert abs(np.mean(residual)) < 0.02 and 0.02 < np.std(residual) < 0.06


def test_images_are_rendered_jpegs(exact_flight: Path) -> None:
    images = sorted((exact_flight / "images").glob("*.jpg"))
    assert len(images) == len(read_flight(exact_flight).nav.image_ids)
    image = cv2.imread(str(images[0]))
    assert image.shape == (120, 160, 3) and image.std() > 10


@pytest.fixture(scope="module")
def noisy_flight(sources: Path) -> Path:
    """``seqat simulate`` of the noisy-nav config (the CLI; read-only for the tests)."""
    from typer.testing import CliRunner

    from pipeline.cli import app

    out = sources.parent / "noisy_flight"
    result = CliRunner().invoke(app, ["simulate", str(write_config(sources)), "--out", str(out),
                                      "--seed", "12"])
    assert result.exit_code == 0, result.output
    return out


def test_noisy_nav_differs_within_its_sigma(noisy_flight: Path) -> None:
    out = noisy_flight
    flight = read_flight(out)
    truth = read_truth(out)
    assert truth is not None
    d = np.linalg.norm(flight.nav.eop[:, :3] - truth.eop.eop[:, :3], axis=1)
    assert 0.001 < d.max() < 1.0


def test_unknown_key_names_it(sources: Path) -> None:
    path = write_config(sources, extra="  jpeg_qualty: 50\n")
    with pytest.raises(ConfigError, match="output.jpeg_qualty"):
        load_simulate_config(path)


def test_a_folding_distortion_names_the_camera(sources: Path) -> None:
    """The rendered flight's camera is checked as a flight.yaml's: k1 -5 where -0.05 was
    meant folds back inside the image."""
    path = write_config(sources)
    path.write_text(path.read_text().replace("k1: -0.05", "k1: -5.0"))
    with pytest.raises(ConfigError, match=r"camera: the distortion \(k1 -5, k2 0.01.*folds back"):
        load_simulate_config(path)


def test_missing_texture_names_the_file(sources: Path, tmp_path: Path) -> None:
    path = write_config(sources)
    path.write_text(path.read_text().replace("tex.png", "nope.png"))
    with pytest.raises(InputDataError, match="nope.png"):
        simulate_to_folder(path, tmp_path / "out", seed=1)


@pytest.mark.shared
def test_autzen_wkt_is_epsg_2994(shared_data: Path) -> None:
    wkt = pyproj.CRS((shared_data / "autzen" / "autzen-srs.wkt").read_text())
    assert wkt.equals(pyproj.CRS("EPSG:2994"), ignore_axis_order=True)
    assert wkt.axis_info[0].unit_name == "foot"


@pytest.mark.parametrize(("name", "n_images"), [("autzen_sample.yaml", 12),
                                                ("autzen_block.yaml", 100)])
def test_autzen_configs_plan_the_documented_block(name: str, n_images: int) -> None:
    config = load_simulate_config(Path(__file__).resolve().parents[3] / "configs" / name)
    assert isinstance(config, RenderSimulateConfig)
    plan, cam = config.plan, config.camera
    flight = plan_poses(config, (0.0, 0.0), 0.0, np.random.default_rng(0))
    assert len(flight.image_ids) == n_images
    assert plan.height_m / cam.fx_px == pytest.approx(0.3)  # GSD of the texture
    base_m = plan.speed_m_s / plan.frame_rate_hz
    assert 1 - base_m / (cam.height_px * 0.3) == pytest.approx(0.8)
    assert 1 - plan.strip_spacing_m / (cam.width_px * 0.3) == pytest.approx(0.6)


def test_the_weak_gps_config_plans_the_documented_block() -> None:
    """configs/autzen_weak_gps.yaml: 102 images, GSD 0.25 m, 90 % / 70 % overlap, GPS 1.5 m
    and INS 2 deg (docs/benchmarks.md, *A block on a weak GPS/INS*)."""
    config = load_simulate_config(Path(__file__).resolve().parents[3] / "configs"
                                  / "autzen_weak_gps.yaml")
    assert isinstance(config, RenderSimulateConfig)
    plan, cam = config.plan, config.camera
    flight = plan_poses(config, (0.0, 0.0), 0.0, np.random.default_rng(0))
    assert len(flight.image_ids) == 102
    gsd = plan.height_m / cam.fx_px
    assert gsd == pytest.approx(0.25)
    assert 1 - plan.speed_m_s / plan.frame_rate_hz / (cam.height_px * gsd) == pytest.approx(0.9)
    assert 1 - plan.strip_spacing_m / (cam.width_px * gsd) == pytest.approx(0.7)
    assert (config.nav.sigma_position_m, config.nav.sigma_attitude_deg) == (1.5, 2.0)


def test_cli_simulate_rendered(sources: Path, noisy_flight: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    config = write_config(sources)
    assert (noisy_flight / "images" / "img_0001.jpg").is_file()  # seqat simulate: exit 0
    bad = tmp_path / "bad.yaml"
    bad.write_text(config.read_text().replace("strips: 2", "strips: 0"))
    result = CliRunner().invoke(app, ["simulate", str(bad), "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "plan" in result.output and "strips" in result.output


@pytest.mark.shared
def test_autzen_scene_renders_texture_everywhere(shared_data: Path) -> None:
    from pipeline.simulate.render import Renderer
    from pipeline.simulate.render_scene import load_scene

    autzen = shared_data / "autzen"
    wkt = pyproj.CRS((autzen / "autzen-srs.wkt").read_text())
    crs = pyproj.CRS(CRS)
    cx, cy = 494300.0, 4877580.0
    scene = load_scene(autzen / "autzen.jpg", wkt, [autzen / "autzen_trim.las"], wkt, crs, 1.0,
                       (cx - 60, cy - 60, cx + 60, cy + 60))
    z0, z1 = scene.surface.z_range_m
    assert 120.0 < z0 < z1 < 165.0  # 406-520 ft of the LAS header, in metres
    image = Renderer(scene, _camera()).render(np.array([cx, cy, z1 + 60.0, 0.0, 0.0, 0.0]))
    assert image.shape == (120, 160, 3)
    assert np.mean(np.all(image == 0, axis=2)) < 0.001 and image.std() > 10
