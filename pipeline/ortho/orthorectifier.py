"""Orthorectification of one image at a time on a DSM (``seqat ortho``, ``seqat run --ortho``).

:class:`Orthorectifier` is the streaming stage: ``add_image(image_id, image, eop)`` turns one
georeferenced image into an :class:`OrthoResult` (and ``ortho/<image>.tif``) as soon as its
EOP is known; :class:`pipeline.ortho.mosaic.MosaicBuilder` then pastes it into the growing mosaic::

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
from pathlib import Path

import cv2
import numpy as np
import pyproj

from pipeline.flight.camera import DistortionTable, PixelCorrector, pinhole_camera
from pipeline.flight.schema import CameraConfig
from pipeline.ortho.base import (
    ALPHA_OPAQUE,
    MIN_DEPRESSION_SIN,
    PIXEL_SIGNIFICANT_DIGITS,
    OrthoOptions,
    OrthoRaster,
    OrthoResult,
)
from pipeline.ortho.dsm import Dsm
from pipeline.ortho.footprint import FootprintMixin
from pipeline.ortho.occlusion import OcclusionMixin
from pipeline.ortho.projection import ProjectionMixin
from pipeline.ortho.raycast import DsmMesh
from pipeline.ortho.writing import cropped, write_ortho
from seqat.errors import InputDataError
from seqat.geometry import rays_world, rotation_matrix
from seqat.types import FloatArray


def _checked_eop(image_id: str, eop: FloatArray) -> FloatArray:
    eop = np.asarray(eop, dtype=np.float64).reshape(-1)
    if eop.shape != (6,) or not np.all(np.isfinite(eop)):
        raise InputDataError(f"image {image_id!r}: EOP must be 6 finite numbers, got {eop}")
    return eop


def _nice_pixel(gsd_m: float) -> float:
    digits = PIXEL_SIGNIFICANT_DIGITS - 1 - int(math.floor(math.log10(gsd_m)))
    return round(gsd_m, digits)


class Orthorectifier(FootprintMixin, ProjectionMixin, OcclusionMixin):
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
        self._distorted = not self._corrector.is_identity
        self._buffers: dict[str, np.ndarray] = {}
        self._mesh: DsmMesh | None = None  # the DSM for ray-cast occlusion, built on first use
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
        if not self.options.occlusion:
            occluded = 0
        elif self.options.occlusion_method == "raycast":
            occluded = self._hide_occluded_raycast(proj, eop, col0, row0, window)
        else:
            occluded = self._hide_occluded(proj, eop, R, col0, row0, window)
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
        raster = cropped(OrthoRaster(image_id=image_id, col0=col0, row0=row0, pixel_m=p,
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

    def auto_pixel_m(self, image_id: str, eop: FloatArray) -> float:
        """The pixel size :meth:`add_image` fixes on its first image when none is given: the
        GSD at the nadir, rounded to 3 significant digits (a campaign fixes one for all its
        flights, :mod:`pipeline.campaign`).

        Raises
        ------
        InputDataError
            As :meth:`add_image` for a camera below the surface or off the DSM.
        """
        eop = _checked_eop(image_id, eop)
        return _nice_pixel((eop[2] - self._ground_height(image_id, eop)) / self.camera.fx_px)

    def prepare_occlusion(self) -> int:
        """Build the DSM's ray-casting mesh now (``occlusion_method: raycast``; otherwise on
        the first image that needs it); the number of its triangles (0 for the z-buffer)."""
        if self.options.occlusion_method != "raycast":
            return 0
        if self._mesh is None:
            self._mesh = DsmMesh(self.dsm)
        return self._mesh.triangles

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

