"""``seqat simulate`` with ``kind: rendered``: a complete image flight folder with exact truth.

Truth poses come from a strip plan (:func:`plan_poses`): the aircraft body flies parallel
strips with a smoothly wandering roll, pitch and yaw; the camera sits on it with the nadir
mount, so ``R_world_from_cam = R_ENU_FROM_NED · R_ned_from_body(roll, pitch, yaw_grid) ·
R_body_from_cam`` (docs/conventions.md, *Navigation attitude*). The navigation is the truth
plus white noise and a random-walk bias, written as a *geodetic* ``nav.csv`` of the GPS
antenna (the camera minus the lever arm turned into the world) with the true heading
``yaw = yaw_grid + γ``; :func:`pipeline.flight.navigation.geodetic_to_eop` inverts this exactly
(tests/pipeline/simulate/test_render_flight.py). Images are rendered by
:mod:`pipeline.simulate.render`.

Folder (docs/formats.md, *Rendered flights*): ``flight.yaml``, ``nav.csv``, ``images/``,
``lidar/surface.laz`` (source CRS and units), ``checkpoints.csv`` + ``checkpoint_obs.csv``,
``truth/eop.csv`` + ``truth/points.csv`` (the check points).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import laspy
import numpy as np
import pyproj
import yaml

from pipeline.common.atomic import building_folder, write_synced
from pipeline.common.columns import (
    CHECKPOINT_OBS_FILE,
    CHECKPOINTS_FILE,
    FLIGHT_YAML,
    GROUND_POINT_COLUMNS,
    IMAGES_DIR,
    NAV_FILE,
    NAV_GEODETIC_COLUMNS,
    TRUTH_DIR,
)
from pipeline.common.csvio import format_csv_line
from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.navigation import (
    R_ENU_FROM_NED,
    WGS84_3D,
    BoresightConfig,
    R_ned_from_body,
    grid_convergence_rad,
    resolve_projected_crs,
)
from pipeline.flight.schema import CameraConfig
from pipeline.ortho.dsm import linear_unit_factor, parse_crs
from pipeline.run.store import fmt, format_nav_csv, format_observation_lines
from pipeline.simulate.config import RenderSimulateConfig
from pipeline.simulate.folder import check_replaceable
from pipeline.simulate.render import HeightField, Renderer, Scene, cast_rays, finish_image
from pipeline.simulate.render_scene import las_center_m, load_scene
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import angles_from_rotation, project
from seqat.types import FloatArray

LIDAR_DIR = "lidar"
LIDAR_FILE = "surface.laz"
#: Sinusoids summed per wandering angle (periods wander_period_s · PERIOD_FACTORS).
PERIOD_FACTORS = (1.0, 0.61, 0.37)
#: Margin around the camera positions covered by the surface grid, beyond the footprint (m).
SURFACE_MARGIN_M = 30.0
#: A check point is visible when the ray through its pixel hits the surface this close to it.
VISIBILITY_TOLERANCE_M = 0.05
#: Check points need this many observing images.
MIN_CHECKPOINT_RAYS = 2
#: Keep check point observations this far inside the image border (px).
CHECKPOINT_BORDER_PX = 2.0
#: Largest share of an image that may see no texture (the plan leaves the texture or terrain).
MAX_BACKGROUND_FRACTION = 0.01
#: Floor of the a priori nav sigmas written to flight.yaml (they must be positive; a noise-free
#: simulation still gets a finite weight): metres, degrees.
MIN_PRIOR_SIGMA_M = 0.001
MIN_PRIOR_SIGMA_DEG = 0.001
#: LAS coordinate scale (source units, e.g. feet) and the LAS version written.
LAS_SCALE = 0.001


@dataclass(frozen=True, kw_only=True, eq=False)
class PlannedFlight:
    """Truth of a planned flight.

    Attributes
    ----------
    image_ids : tuple of str
    times_s : (n,) float
    eop : (n, 6) float
        Camera EOPs ``[X, Y, Z, omega, phi, kappa]``, metres and radians.
    body_rpy_rad : (n, 3) float
        Body roll, pitch and *grid* yaw (heading from grid north).
    """

    image_ids: tuple[str, ...]
    times_s: FloatArray
    eop: FloatArray
    body_rpy_rad: FloatArray


def footprint_m(camera: CameraConfig, height_m: float) -> tuple[float, float]:
    """Ground width and height (m) of a nadir image from ``height_m`` above ground."""
    return camera.width_px * height_m / camera.fx_px, camera.height_px * height_m / camera.fx_px


def _wander(times_s: FloatArray, sigma_rad: float, period_s: float,
            rng: np.random.Generator) -> FloatArray:
    """Smooth zero-mean angles: sinusoids of random phase, standard deviation ``sigma_rad``."""
    out = np.zeros_like(times_s)
    amplitude = sigma_rad * math.sqrt(2.0 / len(PERIOD_FACTORS))
    for factor in PERIOD_FACTORS:
        phase = rng.uniform(0.0, 2.0 * math.pi)
        out += amplitude * np.sin(2.0 * math.pi * times_s / (period_s * factor) + phase)
    return out


def R_world_from_cam_body(rpy_rad: FloatArray, R_body_from_cam: FloatArray) -> FloatArray:
    """Camera -> world for a body attitude with grid yaw (docs/conventions.md)."""
    return R_ENU_FROM_NED @ R_ned_from_body(*rpy_rad) @ R_body_from_cam


def plan_poses(config: RenderSimulateConfig, center_m: tuple[float, float], ground_z_m: float,
               rng: np.random.Generator) -> PlannedFlight:
    """Camera poses of the strip plan with attitude wander (nadir mount, no misalignment)."""
    plan = config.plan
    base_m = plan.speed_m_s / plan.frame_rate_hz
    per_strip = max(2, int(math.floor(plan.strip_length_m / base_m)) + 1)
    along = (np.arange(per_strip) - (per_strip - 1) / 2.0) * base_m
    az = math.radians(plan.direction_deg)
    forward = np.array([math.sin(az), math.cos(az)])
    right = np.array([forward[1], -forward[0]])
    positions, headings, times = [], [], []
    t = 0.0
    for k in range(plan.strips):
        offset = (k - (plan.strips - 1) / 2.0) * plan.strip_spacing_m
        sign = 1.0 if k % 2 == 0 else -1.0
        for a in along[::int(sign)]:
            positions.append(np.asarray(center_m) + a * forward + offset * right)
            headings.append(az if sign > 0 else az + math.pi)
            times.append(t)
            t += 1.0 / plan.frame_rate_hz
        t += plan.turn_time_s
    times_s = np.asarray(times)
    sigma = math.radians(plan.attitude_wander_deg)
    rpy = np.column_stack([_wander(times_s, sigma, plan.wander_period_s, rng) for _ in range(3)])
    rpy[:, 2] += np.asarray(headings)
    mount = BoresightConfig().R_body_from_cam()
    eop = np.empty((len(times_s), 6))
    for i, (xy, angles) in enumerate(zip(positions, rpy, strict=True)):
        eop[i, :2] = xy
        eop[i, 2] = ground_z_m + plan.height_m
        eop[i, 3:] = angles_from_rotation(R_world_from_cam_body(angles, mount))
    ids = tuple(f"img_{i + 1:04d}" for i in range(len(times_s)))
    return PlannedFlight(image_ids=ids, times_s=times_s, eop=eop, body_rpy_rad=rpy)


def _noise(n: int, white: float, drift_per_sqrt_s: float, times_s: FloatArray,
           rng: np.random.Generator) -> FloatArray:
    """(n, 3) white noise + random-walk bias sampled at ``times_s``."""
    dt = np.diff(times_s, prepend=times_s[0])
    steps = rng.normal(0.0, 1.0, (n, 3)) * (drift_per_sqrt_s * np.sqrt(dt))[:, None]
    bias = rng.normal(0.0, drift_per_sqrt_s, 3) + np.cumsum(steps, axis=0)
    return rng.normal(0.0, white, (n, 3)) + bias


def geodetic_nav(flight: PlannedFlight, crs: pyproj.CRS, lever_arm_m: FloatArray,
                 position_error_m: FloatArray, attitude_error_rad: FloatArray) -> FloatArray:
    """Rows ``lat_deg, lon_deg, h_m, roll_deg, pitch_deg, yaw_deg`` of a geodetic ``nav.csv``.

    The fix is the GPS antenna, ``X_cam - R_world_from_body · lever_arm`` plus the position
    error (world axes); the attitude is the body's plus the error, with the true heading
    ``yaw_grid + γ`` (γ at the fix). :func:`pipeline.flight.navigation.geodetic_to_eop` with the
    same lever arm gives back the camera EOP exactly when the errors are zero.

    Returns
    -------
    (n, 6) float
    """
    n = len(flight.image_ids)
    to_geo = pyproj.Transformer.from_crs(crs.to_3d() if len(crs.axis_info) == 2 else crs,
                                         WGS84_3D, always_xy=True)
    rpy = flight.body_rpy_rad + attitude_error_rad
    antenna = np.empty((n, 3))
    for i in range(n):
        R_world_from_body = R_ENU_FROM_NED @ R_ned_from_body(*flight.body_rpy_rad[i])
        antenna[i] = flight.eop[i, :3] - R_world_from_body @ lever_arm_m
    antenna += position_error_m
    lon, lat, h = to_geo.transform(antenna[:, 0], antenna[:, 1], antenna[:, 2], errcheck=True)
    out = np.empty((n, 6))
    out[:, 0], out[:, 1], out[:, 2] = lat, lon, h
    for i in range(n):
        gamma = grid_convergence_rad(crs, float(lon[i]), float(lat[i]))
        yaw = (rpy[i, 2] + gamma) % (2.0 * math.pi)
        out[i, 3:] = np.degrees([rpy[i, 0], rpy[i, 1], yaw])
    return out


def checkpoint_grid(flight: PlannedFlight, surface: HeightField, count: int,
                    rng: np.random.Generator) -> FloatArray:
    """(count, 3) points on the surface, a jittered grid over the camera positions' extent."""
    lo, hi = flight.eop[:, :2].min(axis=0), flight.eop[:, :2].max(axis=0)
    span = np.maximum(hi - lo, 1.0)
    nx = max(1, int(round(math.sqrt(count * span[0] / span[1]))))
    ny = max(1, int(math.ceil(count / nx)))
    gx = lo[0] + (np.arange(nx) + 0.5) / nx * span[0]
    gy = lo[1] + (np.arange(ny) + 0.5) / ny * span[1]
    xy = np.array([[x, y] for y in gy for x in gx])[:count]
    xy += rng.uniform(-0.25, 0.25, xy.shape) * (span / np.array([nx, ny]))
    return np.column_stack([xy, surface.sample(xy[:, 0], xy[:, 1])])


def checkpoint_observations(flight: PlannedFlight, scene: Scene, camera: CameraConfig,
                            points_m: FloatArray) -> list[tuple[int, int, FloatArray]]:
    """``(image_row, point_row, observed_uv_px)`` of every visible check point in every image."""
    pin = pinhole_camera(camera)
    corrector = PixelCorrector(camera=camera)
    out = []
    for i, eop in enumerate(flight.eop):
        ideal = project(eop, points_m, pin)
        observed = corrector.observed_pixels(ideal)
        inside = np.flatnonzero(
            (observed[:, 0] > CHECKPOINT_BORDER_PX)
            & (observed[:, 0] < camera.width_px - 1 - CHECKPOINT_BORDER_PX)
            & (observed[:, 1] > CHECKPOINT_BORDER_PX)
            & (observed[:, 1] < camera.height_px - 1 - CHECKPOINT_BORDER_PX))
        if inside.size == 0:
            continue
        dirs = points_m[inside] - eop[:3]
        hits = cast_rays(scene.surface, eop[:3], dirs)
        visible = np.linalg.norm(hits - points_m[inside], axis=1) < VISIBILITY_TOLERANCE_M
        out += [(i, int(j), observed[j]) for j in inside[visible]]
    return out


def write_lidar(path: Path, surface: HeightField, bounds_m: tuple[float, float, float, float],
                crs: pyproj.CRS, las_crs: pyproj.CRS, density_per_m2: float, sigma_m: float,
                rng: np.random.Generator) -> int:
    """Points sampled from the surface with noise, written in the LiDAR source CRS and units."""
    west, south, east, north = bounds_m
    n = max(1, int(density_per_m2 * (east - west) * (north - south)))
    x = rng.uniform(west, east, n)
    y = rng.uniform(south, north, n)
    z = surface.sample(x, y) + rng.normal(0.0, sigma_m, n)
    tx, ty = pyproj.Transformer.from_crs(crs, las_crs, always_xy=True).transform(x, y)
    tz = z / linear_unit_factor(las_crs)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = np.floor([tx.min(), ty.min(), tz.min()])
    header.scales = np.array([LAS_SCALE, LAS_SCALE, LAS_SCALE])
    header.add_crs(las_crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = tx, ty, tz
    las.write(str(path))
    return n


def _flight_yaml(config: RenderSimulateConfig, sigma_position_m: float,
                 sigma_attitude_deg: float) -> str:
    cam = config.camera
    camera = {"model": cam.model, "width_px": cam.width_px, "height_px": cam.height_px,
              "fx_px": cam.fx_px, "fy_px": cam.fy_px, "cx_px": cam.cx_px, "cy_px": cam.cy_px}
    if cam.model == "OPENCV":
        camera.update(k1=cam.k1, k2=cam.k2, p1=cam.p1, p2=cam.p2, k3=cam.k3)
    doc = {
        "crs": config.crs,
        "camera": camera,
        "nav": {"file": NAV_FILE, "frame": "geodetic", "height": "ellipsoidal",
                "sigma_position_m": float(f"{sigma_position_m:.6g}"),
                "sigma_attitude_deg": float(f"{sigma_attitude_deg:.6g}"),
                "lever_arm_m": [float(v) for v in config.nav.lever_arm_m]},
        "sigma_image_px": config.output.sigma_image_px,
        "images": IMAGES_DIR,
        "lidar": f"{LIDAR_DIR}/{LIDAR_FILE}",
        "checkpoints": CHECKPOINTS_FILE,
    }
    return yaml.safe_dump(doc, sort_keys=False)


@dataclass(frozen=True, kw_only=True)
class RenderSummary:
    """What a rendered ``seqat simulate`` wrote."""

    out_dir: Path
    crs: str
    seed: int
    n_images: int
    n_points: int
    n_observations: int
    duration_s: float
    gsd_m: float
    forward_overlap: float
    side_overlap: float
    render_s_per_image: float


def render_to_folder(config: RenderSimulateConfig, config_dir: Path, out_dir: Path | str,
                     seed: int) -> RenderSummary:
    """Plan, render and write a flight folder (appears complete or not at all).

    Raises
    ------
    ConfigError
        Bad CRS.
    InputDataError
        Missing texture or LAS file, no LiDAR in the flight area, or an output folder that
        cannot be replaced.
    """
    out = Path(out_dir)
    check_replaceable(out)
    crs = resolve_projected_crs(config.crs, "crs")
    src = config.source
    texture_path = _resolve(src.texture, config_dir)
    las_paths = [_resolve(p, config_dir) for p in src.lidar]
    texture_crs = parse_crs(src.texture_crs, "source.texture_crs", config_dir)
    las_crs = parse_crs(src.las_crs, "source.las_crs", config_dir) if src.las_crs else None
    rng = np.random.default_rng(seed)
    center = (config.plan.center_m if config.plan.center_m is not None
              else las_center_m(las_paths[0], crs, las_crs))
    # a first, coarse surface around the centre gives the mean ground height
    fw, fh = footprint_m(config.camera, config.plan.height_m)
    reach = 0.5 * max(config.plan.strip_length_m, (config.plan.strips - 1)
                      * config.plan.strip_spacing_m) + max(fw, fh) + SURFACE_MARGIN_M
    bounds = (center[0] - reach, center[1] - reach, center[0] + reach, center[1] + reach)
    scene = load_scene(texture_path, texture_crs, las_paths, las_crs, crs, src.cell_m, bounds)
    ground_z = float(np.mean(scene.surface.heights_m))
    flight = plan_poses(config, center, ground_z, rng)
    n = len(flight.image_ids)
    nav_cfg = config.nav
    pos_err = _noise(n, nav_cfg.sigma_position_m, nav_cfg.position_drift_m_per_sqrt_s,
                     flight.times_s, rng)
    att_err = np.radians(_noise(n, nav_cfg.sigma_attitude_deg,
                                nav_cfg.attitude_drift_deg_per_sqrt_s, flight.times_s, rng))
    nav_rows = geodetic_nav(flight, crs, np.asarray(nav_cfg.lever_arm_m), pos_err, att_err)
    duration = float(flight.times_s[-1] - flight.times_s[0])
    sigma_pos = math.hypot(nav_cfg.sigma_position_m,
                           nav_cfg.position_drift_m_per_sqrt_s * math.sqrt(max(duration, 1.0)))
    sigma_att = math.hypot(nav_cfg.sigma_attitude_deg,
                           nav_cfg.attitude_drift_deg_per_sqrt_s * math.sqrt(max(duration, 1.0)))
    sigma_pos, sigma_att = max(sigma_pos, MIN_PRIOR_SIGMA_M), max(sigma_att, MIN_PRIOR_SIGMA_DEG)
    checkpoints = checkpoint_grid(flight, scene.surface, config.output.checkpoints, rng)
    cp_obs = checkpoint_observations(flight, scene, config.camera, checkpoints)
    rays = np.bincount([j for _, j, _ in cp_obs], minlength=len(checkpoints))
    keep = np.flatnonzero(rays >= MIN_CHECKPOINT_RAYS)
    cp_ids = {int(j): f"c{k + 1:03d}" for k, j in enumerate(keep)}

    renderer = Renderer(scene, config.camera)
    render_s = 0.0
    with building_folder(out) as tmp:
        (tmp / IMAGES_DIR).mkdir()
        for image_id, eop in zip(flight.image_ids, flight.eop, strict=True):
            start = time.perf_counter()
            image = renderer.render(eop)
            render_s += time.perf_counter() - start
            empty = float(np.mean(np.all(image.reshape(-1, image.shape[-1]) == 0, axis=1)
                                  if image.ndim == 3 else image == 0))
            if empty > MAX_BACKGROUND_FRACTION:
                raise ConfigError(f"plan: image {image_id} sees no texture in {empty:.0%} of its "
                                  f"pixels: the flight leaves the texture; move plan.center_m "
                                  f"or shorten the strips")
            image = finish_image(image, vignetting=config.output.vignetting,
                                 noise_sigma_dn=config.output.noise_sigma_dn, rng=rng)
            ok = cv2.imwrite(str(tmp / IMAGES_DIR / f"{image_id}.jpg"), image,
                             [cv2.IMWRITE_JPEG_QUALITY, config.output.jpeg_quality])
            if not ok:
                raise OSError(f"{tmp / IMAGES_DIR / image_id}.jpg: cannot write the image")
        write_synced(tmp / FLIGHT_YAML, _flight_yaml(config, sigma_pos, sigma_att))
        lines = [format_csv_line(NAV_GEODETIC_COLUMNS)]
        lines += [format_csv_line([iid, fmt(t), *(fmt(v) for v in row)])
                  for iid, t, row in zip(flight.image_ids, flight.times_s, nav_rows, strict=True)]
        write_synced(tmp / NAV_FILE, "".join(lines))
        (tmp / LIDAR_DIR).mkdir()
        lidar_crs = las_crs if las_crs is not None else _las_file_crs(las_paths[0])
        write_lidar(tmp / LIDAR_DIR / LIDAR_FILE, scene.surface, _covered(flight, fw, fh), crs,
                    lidar_crs, config.output.lidar_density_per_m2, config.output.lidar_sigma_m,
                    rng)
        points_csv = _points_csv([cp_ids[int(j)] for j in keep], checkpoints[keep])
        write_synced(tmp / CHECKPOINTS_FILE, points_csv)
        obs_text = format_csv_line(("image", "point", "x_px", "y_px"))
        for i, image_id in enumerate(flight.image_ids):
            rows = [(cp_ids[j], uv) for r, j, uv in cp_obs if r == i and j in cp_ids]
            if rows:
                obs_text += format_observation_lines(image_id, [p for p, _ in rows],
                                                     np.array([uv for _, uv in rows]))
        write_synced(tmp / CHECKPOINT_OBS_FILE, obs_text)
        (tmp / TRUTH_DIR).mkdir()
        write_synced(tmp / TRUTH_DIR / "eop.csv", format_nav_csv(flight.image_ids, flight.times_s,
                                                           flight.eop))
        write_synced(tmp / TRUTH_DIR / "points.csv", points_csv)
    base = config.plan.speed_m_s / config.plan.frame_rate_hz
    return RenderSummary(
        out_dir=out, crs=config.crs, seed=seed, n_images=n, n_points=len(keep),
        n_observations=sum(1 for _, j, _ in cp_obs if j in cp_ids), duration_s=duration,
        gsd_m=config.plan.height_m / config.camera.fx_px,
        forward_overlap=max(0.0, 1.0 - base / fh),
        side_overlap=max(0.0, 1.0 - config.plan.strip_spacing_m / fw),
        render_s_per_image=render_s / n)


def _resolve(name: str, base: Path) -> Path:
    path = Path(name)
    return path if path.is_absolute() else base / path


def _las_file_crs(path: Path) -> pyproj.CRS:
    """CRS declared in a LAS file's header (checked readable by :func:`load_scene`)."""
    with laspy.open(str(path)) as reader:
        crs = reader.header.parse_crs()
    if crs is None:
        raise InputDataError(f"{path}: no CRS in the LAS file; give source.las_crs")
    return crs


def _covered(flight: PlannedFlight, fw: float, fh: float) -> tuple[float, float, float, float]:
    half = 0.5 * math.hypot(fw, fh)
    lo, hi = flight.eop[:, :2].min(axis=0) - half, flight.eop[:, :2].max(axis=0) + half
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _points_csv(ids: list[str], xyz_m: FloatArray) -> str:
    lines = [format_csv_line(GROUND_POINT_COLUMNS)]
    lines += [format_csv_line([pid, *(fmt(v) for v in p)]) for pid, p in zip(ids, xyz_m,
                                                                             strict=True)]
    return "".join(lines)

