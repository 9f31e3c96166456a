"""Flight folders: ``flight.yaml`` + ``nav.csv`` + ``observations.csv`` -> :class:`Frame` stream.

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

import numpy as np
import pyproj
from pyproj.exceptions import CRSError

from pipeline.camera import PixelCorrector, pinhole_camera
from pipeline.config import FlightConfig, load_flight_config
from pipeline.csvio import read_csv
from pipeline.tables import GroundPoints, NavTable
from seqat.errors import ConfigError, InputDataError
from seqat.types import FloatArray, Frame, PinholeCamera

#: Name of the flight description inside a flight folder.
FLIGHT_YAML = "flight.yaml"
#: Folder of the exact truth of simulated flights.
TRUTH_DIR = "truth"
#: Columns of a projected ``nav.csv`` and of ``truth/eop.csv``.
NAV_PROJECTED_COLUMNS = ("image", "time_s", "x_m", "y_m", "z_m", "omega_deg", "phi_deg",
                         "kappa_deg")
#: Columns of ``observations.csv``.
OBSERVATION_COLUMNS = ("image", "point", "x_px", "y_px")
#: Columns of ``truth/points.csv`` and ``checkpoints.csv``.
GROUND_POINT_COLUMNS = ("point", "x_m", "y_m", "z_m")
#: An adjustment needs at least this many images.
MIN_IMAGES = 2
#: Half a pixel: observed pixel centres lie in ``[-0.5, width - 0.5]`` (OpenCV convention).
HALF_PIXEL = 0.5
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


def read_nav_projected(path: Path | str) -> NavTable:
    """Read a projected ``nav.csv`` (or ``truth/eop.csv``).

    Columns ``image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg``: ``x_m`` easting,
    ``y_m`` northing, ``z_m`` height (all in the flight CRS), angles in degrees.

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
    ids: list[str] = []
    times: list[float] = []
    rows: list[list[float]] = []
    first_line: dict[str, int] = {}
    prev_time, prev_line = -math.inf, 0
    for row in read_csv(path, NAV_PROJECTED_COLUMNS):
        image = row.ident("image")
        if image in first_line:
            raise row.error(f"duplicate nav row for image {image!r} (first at line "
                            f"{first_line[image]})")
        time_s = row.number("time_s")
        if not time_s > prev_time:
            raise row.error(f"nav out of time order: time_s {time_s!r} of image {image!r} is "
                            f"not after {prev_time!r} (line {prev_line})")
        values = [row.number(c) for c in NAV_PROJECTED_COLUMNS[2:]]
        first_line[image] = row.line
        prev_time, prev_line = time_s, row.line
        ids.append(image)
        times.append(time_s)
        rows.append(values)
    if len(ids) < MIN_IMAGES:
        raise InputDataError(f"{path}: {len(ids)} image(s); at least {MIN_IMAGES} are needed")
    eop = np.asarray(rows, dtype=np.float64)
    eop[:, 3:] = np.radians(eop[:, 3:])
    return NavTable(image_ids=tuple(ids), times_s=np.asarray(times, dtype=np.float64), eop=eop)


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
    """A validated flight folder (navigation read; observations streamed by :meth:`frames`).

    Attributes
    ----------
    path : Path
        The flight folder.
    config : FlightConfig
    crs : pyproj.CRS
        Projected, metre axes; ``x_m`` is the easting and ``y_m`` the northing whatever the
        CRS's own axis order.
    camera : PinholeCamera
        Ideal camera of the frames (distortion removed).
    corrector : PixelCorrector
        Observed -> ideal pixels.
    nav : NavTable
        GPS/INS EOPs in acquisition order.
    observations_path : Path
    """

    path: Path
    config: FlightConfig
    crs: pyproj.CRS
    camera: PinholeCamera
    corrector: PixelCorrector
    nav: NavTable
    observations_path: Path

    def frames(self) -> FrameSource:
        """The flight as a lazy stream of frames in acquisition order."""
        return FrameSource(self)


def _in_folder(folder: Path, name: str) -> Path:
    path = Path(name)
    return path if path.is_absolute() else folder / path


def read_flight(flight_dir: Path | str) -> Flight:
    """Open and validate a flight folder (observations mode, projected nav).

    Parameters
    ----------
    flight_dir : Path or str
        Folder with ``flight.yaml`` (docs/formats.md).

    Raises
    ------
    InputDataError
        Missing folder or file, unknown or unsuitable CRS, bad ``nav.csv``.
    ConfigError
        Bad ``flight.yaml``; geodetic nav or a flight without an observations file (these
        need later pipeline stages).
    """
    folder = Path(flight_dir)
    yaml_path = folder / FLIGHT_YAML
    if not folder.is_dir():
        raise InputDataError(f"{folder}: no such flight folder")
    if not yaml_path.is_file():
        raise InputDataError(f"{yaml_path}: no such file (a flight folder needs {FLIGHT_YAML})")
    config = load_flight_config(yaml_path)
    if config.nav.frame == "geodetic":
        raise ConfigError(f"{yaml_path}: nav.frame: geodetic nav needs the real-flight stage "
                          "(not yet supported); give projected nav")
    crs = resolve_projected_crs(config.crs, str(yaml_path))
    if config.observations is None:
        raise ConfigError(f"{yaml_path}: observations: no observations file given; flights "
                          "from images need the tracking stage (not yet supported)")
    obs_path = _in_folder(folder, config.observations)
    if not obs_path.is_file():
        raise InputDataError(f"{obs_path}: no such file (observations in {yaml_path})")
    nav = read_nav_projected(_in_folder(folder, config.nav.file))
    return Flight(path=folder, config=config, crs=crs, camera=pinhole_camera(config.camera),
                  corrector=PixelCorrector(camera=config.camera), nav=nav,
                  observations_path=obs_path)


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
        self._nav_sigma = flight.config.nav.sigma_eop

    def __len__(self) -> int:
        return len(self._flight.nav)

    def __iter__(self) -> Iterator[Frame]:
        next_row = 0
        for group in self._groups():
            while next_row < group.nav_row:
                yield self._frame(next_row, (), np.zeros((0, 2)))
                next_row += 1
            uv = self._flight.corrector.ideal_pixels(group.uv_px)
            yield self._frame(group.nav_row, group.point_ids, uv)
            next_row = group.nav_row + 1
        while next_row < len(self._flight.nav):
            yield self._frame(next_row, (), np.zeros((0, 2)))
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
        nav = self._flight.nav
        return Frame(image_id=nav.image_ids[row], nav_eop=nav.eop[row], nav_sigma=self._nav_sigma,
                     point_ids=point_ids, uv_px=uv_px,
                     sigma_px=self._flight.config.sigma_image_px)

    def _groups(self) -> Iterator[_Group]:
        """Contiguous per-image groups of ``observations.csv``, validated, in nav order."""
        cam = self._flight.config.camera
        u_max, v_max = cam.width_px - HALF_PIXEL, cam.height_px - HALF_PIXEL
        done: dict[str, int] = {}  # finished image -> last line of its rows
        current: str | None = None
        current_row = -1
        point_line: dict[str, int] = {}
        uvs: list[tuple[float, float]] = []
        last_line = 0
        nav_name = self._flight.config.nav.file
        for row in read_csv(self._flight.observations_path, OBSERVATION_COLUMNS):
            image = row.ident("image")
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
            point = row.ident("point")
            if point in point_line:
                raise row.error(f"duplicate observation of point {point!r} in image {image!r} "
                                f"(first at line {point_line[point]})")
            u, v = row.number("x_px"), row.number("y_px")
            if not (-HALF_PIXEL <= u <= u_max and -HALF_PIXEL <= v <= v_max):
                raise row.error(f"pixel ({u!r}, {v!r}) of point {point!r} lies outside the "
                                f"{cam.width_px} x {cam.height_px} px image")
            point_line[point] = row.line
            uvs.append((u, v))
            last_line = row.line
        if current is not None:
            yield _Group(image_id=current, nav_row=current_row, point_ids=tuple(point_line),
                         uv_px=np.asarray(uvs))


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
