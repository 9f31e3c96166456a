"""Gap filling of a gridded DSM at the cell size asked for (docs/formats.md, *dsm.tif*).

A highest-return grid at a fine cell has empty cells wherever the LiDAR left no return in
them: between the points of a sparse cloud, under dense canopy, over water. Instead of
coarsening the whole grid until the cells are full (the rule this replaces), the grid keeps
``cell_m`` and its gaps are filled:

* **interpolated**: an empty cell within ``fill_distance_m`` of a cell with a return takes the
  linear interpolation (a Delaunay TIN, ``scipy.spatial.Delaunay``, :func:`tin_heights`) of the cell
  heights around it: exact on planes, never above the highest neighbour;
* **ground**: an empty cell farther from data but enclosed by it (a lake, a hole in the
  returns) takes the *ground fallback*, the lowest return per ``ground_cell_m`` cell (its own
  gaps filled by GDAL's ``FillNodata``), read bilinearly. Those cells are the only ones
  coarser than ``cell_m``; :class:`GapFill` counts them and the DSM says so in a warning
  and in its GeoTIFF metadata (``SEQAT_GROUND_CELLS``). The ground samples enter the same TIN
  as the returns around the gap, so the surface is continuous from the rim into the gap;
* **outside**: empty cells not enclosed by the data (beyond the cloud's edge) stay nodata.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import rasterio.fill
from affine import Affine
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError, cKDTree

#: Steps of the walk that moves a rasterised cell into the triangle that holds it.
WALK_STEPS = 8


@dataclass(frozen=True, kw_only=True)
class GapFill:
    """What :func:`fill_gaps` did.

    Attributes
    ----------
    interpolated_cells : int
        Empty cells interpolated from returns within the fill distance.
    ground_cells : int
        Empty cells enclosed by data but farther from it: the ground fallback (coarser).
    nodata_cells : int
        Cells left nodata (outside the data).
    fill_distance_m : float
        Interpolation distance used (the option, or twice the mean point spacing if larger).
    ground_cell_m : float
        Cell of the ground fallback.
    """

    interpolated_cells: int
    ground_cells: int
    nodata_cells: int
    fill_distance_m: float
    ground_cell_m: float


def grid_lowest(xyz_m: np.ndarray, transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """Lowest point per cell of a north-up grid (NaN where none falls)."""
    rows, cols = shape
    cell_w, cell_h = transform.a, -transform.e
    col = np.floor((xyz_m[:, 0] - transform.c) / cell_w).astype(np.int64)
    row = np.floor((transform.f - xyz_m[:, 1]) / cell_h).astype(np.int64)
    inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
    grid = np.full(rows * cols, np.inf)
    np.minimum.at(grid, row[inside] * cols + col[inside], xyz_m[inside, 2])
    grid[~np.isfinite(grid)] = np.nan
    return grid.reshape(rows, cols)


def ground_surface(xyz_m: np.ndarray, transform: Affine, shape: tuple[int, int],
                   ground_cell_m: float) -> np.ndarray:
    """The ground fallback on the DSM grid: the lowest return per ``ground_cell_m`` cell, its
    empty cells filled by GDAL's inverse-distance ``FillNodata`` (no distance limit), read
    bilinearly at the DSM's cell centres.

    Returns
    -------
    (rows, cols) float64
    """
    rows, cols = shape
    cell_m = transform.a
    west, north = transform.c, transform.f
    g_west = math.floor(west / ground_cell_m) * ground_cell_m - ground_cell_m
    g_north = math.ceil(north / ground_cell_m) * ground_cell_m + ground_cell_m
    g_cols = int(math.ceil((west + cols * cell_m - g_west) / ground_cell_m)) + 1
    g_rows = int(math.ceil((g_north - (north - rows * cell_m)) / ground_cell_m)) + 1
    g_transform = Affine(ground_cell_m, 0.0, g_west, 0.0, -ground_cell_m, g_north)
    lowest = grid_lowest(xyz_m, g_transform, (g_rows, g_cols))
    known = np.isfinite(lowest)
    work = np.where(known, lowest, 0.0).astype(np.float32)
    filled = rasterio.fill.fillnodata(work, mask=known.astype(np.uint8),
                                      max_search_distance=float(g_rows + g_cols),
                                      smoothing_iterations=0)
    # DSM cell centre (c, r) in ground-grid cell coordinates (centre of cell 0 = 0).
    scale = cell_m / ground_cell_m
    c0 = (west + 0.5 * cell_m - g_west) / ground_cell_m - 0.5
    r0 = (g_north - north + 0.5 * cell_m) / ground_cell_m - 0.5
    M = np.array([[scale, 0.0, c0], [0.0, scale, r0]])
    return cv2.warpAffine(filled.astype(np.float32), M, (cols, rows),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


def point_spacing_m(xyz_m: np.ndarray, sample: int = 100_000) -> float:
    """Typical horizontal distance between neighbouring points: twice the median distance to
    the nearest neighbour (``1 / sqrt(density)`` for randomly scattered points), from at most
    ``sample`` points (a fixed, evenly spaced subset of the rest, whose neighbours are all)."""
    if len(xyz_m) < 2:
        return 0.0
    tree = cKDTree(xyz_m[:, :2])
    subset = xyz_m[:: max(1, len(xyz_m) // sample), :2]
    distance, _ = tree.query(subset, k=2)
    return 2.0 * float(np.median(distance[:, 1]))


def _disk(radius_cells: int) -> np.ndarray:
    r = np.arange(-radius_cells, radius_cells + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= radius_cells ** 2


def _barycentric(points: np.ndarray, simplices: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Barycentric weights (n, 3) of points ``x`` in triangles ``simplices`` (scipy's
    ``Delaunay.transform`` would invert every triangle of the TIN)."""
    a, b, c = (points[simplices[:, i]] for i in range(3))
    v0, v1, v2 = b - a, c - a, x - a
    det = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        wb = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / det
        wc = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / det
    return np.column_stack([1.0 - wb - wc, wb, wc])


def tin_heights(vr: np.ndarray, vc: np.ndarray, vz: np.ndarray, shape: tuple[int, int],
                qr: np.ndarray, qc: np.ndarray) -> np.ndarray:
    """Linear interpolation in the Delaunay TIN of vertices at cell centres ``(vr, vc)``.

    Each triangle is rasterised once (``cv2.fillConvexPoly`` writes its index into the cells it
    covers) and the queried cells read their triangle's plane from barycentric coordinates:
    scipy's point location (``find_simplex``) costs microseconds per cell and searches every
    triangle for a cell outside the hull.

    Returns
    -------
    (k,) float64
        Heights at cells ``(qr, qc)``; NaN outside the TIN (or with fewer than 3 vertices not
        on a line).
    """
    z = np.full(qr.shape, np.nan)
    points = np.column_stack([vc, vr]).astype(np.float64)
    try:
        tri = Delaunay(points)
    except (QhullError, ValueError):  # fewer than 3 vertices, or all on a line
        return z
    index = np.full(shape, -1, dtype=np.int32)
    corners = points[tri.simplices].astype(np.int32)
    for k, triangle in enumerate(corners):
        cv2.fillConvexPoly(index, triangle, k)
    k = index[qr, qc]
    ok = k >= 0
    k = k[ok]
    x = np.column_stack([qc[ok], qr[ok]]).astype(np.float64)
    w = _barycentric(points, tri.simplices[k], x)
    # The rasterisation also gives a cell whose centre lies just outside a triangle's edge to
    # it: such cells walk across that edge (the vertex with the most negative weight is
    # opposite it: ``neighbors``) until they are inside; at the hull, or after
    # WALK_STEPS, they take the nearest point of their triangle (clipped weights), never an
    # extrapolation.
    for _ in range(WALK_STEPS):
        off = np.flatnonzero(np.any(w < -1e-9, axis=1))
        if off.size == 0:
            break
        across = tri.neighbors[k[off], np.argmin(w[off], axis=1)]
        move = across >= 0
        if not move.any():
            break
        off = off[move]
        k[off] = across[move]
        w[off] = _barycentric(points, tri.simplices[k[off]], x[off])
    w = np.clip(w, 0.0, 1.0)
    w /= w.sum(axis=1, keepdims=True)
    z[ok] = np.einsum("ni,ni->n", w, vz[tri.simplices[k]])
    return z


def fill_gaps(heights_m: np.ndarray, transform: Affine, xyz_m: np.ndarray, *,
              fill_distance_m: float, ground_cell_m: float) -> tuple[np.ndarray, GapFill]:
    """Fill the empty cells of a highest-return grid (module docstring).

    Parameters
    ----------
    heights_m : (rows, cols) float32
        NaN = no return in the cell.
    transform : Affine
        North-up geotransform of the grid (square cells).
    xyz_m : (n, 3) float
        The points gridded (for the point spacing and the ground fallback).
    fill_distance_m : float
        Empty cells up to this distance from a cell with a return are interpolated; raised to
        twice the point spacing (:func:`point_spacing_m`) when that is larger (a sparse cloud
        at a fine cell is interpolated, not left with holes between its points).
    ground_cell_m : float
        Cell of the ground fallback.

    Returns
    -------
    heights_m : (rows, cols) float32
    GapFill
    """
    cell_m = float(transform.a)
    occupied = np.isfinite(heights_m)
    n_occupied = int(occupied.sum())
    rows, cols = heights_m.shape
    distance_m = max(fill_distance_m, 2.0 * point_spacing_m(xyz_m))
    none = GapFill(interpolated_cells=0, ground_cells=0, nodata_cells=int((~occupied).sum()),
                   fill_distance_m=distance_m, ground_cell_m=ground_cell_m)
    if n_occupied < 3 or n_occupied == heights_m.size:
        return heights_m, none
    radius = max(1, int(math.ceil(distance_m / cell_m)))
    # Distance of every empty cell to the nearest return (in cells).
    dist = ndimage.distance_transform_edt(~occupied)
    near = ~occupied & (dist <= radius)
    # Enclosed: inside the data's outline (the occupied cells closed over the fill distance,
    # holes of any size included); beyond it, the cloud has ended.
    padded = np.pad(occupied, radius)
    closed = ndimage.binary_closing(padded, structure=_disk(radius))[radius:-radius,
                                                                     radius:-radius]
    outline = ndimage.binary_fill_holes(closed | occupied)
    near &= outline
    far = ~occupied & ~near & outline
    if not near.any() and not far.any():
        return heights_m, none
    values = heights_m.astype(np.float64)
    # TIN vertices: returns within reach of a gap, plus ground samples inside the far gaps.
    gaps = near | far
    rim = occupied & ndimage.binary_dilation(gaps, structure=_disk(radius + 1))
    vr, vc = np.nonzero(rim)
    vz = values[vr, vc]
    ground = None
    if far.any():
        ground = ground_surface(xyz_m, transform, heights_m.shape, ground_cell_m)
        step = max(1, int(round(ground_cell_m / cell_m / 2)))
        lattice = np.zeros_like(far)
        lattice[::step, ::step] = True
        edge = far & ~ndimage.binary_erosion(far)
        gr, gc = np.nonzero(far & (lattice | edge))
        vr, vc = np.concatenate([vr, gr]), np.concatenate([vc, gc])
        vz = np.concatenate([vz, ground[gr, gc]])
    out = heights_m.copy()
    tr, tc = np.nonzero(gaps)
    z = tin_heights(vr, vc, vz, heights_m.shape, tr, tc)
    if ground is not None:  # outside the TIN's hull (corners of a gap): the ground
        missing = ~np.isfinite(z)
        z[missing] = ground[tr[missing], tc[missing]]
    out[tr, tc] = z.astype(np.float32)
    still = ~np.isfinite(out)
    return out, GapFill(interpolated_cells=int(np.count_nonzero(near & ~still)),
                        ground_cells=int(np.count_nonzero(far & ~still)),
                        nodata_cells=int(still.sum()), fill_distance_m=distance_m,
                        ground_cell_m=ground_cell_m)
