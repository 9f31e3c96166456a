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

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pyproj

from pipeline.camera import PixelCorrector, pinhole_camera
from pipeline.config import CameraConfig, FlightConfig, NavConfig, load_flight_config
from pipeline.csvio import CsvRow, read_csv
from pipeline.dropout import dropout_sigma, predict_missing
from pipeline.image_metadata import HeightKind, ImageMetadata, found_tags, read_image_metadata
from pipeline.navigation import (
    MIN_IMAGES,
    geodetic_to_eop,
    image_files,
    read_image_folder_nav,
    resolve_projected_crs,
    resolve_working_crs,
)
from pipeline.store import NAV_COLUMNS, OBS_COLUMNS, RunInputs, SkippedImage
from pipeline.tables import GroundPoints, NavTable
from seqat.errors import ConfigError, InputDataError
from seqat.types import FloatArray, Frame, PinholeCamera

#: Name of the flight description inside a flight folder.
FLIGHT_YAML = "flight.yaml"
#: Folder of the exact truth of simulated flights.
TRUTH_DIR = "truth"
#: Columns of a projected ``nav.csv`` and of ``truth/eop.csv``.
NAV_PROJECTED_COLUMNS = NAV_COLUMNS
#: Columns of a geodetic ``nav.csv``.
NAV_GEODETIC_COLUMNS = ("image", "time_s", "lat_deg", "lon_deg", "h_m", "roll_deg",
                        "pitch_deg", "yaw_deg")
#: Columns of ``observations.csv``.
OBSERVATION_COLUMNS = OBS_COLUMNS
#: Columns of ``truth/points.csv`` and ``checkpoints.csv``.
GROUND_POINT_COLUMNS = ("point", "x_m", "y_m", "z_m")
#: Default image sub-folder of a bare flight folder.
IMAGES_DIR = "images"
#: Diagonal of a 36 x 24 mm frame: 35 mm-equivalent focal lengths refer to it.
FULL_FRAME_DIAGONAL_MM = 43.2666
#: Relative aspect-ratio difference still taken as "the same camera, resized".
ASPECT_TOLERANCE = 2e-3
#: Half a pixel: observed pixel centres lie in ``[-0.5, width - 0.5]`` (OpenCV convention).
HALF_PIXEL = 0.5

#: Value columns of a nav row taken together: a fix (3 positions) and an attitude (3 angles).
NAV_GROUPS = (slice(0, 3), slice(3, 6))
#: Fields read as "missing" in a nav row (a GNSS dropout) when missing values are allowed.
MISSING_TEXT = ("", "nan", "NaN", "NAN")


class NavRowChecker:
    """Validates ``nav.csv`` rows one at a time: ids unique, times strictly increasing.

    Shared by the batch reader and the watch mode's reader of a growing ``nav.csv``. With
    ``allow_missing`` an empty or ``nan`` value field is a dropout: the whole group it belongs
    to (the 3 position or the 3 attitude fields) is NaN.
    """

    def __init__(self, columns: tuple[str, ...], *, allow_missing: bool = False) -> None:
        self.columns = columns
        self.allow_missing = allow_missing
        self._first_line: dict[str, int] = {}
        self._prev_time, self._prev_line = -math.inf, 0

    def check(self, row: CsvRow) -> tuple[str, float, list[float]]:
        """Image id, time and the 6 value columns of a row (as written: degrees)."""
        image = row.ident("image")
        if image in self._first_line:
            raise row.error(f"duplicate nav row for image {image!r} (first at line "
                            f"{self._first_line[image]})")
        time_s = row.number("time_s")
        if not time_s > self._prev_time:
            raise row.error(f"nav out of time order: time_s {time_s!r} of image {image!r} is "
                            f"not after {self._prev_time!r} (line {self._prev_line})")
        values = [math.nan if self.allow_missing and row.values[c] in MISSING_TEXT
                  else row.number(c) for c in self.columns[2:]]
        for group in NAV_GROUPS:
            if any(math.isnan(v) for v in values[group]):
                values[group] = [math.nan] * 3
        self._first_line[image] = row.line
        self._prev_time, self._prev_line = time_s, row.line
        return image, time_s, values


def _read_nav_rows(path: Path | str, columns: tuple[str, ...], *,
                   allow_missing: bool = False) -> (
        tuple[tuple[str, ...], FloatArray, FloatArray]):
    """Ids, times and the 6 value columns of a ``nav.csv`` (validated, order kept; missing
    values as :class:`NavRowChecker`). At least :data:`MIN_IMAGES` rows must keep their
    position."""
    checker = NavRowChecker(columns, allow_missing=allow_missing)
    ids: list[str] = []
    times: list[float] = []
    rows: list[list[float]] = []
    for row in read_csv(path, columns):
        image, time_s, values = checker.check(row)
        ids.append(image)
        times.append(time_s)
        rows.append(values)
    eop = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    with_fix = int(np.count_nonzero(np.isfinite(eop[:, 0])))
    if with_fix < MIN_IMAGES:
        what = "image(s)" if with_fix == len(ids) else f"of {len(ids)} image(s) with a position"
        raise InputDataError(f"{path}: {with_fix} {what}; at least {MIN_IMAGES} are needed")
    return tuple(ids), np.asarray(times, dtype=np.float64), eop


def read_nav_projected(path: Path | str, *, allow_missing: bool = False) -> NavTable:
    """Read a projected ``nav.csv`` (or ``truth/eop.csv``).

    Columns ``image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg``: ``x_m`` easting,
    ``y_m`` northing, ``z_m`` height (all in the flight CRS), angles in degrees.
    ``allow_missing``: empty or ``nan`` fields are a GNSS dropout (NaN for the whole
    position or attitude group).

    Returns
    -------
    NavTable
        Angles converted to radians.

    Raises
    ------
    InputDataError
        Malformed row, non-finite value, duplicate image, time not strictly increasing,
        fewer than :data:`MIN_IMAGES` rows.
    """
    ids, times, eop = _read_nav_rows(path, NAV_PROJECTED_COLUMNS, allow_missing=allow_missing)
    eop[:, 3:] = np.radians(eop[:, 3:])
    return NavTable(image_ids=ids, times_s=times, eop=eop)


@dataclass(frozen=True, kw_only=True, eq=False)
class GeodeticNav:
    """A geodetic ``nav.csv``: WGS 84 fixes and aircraft attitude, as read (degrees)."""

    image_ids: tuple[str, ...]
    times_s: FloatArray
    lat_lon_h: FloatArray  # (n, 3) degrees, degrees, metres
    roll_pitch_yaw_deg: FloatArray  # (n, 3)


def read_nav_geodetic(path: Path | str, *, allow_missing: bool = False) -> GeodeticNav:
    """Read a geodetic ``nav.csv``.

    Columns ``image,time_s,lat_deg,lon_deg,h_m,roll_deg,pitch_deg,yaw_deg``: WGS 84 fix of the
    GPS antenna, aircraft attitude (yaw from true north), degrees. ``allow_missing``: as
    :func:`read_nav_projected`.

    Raises
    ------
    InputDataError
        As :func:`read_nav_projected`, and latitude or longitude out of range.
    """
    ids, times, values = _read_nav_rows(path, NAV_GEODETIC_COLUMNS, allow_missing=allow_missing)
    check_lat_lon(path, ids, values)
    return GeodeticNav(image_ids=ids, times_s=times, lat_lon_h=values[:, :3].copy(),
                       roll_pitch_yaw_deg=values[:, 3:].copy())


def check_lat_lon(path: Path | str, ids: tuple[str, ...], values: FloatArray) -> None:
    """Raise unless every latitude (column 0) and longitude (column 1) is in range (NaN: a
    dropout, not checked)."""
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero((np.abs(values[:, 0]) > 90.0) | (np.abs(values[:, 1]) > 180.0))
    if bad.size:
        i = int(bad[0])
        raise InputDataError(f"{path}: image {ids[i]!r}: latitude {values[i, 0]!r} / longitude "
                             f"{values[i, 1]!r} out of range (degrees, [-90, 90] / [-180, 180])")


def read_ground_points(path: Path | str) -> GroundPoints:
    """Read ``point,x_m,y_m,z_m`` (``truth/points.csv``, ``checkpoints.csv``); ids unique."""
    ids: list[str] = []
    xyz: list[list[float]] = []
    first_line: dict[str, int] = {}
    for row in read_csv(path, GROUND_POINT_COLUMNS):
        point = row.ident("point")
        if point in first_line:
            raise row.error(f"duplicate point {point!r} (first at line {first_line[point]})")
        xyz.append([row.number(c) for c in GROUND_POINT_COLUMNS[1:]])
        first_line[point] = row.line
        ids.append(point)
    return GroundPoints(point_ids=tuple(ids),
                        xyz_m=np.asarray(xyz, dtype=np.float64).reshape(-1, 3))


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
        Ideal camera of the frames (distortion removed).
    corrector : PixelCorrector
        Observed -> ideal pixels.
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

    def __post_init__(self) -> None:
        # start values of dropout components, from earlier rows only (pipeline.dropout)
        object.__setattr__(self, "_nav_start", predict_missing(self.nav.eop, self.nav.times_s))

    def frame_nav(self, row: int) -> tuple[FloatArray, FloatArray]:
        """The ``nav_eop`` and ``nav_sigma`` of the frame of nav row ``row``.

        A dropout's missing components get ``inf`` σ (no constraint) and a start value
        predicted from the earlier rows (:func:`pipeline.dropout.predict_missing`).
        """
        missing = np.isnan(self.nav.eop[row])
        start: FloatArray = self._nav_start[row]  # type: ignore[attr-defined]
        return start, dropout_sigma(self.nav_sigma, missing)

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
                              "frames come from the tracker (pipeline.tracking)")
        return FrameSource(self)

    def inputs(self) -> RunInputs:
        """What the estimator is given, for the run folder (:class:`RunInputs`)."""
        return RunInputs(crs=self.crs, camera=self.camera_config,
                         camera_approximate=self.camera_approximate, nav=self.nav,
                         nav_sigma=self.nav_sigma, sigma_image_px=self.config.sigma_image_px,
                         images_dir=self.images_dir, skipped=self.skipped,
                         warnings=self.warnings)


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


def read_flight(flight_dir: Path | str) -> Flight:
    """Open and validate a flight folder (docs/formats.md, *Flight folder*).

    Three kinds: observations (``observations:`` given), images with a ``nav.csv``
    (``images:`` given, ``nav.source: file``, projected or geodetic), images with the
    navigation in their metadata (``nav.source: images``, or a bare folder of JPEGs without
    ``flight.yaml``). For image flights, unusable images (truncated, no GPS, listed in
    ``nav.csv`` but missing, of another aspect ratio, ...) are skipped and listed in
    :attr:`Flight.skipped`; the run goes on with the others.

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
    if not folder.is_dir():
        raise InputDataError(f"{folder}: no such flight folder")
    warnings: list[str] = []
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
        raise InputDataError(f"{images_dir}: no such image folder (images in {source})")
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
            raise InputDataError(f"{obs_path}: no such file (observations in {source})")
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
        nav = _check_sizes(nav, metas, camera_config, skipped, warnings)
    if len(nav) < MIN_IMAGES:
        raise InputDataError(f"{folder}: {len(nav)} usable image(s); at least {MIN_IMAGES} are "
                             f"needed (skipped: {'; '.join(s.reason for s in skipped)})")
    paths = tuple(metas[i].path for i in nav.image_ids) if obs_path is None else ()
    return Flight(path=folder, config=config, crs=crs, camera_config=camera_config,
                  camera_approximate=approximate, camera=pinhole_camera(camera_config),
                  corrector=PixelCorrector(camera=camera_config), nav=nav,
                  nav_sigma=config.nav.sigma_eop, observations_path=obs_path,
                  images_dir=images_dir, image_paths=paths, skipped=tuple(skipped),
                  warnings=tuple(warnings))


def _image_metadata_for_nav(images_dir: Path, nav: NavTable, skipped: list[SkippedImage], *,
                            bridge: bool = False) -> tuple[dict[str, ImageMetadata], list[str]]:
    """Metadata of the image of each nav row; unreadable or missing ones go to ``skipped``.

    Images without a nav row are skipped, or with ``bridge`` returned as dropouts (second
    value; their metadata is in the first).
    """
    files = {p.stem: p for p in image_files(images_dir)}
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
    for row, image in enumerate(nav.image_ids):
        meta = metas.get(image)
        if meta is None:
            continue
        skip, warning = check_image_size(meta, camera)
        if warning is not None:
            warnings.append(warning)
        if skip is not None:
            skipped.append(SkippedImage(image=image, reason=skip))
            continue
        keep.append(row)
    return NavTable(image_ids=tuple(nav.image_ids[i] for i in keep), times_s=nav.times_s[keep],
                    eop=nav.eop[keep])


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


@dataclass(frozen=True, kw_only=True, eq=False)
class _Group:
    """The contiguous observation rows of one image."""

    image_id: str
    nav_row: int
    point_ids: tuple[str, ...]
    uv_px: FloatArray  # (k, 2) observed pixels


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

    def __len__(self) -> int:
        return len(self._flight.nav)

    def __iter__(self) -> Iterator[Frame]:
        for frame, _ in self.with_observed():
            yield frame

    def with_observed(self) -> Iterator[tuple[Frame, FloatArray]]:
        """Frames together with their observed (distorted) pixels, ``(k, 2)``."""
        next_row = 0
        empty = np.zeros((0, 2))
        for group in self._groups():
            while next_row < group.nav_row:
                yield self._frame(next_row, (), empty), empty
                next_row += 1
            uv = self._flight.corrector.ideal_pixels(group.uv_px)
            yield self._frame(group.nav_row, group.point_ids, uv), group.uv_px
            next_row = group.nav_row + 1
        while next_row < len(self._flight.nav):
            yield self._frame(next_row, (), empty), empty
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
            n_obs += len(group.point_ids)
            n_images += 1
            points.update(group.point_ids)
        return ObservationStats(n_observations=n_obs, n_points=len(points),
                                n_images_observed=n_images)

    def _frame(self, row: int, point_ids: tuple[str, ...], uv_px: FloatArray) -> Frame:
        nav_eop, nav_sigma = self._flight.frame_nav(row)
        return Frame(image_id=self._flight.nav.image_ids[row], nav_eop=nav_eop,
                     nav_sigma=nav_sigma, point_ids=point_ids, uv_px=uv_px,
                     sigma_px=self._flight.config.sigma_image_px)

    def _groups(self) -> Iterator[_Group]:
        """Contiguous per-image groups of ``observations.csv``, validated, in nav order."""
        cam = self._flight.camera_config
        done: dict[str, int] = {}  # finished image -> last line of its rows
        current: str | None = None
        current_row = -1
        point_line: dict[str, int] = {}
        uvs: list[tuple[float, float]] = []
        last_line = 0
        nav_name = self._flight.config.nav.file
        left_out = {s.image for s in self._flight.skipped}  # nav.dropout: skip
        assert self._flight.observations_path is not None
        for row in read_csv(self._flight.observations_path, OBSERVATION_COLUMNS):
            image = row.ident("image")
            if image in left_out and image not in self._nav_index:
                continue
            if image != current:
                if current is not None:
                    yield _Group(image_id=current, nav_row=current_row,
                                 point_ids=tuple(point_line), uv_px=np.asarray(uvs))
                    done[current] = last_line
                if image in done:
                    raise row.error(f"rows of image {image!r} are not contiguous (its earlier "
                                    f"rows end at line {done[image]}); group rows by image")
                nav_row = self._nav_index.get(image)
                if nav_row is None:
                    raise row.error(f"field 'image': unknown image {image!r} (not in "
                                    f"{nav_name})")
                if nav_row < current_row:
                    raise row.error(f"image {image!r} comes after image {current!r} but was "
                                    f"acquired before it ({nav_name}); rows must follow the "
                                    "acquisition order")
                current, current_row = image, nav_row
                point_line, uvs = {}, []
            point, u, v = observation_row(row, image, point_line, cam)
            uvs.append((u, v))
            last_line = row.line
        if current is not None:
            yield _Group(image_id=current, nav_row=current_row, point_ids=tuple(point_line),
                         uv_px=np.asarray(uvs))


def observation_row(row: CsvRow, image: str, point_line: dict[str, int],
                    camera: CameraConfig) -> tuple[str, float, float]:
    """Point id and pixel of an ``observations.csv`` row of ``image``, checked.

    ``point_line`` (point -> line) holds the image's earlier rows; the row is added to it.

    Raises
    ------
    InputDataError
        A point observed twice in the image, a pixel outside the image.
    """
    point = row.ident("point")
    if point in point_line:
        raise row.error(f"duplicate observation of point {point!r} in image {image!r} "
                        f"(first at line {point_line[point]})")
    u, v = row.number("x_px"), row.number("y_px")
    if not (-HALF_PIXEL <= u <= camera.width_px - HALF_PIXEL
            and -HALF_PIXEL <= v <= camera.height_px - HALF_PIXEL):
        raise row.error(f"pixel ({u!r}, {v!r}) of point {point!r} lies outside the "
                        f"{camera.width_px} x {camera.height_px} px image")
    point_line[point] = row.line
    return point, u, v


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
        ``None`` when the flight has no ``truth/`` folder (real flights).

    Raises
    ------
    InputDataError
        ``truth/`` exists but a file is missing or malformed.
    """
    truth_dir = Path(flight_dir) / TRUTH_DIR
    if not truth_dir.is_dir():
        return None
    return Truth(eop=read_nav_projected(truth_dir / "eop.csv"),
                 points=read_ground_points(truth_dir / "points.csv"))
