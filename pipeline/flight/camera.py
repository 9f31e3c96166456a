"""From the ``flight.yaml`` camera to seqat's camera and its frames' pixels, and back.

seqat's camera has square pixels (:class:`seqat.types.PinholeCamera`, ``f_px = fx_px``) and
carries the lens distortion in its model: the image points reach seqat as observed pixels
with only the pixel aspect made square (``v`` scaled by ``fx / fy`` about ``cy``;
:func:`frame_camera`), so their residuals, weights and σ0 are in the pixels the features were
measured in, with or without self-calibration (docs/architecture.md, *Distortion is in the
model*). *Ideal pixels* (:class:`PixelCorrector`: the distortion inverted by seqat's Newton
iteration, :meth:`CameraConfig.ideal_normalized`, then the camera matrix
``P = [[fx, 0, cx], [0, fx, cy], [0, 0, 1]]``) serve the geometry outside the
estimator: rays for intersections, footprints and the orthorectifier. The way back (ideal ->
observed, :func:`distort_normalized`, used by the orthorectifier) applies the OpenCV model in
closed form, vectorised over whole grids.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from pipeline.flight.schema import CameraConfig, SelfCalibrationConfig
from seqat.calibration import SelfCalibration
from seqat.types import FloatArray, PinholeCamera

#: Default number of samples per image edge of :func:`border_pixels`.
BORDER_SAMPLES_PER_EDGE = 16
#: Distortion lookup table: node spacing and margin around the image's ideal pixels (px),
#: border samples per edge used to find that range. Outside it cells are not projected (the
#: distortion polynomial may fold back far outside the field of view).
LUT_STEP_PX = 4.0
LUT_MARGIN_PX = 8.0
LUT_BORDER_SAMPLES = 64


def pinhole_camera(camera: CameraConfig) -> PinholeCamera:
    """The ideal pinhole camera of ``camera`` (``f_px = fx_px``, no distortion): the camera of
    its ideal pixels (:class:`PixelCorrector`)."""
    return PinholeCamera(f_px=camera.fx_px, cx_px=camera.cx_px, cy_px=camera.cy_px,
                         width_px=camera.width_px, height_px=camera.height_px)


def seqat_camera(camera: CameraConfig) -> tuple[PinholeCamera, CameraConfig]:
    """seqat's camera for ``camera`` and the pixel camera of its frames.

    seqat's camera carries ``camera``'s distortion (fixed, or the prior of self-calibration:
    docs/algorithm.md, *Self-calibration*); image points reach it as observed pixels with
    only the pixel aspect made square (``v`` scaled by ``fx / fy`` about ``cy``). Returns
    that camera and the distortion-free camera whose :class:`PixelCorrector` maps observed
    pixels to seqat's.
    """
    square = dataclasses.replace(camera, model="OPENCV", k1=0.0, k2=0.0, p1=0.0, p2=0.0,
                                 k3=0.0)
    return camera.model_camera, square


def frame_camera(camera: CameraConfig, self_calibration: SelfCalibrationConfig,
                 from_exif: bool) -> tuple[SelfCalibration | None, PinholeCamera,
                                           PixelCorrector]:
    """The flight's self-calibration (``flight.yaml`` ``self_calibration:`` for a camera
    from EXIF or not), seqat's camera and the corrector from observed pixels to its
    frames' (:func:`seqat_camera`: the same with or without self-calibration, so a
    calibration whose every parameter is held gives the fixed camera's solution)."""
    seqat_cam, square = seqat_camera(camera)
    return self_calibration.resolve(from_exif), seqat_cam, PixelCorrector(camera=square)


def estimated_camera(prior: CameraConfig, estimate: PinholeCamera) -> CameraConfig:
    """The ``flight.yaml``-style camera of a self-calibrated seqat camera ``estimate``
    (:func:`seqat_camera` inverted: the aspect of ``prior`` restored)."""
    aspect = prior.fy_px / prior.fx_px
    return dataclasses.replace(
        prior, model="OPENCV", fx_px=estimate.f_px, fy_px=estimate.f_px * aspect,
        cx_px=estimate.cx_px, cy_px=prior.cy_px + (estimate.cy_px - prior.cy_px) * aspect,
        k1=estimate.k1, k2=estimate.k2, p1=estimate.p1, p2=estimate.p2, k3=estimate.k3)


@dataclass(frozen=True, kw_only=True, eq=False)
class PixelCorrector:
    """Maps observed pixels of a configured camera to ideal pinhole pixels.

    Parameters
    ----------
    camera : CameraConfig
    """

    camera: CameraConfig

    @property
    def is_identity(self) -> bool:
        """True when observed pixels already are ideal pixels (no distortion, square pixels)."""
        return not self.camera.has_distortion and self.camera.fx_px == self.camera.fy_px

    def ideal_pixels(self, uv_px: FloatArray) -> FloatArray:
        """Remove lens distortion (and pixel aspect) from observed pixel coordinates.

        Parameters
        ----------
        uv_px : (k, 2) float
            Observed OpenCV pixels (u right, v down, origin at the centre of the top-left pixel).

        Returns
        -------
        (k, 2) float
            Pixels of the ideal camera :func:`pinhole_camera`.
        """
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        if self.is_identity or uv.shape[0] == 0:
            return uv.copy()
        cam = self.camera
        # seqat's inverse of the distortion, the estimator's own (OpenCV's fixed-point
        # undistortPoints stopped up to 1 px short in a strong barrel lens's corners)
        xn, yn, _ = cam.ideal_normalized(uv[:, 0], uv[:, 1])
        return np.column_stack([cam.fx_px * xn + cam.cx_px, cam.fx_px * yn + cam.cy_px])

    def observed_pixels(self, uv_px: FloatArray) -> FloatArray:
        """Add lens distortion (and pixel aspect) to ideal pixels: inverse of :meth:`ideal_pixels`.

        Parameters
        ----------
        uv_px : (k, 2) float
            Ideal pinhole pixels (:func:`pinhole_camera`).

        Returns
        -------
        (k, 2) float
            Observed OpenCV pixels.
        """
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        cam = self.camera
        xn = (uv[:, 0] - cam.cx_px) / cam.fx_px
        yn = (uv[:, 1] - cam.cy_px) / cam.fx_px
        u, v = distort_normalized(xn, yn, cam)
        return np.column_stack([u, v])


def distort_normalized(xn: np.ndarray, yn: np.ndarray, camera: CameraConfig) -> (
        tuple[np.ndarray, np.ndarray]):
    """OpenCV projection of normalised camera coordinates to observed pixels.

    ``r2 = xn^2 + yn^2``, ``radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3``,
    ``xd = xn radial + 2 p1 xn yn + p2 (r2 + 2 xn^2)``,
    ``yd = yn radial + p1 (r2 + 2 yn^2) + 2 p2 xn yn``, ``u = fx xd + cx``, ``v = fy yd + cy``
    (OpenCV's ``projectPoints`` model with ``k4..k6 = s1..s4 = 0``; pinned against it and
    against :meth:`PixelCorrector.ideal_pixels` by tests/pipeline/flight/test_camera.py).

    Parameters
    ----------
    xn, yn : array of float32 or float64 (any shape)
        Normalised coordinates in the OpenCV camera frame ``(x, -y, -z)``:
        ``xn = x_cv / z_cv``, ``yn = y_cv / z_cv``.
    camera : CameraConfig

    Returns
    -------
    u_px, v_px : arrays of the input shape and dtype
        Observed OpenCV pixels. Valid only within the image's field of view: far outside
        it the polynomial may fold back (callers bound ``r2``).
    """
    dtype = np.result_type(xn, yn)
    c = {name: dtype.type(getattr(camera, name)) for name in (
        "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2")}
    if not camera.has_distortion:
        return c["fx_px"] * xn + c["cx_px"], c["fy_px"] * yn + c["cy_px"]
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (c["k1"] + r2 * (c["k2"] + r2 * c["k3"]))
    xy2 = 2 * xn * yn
    xd = xn * radial + c["p1"] * xy2 + c["p2"] * (r2 + 2 * xn * xn)
    yd = yn * radial + c["p1"] * (r2 + 2 * yn * yn) + c["p2"] * xy2
    return c["fx_px"] * xd + c["cx_px"], c["fy_px"] * yd + c["cy_px"]


def border_pixels(width_px: int, height_px: int, n: int = BORDER_SAMPLES_PER_EDGE) -> (
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


@dataclass(frozen=True, kw_only=True, eq=False)
class DistortionTable:
    """Ideal -> observed pixels as a table, read with ``cv2.remap`` (bilinear).

    ``table[j, i] = observed(u0 + i step, v0 + j step) - (i step, j step)``: for ideal pixels
    ``(u, v)`` the observed ones are ``step * ((u - u0) / step, (v - v0) / step) + table``
    interpolated there (``cv2.remap(table, (u - u0) / step, ...)``). Covers the ideal pixels
    of the image plus ``LUT_MARGIN_PX``; outside it the caller's border value applies (the
    orthorectifier's lies far outside any image, so such cells are unseen: the polynomial may
    fold back there). The OpenCV polynomial is smooth: bilinear interpolation over
    ``LUT_STEP_PX`` adds < 0.01 px (tests/pipeline/flight/test_camera.py).
    """

    table: np.ndarray  # (nv, nu, 2) float32
    u0: float
    v0: float
    step_px: float

    @classmethod
    def for_camera(cls, camera: CameraConfig) -> DistortionTable:
        """The table of ``camera`` (closed-form :func:`distort_normalized` at every node)."""
        corrector = PixelCorrector(camera=camera)
        ideal = corrector.ideal_pixels(border_pixels(camera.width_px, camera.height_px,
                                                     LUT_BORDER_SAMPLES))
        u0 = math.floor(ideal[:, 0].min()) - LUT_MARGIN_PX
        v0 = math.floor(ideal[:, 1].min()) - LUT_MARGIN_PX
        nu = int(math.ceil((ideal[:, 0].max() + LUT_MARGIN_PX - u0) / LUT_STEP_PX)) + 2
        nv = int(math.ceil((ideal[:, 1].max() + LUT_MARGIN_PX - v0) / LUT_STEP_PX)) + 2
        gu = np.arange(nu) * LUT_STEP_PX
        gv = np.arange(nv) * LUT_STEP_PX
        U, V = np.meshgrid(u0 + gu, v0 + gv)
        uo, vo = distort_normalized((U - camera.cx_px) / camera.fx_px,
                                    (V - camera.cy_px) / camera.fx_px, camera)
        table = np.stack([uo - gu[None, :], vo - gv[:, None]], axis=-1).astype(np.float32)
        return cls(table=table, u0=float(u0), v0=float(v0), step_px=float(LUT_STEP_PX))
