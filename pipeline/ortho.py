"""Orthorectification of one image at a time on a DSM (``seqat ortho``, ``seqat run --ortho``).

:class:`Orthorectifier` is the streaming stage: ``add_image(image_id, image, eop)`` turns one
georeferenced image into an :class:`OrthoResult` (and ``ortho/<image>.tif``) as soon as its
EOP is known; :class:`pipeline.mosaic.MosaicBuilder` then pastes it into the growing mosaic.

Per image (all vectorised, no Python loop over pixels):

1. **Footprint**: rays through the image border (observed pixels, undistorted) meet the planes
   at the lowest and highest DSM height under the image; their union, clipped to the DSM and
   to ``max_range_factor`` x the height above ground, is the ground window.
2. **Ground grid**: cells of ``pixel_m`` on a *global* grid (cell edges at multiples of
   ``pixel_m``) so every ortho and the mosaic share it; ``pixel_m`` is the GSD of the first
   image unless given. Heights come from the DSM (bilinear, ``cv2.warpAffine``).
3. **Collinearity** ``p = R^T (X - X0)`` (docs/conventions.md) and the OpenCV distortion
   (:func:`pipeline.camera.distort_normalized`) give the observed pixel of every cell; float32
   with the projection centre subtracted, in row blocks on a small thread pool.
4. **Occlusion** (z-buffer): the nearest depth per image bucket (``np.minimum.at``), widened by a
   3 x 3 minimum filter; a cell farther than that depth plus a tolerance is hidden from this
   image and left empty, so facades and roofs do not smear over the ground they hide.
5. **Resampling** with ``cv2.remap`` (bilinear, or cubic), alpha = seen and inside the image.

Errors: an EOP looking at or above the horizon, a camera below the surface, a DSM that does
not reach the footprint -> :class:`~seqat.errors.InputDataError`; a footprint partly outside
the DSM or partly above the horizon -> a partial ortho and a warning in the result.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pyproj
from affine import Affine
from rasterio.transform import from_origin

from pipeline.camera import PixelCorrector, distort_normalized, pinhole_camera
from pipeline.config import CameraConfig
from pipeline.dsm import Dsm
from pipeline.raster import write_cog
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import rays_world, rotation_matrix
from seqat.types import FloatArray

#: Border pixels sampled per image edge for the footprint.
FOOTPRINT_SAMPLES_PER_EDGE = 16
#: A ray whose downward component is below this (sine of the depression angle) misses the
#: ground: the viewing axis must look at least this far below the horizon.
MIN_DEPRESSION_SIN = math.sin(math.radians(1.0))
#: Cells whose undistorted radius exceeds the image corners' by this factor are not projected
#: (the distortion polynomial folds back outside the field of view).
FOV_RADIUS_MARGIN = 1.05
#: Map value that makes ``cv2.remap`` sample nothing (far outside any image).
OUTSIDE_PX = -1.0e5
#: Rows per block of the projection (fits the work arrays in the cache).
BLOCK_ROWS = 128
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
        Hide cells the camera cannot see (z-buffer).
    occlusion_tolerance_cells : float
        A cell is hidden when it lies farther than the nearest surface in its image bucket by
        more than this many ground cells.
    max_range_factor : float
        The footprint reaches at most this many heights above ground from the nadir point.
    threads : int
        Worker threads of the projection.
    write_images : bool
        Write ``ortho/<image>.tif`` (else only return the raster, e.g. for the mosaic).
    """

    pixel_m: float | None = None
    resampling: Literal["bilinear", "cubic"] = "bilinear"
    occlusion: bool = True
    occlusion_tolerance_cells: float = 3.0
    max_range_factor: float = 3.0
    threads: int = 2
    write_images: bool = True

    def __post_init__(self) -> None:
        if self.pixel_m is not None and not (math.isfinite(self.pixel_m) and self.pixel_m > 0):
            raise ConfigError(f"pixel_m: expected a positive number of metres, "
                              f"got {self.pixel_m!r}")
        if self.resampling not in ("bilinear", "cubic"):
            raise ConfigError(f"resampling: expected bilinear or cubic, got {self.resampling!r}")
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
        The written ``ortho/<image>.tif`` (None with ``write_images=False``).
    raster : OrthoRaster
        Cropped to the cells seen.
    footprint_m : (k, 2) float
        Ground polygon of the image border on the plane at the DSM height under the nadir
        (closed ring, east/north metres).
    seen_cells, occluded_cells, off_dsm_cells : int
        Cells filled; hidden by higher surfaces; without DSM height.
    compute_ms, write_ms : float
        Orthorectification time (projection, occlusion, resampling) and COG writing time.
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
    warnings: tuple[str, ...] = field(default=())


def _nice_pixel(gsd_m: float) -> float:
    digits = PIXEL_SIGNIFICANT_DIGITS - 1 - int(math.floor(math.log10(gsd_m)))
    return round(gsd_m, digits)


def border_pixels(width_px: int, height_px: int, n: int = FOOTPRINT_SAMPLES_PER_EDGE) -> (
        FloatArray):
    """Observed pixels along the image border, clockwise from the top-left corner.

    Returns
    -------
    (4 n, 2) float
        On the outer pixel edges (``-0.5`` and ``size - 0.5``).
    """
    w, h = width_px - 0.5, height_px - 0.5
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    top = np.column_stack([-0.5 + t * (w + 0.5), np.full(n, -0.5)])
    right = np.column_stack([np.full(n, w), -0.5 + t * (h + 0.5)])
    bottom = np.column_stack([w - t * (w + 0.5), np.full(n, h)])
    left = np.column_stack([np.full(n, -0.5), h - t * (h + 0.5)])
    return np.vstack([top, right, bottom, left])


class Orthorectifier:
    """Streaming orthorectification: one image in, one ortho COG out.

    Parameters
    ----------
    dsm : Dsm
        Surface in the working CRS.
    camera : CameraConfig
    crs : pyproj.CRS
        Working CRS (the DSM's and the EOPs').
    out_dir : Path or None
        ``<out_dir>/<image>.tif`` per image (None: nothing written).
    options : OrthoOptions, optional
    """

    def __init__(self, dsm: Dsm, camera: CameraConfig, crs: pyproj.CRS, out_dir: Path | None,
                 options: OrthoOptions | None = None) -> None:
        if not dsm.crs.equals(crs, ignore_axis_order=True):
            raise InputDataError(f"{dsm.source}: DSM CRS {dsm.crs.name!r} differs from the "
                                 f"working CRS {crs.name!r}")
        self.dsm = dsm
        self.camera = camera
        self.crs = crs
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.options = options or OrthoOptions()
        self.pixel_m: float | None = self.options.pixel_m
        self._corrector = PixelCorrector(camera=camera)
        self._pinhole = pinhole_camera(camera)
        corners = self._corrector.ideal_pixels(border_pixels(camera.width_px, camera.height_px, 1))
        xn = (corners[:, 0] - camera.cx_px) / camera.fx_px
        yn = (corners[:, 1] - camera.cy_px) / camera.fx_px
        self._r2_max = float(np.max(xn * xn + yn * yn)) * FOV_RADIUS_MARGIN**2
        self._pool = ThreadPoolExecutor(max_workers=self.options.threads)

    def close(self) -> None:
        """Stop the worker threads."""
        self._pool.shutdown(wait=True)

    def __enter__(self) -> Orthorectifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------------------

    def add_image(self, image_id: str, image: np.ndarray, eop: FloatArray) -> OrthoResult:
        """Orthorectify one image.

        Parameters
        ----------
        image_id : str
        image : (height, width) or (height, width, bands) uint8 or uint16
            RGB (not OpenCV's BGR) or grey, the camera's size.
        eop : (6,) float
            ``[X0_m, Y0_m, Z0_m, omega_rad, phi_rad, kappa_rad]`` (refined EOP).

        Returns
        -------
        OrthoResult

        Raises
        ------
        InputDataError
            Wrong image size or type, the camera looks at or above the horizon or is below
            the surface, or the DSM does not reach the footprint.
        """
        t0 = time.perf_counter()
        image = self._check_image(image_id, image)
        eop = np.asarray(eop, dtype=np.float64).reshape(-1)
        if eop.shape != (6,) or not np.all(np.isfinite(eop)):
            raise InputDataError(f"image {image_id!r}: EOP must be 6 finite numbers, got {eop}")
        warnings: list[str] = []
        R = rotation_matrix(eop[3], eop[4], eop[5])
        axis = -R[:, 2]
        if axis[2] > -MIN_DEPRESSION_SIN:
            elevation = math.degrees(math.asin(float(np.clip(axis[2], -1.0, 1.0))))
            raise InputDataError(
                f"image {image_id!r}: the viewing axis points {elevation:+.1f} deg from the "
                f"horizon (omega {math.degrees(eop[3]):.1f}, phi {math.degrees(eop[4]):.1f} deg); "
                "it must look at least 1 deg below the horizon to be orthorectified")
        z_ground = self._ground_height(image_id, eop)
        height_agl = eop[2] - z_ground
        if self.pixel_m is None:
            self.pixel_m = _nice_pixel(height_agl / self.camera.fx_px)
        p = self.pixel_m
        footprint, window, partial = self._footprint(image_id, eop, R, z_ground, height_agl)
        if partial:
            warnings.append(f"image {image_id!r}: part of the image looks beyond "
                            f"{self.options.max_range_factor:g} x the height above ground (or "
                            "above the horizon); that part is not orthorectified")
        west, south, east, north = window
        col0, col1 = int(math.floor(west / p)), int(math.ceil(east / p))
        row0, row1 = int(math.floor(-north / p)), int(math.ceil(-south / p))
        rows, cols = row1 - row0, col1 - col0
        max_cells = (self.options.max_range_factor * 2 + 1) ** 2 * image.shape[0] * image.shape[1]
        if rows * cols > max_cells:
            raise InputDataError(f"image {image_id!r}: footprint of {cols} x {rows} cells at "
                                 f"{p:g} m is too large (pixel_m too small for this image?)")
        Z = self.dsm.sample_grid(col0 * p, -row0 * p, p, rows, cols)
        u, v, depth, off_nadir, inside = self._project(eop, R, col0, row0, Z)
        on_dsm = np.isfinite(Z)
        seen = inside & on_dsm
        off_dsm = int(np.count_nonzero(inside & ~on_dsm))
        if off_dsm:
            warnings.append(f"image {image_id!r}: {off_dsm} cells of the footprint have no DSM "
                            f"height ({self.dsm.source}); they are left empty")
        occluded = 0
        if self.options.occlusion:
            hidden = self._occlusion(u, v, depth, seen, eop, window)
            if hidden is not None:
                occluded = int(np.count_nonzero(hidden))
                seen &= ~hidden
        if not np.any(seen):
            raise InputDataError(f"image {image_id!r}: no ground cell is seen: the DSM "
                                 f"({self.dsm.source}) does not cover the image footprint "
                                 f"{tuple(round(b, 1) for b in window)}")
        u[~seen] = OUTSIDE_PX
        v[~seen] = OUTSIDE_PX
        interp = cv2.INTER_CUBIC if self.options.resampling == "cubic" else cv2.INTER_LINEAR
        pixels = cv2.remap(image, u, v, interp, borderMode=cv2.BORDER_REPLICATE)
        if pixels.ndim == 2:
            pixels = pixels[:, :, None]
        pixels[~seen] = 0
        raster = _cropped(OrthoRaster(image_id=image_id, col0=col0, row0=row0, pixel_m=p,
                                      pixels=pixels, seen=seen, off_nadir=off_nadir,
                                      height_agl_m=float(height_agl)))
        compute_ms = (time.perf_counter() - t0) * 1e3
        path = None
        t1 = time.perf_counter()
        if self.out_dir is not None and self.options.write_images:
            path = write_ortho(self.out_dir / f"{image_id}.tif", raster, self.crs)
        return OrthoResult(image_id=image_id, path=path, raster=raster, footprint_m=footprint,
                           seen_cells=int(np.count_nonzero(raster.seen)),
                           occluded_cells=occluded, off_dsm_cells=off_dsm,
                           compute_ms=compute_ms, write_ms=(time.perf_counter() - t1) * 1e3,
                           warnings=tuple(warnings))

    # ----------------------------------------------------------------------------------------

    def _check_image(self, image_id: str, image: np.ndarray) -> np.ndarray:
        image = np.asarray(image)
        cam = self.camera
        if image.shape[:2] != (cam.height_px, cam.width_px) or image.ndim not in (2, 3):
            raise InputDataError(f"image {image_id!r}: size {image.shape[1::-1]} px differs "
                                 f"from the camera's {cam.width_px} x {cam.height_px} px")
        if image.dtype not in ALPHA_OPAQUE:
            raise InputDataError(f"image {image_id!r}: pixel type {image.dtype} (expected "
                                 "uint8 or uint16)")
        if image.ndim == 3 and image.shape[2] > 4:  # noqa: PLR2004 - cv2.remap's channel limit
            raise InputDataError(f"image {image_id!r}: {image.shape[2]} bands (at most 4)")
        return np.ascontiguousarray(image)

    def _ground_height(self, image_id: str, eop: FloatArray) -> float:
        """DSM height under the camera (the median of the DSM when that cell is empty)."""
        z = float(self.dsm.sample(eop[:1], eop[1:2])[0])
        if not math.isfinite(z):
            z = float(np.nanmedian(self.dsm.heights_m))
        if eop[2] <= z:
            raise InputDataError(f"image {image_id!r}: the camera (Z0 = {eop[2]:.2f} m) is not "
                                 f"above the DSM ({z:.2f} m under it)")
        return z

    def _ground_points(self, eop: FloatArray, rays: FloatArray, z_m: float, range_m: float) -> (
            tuple[FloatArray, bool]):
        """Rays meet the plane ``Z = z_m``, at most ``range_m`` from the nadir point."""
        down = rays[:, 2] < -MIN_DEPRESSION_SIN
        t = np.where(down, (z_m - eop[2]) / np.where(down, rays[:, 2], -1.0), np.inf)
        horiz = np.linalg.norm(rays[:, :2], axis=1)
        t_max = range_m / np.maximum(horiz, 1e-12)
        partial = bool(np.any(t > t_max))
        t = np.minimum(t, t_max)
        return eop[:2] + t[:, None] * rays[:, :2], partial

    def _footprint(self, image_id: str, eop: FloatArray, R: FloatArray, z_ground: float,
                   height_agl: float) -> tuple[FloatArray, tuple[float, float, float, float],
                                               bool]:
        """Footprint ring on the nadir plane and the ground window over the DSM's heights."""
        ideal = self._corrector.ideal_pixels(border_pixels(self.camera.width_px,
                                                           self.camera.height_px))
        rays = rays_world(np.tile(eop, (len(ideal), 1)), ideal, self._pinhole)
        range_m = self.options.max_range_factor * height_agl
        ring, partial = self._ground_points(eop, rays, z_ground, range_m)
        box = (ring[:, 0].min(), ring[:, 1].min(), ring[:, 0].max(), ring[:, 1].max())
        z_lo, z_hi = self.dsm.height_range(box)
        if not math.isfinite(z_lo):
            z_lo = z_hi = z_ground
        z_hi = min(z_hi, eop[2] - 1e-3 * height_agl)
        pts = [ring]
        for z in (min(z_lo, z_ground), max(z_hi, z_ground)):
            ground, part = self._ground_points(eop, rays, z, range_m * (eop[2] - z) / height_agl)
            pts.append(ground)
            partial |= part
        allp = np.vstack(pts)
        dw, ds, de, dn = self.dsm.bounds
        window = (max(allp[:, 0].min(), dw), max(allp[:, 1].min(), ds),
                  min(allp[:, 0].max(), de), min(allp[:, 1].max(), dn))
        if window[0] >= window[2] or window[1] >= window[3]:
            raise InputDataError(
                f"image {image_id!r}: the DSM ({self.dsm.source}, bounds "
                f"{tuple(round(b, 1) for b in self.dsm.bounds)}) does not cover the image "
                f"footprint {tuple(round(float(b), 1) for b in box)}")
        return np.vstack([ring, ring[:1]]), window, partial

    def _project(self, eop: FloatArray, R: FloatArray, col0: int, row0: int, Z: np.ndarray) -> (
            tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]):
        """Observed pixel, depth and off-nadir tangent of every cell (float32, row blocks)."""
        rows, cols = Z.shape
        p = self.pixel_m
        assert p is not None
        cam = self.camera
        f32 = np.float32
        # Cell centres relative to the projection centre (float32 keeps cm over km).
        dx = ((col0 + np.arange(cols) + 0.5) * p - eop[0]).astype(f32)
        dy = (-(row0 + np.arange(rows) + 0.5) * p - eop[1]).astype(f32)
        Rt = R.T.astype(f32)  # rows: camera axes in world coordinates
        u = np.empty((rows, cols), f32)
        v = np.empty_like(u)
        depth = np.empty_like(u)
        off_nadir = np.empty_like(u)
        inside = np.empty((rows, cols), bool)
        z0 = f32(eop[2])
        r2_max = f32(self._r2_max)
        w_max, h_max = f32(cam.width_px - 0.5), f32(cam.height_px - 0.5)

        def block(r0: int) -> None:
            r1 = min(r0 + BLOCK_ROWS, rows)
            dz = Z[r0:r1] - z0
            y = dy[r0:r1, None]
            p0 = Rt[0, 0] * dx + Rt[0, 1] * y + Rt[0, 2] * dz
            p1 = Rt[1, 0] * dx + Rt[1, 1] * y + Rt[1, 2] * dz
            d = -(Rt[2, 0] * dx + Rt[2, 1] * y + Rt[2, 2] * dz)  # depth along the view axis
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = f32(1) / d
                xn = p0 * inv
                yn = -p1 * inv  # OpenCV frame (x, -y, -z)
                ok = (d > 0) & (xn * xn + yn * yn <= r2_max)
                ub, vb = distort_normalized(xn, yn, cam)
                ok &= (ub >= -0.5) & (ub <= w_max) & (vb >= -0.5) & (vb <= h_max)
                off_nadir[r0:r1] = np.sqrt(dx * dx + y * y) / -dz
            u[r0:r1] = np.where(ok, ub, f32(OUTSIDE_PX))
            v[r0:r1] = np.where(ok, vb, f32(OUTSIDE_PX))
            depth[r0:r1] = d
            inside[r0:r1] = ok

        list(self._pool.map(block, range(0, rows, BLOCK_ROWS)))
        return u, v, depth, off_nadir, inside

    def _occlusion(self, u: np.ndarray, v: np.ndarray, depth: np.ndarray, seen: np.ndarray,
                   eop: FloatArray, window: tuple[float, float, float, float]) -> (
            np.ndarray | None):
        """Cells hidden by nearer surfaces (z-buffer); None when the relief cannot hide any."""
        z_lo, z_hi = self.dsm.height_range(window)
        p = self.pixel_m
        assert p is not None
        if not math.isfinite(z_lo) or z_hi - z_lo <= self.options.occlusion_tolerance_cells * p:
            return None
        fx = self.camera.fx_px
        # Bucket = image spacing of neighbouring cells on the highest surface (no gaps there).
        bucket_px = max(1.0, p * fx / max(eop[2] - z_hi, 1e-6))
        tol_m = self.options.occlusion_tolerance_cells * bucket_px * (eop[2] - z_lo) / fx
        nbu = int(self.camera.width_px / bucket_px) + 2
        nbv = int(self.camera.height_px / bucket_px) + 2
        scale = np.float32(1.0 / bucket_px)
        bu = ((u + np.float32(0.5)) * scale).astype(np.int32)
        bv = ((v + np.float32(0.5)) * scale).astype(np.int32)
        np.clip(bu, 0, nbu - 1, out=bu)
        np.clip(bv, 0, nbv - 1, out=bv)
        index = bv * nbu + bu
        zbuf = np.full(nbu * nbv, np.inf, dtype=np.float32)
        np.minimum.at(zbuf, index[seen], depth[seen])
        zbuf = cv2.erode(zbuf.reshape(nbv, nbu), np.ones((3, 3), np.uint8)).reshape(-1)
        return seen & (depth > zbuf[index] + np.float32(tol_m))


def _cropped(raster: OrthoRaster) -> OrthoRaster:
    """The raster cut to the bounding box of its seen cells."""
    rows = np.flatnonzero(raster.seen.any(axis=1))
    cols = np.flatnonzero(raster.seen.any(axis=0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    if (r0, c0) == (0, 0) and (r1, c1) == raster.shape:
        return raster
    return OrthoRaster(image_id=raster.image_id, col0=raster.col0 + int(c0),
                       row0=raster.row0 + int(r0), pixel_m=raster.pixel_m,
                       pixels=raster.pixels[r0:r1, c0:c1], seen=raster.seen[r0:r1, c0:c1],
                       off_nadir=raster.off_nadir[r0:r1, c0:c1],
                       height_agl_m=raster.height_agl_m)


def write_ortho(path: Path, raster: OrthoRaster, crs: pyproj.CRS) -> Path:
    """Write an ortho as a COG: the image bands plus an alpha band (0 = not seen)."""
    alpha = raster.seen.astype(raster.pixels.dtype) * raster.pixels.dtype.type(
        ALPHA_OPAQUE[raster.pixels.dtype])
    data = np.concatenate([np.moveaxis(raster.pixels, 2, 0), alpha[None]])
    return write_cog(path, data, transform=raster.transform, crs=crs, alpha=True)
