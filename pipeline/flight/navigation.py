"""Geodetic navigation -> working frame: projected positions, attitude -> omega, phi, kappa.

* :func:`resolve_working_crs` turns ``crs:`` (``auto`` = UTM zone of the first fix, or any
  projected metre CRS) into a :class:`pyproj.CRS`.
* :class:`GeodeticToProjected` moves WGS 84 fixes (ellipsoidal or EGM96 heights) into it with
  pyproj only (PROJ network off; a missing geoid grid is a :class:`ConfigError`).
* :func:`world_from_cam` / :func:`opk_from_attitude` convert roll, pitch, yaw to the
  camera->world rotation of docs/conventions.md (*Navigation attitude*, where the derivation
  is written out) through the boresight mount and the grid convergence.
* :func:`read_image_folder_nav` does all of it for a folder of JPEGs
  (:mod:`pipeline.flight.image_metadata`); not yet wired into the runner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pyproj
from pyproj.exceptions import CRSError, ProjError

from pipeline.common.tables import NavTable
from pipeline.common.text import first_few
from pipeline.flight.image_metadata import (
    AttitudeFrame,
    HeightKind,
    ImageMetadata,
    found_tags,
    read_image_metadata,
    require_position,
)
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import angles_from_rotation
from seqat.types import FloatArray

#: Geographic 3D WGS 84 (lat, lon, ellipsoidal height): the CRS of GPS fixes.
WGS84_3D = "EPSG:4979"
#: WGS 84 with EGM96 heights: fixes whose height is orthometric (DJI).
WGS84_EGM96 = "EPSG:4326+5773"
#: Width of a UTM zone (degrees of longitude).
UTM_ZONE_WIDTH_DEG = 6.0
#: A converted height that differs from the input by less than this (metres) while the
#: vertical datum changes means PROJ silently skipped the geoid (undulations are never this
#: close to zero over a flight's first fix in practice).
MIN_GEOID_SHIFT_M = 1e-6
#: File suffixes read as images by :func:`read_image_folder_nav`.
IMAGE_SUFFIXES = (".jpg", ".jpeg")
#: Skipped images whose reason a "too few usable images" error gives (the rest are counted).
SKIPPED_NAMED = 3

#: Camera axes in the mount's reference frame (columns = camera x, y, z).
#: ``nadir``: camera fixed to the airframe looking down, image top towards the nose, image
#: right towards the right wing (body x forward, y right, z down).
R_BODY_FROM_CAM_NADIR = np.array([[0.0, 1.0, 0.0],
                                  [1.0, 0.0, 0.0],
                                  [0.0, 0.0, -1.0]])
#: ``forward``: camera looking along the frame's x axis, image top up (-z), image right = y.
#: A gimbal's roll, pitch, yaw use this mount (pitch -90 deg = nadir, image top forward).
R_BODY_FROM_CAM_FORWARD = np.array([[0.0, 0.0, -1.0],
                                    [1.0, 0.0, 0.0],
                                    [0.0, -1.0, 0.0]])
#: NED -> ENU axes (swap north and east, flip down).
R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0],
                           [1.0, 0.0, 0.0],
                           [0.0, 0.0, -1.0]])


@dataclass(frozen=True, kw_only=True)
class BoresightConfig:
    """How the camera sits on the airframe (``nav.boresight`` of a flight configuration).

    Attributes
    ----------
    mount : {"nadir", "forward"}
        ``nadir`` (default): looking down, image top towards the nose. ``forward``: looking
        along the nose, image top up.
    roll_deg, pitch_deg, yaw_deg : float
        Small misalignment of the camera relative to the mount, a Z-Y-X rotation in the body
        frame (same sequence as the aircraft attitude), degrees.
    """

    mount: Literal["nadir", "forward"] = "nadir"
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0

    def R_body_from_cam(self) -> FloatArray:
        """(3, 3) camera -> aircraft body rotation (misalignment · mount)."""
        mount = R_BODY_FROM_CAM_NADIR if self.mount == "nadir" else R_BODY_FROM_CAM_FORWARD
        misalignment = R_ned_from_body(math.radians(self.roll_deg), math.radians(self.pitch_deg),
                                       math.radians(self.yaw_deg))
        return misalignment @ mount


#: An adjustment needs at least this many images.
MIN_IMAGES = 2
#: Unit names pyproj gives for metre axes.
METRE_UNITS = ("metre", "meter", "m")


def resolve_projected_crs(crs: str, source: str) -> pyproj.CRS:
    """Parse ``crs`` and check it is projected with metre axes.

    Parameters
    ----------
    crs : str
        Anything ``pyproj.CRS.from_user_input`` accepts (``EPSG:32652``, WKT, PROJ string).
        A compound CRS (``EPSG:32652+5773``) fixes the vertical datum of the heights.
    source : str
        File the value came from (for messages).

    Raises
    ------
    InputDataError
        Unknown CRS (PROJ's message attached), geographic CRS, or axes not in metres.
    """
    if crs.strip().lower() == "auto":
        raise InputDataError(f"{source}: crs: 'auto' (UTM zone of the first fix) needs geodetic "
                             "nav; give an EPSG code for projected nav")
    try:
        parsed = pyproj.CRS.from_user_input(crs)
    except CRSError as err:
        raise InputDataError(f"{source}: crs: unknown CRS {crs!r}: {err}") from err
    if not parsed.is_projected:
        raise InputDataError(f"{source}: crs: {crs!r} ({parsed.name}) is not a projected CRS; "
                             "seqat works in east/north/up metres")
    units = {axis.unit_name for axis in parsed.axis_info}
    if not units <= set(METRE_UNITS):
        raise InputDataError(f"{source}: crs: {crs!r} ({parsed.name}) has axes in "
                             f"{', '.join(sorted(units))}; a metre CRS is needed")
    return parsed


# --------------------------------------------------------------------------------------------
# CRS and positions
# --------------------------------------------------------------------------------------------


def utm_epsg(lon_deg: float, lat_deg: float) -> int:
    """EPSG code of the WGS 84 UTM zone holding a point (326zz north, 327zz south).

    The standard 6-degree zones; the Norway/Svalbard exceptions are not applied.
    """
    zone = int(math.floor((lon_deg + 180.0) / UTM_ZONE_WIDTH_DEG)) % 60 + 1
    return (32600 if lat_deg >= 0.0 else 32700) + zone


def resolve_working_crs(crs: str, first_lon_deg: float, first_lat_deg: float, *,
                        source: str = "flight.yaml") -> pyproj.CRS:
    """The projected working CRS of a flight with geodetic navigation.

    Parameters
    ----------
    crs : str
        ``auto`` (UTM zone of the first fix, WGS 84, ellipsoidal heights) or anything
        ``pyproj.CRS.from_user_input`` accepts; it must be projected with metre axes,
        optionally compound with a vertical CRS (``EPSG:32617+5773``: orthometric heights).
    first_lon_deg, first_lat_deg : float
        First GPS fix, degrees.
    source : str
        Where ``crs`` came from (for messages).

    Raises
    ------
    InputDataError
        Unknown CRS (PROJ's message attached), not projected, or axes not in metres (the
        checks of :func:`resolve_projected_crs`).
    """
    if crs.strip().lower() == "auto":
        return pyproj.CRS.from_epsg(utm_epsg(first_lon_deg, first_lat_deg))
    return resolve_projected_crs(crs, source)


def _horizontal(crs: pyproj.CRS) -> pyproj.CRS | None:
    """The horizontal part of a CRS (itself unless compound)."""
    if crs.is_compound:
        return next((sub for sub in crs.sub_crs_list if sub.is_projected or sub.is_geographic),
                    None)
    return crs


def has_vertical_datum(crs: pyproj.CRS) -> bool:
    """A compound CRS with a vertical part (orthometric heights)."""
    return crs.is_compound and any(sub.is_vertical for sub in crs.sub_crs_list)


def checked_transform(transformer: pyproj.Transformer, x: FloatArray, y: FloatArray,
                      z: FloatArray, *, vertical_change: bool, where: str,
                      error: type[Exception]) -> FloatArray:
    """``transformer`` applied to points, (n, 3), refusing what PROJ does silently wrong.

    Raises ``error`` naming ``where`` when PROJ fails, returns non-finite values (a missing
    grid), or leaves heights unchanged although the vertical datum changes (a skipped
    geoid: :data:`MIN_GEOID_SHIFT_M`).
    """
    try:
        xt, yt, zt = transformer.transform(x, y, z, errcheck=True)
    except ProjError as err:
        raise error(f"{where}: coordinate transformation failed: {err}") from err
    out = np.column_stack([xt, yt, zt]).astype(np.float64)
    if not np.all(np.isfinite(out)):
        raise error(f"{where}: the coordinate transformation gave non-finite coordinates "
                    "(missing grid?)")
    if vertical_change and np.any(np.abs(out[:, 2] - z) < MIN_GEOID_SHIFT_M):
        raise error(f"{where}: heights unchanged by the vertical datum change: the geoid "
                    "grid was not applied")
    return out


def grid_convergence_rad(crs: pyproj.CRS, lon_deg: float, lat_deg: float) -> float:
    """Meridian (grid) convergence of a projected CRS at a point, radians.

    pyproj's ``meridian_convergence`` (``Proj.get_factors``): positive east of a transverse
    Mercator central meridian in the northern hemisphere, where true north points to the
    *west* of grid north. The grid azimuth of a direction is its true azimuth minus this
    angle (pinned by tests/pipeline/flight/test_navigation.py).
    """
    horizontal = _horizontal(crs)
    factors = pyproj.Proj(horizontal).get_factors(lon_deg, lat_deg)
    return math.radians(factors.meridian_convergence)


class GeodeticToProjected:
    """WGS 84 latitude, longitude, height -> working CRS ``x_m`` (east), ``y_m`` (north), ``z_m``.

    Parameters
    ----------
    crs : pyproj.CRS
        Projected working CRS (:func:`resolve_working_crs`).
    height_kind : {"ellipsoidal", "orthometric", "unknown"}
        Of the input heights. ``unknown`` is taken as ellipsoidal (the caller warns);
        ``orthometric`` means EGM96.

    Raises
    ------
    ConfigError
        The heights need a geoid grid PROJ does not have (the network is switched off, so
        grids must be installed: ``projsync --file us_nga_egm96_15.tif`` or a
        ``proj-data`` package).

    Notes
    -----
    Uses ``Transformer.from_crs(..., always_xy=True)``. When the vertical datum changes,
    only PROJ's best operation is accepted (``only_best=True``, no ballpark): PROJ would
    otherwise fall back to a "ballpark" operation that leaves heights unchanged.
    """

    def __init__(self, crs: pyproj.CRS, height_kind: HeightKind = "ellipsoidal") -> None:
        pyproj.network.set_network_enabled(False)
        self.crs = crs
        source = pyproj.CRS.from_user_input(WGS84_EGM96 if height_kind == "orthometric"
                                            else WGS84_3D)
        self._vertical_change = has_vertical_datum(crs) != (height_kind == "orthometric")
        target = crs if has_vertical_datum(crs) else to_3d(crs)
        try:
            if self._vertical_change:
                self._transformer = pyproj.Transformer.from_crs(
                    source, target, always_xy=True, only_best=True, allow_ballpark=False)
            else:
                self._transformer = pyproj.Transformer.from_crs(source, target, always_xy=True)
        except ProjError as err:
            raise ConfigError(f"crs: cannot convert {height_kind} heights to {crs.name!r}: "
                              f"{err}; install the geoid grid (PROJ network access is off)"
                              ) from err

    def __call__(self, lon_deg: FloatArray, lat_deg: FloatArray, h_m: FloatArray) -> FloatArray:
        """Transform fixes.

        Parameters
        ----------
        lon_deg, lat_deg, h_m : (n,) float

        Returns
        -------
        (n, 3) float
            ``[x_m, y_m, z_m]``, east, north, up.

        Raises
        ------
        ConfigError
            PROJ returned non-finite values, or heights unchanged although the vertical datum
            changes (a silently skipped geoid).
        """
        lon, lat, h = (np.asarray(a, dtype=np.float64) for a in (lon_deg, lat_deg, h_m))
        return checked_transform(self._transformer, lon, lat, h,
                                 vertical_change=self._vertical_change,
                                 where=f"crs (to {self.crs.name!r})", error=ConfigError)


def to_3d(crs: pyproj.CRS) -> pyproj.CRS:
    """The 3D version of a 2D CRS (ellipsoidal height as third axis); others unchanged."""
    return crs.to_3d() if len(crs.axis_info) == 2 else crs


# --------------------------------------------------------------------------------------------
# Attitude
# --------------------------------------------------------------------------------------------


def R_ned_from_body(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Aircraft body -> NED rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` (aerospace Z-Y-X).

    Body axes x forward (nose), y right wing, z down. Positive roll lowers the right wing,
    positive pitch raises the nose, yaw is the heading clockwise from north.

    Returns
    -------
    (3, 3) float
    """
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return Rz @ Ry @ Rx


def world_from_cam(roll_rad: float, pitch_rad: float, yaw_rad: float,
                   R_body_from_cam: FloatArray, convergence_rad: float) -> FloatArray:
    """Camera -> world (projected east-north-up) rotation from a navigation attitude.

    ``R_world_from_cam = R_enu_from_ned · R_ned_from_body(roll, pitch, yaw - γ) ·
    R_body_from_cam`` with γ the grid convergence (:func:`grid_convergence_rad`): the NED
    frame is taken along *grid* north, so the true heading is turned into a grid heading.
    Derivation: docs/conventions.md, *Navigation attitude*.

    Parameters
    ----------
    roll_rad, pitch_rad, yaw_rad : float
        Attitude of the frame the camera is mounted on, yaw from true north.
    R_body_from_cam : (3, 3) float
        Mount (:class:`BoresightConfig`).
    convergence_rad : float

    Returns
    -------
    (3, 3) float
    """
    R_ned = R_ned_from_body(roll_rad, pitch_rad, yaw_rad - convergence_rad)
    return R_ENU_FROM_NED @ R_ned @ np.asarray(R_body_from_cam, dtype=np.float64)


def opk_from_attitude(roll_rad: float, pitch_rad: float, yaw_rad: float,
                      R_body_from_cam: FloatArray, convergence_rad: float) -> FloatArray:
    """``[omega_rad, phi_rad, kappa_rad]`` of :func:`world_from_cam` (seqat convention)."""
    return angles_from_rotation(world_from_cam(roll_rad, pitch_rad, yaw_rad, R_body_from_cam,
                                               convergence_rad))


def mount_for(frame: AttitudeFrame, boresight: BoresightConfig) -> FloatArray:
    """``R_body_from_cam`` for an attitude kind (:mod:`pipeline.flight.image_metadata`).

    ``body``: the configured boresight. ``gimbal``: the forward mount (gimbal angles are
    the camera's own; the boresight does not apply). ``camera`` (Pix4D ``Camera:``
    angles, 0/0/0 = nadir with image top north): the nadir mount.
    """
    if frame == "body":
        return boresight.R_body_from_cam()
    if frame == "gimbal":
        return R_BODY_FROM_CAM_FORWARD
    return R_BODY_FROM_CAM_NADIR


def geodetic_to_eop(lon_deg: FloatArray, lat_deg: FloatArray, h_m: FloatArray,
                    attitude_deg: FloatArray, frames: list[AttitudeFrame],
                    height_kinds: list[HeightKind], crs: pyproj.CRS, boresight: BoresightConfig,
                    lever_arm_m: FloatArray | None = None) -> FloatArray:
    """GPS/INS records -> camera EOPs ``[X, Y, Z, omega, phi, kappa]`` in the working CRS.

    Parameters
    ----------
    lon_deg, lat_deg, h_m : (n,) float
        WGS 84 fixes of the GPS antenna.
    attitude_deg : (n, 3) float
        Roll, pitch, yaw (yaw from true north), degrees, in ``frames``.
    frames : list of {"body", "gimbal", "camera"}
        What each attitude describes (:func:`mount_for`).
    height_kinds : list of {"ellipsoidal", "orthometric", "unknown"}
        Per record; ``unknown`` is taken as ellipsoidal.
    crs : pyproj.CRS
        Working CRS.
    boresight : BoresightConfig
    lever_arm_m : (3,) float, optional
        From the GPS antenna to the camera's projection centre in body axes (x forward,
        y right wing, z down), metres; applied with the body attitude (``body`` records only).

    Returns
    -------
    (n, 6) float
        Metres and radians.
    """
    n = len(frames)
    lon, lat, h = (np.asarray(a, dtype=np.float64).reshape(n) for a in (lon_deg, lat_deg, h_m))
    att = np.radians(np.asarray(attitude_deg, dtype=np.float64).reshape(n, 3))
    out = np.empty((n, 6))
    for kind in sorted(set(height_kinds)):
        rows = [i for i, k in enumerate(height_kinds) if k == kind]
        convert = GeodeticToProjected(crs, "ellipsoidal" if kind == "unknown" else kind)
        out[rows, :3] = convert(lon[rows], lat[rows], h[rows])
    lever = np.zeros(3) if lever_arm_m is None else np.asarray(lever_arm_m, dtype=np.float64)
    for i in range(n):
        gamma = grid_convergence_rad(crs, float(lon[i]), float(lat[i]))
        R = world_from_cam(*att[i], mount_for(frames[i], boresight), gamma)
        out[i, 3:] = angles_from_rotation(R)
        if frames[i] == "body" and np.any(lever != 0.0):
            R_world_from_body = R_ENU_FROM_NED @ R_ned_from_body(att[i, 0], att[i, 1],
                                                                 att[i, 2] - gamma)
            out[i, :3] += R_world_from_body @ lever
    return out


# --------------------------------------------------------------------------------------------
# Image folder
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class NavRecord:
    """Navigation of one image in the working CRS (metres, radians).

    Attributes
    ----------
    image : str
        File name without suffix (the image id).
    path : Path
    time_s : float or None
    x_m, y_m, z_m : float
        Projection centre (GPS antenna; no lever arm applied), east, north, up.
    omega_rad, phi_rad, kappa_rad : float or None
        ``None`` when the image has no attitude.
    metadata : ImageMetadata
    """

    image: str
    path: Path
    time_s: float | None
    x_m: float
    y_m: float
    z_m: float
    omega_rad: float | None
    phi_rad: float | None
    kappa_rad: float | None
    metadata: ImageMetadata


@dataclass(frozen=True, kw_only=True, eq=False)
class ImageFolderNav:
    """Result of :func:`read_image_folder_nav`.

    Attributes
    ----------
    crs : pyproj.CRS
        The working CRS.
    records : tuple[NavRecord, ...]
        In acquisition order.
    warnings : tuple[str, ...]
        One line each, naming the image.
    skipped : tuple[tuple[str, str], ...]
        ``(image id, reason)`` of images left out (``skip_bad``).
    """

    crs: pyproj.CRS
    records: tuple[NavRecord, ...]
    warnings: tuple[str, ...]
    skipped: tuple[tuple[str, str], ...] = ()

    def to_nav_table(self) -> NavTable:
        """The records as a projected :class:`NavTable`.

        Raises
        ------
        InputDataError
            An image without time or attitude.
        """
        for r in self.records:
            if r.time_s is None or r.omega_rad is None:
                missing = "time" if r.time_s is None else "attitude"
                raise InputDataError(f"{r.path.name}: no {missing} "
                                     f"(found: {found_tags(r.metadata)})")
        eop = np.array([[r.x_m, r.y_m, r.z_m, r.omega_rad, r.phi_rad, r.kappa_rad]
                        for r in self.records], dtype=np.float64)
        times = np.array([r.time_s for r in self.records], dtype=np.float64)
        return NavTable(image_ids=tuple(r.image for r in self.records), times_s=times, eop=eop)


def _all_image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir()
                  if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def image_files(folder: Path) -> list[Path]:
    """The JPEGs of a folder (``*.jpg``, ``*.jpeg``, any case), sorted by name, one per image
    id (the file name without suffix): of files sharing an id (``a.jpg`` and ``a.JPEG``) the
    first by name; :func:`clashing_image_files` names the others."""
    first: dict[str, Path] = {}
    for p in _all_image_files(folder):
        first.setdefault(p.stem, p)
    return sorted(first.values())


def clashing_image_files(folder: Path) -> list[tuple[str, str]]:
    """``(file name, reason)`` of each JPEG left out because an earlier file (by name) has its
    image id."""
    first: dict[str, Path] = {}
    out = []
    for p in _all_image_files(folder):
        kept = first.setdefault(p.stem, p)
        if kept is not p:
            out.append((p.name, f"{p.name}: same image id {p.stem!r} as {kept.name} (an image's "
                                f"id is its file name without suffix); left out"))
    return out


def read_image_folder_nav(folder: Path | str, crs: str = "auto",
                          boresight: BoresightConfig | None = None,
                          lever_arm_m: FloatArray | None = None, *,
                          skip_bad: bool = False, dropout: bool = False) -> ImageFolderNav:
    """Navigation of every JPEG of a folder in the working CRS.

    Parameters
    ----------
    folder : Path or str
    crs : str
        Working CRS (:func:`resolve_working_crs`); ``auto`` = UTM zone of the first fix.
    boresight : BoresightConfig, optional
        Mount of a camera fixed to the airframe; default nadir, image top forward.
    lever_arm_m : (3,) float, optional
        GPS antenna -> camera, body axes (:func:`geodetic_to_eop`).
    skip_bad : bool
        Leave out (and list in ``skipped``) images that cannot be read, are truncated, or
        lack a GPS position, attitude or time, instead of raising.
    dropout : bool
        Keep an image without a GPS position but with a time as a GNSS dropout: its record
        has NaN ``x_m``, ``y_m``, ``z_m`` (its attitude is converted with the previous fix).

    Returns
    -------
    ImageFolderNav
        Images sorted by time (file name for equal or missing times). Warnings: missing
        time, missing attitude, height of unknown kind (taken as ellipsoidal), times not
        strictly increasing (image sizes are checked against the camera when the flight's
        images are read: ``pipeline.flight.folder``).

    Raises
    ------
    InputDataError
        No such folder, fewer than :data:`MIN_IMAGES` (usable) images, an unreadable image,
        an image without GPS position (unless ``skip_bad``), bad CRS.
    ConfigError
        Missing geoid grid.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputDataError(f"{folder}: no such image folder")
    paths = image_files(folder)
    metas: list[ImageMetadata] = []
    skipped: list[tuple[str, str]] = clashing_image_files(folder)
    for p in paths:
        try:
            meta = read_image_metadata(p)
            if not (dropout and meta.time_s is not None and not meta.has_position):
                require_position(meta)
            if skip_bad and (meta.time_s is None or not meta.has_attitude):
                missing = "acquisition time" if meta.time_s is None else "attitude in XMP"
                raise InputDataError(f"{p.name}: no {missing} (found: {found_tags(meta)})")
        except InputDataError as err:
            if not skip_bad:
                raise
            skipped.append((p.stem, str(err)))
            continue
        metas.append(meta)
    with_fix = sum(1 for m in metas if m.has_position)
    if with_fix < MIN_IMAGES:
        extra = f" ({len(metas) - with_fix} without a position)" if with_fix < len(metas) else ""
        why = ""
        if skipped:  # why the first images were left out (the rest, counted)
            why = f" (left out: {first_few([r for _, r in skipped], SKIPPED_NAMED, '; ')})"
        raise InputDataError(f"{folder}: {with_fix} usable JPEG image(s) of {len(paths)}"
                             f"{extra}; at least {MIN_IMAGES} are needed{why}")
    metas.sort(key=lambda m: (m.time_s is None, m.time_s or 0.0, m.path.name))
    boresight = boresight or BoresightConfig()
    fixes = np.array([_fix(m) if m.has_position else (np.nan, np.nan, np.nan)
                      for m in metas])
    no_fix = np.isnan(fixes[:, 0])
    ok = np.flatnonzero(~no_fix)
    for i in np.flatnonzero(no_fix):  # converted with the previous fix, position set to NaN
        before = ok[ok < i]
        fixes[i] = fixes[before[-1] if before.size else ok[0]]
    first_lon, first_lat, _ = fixes[ok[0]]
    working = resolve_working_crs(crs, float(first_lon), float(first_lat))
    warnings = _folder_warnings(metas)
    with_att = [i for i, m in enumerate(metas) if m.has_attitude and m.attitude_frame]
    eop = np.full((len(metas), 6), np.nan)
    xyz_only = geodetic_to_eop(fixes[:, 0], fixes[:, 1], fixes[:, 2], np.zeros((len(metas), 3)),
                               ["camera"] * len(metas), [m.height_kind for m in metas], working,
                               boresight)
    eop[:, :3] = xyz_only[:, :3]
    if with_att:
        sub = [metas[i] for i in with_att]
        eop[with_att] = geodetic_to_eop(
            fixes[with_att, 0], fixes[with_att, 1], fixes[with_att, 2],
            np.array([[m.roll_deg, m.pitch_deg, m.yaw_deg] for m in sub], dtype=np.float64),
            [m.attitude_frame for m in sub],  # type: ignore[misc]
            [m.height_kind for m in sub], working, boresight, lever_arm_m)
    eop[no_fix, :3] = np.nan
    records = []
    for m, e in zip(metas, eop, strict=True):
        has_att = bool(np.isfinite(e[3]))
        records.append(NavRecord(image=m.path.stem, path=m.path, time_s=m.time_s,
                                 x_m=float(e[0]), y_m=float(e[1]), z_m=float(e[2]),
                                 omega_rad=float(e[3]) if has_att else None,
                                 phi_rad=float(e[4]) if has_att else None,
                                 kappa_rad=float(e[5]) if has_att else None, metadata=m))
    return ImageFolderNav(crs=working, records=tuple(records), warnings=tuple(warnings),
                          skipped=tuple(skipped))


def _fix(meta: ImageMetadata) -> tuple[float, float, float]:
    """``(lon_deg, lat_deg, h_m)`` of an image checked by :func:`require_position`."""
    if meta.lon_deg is None or meta.lat_deg is None or meta.h_m is None:
        require_position(meta)
        raise AssertionError("unreachable")
    return meta.lon_deg, meta.lat_deg, meta.h_m


def _folder_warnings(metas: list[ImageMetadata]) -> list[str]:
    warnings = []
    prev_time: float | None = None
    for m in metas:  # sizes: checked against the camera when the images are read
        name = m.path.name
        if m.time_s is None:
            warnings.append(f"{name}: no acquisition time (found: {found_tags(m)})")
        elif prev_time is not None and m.time_s <= prev_time:
            warnings.append(f"{name}: time {m.time_s!r} s is not after the previous image's")
        if not m.has_attitude:
            warnings.append(f"{name}: no attitude in XMP (found: {found_tags(m)})")
        if m.height_kind == "unknown":
            warnings.append(f"{name}: height kind of EXIF GPSAltitude unknown for make "
                            f"{m.make!r}; taken as ellipsoidal")
        prev_time = m.time_s if m.time_s is not None else prev_time
    return warnings
