"""Real texture and terrain for the renderer: an orthophoto with a world file + LiDAR.

The texture keeps its own CRS (for Autzen, Oregon Lambert in international feet, the WKT
``autzen-srs.wkt``, which pyproj finds equal to EPSG:2994 up to axis order:
tests/pipeline/simulate/test_render_flight.py); hit points of the working CRS are mapped into
it with a pyproj transformer and the world file. The surface is the highest LiDAR point per cell of
the working CRS (:func:`pipeline.ortho.dsm.grid_highest` after
:func:`pipeline.ortho.dsm.to_working_crs` and open3d's outlier removal); empty cells are
interpolated linearly between the filled
cells around them (Delaunay of the gaps' rims, scipy) and, outside their hull, take the
nearest filled cell. LiDAR without a vertical datum has its heights converted to metres and
taken as heights of the working CRS (as ``seqat dsm`` does), so the simulated world is
self-consistent.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyproj
from scipy import ndimage
from scipy.interpolate import LinearNDInterpolator

from pipeline.ortho.dsm import (
    fill_small_holes,
    grid_highest,
    read_las,
    remove_outliers,
    to_working_crs,
)
from pipeline.simulate.render import HeightField, Scene, Texture, TextureMap
from seqat.errors import InputDataError

#: World file suffixes tried beside a texture image, in order.
WORLD_FILE_SUFFIXES = (".wld", ".jgw", ".jpgw", ".tfw", ".pgw")
#: Outlier removal of the LiDAR before gridding (open3d statistical filter).
OUTLIER_NEIGHBORS = 8
OUTLIER_STD_RATIO = 3.0
#: Gaps up to this many cells are filled by inverse distance before the linear fill.
SMALL_HOLE_CELLS = 16


@dataclass(frozen=True, kw_only=True)
class WorldFile:
    """The six lines of a world file: ``x = a col + c``, ``y = e row + f`` (pixel centres)."""

    a: float
    e: float
    c: float
    f: float


def read_world_file(image_path: Path) -> WorldFile:
    """The world file beside ``image_path`` (north-up only).

    Raises
    ------
    InputDataError
        No world file, not six numbers, or a rotated one.
    """
    for suffix in WORLD_FILE_SUFFIXES:
        path = image_path.with_suffix(suffix)
        if path.is_file():
            break
    else:
        raise InputDataError(f"{image_path}: no world file beside it "
                             f"({', '.join(WORLD_FILE_SUFFIXES)})")
    try:
        values = [float(line) for line in path.read_text(encoding="utf-8").split()]
    except ValueError as err:
        raise InputDataError(f"{path}: expected six numbers: {err}") from err
    if len(values) != 6:
        raise InputDataError(f"{path}: expected six numbers, got {len(values)}")
    a, d, b, e, c, f = values
    if d != 0.0 or b != 0.0 or a == 0.0 or e == 0.0:
        raise InputDataError(f"{path}: rotated or degenerate world file ({values}); "
                             "only north-up textures are supported")
    return WorldFile(a=a, e=e, c=c, f=f)


def projected_texture_map(world: WorldFile, working_crs: pyproj.CRS,
                          texture_crs: pyproj.CRS) -> TextureMap:
    """Working CRS -> texture pixels through pyproj (``always_xy``) and the world file."""
    transformer = pyproj.Transformer.from_crs(working_crs, texture_crs, always_xy=True)

    def to_pixel(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tx, ty = transformer.transform(x, y)
        return (np.asarray(tx) - world.c) / world.a, (np.asarray(ty) - world.f) / world.e

    return to_pixel


def read_texture(path: Path, working_crs: pyproj.CRS, texture_crs: pyproj.CRS) -> Texture:
    """Read a texture image (BGR) and its world file.

    Raises
    ------
    InputDataError
        Missing or unreadable image or world file.
    """
    if not path.is_file():
        raise InputDataError(f"{path}: no such texture image")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputDataError(f"{path}: cannot read the texture image")
    world = read_world_file(path)
    return Texture(image=image, to_pixel=projected_texture_map(world, working_crs, texture_crs))


def fill_all(heights_m: np.ndarray) -> np.ndarray:
    """Fill every NaN cell: small holes by inverse distance, larger gaps linearly between the
    filled cells on their rims, nearest filled cell outside those."""
    # small holes first (GDAL's inverse-distance fill, as seqat dsm): the many one-cell gaps
    # of a LiDAR gridded near its point spacing would otherwise all be Delaunay rims
    small_filled, _ = fill_small_holes(np.asarray(heights_m, dtype=np.float32),
                                       SMALL_HOLE_CELLS)
    out = np.asarray(small_filled, dtype=np.float64)
    empty = ~np.isfinite(out)
    if not empty.any():
        return out
    if empty.all():
        raise InputDataError("no LiDAR point falls into the surface grid")
    # only filled cells on the rim of a gap span the triangles across it (a Delaunay
    # triangulation of every filled cell is slow on a regular grid and changes nothing there)
    rim = ~empty & ndimage.binary_dilation(empty, structure=np.ones((3, 3), dtype=bool))
    rows, cols = np.nonzero(rim)
    erows, ecols = np.nonzero(empty)
    if len(rows) >= 3:
        interp = LinearNDInterpolator(np.column_stack([rows, cols]), out[rows, cols])
        out[erows, ecols] = interp(np.column_stack([erows, ecols]))
    still = ~np.isfinite(out)
    if still.any():
        _, (ir, ic) = ndimage.distance_transform_edt(still, return_indices=True)
        out[still] = out[ir[still], ic[still]]
    return out


def lidar_surface(las_paths: list[Path], working_crs: pyproj.CRS, las_crs: pyproj.CRS | None,
                  cell_m: float, bounds_m: tuple[float, float, float, float]) -> HeightField:
    """The rendering surface: highest LiDAR point per cell inside ``bounds_m``, gaps filled.

    Parameters
    ----------
    bounds_m : (west, south, east, north)
        Region of interest in the working CRS; the grid covers it (cells aligned to
        multiples of ``cell_m``).

    Raises
    ------
    InputDataError
        Missing or unreadable LAS file, or no point inside ``bounds_m``.
    """
    clouds = [to_working_crs(read_las(p, las_crs), working_crs)[0] for p in las_paths]
    xyz = np.vstack(clouds)
    west, south, east, north = bounds_m
    inside = ((xyz[:, 0] >= west) & (xyz[:, 0] <= east) & (xyz[:, 1] >= south)
              & (xyz[:, 1] <= north))
    xyz = xyz[inside]
    if len(xyz) == 0:
        raise InputDataError(f"{', '.join(map(str, las_paths))}: no LiDAR point inside "
                             f"the flight area {bounds_m}")
    xyz = xyz[remove_outliers(xyz, OUTLIER_NEIGHBORS, OUTLIER_STD_RATIO)]
    # pin the grid to the region of interest: two corner points at the lowest height
    low = float(xyz[:, 2].min())
    corners = np.array([[west, south, low], [east, north, low]])
    heights, transform = grid_highest(np.vstack([xyz, corners]), cell_m)
    return HeightField(heights_m=fill_all(heights), west_m=transform.c, north_m=transform.f,
                       cell_m=cell_m)


def las_center_m(las_path: Path, working_crs: pyproj.CRS, las_crs: pyproj.CRS | None) -> (
        tuple[float, float]):
    """Centre of a LAS file's points in the working CRS (the default flight centre)."""
    xyz, _ = to_working_crs(read_las(las_path, las_crs), working_crs)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    return float(0.5 * (lo[0] + hi[0])), float(0.5 * (lo[1] + hi[1]))


def load_scene(texture_path: Path, texture_crs: pyproj.CRS, las_paths: list[Path],
               las_crs: pyproj.CRS | None, working_crs: pyproj.CRS, cell_m: float,
               bounds_m: tuple[float, float, float, float]) -> Scene:
    """Texture and LiDAR surface of the region ``bounds_m`` (working CRS)."""
    texture = read_texture(texture_path, working_crs, texture_crs)
    surface = lidar_surface(las_paths, working_crs, las_crs, cell_m, bounds_m)
    return Scene(surface=surface, texture=texture)
