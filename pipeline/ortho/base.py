"""Options, constants and raster types of the orthorectifier
(:mod:`pipeline.ortho.orthorectifier`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from affine import Affine
from rasterio.transform import from_origin

from seqat.errors import ConfigError
from seqat.types import FloatArray

#: A ray whose downward component is below this (sine of the depression angle) misses the
#: ground: the viewing axis must look at least this far below the horizon.
MIN_DEPRESSION_SIN = math.sin(math.radians(1.0))
#: Map value that makes ``cv2.remap`` sample nothing (far outside any image).
OUTSIDE_PX = -1.0e5
#: Rows per block of the projection (fits the work arrays in the cache); a multiple of
#: OCCLUSION_SUBSAMPLE.
BLOCK_ROWS = 128
#: The z-buffer is filled from every k-th cell in each direction (k^2 times less work).
OCCLUSION_SUBSAMPLE = 2
#: Scattered points are projected through the distortion table in rows of this many.
POINTS_PER_ROW = 4096
#: Longest facade segment sampled into the z-buffer, image pixels.
MAX_FACADE_PX = 4000.0
#: Significant digits of the automatic pixel size (GSD).
PIXEL_SIGNIFICANT_DIGITS = 3
#: Lowest valid 8/16-bit alpha value ("seen").
ALPHA_OPAQUE = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}


@dataclass(frozen=True, kw_only=True)
class OrthoOptions:
    """Options of the orthorectifier.

    Attributes
    ----------
    pixel_m : float or None
        Ground pixel size, metres. ``None``: the GSD of the first image at its nadir
        (``(Z0 - Z_ground) / fx``), rounded to 3 significant digits, then fixed for the flight.
    resampling : {"bilinear", "cubic"}
    occlusion : bool
        Hide cells the camera cannot see.
    occlusion_method : {"zbuffer", "raycast"}
        ``zbuffer``: nearest depth per image bucket from the cells and the facades of the
        2.5D DSM; ``raycast``: one ray per sampled cell through the DSM's triangle mesh
        (open3d ``RaycastingScene``). Compared in docs/benchmarks.md.
    occlusion_tolerance_cells : float
        A cell is hidden when it lies farther than the nearest surface in its image bucket by
        more than this many ground cells.
    max_range_factor : float
        The footprint reaches at most this many heights above ground from the nadir point.
    threads : int
        Worker threads of the projection.
    write_images : bool
        Write ``ortho/<image>.tif`` (else only return the raster, e.g. for the mosaic).
    background_writes : bool
        Write each COG on a background thread while the next image is orthorectified (at most
        one write pending); the file is complete after the next ``add_image``, ``flush()`` or
        ``close()``.
    """

    pixel_m: float | None = None
    resampling: Literal["bilinear", "cubic"] = "bilinear"
    occlusion: bool = True
    occlusion_method: Literal["zbuffer", "raycast"] = "zbuffer"
    occlusion_tolerance_cells: float = 3.0
    max_range_factor: float = 3.0
    threads: int = 2
    write_images: bool = True
    background_writes: bool = True

    def __post_init__(self) -> None:
        if self.pixel_m is not None and not (math.isfinite(self.pixel_m) and self.pixel_m > 0):
            raise ConfigError(f"pixel_m: expected a positive number of metres, "
                              f"got {self.pixel_m!r}")
        if self.resampling not in ("bilinear", "cubic"):
            raise ConfigError(f"resampling: expected bilinear or cubic, got {self.resampling!r}")
        if self.occlusion_method not in ("zbuffer", "raycast"):
            raise ConfigError(f"occlusion_method: expected zbuffer or raycast, got "
                              f"{self.occlusion_method!r}")
        if not self.max_range_factor > 0:
            raise ConfigError(f"max_range_factor: expected > 0, got {self.max_range_factor!r}")
        if self.threads < 1:
            raise ConfigError(f"threads: expected >= 1, got {self.threads}")


@dataclass(frozen=True, kw_only=True, eq=False)
class OrthoRaster:
    """One orthorectified image on the global grid.

    Attributes
    ----------
    image_id : str
    col0, row0 : int
        Global index of the top-left cell: its west edge is ``col0 * pixel_m``, its north
        edge ``-row0 * pixel_m`` (rows grow southwards).
    pixel_m : float
    pixels : (rows, cols, bands) uint8 or uint16
        Resampled image (RGB or grey); zero where not ``seen``.
    seen : (rows, cols) bool
        Inside the image, on the DSM and not occluded.
    off_nadir : (rows, cols) float32
        Tangent of the angle between the cell's ray and the vertical (the mosaic picks the
        most nadir view).
    height_agl_m : float
        Camera height above the ground at its nadir (scales the mosaic's feather).
    """

    image_id: str
    col0: int
    row0: int
    pixel_m: float
    pixels: np.ndarray
    seen: np.ndarray
    off_nadir: np.ndarray
    height_agl_m: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.seen.shape  # type: ignore[return-value]

    @property
    def transform(self) -> Affine:
        """Pixel-is-area geotransform (outer corner of the top-left cell)."""
        return from_origin(self.col0 * self.pixel_m, -self.row0 * self.pixel_m, self.pixel_m,
                           self.pixel_m)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(west, south, east, north)``, metres."""
        rows, cols = self.shape
        p = self.pixel_m
        return (self.col0 * p, -(self.row0 + rows) * p, (self.col0 + cols) * p, -self.row0 * p)


@dataclass(frozen=True, kw_only=True, eq=False)
class OrthoResult:
    """What :meth:`Orthorectifier.add_image` returns.

    Attributes
    ----------
    image_id : str
    path : Path or None
        ``ortho/<image>.tif`` (None with ``write_images=False``); with ``background_writes``
        complete after the next ``add_image``, ``flush()`` or ``close()``.
    raster : OrthoRaster
        Cropped to the cells seen.
    footprint_m : (k, 2) float
        Ground polygon of the image border on the plane at the DSM height under the nadir
        (closed ring, east/north metres).
    seen_cells, occluded_cells, off_dsm_cells : int
        Cells filled; hidden by higher surfaces; without DSM height.
    compute_ms, write_ms : float
        Orthorectification time (projection, occlusion, resampling) and the time
        ``add_image`` spent writing COGs (with ``background_writes``: waiting for the
        previous image's write).
    occlusion_ms : float
        The part of ``compute_ms`` spent on the z-buffer.
    warnings : tuple[str, ...]
    """

    image_id: str
    path: Path | None
    raster: OrthoRaster
    footprint_m: FloatArray
    seen_cells: int
    occluded_cells: int
    off_dsm_cells: int
    compute_ms: float
    write_ms: float
    occlusion_ms: float = 0.0
    warnings: tuple[str, ...] = field(default=())
