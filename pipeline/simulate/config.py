"""Simulation configs of ``seqat simulate`` (``configs/*_sim.yaml``): observations or rendered.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pipeline.common.strict_yaml import build_dataclass, load_yaml
from pipeline.flight.schema import CameraConfig
from seqat.errors import ConfigError
from seqat.simulate import StripSimConfig

#: ``kind`` of a simulation config: precomputed image observations (the paper's input mode).
SIM_KIND_OBSERVATIONS = "observations"


@dataclass(frozen=True, kw_only=True)
class SimulateConfig:
    """``configs/*_sim.yaml``: what ``seqat simulate`` makes.

    ``simulation`` holds the fields of :class:`seqat.simulate.StripSimConfig` (all optional;
    the defaults reproduce the paper's strip).
    """

    kind: Literal["observations"]
    crs: str
    simulation: StripSimConfig = StripSimConfig()


#: ``kind`` of a simulation config: images rendered over real terrain
#: (pipeline/simulate/rendered.py).
SIM_KIND_RENDERED = "rendered"


@dataclass(frozen=True, kw_only=True)
class RenderSourceConfig:
    """``source:`` of a rendered simulation: texture and terrain (paths relative to the config).

    ``texture`` is a north-up image with a world file beside it (``.wld``, ``.jgw``);
    ``texture_crs`` its CRS (anything pyproj accepts, or a WKT file). ``lidar`` are LAS/LAZ
    files gridded (highest point per ``cell_m`` cell, gaps interpolated) into the surface;
    ``las_crs`` overrides their CRS.
    """

    texture: str
    texture_crs: str
    lidar: tuple[str, ...]
    las_crs: str | None = None
    cell_m: float = 1.0

    def __post_init__(self) -> None:
        if not self.cell_m > 0:
            raise ConfigError(f"cell_m: expected a positive number, got {self.cell_m!r}")
        if not self.lidar:
            raise ConfigError("lidar: expected at least one LAS/LAZ file")


@dataclass(frozen=True, kw_only=True)
class FlightPlanConfig:
    """``plan:`` of a rendered simulation: parallel strips flown back and forth.

    ``direction_deg`` is the grid azimuth of the first strip (clockwise from grid north);
    strips alternate direction, ``strip_spacing_m`` apart, centred on ``center_m`` (default:
    the centre of the first LiDAR file). ``height_m`` is above the mean terrain height.
    Attitude wanders smoothly (``attitude_wander_deg`` standard deviation, periods of about
    ``wander_period_s``).
    """

    strips: int = 2
    strip_spacing_m: float = 75.0
    strip_length_m: float = 200.0
    direction_deg: float = 90.0
    center_m: tuple[float, float] | None = None
    height_m: float = 100.0
    speed_m_s: float = 8.0
    frame_rate_hz: float = 0.3
    turn_time_s: float = 20.0
    attitude_wander_deg: float = 1.0
    wander_period_s: float = 20.0

    def __post_init__(self) -> None:
        if self.strips < 1:
            raise ConfigError(f"strips: expected a positive integer, got {self.strips!r}")
        for name in ("strip_length_m", "height_m", "speed_m_s", "frame_rate_hz",
                     "wander_period_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected a positive number, "
                                  f"got {getattr(self, name)!r}")
        for name in ("strip_spacing_m", "turn_time_s", "attitude_wander_deg"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}: expected a number >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True, kw_only=True)
class NavNoiseConfig:
    """``nav:`` of a rendered simulation: GPS/INS errors (white + random-walk bias) and mount.

    A bias random walk of ``d`` per sqrt(s) grows to ``d * sqrt(t)`` after ``t`` seconds.
    ``lever_arm_m``: GPS antenna -> camera, body axes (x forward, y right, z down).
    """

    sigma_position_m: float = 0.05
    position_drift_m_per_sqrt_s: float = 0.01
    sigma_attitude_deg: float = 0.05
    attitude_drift_deg_per_sqrt_s: float = 0.005
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name != "lever_arm_m" and not getattr(self, f.name) >= 0:
                raise ConfigError(f"{f.name}: expected a number >= 0, "
                                  f"got {getattr(self, f.name)!r}")


@dataclass(frozen=True, kw_only=True)
class RenderOutputConfig:
    """``output:`` of a rendered simulation: image finish, LiDAR sampling and check points."""

    jpeg_quality: int = 92
    vignetting: float = 0.15
    noise_sigma_dn: float = 2.0
    lidar_density_per_m2: float = 1.0
    lidar_sigma_m: float = 0.03
    checkpoints: int = 36
    sigma_image_px: float = 0.5

    def __post_init__(self) -> None:
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"jpeg_quality: expected 1..100, got {self.jpeg_quality!r}")
        if not 0 <= self.vignetting < 1:
            raise ConfigError(f"vignetting: expected a number in [0, 1), got {self.vignetting!r}")
        for name in ("noise_sigma_dn", "lidar_density_per_m2", "lidar_sigma_m", "checkpoints"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}: expected a number >= 0, got {getattr(self, name)!r}")
        if not self.sigma_image_px > 0:
            raise ConfigError(f"sigma_image_px: expected a positive number, "
                              f"got {self.sigma_image_px!r}")


@dataclass(frozen=True, kw_only=True)
class RenderSimulateConfig:
    """``configs/*.yaml`` with ``kind: rendered``: a camera flown over real texture and terrain."""

    kind: Literal["rendered"]
    crs: str
    source: RenderSourceConfig
    camera: CameraConfig
    plan: FlightPlanConfig = FlightPlanConfig()
    nav: NavNoiseConfig = NavNoiseConfig()
    output: RenderOutputConfig = RenderOutputConfig()

    def __post_init__(self) -> None:
        fold = self.camera.fold()  # as flight.yaml's (the rendered flight's own)
        if fold is not None:
            raise ConfigError(f"camera: {fold}")


def load_simulate_config(path: Path | str) -> SimulateConfig | RenderSimulateConfig:
    """Read and validate a simulation config; ``kind`` chooses the class.

    ``kind: observations`` -> :class:`SimulateConfig`, ``kind: rendered`` ->
    :class:`RenderSimulateConfig`.
    """
    mapping = load_yaml(path)
    kind = mapping.get("kind") if isinstance(mapping, Mapping) else None
    if isinstance(kind, str) and kind.strip().lower() == SIM_KIND_RENDERED:  # any case
        return build_dataclass(RenderSimulateConfig, mapping, str(path))
    return build_dataclass(SimulateConfig, mapping, str(path))
