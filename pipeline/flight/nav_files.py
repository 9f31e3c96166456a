"""Navigation and ground-point files of a flight folder: ``nav.csv`` (projected or geodetic),
``truth/points.csv``, ``checkpoints.csv``; strict rows, dropouts allowed where asked."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.common.columns import (
    GROUND_POINT_COLUMNS,
    NAV_COLUMNS,
    NAV_GEODETIC_COLUMNS,
    OBS_COLUMNS,
)
from pipeline.common.csvio import CsvRow, read_csv
from pipeline.common.tables import GroundPoints, NavTable
from pipeline.flight.navigation import (
    MIN_IMAGES,
)
from seqat.errors import InputDataError
from seqat.types import FloatArray

#: Columns of a projected ``nav.csv`` and of ``truth/eop.csv``.
NAV_PROJECTED_COLUMNS = NAV_COLUMNS
#: Columns of ``observations.csv``.
OBSERVATION_COLUMNS = OBS_COLUMNS
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
    if not np.isfinite(eop[:, 3]).any():  # no start value for any image's attitude
        raise InputDataError(f"{path}: no row has an attitude ({', '.join(columns[5:8])} "
                             "empty in every row); at least one is needed (a GPS-only flight "
                             "is not supported)")
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
