"""Digital surface model: LiDAR (LAS/LAZ) -> filtered, gridded, hole-filled COG; DSM access.

Stage function :func:`build_dsm` (``seqat dsm``): read LAS/LAZ files with laspy (LAZ through
lazrs) in the CRS the file declares or the one given, transform to the working CRS with pyproj,
remove outliers with open3d's statistical filter, keep the **highest return per cell** at the
cell size asked for, fill its gaps (:mod:`pipeline.ortho.dsm_fill`: interpolated near returns,
a coarser ground fallback in large enclosed gaps, said in a warning and in the GeoTIFF's
metadata) and write a float32 COG in metres (:mod:`pipeline.ortho.raster`).

:class:`Dsm` is the in-memory surface the orthorectifier samples: read from a GeoTIFF
(:func:`read_dsm`, reprojected to the working CRS if needed) or a flat plane
(:func:`flat_dsm`, the fallback when a flight has neither LiDAR nor a DSM).

Heights: a LAS CRS with a vertical datum is transformed in 3D by pyproj. Without one (the
usual case, e.g. Autzen: a 2D Lambert CRS in international feet) the heights are only
converted to metres with the unit of the horizontal axes (the LAS convention) and taken as
heights of the working CRS's vertical reference; :attr:`DsmResult.warnings` says so.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import laspy
import numpy as np
import open3d as o3d
import pyproj
import rasterio
import rasterio.fill
import rasterio.warp
from affine import Affine
from pyproj.exceptions import CRSError, ProjError
from rasterio.transform import from_origin
from scipy import ndimage

from pipeline.common.paths import file_problem
from pipeline.ortho.dsm_fill import fill_gaps
from pipeline.ortho.raster import write_cog
from seqat.errors import ConfigError, InputDataError
from seqat.types import FloatArray

#: Nodata value of the DSM COG (inside seqat nodata is NaN).
DSM_NODATA = -9999.0
#: Band units of a DSM GeoTIFF read as feet (GDAL ``UNITTYPE``), with their metre factors.
FOOT_UNITS = {"ft": 0.3048, "foot": 0.3048, "feet": 0.3048, "us-ft": 1200.0 / 3937.0,
              "us_survey_foot": 1200.0 / 3937.0}
#: Extra cells around the data when gridding (none: the grid hugs the points).
GRID_MARGIN_CELLS = 0


@dataclass(frozen=True, kw_only=True)
class DsmOptions:
    """Options of :func:`build_dsm` (``seqat dsm``).

    Attributes
    ----------
    cell_m : float
        Cell size of the surface model, metres.
    outlier_neighbors : int
        open3d statistical outlier removal: neighbours of each point (0 switches it off).
    outlier_std_ratio : float
        A point is an outlier when its mean neighbour distance exceeds the mean of all points
        by this many standard deviations.
    fill_distance_m : float
        Empty cells up to this distance from a cell with a return are interpolated from the
        returns around them (linear, a TIN); raised to twice the mean point spacing when that
        is larger, so a sparse cloud keeps the cell asked for (docs/formats.md, *dsm.tif*).
    ground_cell_m : float
        Empty cells farther from any return but enclosed by the data take the ground
        fallback: the lowest return per cell of this size (coarser; warned about).
    """

    cell_m: float = 1.0
    outlier_neighbors: int = 20
    outlier_std_ratio: float = 2.0
    fill_distance_m: float = 3.0
    ground_cell_m: float = 10.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise ConfigError(f"cell_m: expected a positive number of metres, got {self.cell_m!r}")
        if self.outlier_neighbors < 0:
            raise ConfigError(f"outlier_neighbors: expected >= 0, got {self.outlier_neighbors}")
        if not self.outlier_std_ratio > 0:
            raise ConfigError(f"outlier_std_ratio: expected > 0, got {self.outlier_std_ratio!r}")
        if not (math.isfinite(self.fill_distance_m) and self.fill_distance_m >= 0):
            raise ConfigError(f"fill_distance_m: expected >= 0, got {self.fill_distance_m!r}")
        if not (math.isfinite(self.ground_cell_m) and self.ground_cell_m > 0):
            raise ConfigError(f"ground_cell_m: expected a positive number of metres, got "
                              f"{self.ground_cell_m!r}")


# --------------------------------------------------------------------------------------------
# The surface
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class Dsm:
    """A north-up height grid in the working CRS.

    Attributes
    ----------
    heights_m : (rows, cols) float32
        Height of each cell (pixel-is-area), NaN = nodata.
    transform : Affine
        Geotransform of the outer corner of the top-left cell (``from_origin``).
    crs : pyproj.CRS
    source : str
        File name, or a description such as ``flat plane at 12.5 m``.
    """

    heights_m: np.ndarray
    transform: Affine
    crs: pyproj.CRS
    source: str

    def __post_init__(self) -> None:
        t = self.transform
        if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            raise InputDataError(f"{self.source}: DSM must be north-up (no rotation), got "
                                 f"geotransform {tuple(t)[:6]}")
        object.__setattr__(self, "heights_m", np.asarray(self.heights_m, dtype=np.float32))

    @property
    def cell_m(self) -> tuple[float, float]:
        """Cell width and height, metres."""
        return float(self.transform.a), float(-self.transform.e)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(west, south, east, north)``, metres."""
        rows, cols = self.heights_m.shape
        west, north = self.transform.c, self.transform.f
        return (west, north + rows * self.transform.e, west + cols * self.transform.a, north)

    def sample(self, x_m: FloatArray, y_m: FloatArray) -> FloatArray:
        """Bilinear heights at scattered points (NaN outside or next to nodata).

        Parameters
        ----------
        x_m, y_m : (n,) float

        Returns
        -------
        (n,) float
        """
        col, row = self._cell_coords(np.asarray(x_m, dtype=np.float64),
                                     np.asarray(y_m, dtype=np.float64))
        out = cv2.remap(self.heights_m, col.astype(np.float32).reshape(-1, 1),
                        row.astype(np.float32).reshape(-1, 1), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
        return out.reshape(-1).astype(np.float64)

    def sample_grid(self, west_m: float, north_m: float, pixel_m: float, rows: int,
                    cols: int, out: np.ndarray | None = None) -> np.ndarray:
        """Bilinear heights at the cell centres of a north-up grid (one ``cv2.warpAffine``).

        Parameters
        ----------
        west_m, north_m : float
            Outer corner of the grid's top-left cell.
        pixel_m : float
        rows, cols : int
        out : (rows, cols) float32, optional
            Written in place (a work array kept by the caller).

        Returns
        -------
        (rows, cols) float32
            NaN outside the DSM and next to its nodata cells. OpenCV interpolates with
            1/32-cell weights: the error is below slope x cell / 64.
        """
        cw, ch = self.cell_m
        # DSM cell coordinates (centre of cell 0 = 0) of grid cell (c, r):
        # col = (west + (c + 0.5) px - W) / cw - 0.5, row = (N - north + (r + 0.5) px) / ch - 0.5
        a = pixel_m / cw
        e = pixel_m / ch
        c0 = (west_m + 0.5 * pixel_m - self.transform.c) / cw - 0.5
        r0 = (self.transform.f - north_m + 0.5 * pixel_m) / ch - 0.5
        M = np.array([[a, 0.0, c0], [0.0, e, r0]], dtype=np.float64)
        return cv2.warpAffine(self.heights_m, M, (cols, rows), dst=out,
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))

    def height_range(self, bounds: tuple[float, float, float, float]) -> tuple[float, float]:
        """Lowest and highest valid height inside ``(west, south, east, north)`` (NaN if none)."""
        cw, ch = self.cell_m
        c0, r0 = (bounds[0] - self.transform.c) / cw, (self.transform.f - bounds[3]) / ch
        c1, r1 = (bounds[2] - self.transform.c) / cw, (self.transform.f - bounds[1]) / ch
        rows, cols = self.heights_m.shape
        r0, r1 = max(int(math.floor(r0)), 0), min(int(math.ceil(r1)), rows)
        c0, c1 = max(int(math.floor(c0)), 0), min(int(math.ceil(c1)), cols)
        if r0 >= r1 or c0 >= c1:
            return float("nan"), float("nan")
        window = self.heights_m[r0:r1, c0:c1]
        if not np.any(np.isfinite(window)):
            return float("nan"), float("nan")
        return float(np.nanmin(window)), float(np.nanmax(window))

    def _cell_coords(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        cw, ch = self.cell_m
        return (x - self.transform.c) / cw - 0.5, (self.transform.f - y) / ch - 0.5


def flat_dsm(z_m: float, bounds: tuple[float, float, float, float], crs: pyproj.CRS,
             cell_m: float = 10.0) -> Dsm:
    """A horizontal plane at ``z_m`` over ``(west, south, east, north)`` (one cell margin)."""
    west = math.floor(bounds[0] / cell_m) * cell_m - cell_m
    north = math.ceil(bounds[3] / cell_m) * cell_m + cell_m
    cols = int(math.ceil((bounds[2] - west) / cell_m)) + 1
    rows = int(math.ceil((north - bounds[1]) / cell_m)) + 1
    return Dsm(heights_m=np.full((rows, cols), z_m, dtype=np.float32),
               transform=from_origin(west, north, cell_m, cell_m), crs=crs,
               source=f"flat plane at {z_m:.3f} m")


def read_dsm(path: Path | str, crs: pyproj.CRS) -> Dsm:
    """Read a DSM GeoTIFF (band 1) into the working CRS.

    A DSM in another CRS is reprojected (bilinear) with ``rasterio.warp.reproject``; band
    units ``ft`` / ``us-ft`` are converted to metres; nodata becomes NaN.

    Raises
    ------
    InputDataError
        Missing or unreadable file, no CRS, no valid height.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: {file_problem(path, 'no such DSM file')}")
    try:
        with rasterio.open(path) as src:
            if src.crs is None:
                raise InputDataError(f"{path}: the DSM has no CRS")
            heights = src.read(1, masked=True).astype(np.float32).filled(np.nan)
            transform, src_crs = src.transform, pyproj.CRS.from_wkt(src.crs.to_wkt())
            unit = (src.units[0] or "").lower() if src.units else ""
    except rasterio.errors.RasterioIOError as err:
        raise InputDataError(f"{path}: cannot read the DSM: {err}") from err
    heights *= np.float32(FOOT_UNITS.get(unit, 1.0))
    if not src_crs.equals(crs, ignore_axis_order=True):
        heights, transform = _reproject(heights, transform, src_crs, crs)
    if not np.any(np.isfinite(heights)):
        raise InputDataError(f"{path}: the DSM has no valid height (all nodata)")
    return Dsm(heights_m=heights, transform=transform, crs=crs, source=str(path))


def _reproject(heights: np.ndarray, transform: Affine, src_crs: pyproj.CRS,
               dst_crs: pyproj.CRS) -> tuple[np.ndarray, Affine]:
    rows, cols = heights.shape
    src_r = rasterio.crs.CRS.from_wkt(src_crs.to_wkt())
    dst_r = rasterio.crs.CRS.from_wkt(dst_crs.to_wkt())
    dst_transform, dst_cols, dst_rows = rasterio.warp.calculate_default_transform(
        src_r, dst_r, cols, rows, *rasterio.transform.array_bounds(rows, cols, transform))
    out = np.full((dst_rows, dst_cols), np.nan, dtype=np.float32)
    rasterio.warp.reproject(heights, out, src_transform=transform, src_crs=src_r,
                            dst_transform=dst_transform, dst_crs=dst_r, src_nodata=np.nan,
                            dst_nodata=np.nan, resampling=rasterio.warp.Resampling.bilinear)
    return out, dst_transform


# --------------------------------------------------------------------------------------------
# LAS / LAZ
# --------------------------------------------------------------------------------------------


def parse_crs(value: str, key: str, base: Path) -> pyproj.CRS:
    """A CRS from anything pyproj accepts, or from a WKT file (relative to ``base``).

    Raises
    ------
    ConfigError
        Unknown CRS or unreadable WKT file (PROJ's message attached), naming ``key``.
    """
    text = value
    candidate = Path(value) if Path(value).is_absolute() else base / value
    if candidate.suffix.lower() in (".wkt", ".prj", ".txt") or candidate.is_file():
        try:
            text = candidate.read_text(encoding="utf-8")
        except OSError as err:
            raise ConfigError(f"{key}: cannot read WKT file {candidate}: {err}") from err
    try:
        return pyproj.CRS.from_user_input(text)
    except CRSError as err:
        raise ConfigError(f"{key}: unknown CRS {value!r}: {err}") from err


def parse_las_crs(value: str) -> pyproj.CRS:
    """The CRS of ``--las-crs``: anything pyproj accepts, or the path of a WKT file."""
    return parse_crs(value, "--las-crs", Path.cwd())


@dataclass(frozen=True, kw_only=True, eq=False)
class LasCloud:
    """Points of one LAS/LAZ file in its own CRS and units.

    Attributes
    ----------
    path : Path
    xyz : (n, 3) float64
        Scaled coordinates as stored (CRS units, e.g. feet).
    crs : pyproj.CRS
    crs_from_file : bool
        The CRS came from the file's VLRs (else from ``--las-crs``).
    """

    path: Path
    xyz: np.ndarray
    crs: pyproj.CRS
    crs_from_file: bool


def las_truncation(path: Path) -> str | None:
    """Why a LAS/LAZ file that laspy cannot read looks truncated (points announced in the
    header vs bytes present), or None when it does not."""
    try:
        with laspy.open(path) as reader:
            header = reader.header
            count = int(header.point_count)
            offset = int(header.offset_to_point_data)
            record = int(header.point_format.size)
            compressed = bool(header.are_points_compressed)
    except (laspy.errors.LaspyException, OSError, ValueError):
        return None
    size = path.stat().st_size
    if compressed:
        return (f"truncated or damaged LAZ file: the header announces {count} points; "
                f"{size - offset} bytes of compressed point data could not be decoded")
    needed = offset + count * record
    if size >= needed:
        return None
    present = max(size - offset, 0)
    return (f"truncated LAS file: the header announces {count} points ({count * record} "
            f"bytes of point data) but the file holds {present} bytes of point data "
            f"({present // record} whole points)")


def read_las(path: Path | str, las_crs: pyproj.CRS | None = None) -> LasCloud:
    """Read a LAS or LAZ file with laspy (LAZ through lazrs).

    Parameters
    ----------
    path : Path or str
    las_crs : pyproj.CRS, optional
        Overrides the CRS in the file (required when the file declares none).

    Raises
    ------
    InputDataError
        Missing or unreadable file, no points, no CRS in the file and none given.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: {file_problem(path, 'no such LAS/LAZ file')}")
    try:
        las = laspy.read(path)
    except (laspy.errors.LaspyException, OSError, ValueError, RuntimeError) as err:
        # RuntimeError: lazrs.LazrsError of a damaged LAZ stream
        truncated = las_truncation(path)
        raise InputDataError(f"{path}: {truncated}" if truncated is not None
                             else f"{path}: cannot read LAS/LAZ: {err}") from err
    if len(las.points) == 0:
        raise InputDataError(f"{path}: the LAS file holds no points")
    try:
        file_crs = las.header.parse_crs()
    except (CRSError, laspy.errors.LaspyException, ValueError) as err:
        raise InputDataError(f"{path}: unreadable CRS in the LAS VLRs: {err}") from err
    crs = las_crs if las_crs is not None else file_crs
    if crs is None:
        raise InputDataError(f"{path}: no CRS in the LAS file (no WKT or GeoTIFF VLR); "
                             "give one with --las-crs EPSG:XXXX or --las-crs FILE.wkt")
    check_las_header(path, las.header)
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    bad = ~np.isfinite(xyz) | (np.abs(xyz) > [MAX_LAS_XY, MAX_LAS_XY, MAX_LAS_Z])
    if bad.any():
        k = int(np.argmax(bad.any(axis=1)))
        raise InputDataError(f"{path}: point {k}: coordinates {xyz[k].tolist()} are not "
                             f"plausible (non-finite, or beyond {MAX_LAS_XY:g} / {MAX_LAS_Z:g} "
                             "units); the header's scales or offsets are damaged")
    return LasCloud(path=path, xyz=xyz.astype(np.float64), crs=crs,
                    crs_from_file=las_crs is None)


#: Largest plausible height in the working CRS, metres.
MAX_HEIGHT_M = 1e5
#: Largest plausible LAS easting / northing and height, in the file's units (feet, metres
#: or degrees): beyond them the header's scale or offset is damaged.
MAX_LAS_XY = 1e9
MAX_LAS_Z = 1e6


def check_las_header(path: Path, header: object) -> None:
    """Refuse a LAS header whose scales are not positive or not finite, or whose offsets are
    not finite: every coordinate would be the offset, mirrored, or garbage (the LAS
    specification's scale factors are positive; a negative one mirrors the cloud)."""
    scales = np.asarray(header.scales, dtype=np.float64)  # type: ignore[attr-defined]
    offsets = np.asarray(header.offsets, dtype=np.float64)  # type: ignore[attr-defined]
    if not (np.all(np.isfinite(scales)) and np.all(scales > 0.0)
            and np.all(np.isfinite(offsets))):
        raise InputDataError(f"{path}: damaged LAS header: scales {scales.tolist()}, offsets "
                             f"{offsets.tolist()} (scales must be finite and positive, "
                             "offsets finite)")


def _vertical_sub_crs(crs: pyproj.CRS) -> pyproj.CRS | None:
    if crs.is_compound:
        return next((sub for sub in crs.sub_crs_list if sub.is_vertical), None)
    return None


def linear_unit_factor(crs: pyproj.CRS) -> float:
    """Metres per unit of the first axis (1 for angular axes)."""
    axis = crs.axis_info[0]
    return float(axis.unit_conversion_factor) if axis.unit_name not in (
        "degree", "radian", "grad") else 1.0


def to_working_crs(cloud: LasCloud, crs: pyproj.CRS) -> tuple[np.ndarray, tuple[str, ...]]:
    """Transform a cloud to the working CRS (east, north, up metres).

    Returns
    -------
    xyz_m : (n, 3) float64
    warnings : tuple[str, ...]
        Heights whose vertical datum is not declared.

    Raises
    ------
    InputDataError
        PROJ cannot transform the points, or gives non-finite coordinates.
    """
    warnings: list[str] = []
    x, y, z = cloud.xyz.T
    try:
        vertical = _vertical_sub_crs(cloud.crs)
        if vertical is not None:
            target = crs if crs.is_compound else crs.to_3d()
            tr = pyproj.Transformer.from_crs(cloud.crs, target, always_xy=True)
            ex, ny, up = tr.transform(x, y, z, errcheck=True)
        elif cloud.crs.equals(crs, ignore_axis_order=True):
            ex, ny, up = x, y, z
        else:
            tr = pyproj.Transformer.from_crs(cloud.crs, crs, always_xy=True)
            ex, ny = tr.transform(x, y, errcheck=True)
            factor = linear_unit_factor(cloud.crs)
            up = z * factor
            unit = cloud.crs.axis_info[0].unit_name
            warnings.append(f"{cloud.path.name}: CRS {cloud.crs.name!r} declares no vertical "
                            f"datum; heights converted from {unit} to metres (x {factor:g}) "
                            f"and taken as heights of {crs.name!r}")
    except ProjError as err:
        raise InputDataError(f"{cloud.path}: cannot transform from {cloud.crs.name!r} to "
                             f"{crs.name!r}: {err}") from err
    xyz = np.column_stack([ex, ny, up]).astype(np.float64)
    if not np.all(np.isfinite(xyz)):
        raise InputDataError(f"{cloud.path}: transformation from {cloud.crs.name!r} to "
                             f"{crs.name!r} gave non-finite coordinates")
    if np.abs(xyz[:, 2]).max() > MAX_HEIGHT_M:
        raise InputDataError(f"{cloud.path}: heights up to {np.abs(xyz[:, 2]).max():.4g} m in "
                             f"{crs.name!r} are not plausible (above {MAX_HEIGHT_M:g} m); the "
                             "header's z scale or offset is damaged")
    return xyz, tuple(warnings)


# --------------------------------------------------------------------------------------------
# Filtering, gridding, filling
# --------------------------------------------------------------------------------------------


def remove_outliers(xyz_m: np.ndarray, neighbors: int, std_ratio: float) -> np.ndarray:
    """Keep-mask of open3d's statistical outlier removal.

    Parameters
    ----------
    xyz_m : (n, 3) float
    neighbors : int
        0 (or fewer points than ``neighbors + 1``) keeps every point.
    std_ratio : float

    Returns
    -------
    (n,) bool
    """
    keep = np.ones(len(xyz_m), dtype=bool)
    if neighbors <= 0 or len(xyz_m) <= neighbors:
        return keep
    origin = np.floor(xyz_m.min(axis=0))  # conditioning: open3d works in float64 anyway
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz_m - origin))
    _, index = cloud.remove_statistical_outlier(nb_neighbors=neighbors, std_ratio=std_ratio)
    keep[:] = False
    keep[np.asarray(index, dtype=np.int64)] = True
    return keep


def grid_highest(xyz_m: np.ndarray, cell_m: float) -> tuple[np.ndarray, Affine]:
    """Highest point per cell on a grid aligned to multiples of ``cell_m``.

    Returns
    -------
    heights_m : (rows, cols) float32
        NaN where no point falls.
    transform : Affine
    """
    west = math.floor(xyz_m[:, 0].min() / cell_m) * cell_m - GRID_MARGIN_CELLS * cell_m
    north = (math.floor(xyz_m[:, 1].max() / cell_m) + 1) * cell_m + GRID_MARGIN_CELLS * cell_m
    col = np.floor((xyz_m[:, 0] - west) / cell_m).astype(np.int64)
    row = np.floor((north - xyz_m[:, 1]) / cell_m).astype(np.int64)
    rows, cols = int(row.max()) + 1 + GRID_MARGIN_CELLS, int(col.max()) + 1 + GRID_MARGIN_CELLS
    grid = np.full(rows * cols, -np.inf)
    np.maximum.at(grid, row * cols + col, xyz_m[:, 2])
    grid[~np.isfinite(grid)] = np.nan
    return grid.reshape(rows, cols).astype(np.float32), from_origin(west, north, cell_m, cell_m)


def fill_small_holes(heights_m: np.ndarray, max_hole_cells: int) -> tuple[np.ndarray, int]:
    """Interpolate nodata areas of at most ``max_hole_cells`` cells enclosed by data.

    A hole is a 4-connected set of NaN cells that does not touch the grid border; holes up
    to ``max_hole_cells`` are filled by GDAL's inverse-distance ``FillNodata``
    (``rasterio.fill.fillnodata``); larger ones and border gaps stay NaN.

    Returns
    -------
    heights_m : (rows, cols) float32
    filled_cells : int
    """
    empty = ~np.isfinite(heights_m)
    labels, n = ndimage.label(empty)
    if n == 0 or max_hole_cells <= 0:
        return heights_m, 0
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    small = sizes <= max_hole_cells
    small[0] = False
    small[border] = False
    fill_mask = small[labels]
    if not np.any(fill_mask):
        return heights_m, 0
    extent = max(max(s.stop - s.start for s in sl) for i, sl in
                 enumerate(ndimage.find_objects(labels), start=1) if small[i])
    work = np.where(empty, np.float32(0), heights_m).astype(np.float32)
    filled = rasterio.fill.fillnodata(work, mask=(~empty).astype(np.uint8),
                                      max_search_distance=float(extent + 1),
                                      smoothing_iterations=0)
    out = heights_m.copy()
    out[fill_mask] = filled[fill_mask]
    return out, int(fill_mask.sum())


# --------------------------------------------------------------------------------------------
# Stage
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class DsmResult:
    """Summary of :func:`build_dsm`."""

    path: Path
    las_files: tuple[Path, ...]
    las_crs: str
    crs: str
    points_read: int
    points_kept: int
    cell_m: float
    rows: int
    cols: int
    bounds: tuple[float, float, float, float]
    height_range_m: tuple[float, float]
    filled_cells: int
    interpolated_cells: int
    ground_cells: int
    ground_cell_m: float
    nodata_cells: int
    time_s: float
    warnings: tuple[str, ...]


def build_dsm(las_paths: Sequence[Path | str], out_path: Path | str, *, crs: pyproj.CRS,
              las_crs: pyproj.CRS | None = None, options: DsmOptions | None = None) -> DsmResult:
    """LAS/LAZ files -> DSM COG in the working CRS (``seqat dsm``).

    Parameters
    ----------
    las_paths : sequence of Path or str
        One or more LAS/LAZ files (same CRS or each declaring its own).
    out_path : Path or str
        The DSM COG to write (atomically).
    crs : pyproj.CRS
        Working CRS (projected, metres).
    las_crs : pyproj.CRS, optional
        CRS of the LAS files, overriding theirs (needed when a file declares none).
    options : DsmOptions, optional

    Returns
    -------
    DsmResult

    Raises
    ------
    InputDataError
        A file is missing, unreadable, empty or without CRS; or nothing is left to grid.
    """
    t0 = time.perf_counter()
    options = options or DsmOptions()
    if not las_paths:
        raise InputDataError("dsm: no LAS/LAZ file given")
    parts: list[np.ndarray] = []
    warnings: list[str] = []
    crs_names: list[str] = []
    for path in las_paths:
        cloud = read_las(path, las_crs)
        if not cloud.crs_from_file:
            warnings.append(f"{cloud.path.name}: CRS taken from --las-crs ({cloud.crs.name})")
        xyz, warn = to_working_crs(cloud, crs)
        parts.append(xyz)
        warnings.extend(warn)
        crs_names.append(cloud.crs.name)
    xyz = np.concatenate(parts)
    keep = remove_outliers(xyz, options.outlier_neighbors, options.outlier_std_ratio)
    kept = xyz[keep]
    cell_m = options.cell_m
    heights, transform = grid_highest(kept, cell_m)
    heights, fill = fill_gaps(heights, transform, kept, fill_distance_m=options.fill_distance_m,
                              ground_cell_m=options.ground_cell_m)
    nodata = ~np.isfinite(heights)
    if fill.ground_cells:
        inside = heights.size - int(nodata.sum())
        warnings.append(
            f"dsm: {fill.ground_cells} cells ({100.0 * fill.ground_cells / inside:.1f} % of the "
            f"surface) are farther than {fill.fill_distance_m:.2g} m from any return; they "
            f"take the ground fallback (lowest return per {fill.ground_cell_m:g} m cell), "
            f"coarser than the {cell_m:g} m cell")
    out = np.where(nodata, np.float32(DSM_NODATA), heights).astype(np.float32)
    tags = {"SEQAT_CELL_M": f"{cell_m:g}", "SEQAT_FILL_DISTANCE_M": f"{fill.fill_distance_m:g}",
            "SEQAT_INTERPOLATED_CELLS": str(fill.interpolated_cells),
            "SEQAT_GROUND_CELLS": str(fill.ground_cells),
            "SEQAT_GROUND_CELL_M": f"{fill.ground_cell_m:g}"}
    path = write_cog(out_path, out[None], transform=transform, crs=crs, nodata=DSM_NODATA,
                     tags=tags)
    rows, cols = heights.shape
    return DsmResult(
        path=path, las_files=tuple(Path(p) for p in las_paths),
        las_crs=", ".join(sorted(set(crs_names))), crs=crs.name, points_read=len(xyz),
        points_kept=int(keep.sum()), cell_m=cell_m, rows=rows, cols=cols,
        bounds=rasterio.transform.array_bounds(rows, cols, transform),
        height_range_m=(float(np.nanmin(heights)), float(np.nanmax(heights))),
        filled_cells=fill.interpolated_cells + fill.ground_cells,
        interpolated_cells=fill.interpolated_cells, ground_cells=fill.ground_cells,
        ground_cell_m=fill.ground_cell_m, nodata_cells=int(nodata.sum()),
        time_s=time.perf_counter() - t0, warnings=tuple(warnings))
