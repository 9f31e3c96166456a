"""Orthorectification of one image at a time on a DSM (``seqat ortho``, ``seqat run --ortho``).

:class:`Orthorectifier` is the streaming stage: ``add_image(image_id, image, eop)`` turns one
georeferenced image into an :class:`OrthoResult` (and ``ortho/<image>.tif``) as soon as its
EOP is known; :class:`pipeline.mosaic.MosaicBuilder` then pastes it into the growing mosaic::

    dsm = read_dsm(out / "dsm.tif", crs)            # or flat_dsm(z_m, bounds, crs)
    mosaic = MosaicBuilder(out / "mosaic.tif", crs)
    with Orthorectifier(dsm, camera, crs, out / "ortho") as ortho:
        for image_id, rgb, eop in frames:           # eop: (6,) metres, radians
            mosaic.add(ortho.add_image(image_id, rgb, eop))
    mosaic.finish()

Per image (all vectorised, no Python loop over pixels):

1. **Footprint**: rays through the image border (observed pixels, undistorted) meet the planes
   at the lowest and highest DSM height under the image; their union, clipped to the DSM and
   to ``max_range_factor`` x the height above ground, is the ground window.
2. **Ground grid**: cells of ``pixel_m`` on a *global* grid (cell edges at multiples of
   ``pixel_m``) so every ortho and the mosaic share it; ``pixel_m`` is the GSD of the first
   image unless given. Heights come from the DSM (bilinear, ``cv2.warpAffine``).
3. **Collinearity** ``p = R^T (X - X0)`` (docs/conventions.md) and the OpenCV distortion
   (closed form :func:`pipeline.flight.camera.distort_normalized`, read from a per-camera
   :class:`pipeline.flight.camera.DistortionTable`) give the observed pixel of every cell; float32
   with the projection centre subtracted, in row blocks on a small thread pool, only over the
   columns the footprint reaches.
4. **Occlusion** (z-buffer): the nearest depth per image bucket from every second cell and
   from the camera-facing walls the DSM implies (``np.minimum.at``), widened by a 3 x 3
   minimum filter; a cell farther than that depth plus a tolerance is hidden from this image
   and left empty, so facades and roofs do not smear over the ground they hide.
5. **Resampling** with ``cv2.remap`` (bilinear, or cubic), alpha = seen and inside the image.

Errors: an EOP looking at or above the horizon, a camera below the surface, a DSM that does
not reach the footprint -> :class:`~seqat.errors.InputDataError`; a footprint partly outside
the DSM or partly above the horizon -> a partial ortho and a warning in the result.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pyproj
from affine import Affine
from rasterio.transform import from_origin

from pipeline.dsm import Dsm
from pipeline.flight.camera import DistortionTable, PixelCorrector, border_pixels, pinhole_camera
from pipeline.flight.schema import CameraConfig
from pipeline.raster import write_cog
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import rays_world, rotation_matrix
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
    background_writes : bool
        Write each COG on a background thread while the next image is orthorectified (at most
        one write pending); the file is complete after the next ``add_image``, ``flush()`` or
        ``close()``.
    """

    pixel_m: float | None = None
    resampling: Literal["bilinear", "cubic"] = "bilinear"
    occlusion: bool = True
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


def _checked_eop(image_id: str, eop: FloatArray) -> FloatArray:
    eop = np.asarray(eop, dtype=np.float64).reshape(-1)
    if eop.shape != (6,) or not np.all(np.isfinite(eop)):
        raise InputDataError(f"image {image_id!r}: EOP must be 6 finite numbers, got {eop}")
    return eop


def _nice_pixel(gsd_m: float) -> float:
    digits = PIXEL_SIGNIFICANT_DIGITS - 1 - int(math.floor(math.log10(gsd_m)))
    return round(gsd_m, digits)


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
        self._lut = DistortionTable.for_camera(camera)
        # An ideal camera (no distortion, square pixels) skips the table: ideal = observed.
        self._distorted = (any((camera.k1, camera.k2, camera.p1, camera.p2, camera.k3))
                           or camera.fy_px != camera.fx_px)
        self._buffers: dict[str, np.ndarray] = {}
        self._pool = ThreadPoolExecutor(max_workers=self.options.threads)
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ortho-cog")
        self._pending: Future[Path] | None = None

    def flush(self) -> None:
        """Wait for the pending COG write; re-raise its error."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def close(self) -> None:
        """Finish the pending write and stop the worker threads."""
        try:
            self.flush()
        finally:
            self._writer.shutdown(wait=True)
            self._pool.shutdown(wait=True)

    def __enter__(self) -> Orthorectifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------------------

    def add_image(self, image_id: str, image: np.ndarray, eop: FloatArray, *,
                  write: bool = True) -> OrthoResult:
        """Orthorectify one image.

        Parameters
        ----------
        image_id : str
        image : (height, width) or (height, width, bands) uint8 or uint16
            RGB (not OpenCV's BGR) or grey, the camera's size.
        eop : (6,) float
            ``[X0_m, Y0_m, Z0_m, omega_rad, phi_rad, kappa_rad]`` (refined EOP).
        write : bool
            Write ``ortho/<image>.tif`` (when the orthorectifier writes images at all).

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
        eop = _checked_eop(image_id, eop)
        warnings: list[str] = []
        R = self._rotation(image_id, eop)
        z_ground = self._ground_height(image_id, eop)
        height_agl = eop[2] - z_ground
        if self.pixel_m is None:
            self.pixel_m = _nice_pixel(height_agl / self.camera.fx_px)
        p = self.pixel_m
        footprint, hull, window, notes = self._footprint(image_id, eop, R, z_ground,
                                                         height_agl)
        warnings.extend(notes)
        west, south, east, north = window
        col0, col1 = int(math.floor(west / p)), int(math.ceil(east / p))
        row0, row1 = int(math.floor(-north / p)), int(math.ceil(-south / p))
        rows, cols = row1 - row0, col1 - col0
        max_cells = (self.options.max_range_factor * 2 + 1) ** 2 * image.shape[0] * image.shape[1]
        if rows * cols > max_cells:
            raise InputDataError(f"image {image_id!r}: footprint of {cols} x {rows} cells at "
                                 f"{p:g} m is too large (pixel_m too small for this image?)")
        Z = self.dsm.sample_grid(col0 * p, -row0 * p, p, rows, cols,
                                 out=self._buffer("Z", (rows, cols)))
        proj = self._project(eop, R, col0, row0, Z, z_ground, hull)
        off_dsm = sum(proj.off_dsm)
        if off_dsm:
            warnings.append(f"image {image_id!r}: {off_dsm} cells of the footprint have no DSM "
                            f"height ({self.dsm.source}); they are left empty")
        t_occ = time.perf_counter()
        occluded = (self._hide_occluded(proj, eop, R, col0, row0, window)
                    if self.options.occlusion else 0)
        occlusion_ms = (time.perf_counter() - t_occ) * 1e3
        if not np.any(proj.seen):
            raise InputDataError(f"image {image_id!r}: no ground cell is seen: the DSM "
                                 f"({self.dsm.source}) does not cover the image footprint "
                                 f"{tuple(round(b, 1) for b in window)}")
        interp = cv2.INTER_CUBIC if self.options.resampling == "cubic" else cv2.INTER_LINEAR
        # Unseen cells map far outside the image: the constant border (0) fills them.
        pixels = cv2.remap(image, proj.uv, None, interp, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0)
        if pixels.ndim == 2:
            pixels = pixels[:, :, None]
        raster = _cropped(OrthoRaster(image_id=image_id, col0=col0, row0=row0, pixel_m=p,
                                      pixels=pixels, seen=proj.seen, off_nadir=proj.off_nadir,
                                      height_agl_m=float(height_agl)))
        compute_ms = (time.perf_counter() - t0) * 1e3
        path = None
        t1 = time.perf_counter()
        if self.out_dir is not None and self.options.write_images and write:
            path = self.out_dir / f"{image_id}.tif"
            self.flush()  # at most one write pending: memory stays bounded
            if self.options.background_writes:
                self._pending = self._writer.submit(write_ortho, path, raster, self.crs)
            else:
                write_ortho(path, raster, self.crs)
        return OrthoResult(image_id=image_id, path=path, raster=raster, footprint_m=footprint,
                           seen_cells=int(np.count_nonzero(raster.seen)),
                           occluded_cells=occluded, off_dsm_cells=off_dsm,
                           compute_ms=compute_ms, write_ms=(time.perf_counter() - t1) * 1e3,
                           occlusion_ms=occlusion_ms,
                           warnings=tuple(warnings))

    def ground_window(self, image_id: str, eop: FloatArray) -> tuple[float, float, float, float]:
        """``(west, south, east, north)`` of the ground an image would cover (what
        :meth:`add_image` grids before cropping to the cells seen), without orthorectifying.

        Raises
        ------
        InputDataError
            As :meth:`add_image` for the geometry (horizon, below the surface, off the DSM).
        """
        eop = _checked_eop(image_id, eop)
        z_ground = self._ground_height(image_id, eop)
        _, _, window, _ = self._footprint(image_id, eop, self._rotation(image_id, eop),
                                          z_ground, eop[2] - z_ground)
        return window

    def footprint_shift_m(self, image_id: str, eop_a: FloatArray, eop_b: FloatArray) -> float:
        """How far the ground under an image moves from ``eop_a`` to ``eop_b``, metres.

        The largest horizontal displacement of the ground points of the image's four corners
        and centre on the plane at the DSM height under the camera (``eop_a``); rays that do
        not meet the plane count as infinite.
        """
        eop_a, eop_b = _checked_eop(image_id, eop_a), _checked_eop(image_id, eop_b)
        w, h = self.camera.width_px - 1.0, self.camera.height_px - 1.0
        observed = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h], [w / 2, h / 2]])
        ideal = self._corrector.ideal_pixels(observed)
        z = self._ground_height(image_id, eop_a)
        ground = []
        for eop in (eop_a, eop_b):
            rays = rays_world(np.tile(eop, (len(ideal), 1)), ideal, self._pinhole)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(rays[:, 2] < -MIN_DEPRESSION_SIN, (z - eop[2]) / rays[:, 2], np.inf)
            ground.append(eop[:2] + t[:, None] * rays[:, :2])
        shift = np.linalg.norm(ground[1] - ground[0], axis=1)
        return float(np.max(np.where(np.isfinite(shift), shift, np.inf)))

    # ----------------------------------------------------------------------------------------

    def _buffer(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """A float32 work array kept from image to image (never part of a result): a fresh
        array of this size costs a page fault per 4 kB on first touch, ~20 % of an image."""
        size = math.prod(shape)
        buf = self._buffers.get(name)
        if buf is None or buf.size < size:
            buf = self._buffers[name] = np.empty(size, np.float32)
        return buf[:size].reshape(shape)

    def _rotation(self, image_id: str, eop: FloatArray) -> FloatArray:
        """``R_world_from_cam``; the viewing axis must look at least 1 deg below the horizon."""
        R = rotation_matrix(eop[3], eop[4], eop[5])
        axis = -R[:, 2]
        if axis[2] > -MIN_DEPRESSION_SIN:
            elevation = math.degrees(math.asin(float(np.clip(axis[2], -1.0, 1.0))))
            raise InputDataError(
                f"image {image_id!r}: the viewing axis points {elevation:+.1f} deg from the "
                f"horizon (omega {math.degrees(eop[3]):.1f}, phi {math.degrees(eop[4]):.1f} deg); "
                "it must look at least 1 deg below the horizon to be orthorectified")
        return R

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
                   height_agl: float) -> tuple[FloatArray, FloatArray,
                                               tuple[float, float, float, float],
                                               tuple[str, ...]]:
        """Footprint ring on the nadir plane, its convex hull over the DSM's heights, the
        ground window (clipped to the DSM) and warnings."""
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
        notes = []
        if partial:
            notes.append(f"image {image_id!r}: part of the image looks beyond "
                         f"{self.options.max_range_factor:g} x the height above ground (or "
                         "above the horizon); that part is not orthorectified")
        if not np.all((ring[:, 0] >= dw) & (ring[:, 0] <= de) & (ring[:, 1] >= ds)
                      & (ring[:, 1] <= dn)):
            notes.append(f"image {image_id!r}: the footprint reaches beyond the DSM "
                         f"({self.dsm.source}); the ortho stops at its edge")
        hull = cv2.convexHull(allp.astype(np.float32)).reshape(-1, 2).astype(np.float64)
        return np.vstack([ring, ring[:1]]), hull, window, tuple(notes)

    def _project(self, eop: FloatArray, R: FloatArray, col0: int, row0: int, Z: np.ndarray,
                 z_ground: float, hull: FloatArray) -> _Projection:
        """Observed pixel, depth and off-nadir tangent of every cell (float32, row blocks).

        With ``d = -p_z`` (the depth) the ideal pixel is ``u = (cx d + f p_x) / d``,
        ``v = (cy d - f p_y) / d``: numerators and depth are affine in the cell's offset from
        the projection centre, so each is an outer sum over the grid's rows and columns plus
        a multiple of the height. The distortion is added from the camera's lookup table
        (:class:`pipeline.flight.camera.DistortionTable`, one ``cv2.remap``). Cells without DSM
        height are projected at ``z_ground`` only to count those inside the image
        (``off_dsm``); they stay unseen.
        In each row block only the columns inside ``hull`` (the footprint's convex hull over
        the DSM's heights, east/north metres) are projected.
        """
        rows, cols = Z.shape
        p = self.pixel_m
        assert p is not None
        f32 = np.float32
        dx = (col0 + np.arange(cols) + 0.5) * p - eop[0]
        dy = -(row0 + np.arange(rows) + 0.5) * p - eop[1]
        k = self._lut_coefficients(R)
        col_terms = (k[:, 0:1] * dx[None, :]).astype(f32)  # (3, cols)
        row_terms = (k[:, 1:2] * dy[None, :]).astype(f32)  # (3, rows)
        k_f32 = k[:, 2].astype(f32)
        dxy2 = ((dx**2).astype(f32), (dy**2).astype(f32))  # squared horizontal offsets
        ks = OCCLUSION_SUBSAMPLE
        sub_shape = (-(-rows // ks), -(-cols // ks))
        out = _Projection(uv=self._buffer("uv", (rows, cols, 2)),
                          off_nadir=np.empty((rows, cols), f32),
                          seen=np.empty((rows, cols), bool), off_dsm=[],
                          uv_s=self._buffer("uv_s", sub_shape + (2,)),
                          depth_s=self._buffer("depth_s", sub_shape),
                          seen_s=np.empty(sub_shape, bool), z_s=self._buffer("z_s", sub_shape))
        z0, z_fill = f32(eop[2]), f32(z_ground)
        margin = 1.0 if self.options.resampling == "cubic" else 0.0  # kernel inside the image
        lo = (margin, margin)
        hi = (self.camera.width_px - 1 - margin, self.camera.height_px - 1 - margin)
        has_holes = bool(np.isnan(Z).any())

        def block(r0: int) -> None:
            rs = slice(r0, min(r0 + BLOCK_ROWS, rows))
            # Only the columns the footprint can reach in these rows are projected.
            c_lo, c_hi = _hull_columns(hull, col0, row0 + rs.start, row0 + rs.stop, p, cols)
            ss = slice(rs.start // ks, -(-rs.stop // ks))
            for part in (slice(0, c_lo), slice(c_hi, cols)):
                out.seen[rs, part] = False
                out.uv[rs, part] = OUTSIDE_PX
                out.off_nadir[rs, part] = np.inf
                out.depth_s[ss, -(-part.start // ks):-(-part.stop // ks)] = np.inf
            cs = slice(c_lo, c_hi)
            if c_lo < c_hi:
                self._project_block(out, rs, cs, Z, k_f32, row_terms, col_terms, dxy2,
                                    z0, z_fill, has_holes, lo, hi)
            # Every ks-th cell for the z-buffer, copied while the block is in the cache.
            out.uv_s[ss] = out.uv[rs][::ks, ::ks]
            out.seen_s[ss] = out.seen[rs][::ks, ::ks]
            out.z_s[ss] = Z[rs][::ks, ::ks]

        list(self._pool.map(block, range(0, rows, BLOCK_ROWS)))
        return out

    def _project_block(self, out: _Projection, rs: slice, cs: slice, Z: np.ndarray,
                       kz: np.ndarray, row_terms: np.ndarray, col_terms: np.ndarray,
                       dxy2: tuple[np.ndarray, np.ndarray], z0: np.float32, z_fill: np.float32,
                       has_holes: bool, lo: tuple[float, float],
                       hi: tuple[float, float]) -> None:
        """Project the cells ``[rs, cs]`` into ``out`` (see :meth:`_project`)."""
        f32 = np.float32
        lut = self._lut
        dz = Z[rs, cs] - z0
        no_height = np.isnan(dz) if has_holes else None
        if no_height is not None:
            dz[no_height] = z_fill - z0
        depth = kz[2] * dz
        depth += row_terms[2, rs, None]
        depth += col_terms[2, cs]
        behind = depth <= 0
        any_behind = bool(behind.any())
        uv_obs = out.uv[rs, cs]  # written in place (OpenCV takes the strided view)
        uv = np.empty(depth.shape + (2,), f32) if self._distorted else uv_obs
        for c in (0, 1):
            num = kz[c] * dz
            num += row_terms[c, rs, None]
            num += col_terms[c, cs]
            np.divide(num, depth, out=uv[:, :, c])
        if any_behind:
            uv[behind] = OUTSIDE_PX
            depth[behind] = np.nan
        if self._distorted:
            delta = cv2.remap(lut.table, uv, None, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=(OUTSIDE_PX,) * 4)
            cv2.scaleAdd(uv, lut.step_px, delta, dst=uv_obs)
        seen = out.seen[rs, cs]
        np.greater(cv2.inRange(uv_obs, lo, hi), 0, out=seen)
        if no_height is not None:
            out.off_dsm.append(int(np.count_nonzero(seen & no_height)))
            seen &= ~no_height
            uv_obs[~seen] = OUTSIDE_PX
        ks = OCCLUSION_SUBSAMPLE  # the z-buffer needs the depth of every ks-th cell only
        out.depth_s[rs.start // ks:-(-rs.stop // ks), -(-cs.start // ks):-(-cs.stop // ks)] = (
            depth[(-rs.start) % ks::ks, (-cs.start) % ks::ks])
        hdist = np.sqrt(dxy2[0][cs] + dxy2[1][rs, None])
        np.divide(hdist, dz, out=hdist)
        np.negative(hdist, out=out.off_nadir[rs, cs])

    def _lut_coefficients(self, R: FloatArray) -> FloatArray:
        """(3, 3) map from ``(X - X0, Y - Y0, Z - Z0)`` to (numerator u, numerator v, depth).

        ``depth = -p_z``; ``u = (cx d + f p_x) / d``, ``v = (cy d - f p_y) / d`` with the
        distortion table's origin and step folded in: ``num_u / d = (u - u0) / step``
        (an ideal camera: ``num_u / d = u``).
        """
        lut = self._lut
        u0, v0, step = (lut.u0, lut.v0, lut.step_px) if self._distorted else (0.0, 0.0, 1.0)
        f, cx, cy = self._pinhole.f_px, self._pinhole.cx_px, self._pinhole.cy_px
        Rt = R.T  # rows: camera axes in world coordinates
        k = np.vstack([f * Rt[0] - (cx - u0) * Rt[2],
                       -f * Rt[1] - (cy - v0) * Rt[2],
                       -Rt[2]])
        k[:2] /= step
        return k

    def _project_points(self, k: FloatArray, offsets_m: FloatArray) -> (
            tuple[np.ndarray, np.ndarray]):
        """Observed pixels (OUTSIDE_PX where not seeable) and depths of scattered points.

        Parameters
        ----------
        k : (3, 3) float
            :meth:`_lut_coefficients`.
        offsets_m : (n, 3) float
            Points minus the projection centre.
        """
        x, y, z = (np.ascontiguousarray(offsets_m[:, i], dtype=np.float32) for i in range(3))
        kf = k.astype(np.float32)
        num_u, num_v, depth = (kf[i, 0] * x + kf[i, 1] * y + kf[i, 2] * z for i in range(3))
        uv = np.empty((len(x), 2), np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(num_u, depth, out=uv[:, 0])
            np.divide(num_v, depth, out=uv[:, 1])
        uv[~(depth > 0)] = OUTSIDE_PX
        if not self._distorted:
            return uv, depth
        n = len(uv)
        # cv2.remap needs maps under 32767 x 32767: lay the points out in rows.
        rows = -(-n // POINTS_PER_ROW)
        grid = np.full((rows * POINTS_PER_ROW, 2), OUTSIDE_PX, np.float32)
        grid[:n] = uv
        delta = cv2.remap(self._lut.table, grid.reshape(rows, POINTS_PER_ROW, 2), None,
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(OUTSIDE_PX,) * 4)
        return uv * np.float32(self._lut.step_px) + delta.reshape(-1, 2)[:n], depth

    def _facade_points(self, Z: np.ndarray, stride: int, col0: int, row0: int,
                       eop: FloatArray, k: FloatArray, step_px: float, min_jump_m: float) -> (
            tuple[np.ndarray, np.ndarray]):
        """Samples of the vertical walls a 2.5D DSM implies, for the z-buffer.

        ``Z`` holds every ``stride``-th cell of the grid in each direction (the grid's top-left
        cell is ``(col0, row0)``). A wall faces the camera where a cell stands more than
        ``min_jump_m`` above its neighbours towards the nadir point (the lowest of the two
        axis neighbours and the diagonal one on that side); the segment from that neighbour's
        height to the cell's is sampled every ``step_px`` image pixels (from its projected
        length). Walls facing away are hidden by their roofs and need no samples.

        Returns
        -------
        uv : (m, 2) float32
        depth : (m,) float32
        """
        p = self.pixel_m
        assert p is not None
        rows, cols = Z.shape
        filled = np.where(np.isnan(Z), np.float32(np.inf), Z)
        # Candidates: above their lowest 8-neighbour (one fast minimum filter) ...
        lowest8 = cv2.erode(filled, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        with np.errstate(invalid="ignore"):
            r, c = np.nonzero(Z - lowest8 > min_jump_m)
        # ... then the neighbours towards the nadir point (columns east, rows south).
        x_cells = (col0 + stride * np.arange(cols) + 0.5) * p - eop[0]
        y_cells = -(row0 + stride * np.arange(rows) + 0.5) * p - eop[1]
        dc = ((x_cells < 0).astype(np.intp) - (x_cells > 0))[c]
        dr = ((y_cells > 0).astype(np.intp) - (y_cells < 0))[r]
        rn, cn = np.clip(r + dr, 0, rows - 1), np.clip(c + dc, 0, cols - 1)
        lowest = np.minimum(np.minimum(filled[rn, c], filled[r, cn]), filled[rn, cn])
        with np.errstate(invalid="ignore"):
            facing = Z[r, c] - lowest > min_jump_m
        r, c, lowest = r[facing], c[facing], lowest[facing]
        empty = (np.empty((0, 2), np.float32), np.empty(0, np.float32))
        if r.size == 0:
            return empty
        x, y = x_cells[c], y_cells[r]
        top, bottom = Z[r, c].astype(np.float64), lowest.astype(np.float64)
        uv_top, _ = self._project_points(k, np.column_stack([x, y, top - eop[2]]))
        uv_bot, _ = self._project_points(k, np.column_stack([x, y, bottom - eop[2]]))
        length = np.linalg.norm(uv_top - uv_bot, axis=1)
        length[~np.isfinite(length) | (length > MAX_FACADE_PX)] = MAX_FACADE_PX
        n = np.ceil(length / step_px).astype(np.int64) + 1
        seg = np.repeat(np.arange(r.size), n)
        first = np.repeat(np.cumsum(n) - n, n)
        t = (np.arange(seg.size) - first) / np.maximum(n[seg] - 1, 1)
        z = bottom[seg] + t * (top[seg] - bottom[seg])
        uv, depth = self._project_points(k, np.column_stack([x[seg], y[seg], z - eop[2]]))
        return uv, depth

    def _hide_occluded(self, proj: _Projection, eop: FloatArray, R: FloatArray,
                       col0: int, row0: int,
                       window: tuple[float, float, float, float]) -> int:
        """Mark cells hidden by nearer surfaces as unseen (z-buffer); the number hidden.

        Skipped (0) when the relief under the window is within the tolerance. The buffer is
        filled from every ``OCCLUSION_SUBSAMPLE``-th cell in each direction (``np.minimum.at``)
        and from the camera-facing walls (:meth:`_facade_points`), with buckets of the image
        spacing of those cells on the highest surface, widened by a 3 x 3 minimum filter. The
        same sub-sampled cells then read their bucket (``cv2.remap``, nearest) and are hidden
        when they lie farther than the tolerance behind it; every cell of a k x k block takes
        its sampled cell's verdict (occlusion edges are exact to k cells).
        """
        z_lo, z_hi = self.dsm.height_range(window)
        p = self.pixel_m
        assert p is not None
        if not math.isfinite(z_lo) or z_hi - z_lo <= self.options.occlusion_tolerance_cells * p:
            return 0
        fx = self.camera.fx_px
        k = OCCLUSION_SUBSAMPLE
        # Integer bucket: pixel (i, j) (nearest to an observed position) lies in bucket
        # (i // b, j // b), so the buffer blown up by b reads back with one nearest remap.
        b = max(1, math.ceil(k * p * fx / max(eop[2] - z_hi, 1e-6)))
        tol = np.float32(self.options.occlusion_tolerance_cells * b * (eop[2] - z_lo) / fx)
        width, height = self.camera.width_px, self.camera.height_px
        nbu, nbv = -(-width // b), -(-height // b)
        uv_s, seen_s, depth_s = proj.uv_s, proj.seen_s, proj.depth_s
        # Bucket of the nearest pixel: floor((u + 0.5) / b); as a map coordinate read with
        # nearest-neighbour rounding: (u + 0.5) / b - 0.5.
        uv_b = cv2.addWeighted(uv_s, 1.0 / b, uv_s, 0.0, 0.5 / b - 0.5)
        pix = (uv_b + np.float32(0.5)).astype(np.int32)
        index = pix[:, :, 1] * nbu + pix[:, :, 0]
        index[~seen_s] = nbu * nbv  # unseen cells go to a spare slot
        zbuf = np.full(nbu * nbv + 1, np.inf, dtype=np.float32)
        with np.errstate(invalid="ignore"):  # unseen cells (spare slot) may have NaN depth
            np.minimum.at(zbuf, index.ravel(), depth_s.ravel())
        # Walls between cells of very different height (facades) hide what lies behind them.
        # Wall samples 2 buckets apart: the 3 x 3 minimum filter closes the gaps between them.
        uv_f, depth_f = self._facade_points(proj.z_s, k, col0, row0, eop,
                                            self._lut_coefficients(R), 2.0 * b, float(tol))
        if len(depth_f):
            pf = np.floor((uv_f + 0.5) / b).astype(np.int64)
            inside = (pf[:, 0] >= 0) & (pf[:, 0] < nbu) & (pf[:, 1] >= 0) & (pf[:, 1] < nbv)
            np.minimum.at(zbuf, pf[inside, 1] * nbu + pf[inside, 0], depth_f[inside])
        zbuf = cv2.erode(zbuf[:-1].reshape(nbv, nbu), np.ones((3, 3), np.uint8))
        zbuf[~np.isfinite(zbuf)] = np.float32(3.0e38)
        # The test runs on the same sub-sampled cells; each full cell takes its k x k block's.
        nearest = cv2.remap(zbuf, uv_b, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        nearest += tol
        hidden_s = (seen_s & (depth_s > nearest)).view(np.uint8)
        rows, cols = proj.seen.shape
        if not hidden_s.any():
            return 0
        hidden_full = cv2.resize(hidden_s, (hidden_s.shape[1] * k, hidden_s.shape[0] * k),
                                 interpolation=cv2.INTER_NEAREST)
        hidden_counts: list[int] = []

        def block(r0: int) -> None:
            rs = slice(r0, min(r0 + BLOCK_ROWS, rows))
            seen = proj.seen[rs]
            hidden = seen & hidden_full[rs, :cols].view(bool)
            seen &= ~hidden
            proj.uv[rs][hidden] = OUTSIDE_PX
            hidden_counts.append(int(np.count_nonzero(hidden)))

        list(self._pool.map(block, range(0, proj.seen.shape[0], BLOCK_ROWS)))
        return sum(hidden_counts)


@dataclass(kw_only=True, eq=False)
class _Projection:
    """Per-cell work arrays of one image (float32 / bool, the ortho grid's shape)."""

    uv: np.ndarray  # (rows, cols, 2) observed pixels, OUTSIDE_PX where unseen
    off_nadir: np.ndarray
    seen: np.ndarray
    off_dsm: list[int]
    # Every OCCLUSION_SUBSAMPLE-th cell in each direction (z-buffer): observed pixels, depth
    # (NaN behind the camera, inf outside the footprint), seen, and the DSM heights there.
    uv_s: np.ndarray
    depth_s: np.ndarray
    seen_s: np.ndarray
    z_s: np.ndarray


def _hull_columns(hull: FloatArray, col0: int, grow0: int, grow1: int, pixel_m: float,
                  cols: int) -> tuple[int, int]:
    """Columns ``[c_lo, c_hi)`` of the grid that the convex polygon ``hull`` reaches in the
    global rows ``[grow0, grow1)`` (one cell of margin); ``(0, 0)`` when none.

    The x range of a convex polygon within a horizontal band: its vertices inside the band
    and its edges' crossings of the band's two lines.
    """
    y_hi, y_lo = -grow0 * pixel_m, -grow1 * pixel_m
    a, b = hull, np.roll(hull, -1, axis=0)
    xs = [a[(a[:, 1] >= y_lo) & (a[:, 1] <= y_hi), 0]]
    for y in (y_lo, y_hi):
        crosses = (a[:, 1] - y) * (b[:, 1] - y) < 0
        t = (y - a[crosses, 1]) / (b[crosses, 1] - a[crosses, 1])
        xs.append(a[crosses, 0] + t * (b[crosses, 0] - a[crosses, 0]))
    x = np.concatenate(xs)
    if x.size == 0:
        return 0, 0
    c_lo = int(math.floor(x.min() / pixel_m)) - col0 - 1
    c_hi = int(math.ceil(x.max() / pixel_m)) - col0 + 1
    return max(c_lo, 0), min(max(c_hi, 0), cols)


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
