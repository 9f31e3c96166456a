"""What a flight gives a run: :class:`RunInputs` (``run.json`` ``inputs``) and skipped images."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj

from pipeline.common.tables import NavTable
from pipeline.flight.schema import CameraConfig


@dataclass(frozen=True, kw_only=True)
class SkippedImage:
    """An image left out of a run, and why (``run.json`` ``skipped``)."""

    image: str
    reason: str


@dataclass(frozen=True, kw_only=True, eq=False)
class RunInputs:
    """What the estimator was given: the self-contained part of a run folder.

    Attributes
    ----------
    crs : pyproj.CRS
        Working CRS (projected, metres).
    camera : CameraConfig
        Camera of the observed (full-resolution) pixels.
    camera_approximate : bool
        ``True`` when the camera comes from EXIF (focal length and sensor size), not from a
        calibration.
    nav : NavTable
        GPS/INS exterior orientations in the working CRS (direct georeferencing), in
        acquisition order; only the images of the run.
    nav_sigma : (6,) float
        A priori σ of ``[X, Y, Z]`` (m) and ``[omega, phi, kappa]`` (rad).
    sigma_image_px : float
    images_dir : Path or None
        Folder of the flight's images (image flights), else ``None``.
    skipped : tuple[SkippedImage, ...]
        Images of the flight left out of the run.
    warnings : tuple[str, ...]
        One line each (e.g. an image of another size, a height of unknown kind).
    """

    crs: pyproj.CRS
    camera: CameraConfig
    camera_approximate: bool
    nav: NavTable
    nav_sigma: np.ndarray
    sigma_image_px: float
    images_dir: Path | None = None
    skipped: tuple[SkippedImage, ...] = ()
    warnings: tuple[str, ...] = ()
