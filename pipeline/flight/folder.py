"""Flight folders: ``flight.yaml`` + navigation + observations or images.

:func:`read_flight` validates the configuration and the CRS and reads the navigation fully
(one small row per image). :class:`FrameSource` then streams ``observations.csv`` and yields
one :class:`seqat.types.Frame` per image in acquisition order (nav order), holding only the
rows of the current image: the same loop serves a batch run and, later, a growing folder.

Every problem with the input raises :class:`~seqat.errors.InputDataError` (or
:class:`~seqat.errors.ConfigError` for ``flight.yaml``) with ``path:line:`` and the field and
value. File formats: docs/formats.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pyproj

from pipeline.common.columns import FLIGHT_YAML, IMAGES_DIR, OBS_FRAME_COLUMN, TRUTH_DIR
from pipeline.common.csvio import CsvRow, read_csv
from pipeline.common.paths import exists_as_anything, file_problem, folder_problem
from pipeline.common.tables import GroundPoints, NavTable
from pipeline.common.text import first_few
from pipeline.flight.camera import PixelCorrector, frame_camera
from pipeline.flight.consistency import check_one_camera, crs_area_warning, duplicate_images
from pipeline.flight.dropout import dropout_sigma, predict_missing
from pipeline.flight.gcp import (
    GroundControl,
    find_gcp_file,
    image_frame,
    read_ground_control,
)
from pipeline.flight.image_metadata import (
    HeightKind,
    ImageMetadata,
    found_tags,
    read_image_metadata,
)
from pipeline.flight.inputs import RunInputs, SkippedImage
from pipeline.flight.nav_files import (
    OBSERVATION_COLUMNS,
    read_ground_points,
    read_nav_geodetic,
    read_nav_projected,
)
from pipeline.flight.navigation import (
    MIN_IMAGES,
    SKIPPED_NAMED,
    clashing_image_files,
    geodetic_to_eop,
    image_files,
    read_image_folder_nav,
    resolve_projected_crs,
    resolve_working_crs,
)
from pipeline.flight.observation_rows import (
    FrameRows,
    ObservationGroup,
    outside_tolerance_px,
    outside_warning,
    row_image_frame,
)
from pipeline.flight.schema import CameraConfig, FlightConfig, NavConfig, load_flight_config
from seqat.calibration import SelfCalibration
from seqat.errors import ConfigError, InputDataError
from seqat.types import FloatArray, Frame, PinholeCamera

#: Diagonal of a 36 x 24 mm frame: 35 mm-equivalent focal lengths refer to it.
FULL_FRAME_DIAGONAL_MM = 43.2666
#: Relative aspect-ratio difference still taken as "the same camera, resized".
ASPECT_TOLERANCE = 2e-3
#: A file with more than this share of its observations outside the image is refused.
MAX_OUTSIDE_FRACTION = 0.5

@dataclass(frozen=True, kw_only=True, eq=False)
class Flight:
    """A validated flight folder: navigation read, images or observations located.

    Attributes
    ----------
    path : Path
        The flight folder.
    config : FlightConfig
        ``flight.yaml`` (defaults for a bare folder of images).
    crs : pyproj.CRS
        Projected, metre axes; ``x_m`` is the easting and ``y_m`` the northing whatever the
        CRS's own axis order.
    camera_config : CameraConfig
        Camera of the observed pixels (full-resolution images).
    camera_approximate : bool
        The camera comes from EXIF, not from ``flight.yaml``.
    camera : PinholeCamera
        Camera of the frames (:func:`pipeline.flight.camera.seqat_camera`): square pixels,
        the lens distortion in the model (fixed, or the prior of the self-calibration).
    corrector : PixelCorrector
        Observed -> frame pixels (only the pixel aspect squared: ``ideal_pixels`` of a
        camera without distortion).
    calibration : SelfCalibration or None
        Self-calibration (``flight.yaml`` ``self_calibration:``); None: the camera is fixed.
    nav : NavTable
        GPS/INS EOPs in the working CRS, acquisition order, usable images only; NaN for the
        position or attitude of a GNSS dropout (``nav.dropout: bridge``).
    nav_sigma : (6,) float
        A priori σ, metres and radians.
    observations_path : Path or None
        ``observations.csv`` (observations flights); ``None`` for image flights.
    images_dir : Path or None
    image_paths : tuple[Path, ...]
        One per ``nav`` row (image flights), else empty.
    skipped : tuple[SkippedImage, ...]
        Images of the flight left out, with the reason.
    warnings : tuple[str, ...]
    control : GroundControl or None
        Ground control points (``gcp:`` in ``flight.yaml``, or ``gcp_list.txt`` in the
        folder; :mod:`pipeline.flight.gcp`), or None.
    """

    path: Path
    config: FlightConfig
    crs: pyproj.CRS
    camera_config: CameraConfig
    camera_approximate: bool
    camera: PinholeCamera
    corrector: PixelCorrector
    nav: NavTable
    nav_sigma: FloatArray
    observations_path: Path | None
    images_dir: Path | None = None
    image_paths: tuple[Path, ...] = ()
    skipped: tuple[SkippedImage, ...] = ()
    warnings: tuple[str, ...] = ()
    calibration: SelfCalibration | None = None
    control: GroundControl | None = None

    def __post_init__(self) -> None:
        # start values of dropout components, from earlier rows only (pipeline.flight.dropout)
        object.__setattr__(self, "_nav_start", predict_missing(self.nav.eop, self.nav.times_s))

    def frame_nav(self, row: int) -> tuple[FloatArray, FloatArray]:
        """The ``nav_eop`` and ``nav_sigma`` of the frame of nav row ``row``.

        A dropout's missing components get ``inf`` σ (no constraint) and a start value
        predicted from the earlier rows (:func:`pipeline.flight.dropout.predict_missing`).
        """
        missing = np.isnan(self.nav.eop[row])
        start: FloatArray = self._nav_start[row]  # type: ignore[attr-defined]
        return start, dropout_sigma(self.nav_sigma, missing)

    def frame_pixels(self, observed_px: FloatArray) -> FloatArray:
        """Observed pixels ``(k, 2)`` as the frames carry them to :attr:`camera` (the pixel
        aspect squared; the distortion stays, :attr:`camera` models it)."""
        return self.corrector.ideal_pixels(observed_px)

    def is_dropout(self, row: int) -> bool:
        """Whether nav row ``row`` misses its position or attitude (a GNSS dropout)."""
        return bool(np.isnan(self.nav.eop[row]).any())

    @property
    def kind(self) -> Literal["observations", "images"]:
        """``observations`` (precomputed image points) or ``images`` (tie points tracked)."""
        return "observations" if self.observations_path is not None else "images"

    def frames(self) -> FrameSource:
        """The observations of an observations flight as a lazy stream of frames."""
        if self.observations_path is None:
            raise ConfigError(f"{self.path}: an image flight has no observations file; its "
                              "frames come from the tracker (pipeline.tracking.tracker)")
        return FrameSource(self)

    def inputs(self) -> RunInputs:
        """What the estimator is given, for the run folder (:class:`RunInputs`)."""
        return RunInputs(crs=self.crs, camera=self.camera_config,
                         camera_approximate=self.camera_approximate, nav=self.nav,
                         nav_sigma=self.nav_sigma, sigma_image_px=self.config.sigma_image_px,
                         images_dir=self.images_dir, skipped=self.skipped,
                         warnings=self.warnings)


def with_self_calibration(flight: Flight, enabled: bool | None) -> Flight:
    """``flight`` with its self-calibration switched on or off (``None``: as configured,
    ``flight.yaml`` ``self_calibration:``)."""
    if enabled is None:
        return flight
    cfg = dataclasses.replace(flight.config.self_calibration, enabled=enabled)
    calibration, camera, corrector = frame_camera(flight.camera_config, cfg,
                                                  flight.camera_approximate)
    return dataclasses.replace(flight, config=dataclasses.replace(flight.config,
                                                                  self_calibration=cfg),
                               calibration=calibration, camera=camera, corrector=corrector)


def _in_folder(folder: Path, name: str) -> Path:
    path = Path(name)
    return path if path.is_absolute() else folder / path


def _bare_image_folder(folder: Path) -> FlightConfig:
    """Defaults for a folder of images without ``flight.yaml`` (nav from the images)."""
    for sub in (".", IMAGES_DIR):
        candidate = folder / sub
        if candidate.is_dir() and image_files(candidate):
            return FlightConfig(images=sub, nav=NavConfig(source="images"))
    raise InputDataError(f"{folder / FLIGHT_YAML}: no such file, and no JPEG images in "
                         f"{folder} or {folder / IMAGES_DIR} (a flight folder needs "
                         f"{FLIGHT_YAML} or images)")


def camera_from_exif(meta: ImageMetadata) -> CameraConfig:
    """An approximate pinhole camera from EXIF focal length and sensor size.

    ``f_px = FocalLength [mm] · FocalPlaneXResolution [px/mm] · width / ExifImageWidth``
    (the focal-plane resolution refers to the camera's original width, which resized files
    keep in ``ExifImageWidth``), else ``f_px = FocalLengthIn35mmFilm / 43.27 mm · diagonal
    [px]``. Principal point at the image centre, no distortion.

    Raises
    ------
    InputDataError
        Neither is in the file.
    """
    w, h = meta.width_px, meta.height_px
    if meta.focal_mm and meta.focal_plane_px_per_mm:
        scale = w / meta.exif_width_px if meta.exif_width_px else 1.0
        f_px = meta.focal_mm * meta.focal_plane_px_per_mm * scale
    elif meta.focal_35mm:
        f_px = meta.focal_35mm / FULL_FRAME_DIAGONAL_MM * math.hypot(w, h)
    else:
        raise InputDataError(
            f"{meta.path.name}: no camera in {FLIGHT_YAML} and EXIF has neither FocalLength "
            f"with FocalPlaneXResolution nor FocalLengthIn35mmFilm (found: {found_tags(meta)}); "
            f"give camera: in {FLIGHT_YAML}")
    return CameraConfig(model="PINHOLE", width_px=w, height_px=h, fx_px=f_px, fy_px=f_px,
                        cx_px=(w - 1) / 2.0, cy_px=(h - 1) / 2.0)


def geodetic_nav_eop(config: FlightConfig, crs: pyproj.CRS, lat_lon_h: FloatArray,
                     roll_pitch_yaw_deg: FloatArray) -> FloatArray:
    """EOPs ``(n, 6)`` of geodetic ``nav.csv`` rows (``nav.height``, boresight, lever arm)."""
    lat, lon, h = np.asarray(lat_lon_h, dtype=np.float64).reshape(-1, 3).T
    n = len(lat)
    kind: HeightKind = "orthometric" if config.nav.height == "egm96" else "ellipsoidal"
    return geodetic_to_eop(lon, lat, h, roll_pitch_yaw_deg, ["body"] * n, [kind] * n, crs,
                           config.nav.boresight, np.asarray(config.nav.lever_arm_m))
def _fill_from_previous(values: FloatArray) -> FloatArray:
    """Rows with NaN take the previous complete row (before the first: the first complete)."""
    out = values.copy()
    ok = np.flatnonzero(np.all(np.isfinite(values), axis=1))
    for i in np.flatnonzero(~np.all(np.isfinite(values), axis=1)):
        before = ok[ok < i]
        out[i] = values[before[-1] if before.size else ok[0]] if ok.size else 0.0
    return out


def _geodetic_file_nav(path: Path, config: FlightConfig, source: str) -> tuple[pyproj.CRS,
                                                                              NavTable]:
    geo = read_nav_geodetic(path, allow_missing=True)  # nav.dropout: skip drops them later
    missing = np.isnan(np.column_stack([geo.lat_lon_h, geo.roll_pitch_yaw_deg]))
    # A dropout row is converted with the previous fix and attitude (the grid convergence
    # and the lever arm need them), then its missing groups are set back to NaN.
    lat_lon_h = _fill_from_previous(geo.lat_lon_h)
    first = int(np.flatnonzero(~missing[:, 0])[0])
    crs = resolve_working_crs(config.crs, float(lat_lon_h[first, 1]),
                              float(lat_lon_h[first, 0]), source=source)
    eop = geodetic_nav_eop(config, crs, lat_lon_h, _fill_from_previous(geo.roll_pitch_yaw_deg))
    eop[missing] = np.nan
    return crs, NavTable(image_ids=geo.image_ids, times_s=geo.times_s, eop=eop)


def _dropout_reason(image: str, missing: np.ndarray, source: str) -> str:
    what = " and ".join(name for name, sl in (("position", slice(0, 3)),
                                             ("attitude", slice(3, 6))) if missing[sl].any())
    return f"{image}: GNSS dropout (no {what} in {source}; nav.dropout: skip)"


def _skip_dropouts(nav: NavTable, skipped: list[SkippedImage], source: str) -> NavTable:
    """``nav.dropout: skip``: leave out the rows with a missing group."""
    missing = np.isnan(nav.eop)
    keep = ~missing.any(axis=1)
    for i in np.flatnonzero(~keep):
        skipped.append(SkippedImage(image=nav.image_ids[i],
                                    reason=_dropout_reason(nav.image_ids[i], missing[i], source)))
    return NavTable(image_ids=tuple(np.asarray(nav.image_ids)[keep]), times_s=nav.times_s[keep],
                    eop=nav.eop[keep])


def _insert_rows(nav: NavTable, images: list[str]) -> NavTable:
    """Add dropout rows (all NaN) for images without a ``nav.csv`` row.

    Each goes after the last nav image whose id sorts before it (file names follow the
    acquisition order); its time is interpolated between its neighbours' (after the last:
    the median interval on), a placeholder that only keeps the times increasing.
    """
    if not images:
        return nav
    order = list(nav.image_ids)
    for image in sorted(images):
        pos = 0
        for k, other in enumerate(order):
            if other < image:
                pos = k + 1
        order.insert(pos, image)
    row_of = nav.index()
    eop = np.full((len(order), 6), np.nan)
    times = np.full(len(order), np.nan)
    for k, image in enumerate(order):
        if image in row_of:
            eop[k], times[k] = nav.eop[row_of[image]], nav.times_s[row_of[image]]
    known = np.flatnonzero(np.isfinite(times))
    step = float(np.median(np.diff(nav.times_s))) if len(nav) > 1 else 1.0
    for k in np.flatnonzero(np.isnan(times)):
        before, after = known[known < k], known[known > k]
        if before.size and after.size:
            a, b = before[-1], after[0]
            times[k] = times[a] + (times[b] - times[a]) * (k - a) / (b - a)
        elif before.size:
            times[k] = times[before[-1]] + step * (k - before[-1])
        else:
            times[k] = times[after[0]] - step * (after[0] - k)
    return NavTable(image_ids=tuple(order), times_s=times, eop=eop)


def read_flight(flight_dir: Path | str, *, gcp_file: Path | str | None = None,
                gcp_sigma_m: tuple[float, float] | None = None) -> Flight:
    """Open and validate a flight folder (docs/formats.md, *Flight folder*).

    Three kinds: observations (``observations:`` given), images with a ``nav.csv``
    (``images:`` given, ``nav.source: file``, projected or geodetic), images with the
    navigation in their metadata (``nav.source: images``, or a bare folder of JPEGs without
    ``flight.yaml``). For image flights, unusable images (truncated, no GPS, listed in
    ``nav.csv`` but missing, of another aspect ratio, ...) are skipped and listed in
    :attr:`Flight.skipped`; the run goes on with the others.

    Ground control: ``gcp_file`` (``--gcp``) in place of the flight's own (``flight.yaml``
    ``gcp:``, else ``gcp_list.txt`` in the folder), with the default σ ``gcp_sigma_m``
    (horizontal, vertical; ``--gcp-sigma-m``) where given.

    Raises
    ------
    InputDataError
        Missing folder or file, unknown or unsuitable CRS, bad ``nav.csv``, too few usable
        images.
    ConfigError
        Bad ``flight.yaml``.
    """
    folder = Path(flight_dir)
    yaml_path = folder / FLIGHT_YAML
    if folder_problem(folder) is not None:
        raise InputDataError(f"{folder}: {folder_problem(folder, 'no such flight folder')}")
    warnings: list[str] = []
    if exists_as_anything(yaml_path) and file_problem(yaml_path) is not None:
        raise InputDataError(f"{yaml_path}: {file_problem(yaml_path)}")
    if yaml_path.is_file():
        config = load_flight_config(yaml_path)
    else:
        config = _bare_image_folder(folder)
    source = str(yaml_path)
    if config.observations is None and config.images is None:
        raise ConfigError(f"{source}: give observations: (image points) or images: (a folder "
                          "of images to track)")
    images_dir = _in_folder(folder, config.images) if config.images is not None else None
    if images_dir is not None and not images_dir.is_dir():
        raise InputDataError(f"{images_dir}: {folder_problem(images_dir, 'no such image folder')} "
                             f"(images in {source})")
    skipped: list[SkippedImage] = []
    metas: dict[str, ImageMetadata] = {}
    bridge = config.nav.dropout == "bridge"
    if config.nav.source == "images":
        if images_dir is None:
            raise ConfigError(f"{source}: nav.source: 'images' needs images: (a folder)")
        folder_nav = read_image_folder_nav(images_dir, config.crs, config.nav.boresight,
                                           np.asarray(config.nav.lever_arm_m), skip_bad=True,
                                           dropout=bridge)
        crs, nav = folder_nav.crs, folder_nav.to_nav_table()
        skipped += [SkippedImage(image=i, reason=r) for i, r in folder_nav.skipped]
        warnings += folder_nav.warnings
        metas = {r.image: r.metadata for r in folder_nav.records}
    else:
        nav_path = _in_folder(folder, config.nav.file)
        if config.nav.frame == "geodetic":
            crs, nav = _geodetic_file_nav(nav_path, config, source)
        else:
            crs = resolve_projected_crs(config.crs, source)
            nav = read_nav_projected(nav_path, allow_missing=True)
    obs_path = None
    if config.observations is not None:
        obs_path = _in_folder(folder, config.observations)
        if not obs_path.is_file():
            raise InputDataError(f"{obs_path}: {file_problem(obs_path)} (observations in "
                                 f"{source})")
    elif images_dir is not None and config.nav.source == "file":
        metas, no_row = _image_metadata_for_nav(images_dir, nav, skipped, bridge=bridge)
        nav = _insert_rows(nav, no_row)
    if not bridge:
        nav = _skip_dropouts(nav, skipped, config.nav.file if config.nav.source == "file"
                             else "the image metadata")
    camera_config, approximate = config.camera, False
    if camera_config is None:
        if not metas:
            raise ConfigError(f"{source}: camera: required for an observations flight")
        camera_config, approximate = camera_from_exif(next(iter(metas.values()))), True
    if obs_path is None:
        check_one_camera(nav.image_ids, metas)
        for dup in duplicate_images(nav.image_ids, metas):
            skipped.append(dup)
            del metas[dup.image]  # its nav row goes with the images without metadata
        nav = _check_sizes(nav, metas, camera_config, skipped, warnings)
    if len(nav) < MIN_IMAGES:
        left_out = first_few([s.reason for s in skipped], SKIPPED_NAMED, "; ")
        raise InputDataError(f"{folder}: {len(nav)} usable image(s); at least {MIN_IMAGES} are "
                             f"needed (skipped: {left_out})")
    crs_warning = crs_area_warning(crs, nav, source)
    if crs_warning is not None:
        warnings.append(crs_warning)
    paths = tuple(metas[i].path for i in nav.image_ids) if obs_path is None else ()
    calibration, camera, corrector = frame_camera(camera_config, config.self_calibration,
                                                  approximate)
    control = None
    gcp_path = Path(gcp_file) if gcp_file is not None else find_gcp_file(folder, config.gcp,
                                                                         source)
    if gcp_path is not None:
        control = read_ground_control(
            gcp_path, crs, image_frame(nav.image_ids, paths, (camera_config.width_px,
                                                               camera_config.height_px)),
            config.gcp, sigma_m=gcp_sigma_m, folder=folder)
        warnings += control.warnings
    return Flight(path=folder, config=config, crs=crs, camera_config=camera_config,
                  camera_approximate=approximate, camera=camera, calibration=calibration,
                  corrector=corrector, nav=nav,
                  nav_sigma=config.nav.sigma_eop, observations_path=obs_path,
                  images_dir=images_dir, image_paths=paths, skipped=tuple(skipped),
                  warnings=tuple(warnings), control=control)


def with_ground_control(flight: Flight, path: Path | str | None,
                        sigma_m: tuple[float, float] | None = None) -> Flight:
    """``flight`` with the GCPs of ``path`` (``--gcp FILE``; None: the flight's own file) and
    the default σ ``sigma_m`` (horizontal, vertical; ``--gcp-sigma-m``) where given."""
    if path is None and (sigma_m is None or flight.control is None):
        return flight
    gcp_path = Path(path) if path is not None else flight.control.path  # type: ignore[union-attr]
    cam = flight.camera_config
    control = read_ground_control(
        gcp_path, flight.crs, image_frame(flight.nav.image_ids, flight.image_paths,
                                          (cam.width_px, cam.height_px)),
        flight.config.gcp, sigma_m=sigma_m, folder=flight.path)
    old = flight.control.warnings if flight.control is not None else ()
    warnings = tuple(w for w in flight.warnings if w not in old) + control.warnings
    return dataclasses.replace(flight, control=control, warnings=warnings)


def _image_metadata_for_nav(images_dir: Path, nav: NavTable, skipped: list[SkippedImage], *,
                            bridge: bool = False) -> tuple[dict[str, ImageMetadata], list[str]]:
    """Metadata of the image of each nav row; unreadable or missing ones go to ``skipped``.

    Images without a nav row are skipped, or with ``bridge`` returned as dropouts (second
    value; their metadata is in the first).
    """
    files = {p.stem: p for p in image_files(images_dir)}
    skipped += [SkippedImage(image=name, reason=reason)
                for name, reason in clashing_image_files(images_dir)]
    metas: dict[str, ImageMetadata] = {}
    for image in nav.image_ids:
        path = files.pop(image, None)
        if path is None:
            skipped.append(SkippedImage(image=image, reason=f"{image}: listed in nav.csv but "
                                        f"no {image}.jpg in {images_dir}"))
            continue
        try:
            metas[image] = read_image_metadata(path)
        except InputDataError as err:
            skipped.append(SkippedImage(image=image, reason=str(err)))
    no_row: list[str] = []
    for stem, path in files.items():
        if not bridge:
            skipped.append(SkippedImage(image=stem, reason=f"{path.name}: no row in nav.csv"))
            continue
        try:
            metas[stem] = read_image_metadata(path)
            no_row.append(stem)
        except InputDataError as err:
            skipped.append(SkippedImage(image=stem, reason=str(err)))
    return metas, no_row


def _check_sizes(nav: NavTable, metas: dict[str, ImageMetadata], camera: CameraConfig,
                 skipped: list[SkippedImage], warnings: list[str]) -> NavTable:
    """Keep the nav rows of images that can be read at the camera's size.

    An image of another size with the same aspect ratio is resampled to the camera size
    when read (warning); one of another aspect ratio is skipped.
    """
    keep = []
    resampled: list[ImageMetadata] = []
    for row, image in enumerate(nav.image_ids):
        meta = metas.get(image)
        if meta is None:
            continue
        skip, warning = check_image_size(meta, camera)
        if warning is not None:
            resampled.append(meta)
        if skip is not None:
            skipped.append(SkippedImage(image=image, reason=skip))
            continue
        keep.append(row)
    warnings += resampling_warnings(resampled, camera)
    return NavTable(image_ids=tuple(nav.image_ids[i] for i in keep), times_s=nav.times_s[keep],
                    eop=nav.eop[keep])


def resampling_warnings(metas: Sequence[ImageMetadata], camera: CameraConfig) -> list[str]:
    """The warnings of images resampled to the camera (:func:`check_image_size`), one line
    per size: an image alone in its own words, several named up to
    :data:`pipeline.common.text.MAX_NAMED`."""
    by_size: dict[tuple[int, int], list[ImageMetadata]] = {}
    for meta in metas:
        by_size.setdefault((meta.width_px, meta.height_px), []).append(meta)
    out = []
    for (w, h), group in by_size.items():
        if len(group) == 1:
            out.append(str(check_image_size(group[0], camera)[1]))
            continue
        names = [m.path.name for m in group]
        out.append(f"{len(names)} images of {w} x {h} px ({first_few(names)}) differ from the "
                   f"camera's {camera.width_px} x {camera.height_px} px; resampled to it "
                   "(same aspect ratio)")
    return out


def check_image_size(meta: ImageMetadata, camera: CameraConfig) -> tuple[str | None, str | None]:
    """``(reason to skip, warning)`` of an image's size against the camera's.

    Another size with the same aspect ratio is resampled when read (warning); another aspect
    ratio is skipped.
    """
    w, h = meta.width_px, meta.height_px
    if (w, h) == (camera.width_px, camera.height_px):
        return None, None
    if abs(w * camera.height_px - h * camera.width_px) <= ASPECT_TOLERANCE * w * h:
        return None, (f"{meta.path.name}: size {w} x {h} px differs from the camera's "
                      f"{camera.width_px} x {camera.height_px} px; resampled to it "
                      "(same aspect ratio)")
    return (f"{meta.path.name}: size {w} x {h} px has another aspect ratio than the camera's "
            f"{camera.width_px} x {camera.height_px} px"), None


@dataclass(frozen=True, kw_only=True)
class ObservationStats:
    """Counts from a full pass over ``observations.csv``."""

    n_observations: int
    n_points: int
    n_images_observed: int
    warnings: tuple[str, ...] = ()


class FrameSource:
    """Lazy stream of :class:`Frame` objects in acquisition order.

    Iterating reads ``observations.csv`` once, keeping only the current image's rows (plus
    the set of finished image ids, to detect non-contiguous rows). Images of ``nav.csv``
    without observations give frames with no image points. Validation errors surface when
    the offending row is reached; call :meth:`validate` for a full check first.

    Parameters
    ----------
    flight : Flight
    """

    def __init__(self, flight: Flight) -> None:
        self._flight = flight
        self._nav_index = flight.nav.index()
        self._nav_sigma = flight.nav_sigma
        #: After a full pass: observations left out (outside the image), rows read, first.
        self.outside: tuple[int, int, str] = (0, 0, "")

    def __len__(self) -> int:
        return len(self._flight.nav)

    def __iter__(self) -> Iterator[Frame]:
        for frame, _, _ in self.with_observed():
            yield frame

    def with_observed(self) -> Iterator[tuple[Frame, FloatArray, FloatArray]]:
        """Frames together with the observed (distorted) pixels of their observations,
        ``(k, 2)``, and of their late observations, ``(m, 2)``."""
        next_row = 0
        empty = np.zeros((0, 2))
        for group in self._groups():
            while next_row < group.nav_row:
                yield self._frame(next_row, (), empty), empty, empty
                next_row += 1
            frame = dataclasses.replace(
                self._frame(group.nav_row, group.point_ids, self._flight.frame_pixels(group.uv_px)),
                late_image_ids=group.late_image_ids, late_point_ids=group.late_point_ids,
                late_uv_px=self._flight.frame_pixels(group.late_uv_px))
            yield frame, group.uv_px, group.late_uv_px
            next_row = group.nav_row + 1
        while next_row < len(self._flight.nav):
            yield self._frame(next_row, (), empty), empty, empty
            next_row += 1

    def validate(self) -> ObservationStats:
        """Read the whole observations file once, raising on the first problem.

        Returns
        -------
        ObservationStats
        """
        n_obs, n_images = 0, 0
        points: set[str] = set()
        for group in self._groups():
            n_obs += len(group.point_ids) + len(group.late_point_ids)
            n_images += 1
            points.update(group.point_ids)
            points.update(group.late_point_ids)
        dropped, total, first = self.outside
        warnings = ((outside_warning(self._flight.observations_path, dropped, total, first),)
                    if dropped else ())
        return ObservationStats(n_observations=n_obs, n_points=len(points),
                                n_images_observed=n_images, warnings=warnings)

    def _frame(self, row: int, point_ids: tuple[str, ...], uv_px: FloatArray) -> Frame:
        nav_eop, nav_sigma = self._flight.frame_nav(row)
        return Frame(image_id=self._flight.nav.image_ids[row], nav_eop=nav_eop,
                     nav_sigma=nav_sigma, point_ids=point_ids, uv_px=uv_px,
                     sigma_px=self._flight.config.sigma_image_px)

    def _groups(self) -> Iterator[ObservationGroup]:
        """Contiguous per-frame groups of ``observations.csv``, validated, in nav order
        (:class:`~pipeline.flight.observation_rows.FrameRows`).

        Without a ``frame`` column every row arrived with its own image (the frame = the
        image); with it, a row of an earlier image than its frame is a late observation."""
        nav_name = self._flight.config.nav.file
        left_out = {s.image for s in self._flight.skipped}  # nav.dropout: skip
        assert self._flight.observations_path is not None
        outside: list[str] = []
        current_row = [-1]

        def open_frame(row: CsvRow, frame: str, image: str) -> int:
            nav_row = self._nav_index.get(frame)
            if nav_row is None:
                field_name = "image" if frame == image else OBS_FRAME_COLUMN
                raise row.error(f"field {field_name!r}: unknown image {frame!r} (not in "
                                f"{nav_name})")
            if nav_row < current_row[0]:
                previous = self._flight.nav.image_ids[current_row[0]]
                raise row.error(f"image {frame!r} comes after image {previous!r} but was "
                                f"acquired before it ({nav_name}); rows must follow the "
                                "acquisition order")
            current_row[0] = nav_row
            return nav_row

        def check_late(row: CsvRow, image: str, frame: str, nav_row: int) -> None:
            image_row = self._nav_index.get(image)
            if image_row is None:
                raise row.error(f"field 'image': unknown image {image!r} (not in {nav_name})")
            if image_row >= nav_row:
                raise row.error(f"late observation of image {image!r} in frame {frame!r}, "
                                "which was not acquired after it (a row's frame is its image "
                                "or a later one)")

        rows = FrameRows(self._flight.camera_config,
                         outside_tolerance_px(self._flight.config.sigma_image_px),
                         open_frame=open_frame, check_late=check_late,
                         on_outside=lambda err: outside.append(str(err)))
        total = 0
        for row in read_csv(self._flight.observations_path, OBSERVATION_COLUMNS,
                            (OBS_FRAME_COLUMN,)):
            total += 1
            image, frame = row_image_frame(row)
            if (image in left_out and image not in self._nav_index) or (
                    frame in left_out and frame not in self._nav_index):
                continue
            group = rows.add(row)
            if group is not None:
                yield group
        dropped, first = len(outside), (outside[0] if outside else "")
        self.outside = (dropped, total, first)
        if dropped > MAX_OUTSIDE_FRACTION * total:
            raise InputDataError(f"{self._flight.observations_path}: {dropped} of {total} "
                                 "observations lie outside the image (first: "
                                 f"{first}); the file does not fit the camera of the flight")
        group = rows.close()
        if group is not None:
            yield group


@dataclass(frozen=True, kw_only=True, eq=False)
class Truth:
    """Exact truth of a simulated flight (``truth/eop.csv``, ``truth/points.csv``)."""

    eop: NavTable
    points: GroundPoints


def read_truth(flight_dir: Path | str) -> Truth | None:
    """Read the ``truth/`` folder of a simulated flight.

    Returns
    -------
    Truth or None
        ``None`` when the flight has no ``truth/`` (real flights).

    Raises
    ------
    InputDataError
        ``truth`` is not a folder, or a file in it is missing or malformed.
    """
    truth_dir = Path(flight_dir) / TRUTH_DIR
    if not exists_as_anything(truth_dir):
        return None
    problem = folder_problem(truth_dir)
    if problem is not None:  # a file or a broken link where the truth folder goes
        raise InputDataError(f"{truth_dir}: {problem} (the simulated flight's truth)")
    return Truth(eop=read_nav_projected(truth_dir / "eop.csv"),
                 points=read_ground_points(truth_dir / "points.csv"))
