"""Streaming mosaic of orthos, kept in tiles on disk (``mosaic.tif``).

:class:`MosaicBuilder` receives one :class:`pipeline.ortho.base.OrthoResult` at a time and updates
only the tiles of the global grid it touches; nothing but those tiles is in memory, so memory
stays flat however long the flight. Per cell the mosaic keeps the image that sees it **most
nadir** (smallest tangent of the off-nadir angle; for images at one height this is the nearest
nadir point, so seamlines are the perpendicular bisectors between nadir points); across a
seamline the two images are blended linearly over ``feather_px`` cells. ``finish()`` writes
the tiles, cropped to the bounding box of the cells any image sees (the tiles are only the
work grid; the COG has its own 512 px blocks), into a tiled GeoTIFF and converts it into the
``mosaic.tif`` COG with overviews (GDAL reads it block by block).

Tiles: the most recently used ``cache_tiles`` stay in memory (consecutive images share most
of their tiles); older ones go to the tile store ``<work_dir>/<col>_<row>.npz`` (bands, alpha,
float32 off-nadir tangent with +inf where empty), written atomically and removed by
``finish()``. Memory is bounded by the cache, whatever the flight's length.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyproj
import rasterio
from affine import Affine
from rasterio.transform import from_origin
from rasterio.windows import Window

from pipeline.ortho.base import ALPHA_OPAQUE, OrthoRaster, OrthoResult
from pipeline.ortho.raster import COG_BLOCK_PX, atomic_path, colorinterp_for, gtiff_to_cog
from seqat.errors import ConfigError, InputDataError

#: Mosaic tile size, cells (= the COG block size, so tiles map to whole blocks).
TILE_PX = COG_BLOCK_PX
#: Default seamline feather width, cells.
FEATHER_PX = 8
#: Tiles kept in memory (about 2 MB each for RGB): more than one image's footprint.
CACHE_TILES = 48


@dataclass(frozen=True, kw_only=True)
class MosaicUpdate:
    """What :meth:`MosaicBuilder.add` reports."""

    image_id: str
    tiles_touched: int
    cells_updated: int
    update_ms: float
    tiles: frozenset[tuple[int, int]] = frozenset()  # (column, row) of each tile touched


@dataclass(frozen=True, kw_only=True)
class MosaicResult:
    """What :meth:`MosaicBuilder.finish` reports."""

    path: Path
    images: int
    tiles: int
    rows: int
    cols: int
    bounds: tuple[float, float, float, float]
    finish_s: float


class MosaicBuilder:
    """Growing mosaic on the global ortho grid.

    Parameters
    ----------
    path : Path
        The ``mosaic.tif`` written by :meth:`finish`.
    crs : pyproj.CRS
    feather_px : int
        Width of the blend across seamlines, cells (0: hard seams).
    work_dir : Path, optional
        Tile store (default: ``.<name>.tiles`` beside ``path``); emptied first.
    cache_tiles : int, optional
        Tiles held in memory. Default: ``CACHE_TILES``, raised to twice the tiles of the
        largest ortho so far (bounded by the image size, not by the flight's length, and
        consecutive images never thrash the tile store).
    """

    def __init__(self, path: Path | str, crs: pyproj.CRS, *, feather_px: int = FEATHER_PX,
                 work_dir: Path | None = None, cache_tiles: int | None = None) -> None:
        if feather_px < 0:
            raise ConfigError(f"feather_px: expected >= 0, got {feather_px}")
        self.path = Path(path)
        self.crs = crs
        self.feather_px = feather_px
        self.work_dir = work_dir or self.path.parent / f".{self.path.name}.tiles"
        if self.work_dir.exists():
            shutil.rmtree(self.work_dir)
        self.work_dir.mkdir(parents=True)
        self.pixel_m: float | None = None
        self.bands: int | None = None
        self.dtype: np.dtype | None = None
        self._tiles: set[tuple[int, int]] = set()  # every tile holding data
        # Global (row0, row1, col0, col1) of the seen cells of each tile: the crop of finish().
        self._extent: dict[tuple[int, int], tuple[int, int, int, int]] = {}
        self._stored: set[tuple[int, int]] = set()  # tiles in the tile store
        self._cache: OrderedDict[tuple[int, int], MosaicTile] = OrderedDict()
        self._dirty: set[tuple[int, int]] = set()
        self._auto_cache = cache_tiles is None
        self._cache_tiles = CACHE_TILES if cache_tiles is None else max(1, cache_tiles)
        self._images: set[str] = set()

    # ----------------------------------------------------------------------------------------

    def add(self, ortho: OrthoResult, *,
            tiles: frozenset[tuple[int, int]] | None = None) -> MosaicUpdate:
        """Paste one ortho into the tiles it touches (only into ``tiles`` when given: the
        recomposition of tiles emptied by :meth:`clear`).

        Raises
        ------
        InputDataError
            Its pixel size, band count or type differs from the first ortho's.
        """
        t0 = time.perf_counter()
        r = ortho.raster
        if self.pixel_m is None:
            self.pixel_m, self.bands, self.dtype = r.pixel_m, r.pixels.shape[2], r.pixels.dtype
        elif (r.pixel_m, r.pixels.shape[2], r.pixels.dtype) != (self.pixel_m, self.bands,
                                                                 self.dtype):
            raise InputDataError(
                f"image {r.image_id!r}: ortho of {r.pixels.shape[2]} {r.pixels.dtype} band(s) at "
                f"{r.pixel_m:g} m does not match the mosaic ({self.bands} {self.dtype} at "
                f"{self.pixel_m:g} m)")
        rows, cols = r.shape
        T = TILE_PX
        if self._auto_cache:
            span = ((r.row0 + rows - 1) // T - r.row0 // T + 1) * ((r.col0 + cols - 1) // T
                                                                  - r.col0 // T + 1)
            self._cache_tiles = max(self._cache_tiles, 2 * span)
        touched_keys: set[tuple[int, int]] = set()
        updated = 0
        for key in raster_tiles(r):
            if tiles is not None and key not in tiles:
                continue
            pasted = paste_into_tile(self._tile(*key), key, r, self.feather_px)
            if pasted is None:
                continue
            cells, extent = pasted
            self._grow_extent(key, extent)
            self._tiles.add(key)
            self._dirty.add(key)
            touched_keys.add(key)
            updated += cells
        self._images.add(r.image_id)
        return MosaicUpdate(image_id=r.image_id, tiles_touched=len(touched_keys),
                            cells_updated=updated, update_ms=(time.perf_counter() - t0) * 1e3,
                            tiles=frozenset(touched_keys))

    def clear(self, tiles: Iterable[tuple[int, int]]) -> None:
        """Empty these tiles (to recompose them from their images in acquisition order)."""
        for key in tiles:
            self._cache.pop(key, None)
            self._dirty.discard(key)
            self._tiles.discard(key)
            self._extent.pop(key, None)
            if key in self._stored:
                self._stored.discard(key)
                self._tile_path(*key).unlink(missing_ok=True)

    def tile_raster(self, key: tuple[int, int]) -> tuple[np.ndarray, Affine] | None:
        """One tile as it is now: ``(bands + alpha, T, T)`` and its geotransform; None when
        it holds no data (emptied, or never touched)."""
        if key not in self._tiles or self.pixel_m is None:
            return None
        tile = self._tile(*key)
        tc, tr = key
        T, p = TILE_PX, self.pixel_m
        data = np.concatenate([np.moveaxis(tile.colour, 2, 0), tile.alpha[None]])
        return data, from_origin(tc * T * p, -tr * T * p, p, p)

    def discard(self) -> None:
        """Drop everything without writing ``mosaic.tif`` (remove the tile store)."""
        self._cache.clear()
        shutil.rmtree(self.work_dir, ignore_errors=True)

    def finish(self) -> MosaicResult:
        """Write ``mosaic.tif`` (COG with overviews, alpha band) and remove the tile store.

        Raises
        ------
        InputDataError
            No ortho was added.
        """
        t0 = time.perf_counter()
        if not self._tiles or self.pixel_m is None or self.dtype is None or self.bands is None:
            raise InputDataError(f"{self.path}: no ortho was added to the mosaic")
        p = self.pixel_m

        def read_tile(key: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
            tile = self._tile(*key)
            return tile.colour, tile.alpha

        row0, row1, col0, col1 = write_tiles_cog(self.path, self.crs, p, self._extent,
                                                 read_tile, self.work_dir)
        rows, cols = row1 - row0, col1 - col0
        shutil.rmtree(self.work_dir, ignore_errors=True)
        bounds = (col0 * p, -row1 * p, col1 * p, -row0 * p)
        return MosaicResult(path=self.path, images=len(self._images), tiles=len(self._tiles),
                            rows=rows, cols=cols, bounds=bounds,
                            finish_s=time.perf_counter() - t0)

    # ----------------------------------------------------------------------------------------

    def _grow_extent(self, key: tuple[int, int], new: tuple[int, int, int, int]) -> None:
        """Widen the tile's extent (global ``row0, row1, col0, col1``) by ``new``."""
        old = self._extent.get(key)
        self._extent[key] = new if old is None else union_extent(old, new)

    def _tile_path(self, tc: int, tr: int) -> Path:
        return self.work_dir / f"{tc}_{tr}.npz"

    def _tile(self, tc: int, tr: int) -> MosaicTile:
        """The tile from the cache, the tile store or new; evicts the least recently used."""
        key = (tc, tr)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        assert self.dtype is not None and self.bands is not None
        if key in self._stored:
            with np.load(self._tile_path(tc, tr)) as npz:
                tile = MosaicTile(colour=npz["colour"], alpha=npz["alpha"], off=npz["off"])
        else:
            tile = new_tile(self.bands, self.dtype)
        self._cache[key] = tile
        while len(self._cache) > self._cache_tiles:
            old_key, old = self._cache.popitem(last=False)
            if old_key in self._dirty:
                self._store(old_key, old)
        return tile

    def _store(self, key: tuple[int, int], tile: MosaicTile) -> None:
        target = self._tile_path(*key)
        fd, tmp = tempfile.mkstemp(dir=self.work_dir, suffix=".npz.tmp")
        try:
            with os.fdopen(fd, "wb") as handle:
                np.savez(handle, colour=tile.colour, alpha=tile.alpha, off=tile.off)
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
        self._stored.add(key)
        self._dirty.discard(key)


def tiles_of_bounds(bounds: tuple[float, float, float, float], pixel_m: float) -> (
        frozenset[tuple[int, int]]):
    """The ``(column, row)`` of every tile a ``(west, south, east, north)`` window reaches on
    the global grid of ``pixel_m`` cells (rows grow southwards from northing 0)."""
    west, south, east, north = bounds
    c0, c1 = math.floor(west / pixel_m), math.ceil(east / pixel_m)
    r0, r1 = math.floor(-north / pixel_m), math.ceil(-south / pixel_m)
    T = TILE_PX
    return frozenset((tc, tr) for tr in range(r0 // T, (max(r1, r0 + 1) - 1) // T + 1)
                     for tc in range(c0 // T, (max(c1, c0 + 1) - 1) // T + 1))


def raster_tiles(raster: OrthoRaster) -> tuple[tuple[int, int], ...]:
    """The ``(column, row)`` of every tile an ortho's window reaches, row by row."""
    rows, cols = raster.shape
    T = TILE_PX
    return tuple((tc, tr) for tr in range(raster.row0 // T, (raster.row0 + rows - 1) // T + 1)
                 for tc in range(raster.col0 // T, (raster.col0 + cols - 1) // T + 1))


def new_tile(bands: int, dtype: np.dtype) -> MosaicTile:
    """An empty tile (nothing seen: off-nadir tangent +inf)."""
    return MosaicTile(colour=np.zeros((TILE_PX, TILE_PX, bands), dtype),
                      alpha=np.zeros((TILE_PX, TILE_PX), dtype),
                      off=np.full((TILE_PX, TILE_PX), np.inf, np.float32))


def paste_into_tile(tile: MosaicTile, key: tuple[int, int], raster: OrthoRaster,
                    feather_px: int) -> tuple[int, tuple[int, int, int, int]] | None:
    """Blend the part of an ortho inside tile ``key = (column, row)`` into ``tile`` in place:
    the one composition step of :class:`MosaicBuilder` and of the distributed mosaic
    (:mod:`pipeline.campaign`). A tile composed from the same orthos in the same order is the
    same, bit for bit, whoever composes it.

    Returns
    -------
    (cells, extent) or None
        Cells the ortho sees in the tile and their bounding box as global ``(row0, row1,
        col0, col1)`` (exclusive ends); None when it sees none there.
    """
    r, T = raster, TILE_PX
    tc, tr = key
    rows, cols = r.shape
    # Overlap of tile (tc, tr) with the ortho, in ortho and in tile coordinates.
    g_r0, g_r1 = max(tr * T, r.row0), min((tr + 1) * T, r.row0 + rows)
    g_c0, g_c1 = max(tc * T, r.col0), min((tc + 1) * T, r.col0 + cols)
    if g_r0 >= g_r1 or g_c0 >= g_c1:
        return None
    src = (slice(g_r0 - r.row0, g_r1 - r.row0), slice(g_c0 - r.col0, g_c1 - r.col0))
    seen = r.seen[src]
    if not seen.any():
        return None
    dst = (slice(g_r0 - tr * T, g_r1 - tr * T), slice(g_c0 - tc * T, g_c1 - tc * T))
    feather = 2.0 * feather_px * r.pixel_m / r.height_agl_m if feather_px else 0.0
    _blend(tile.colour[dst], tile.alpha[dst], tile.off[dst], r.pixels[src], seen,
           r.off_nadir[src], feather, ALPHA_OPAQUE[tile.colour.dtype])
    seen_rows = np.flatnonzero(seen.any(axis=1))
    seen_cols = np.flatnonzero(seen.any(axis=0))
    extent = (g_r0 + int(seen_rows[0]), g_r0 + int(seen_rows[-1]) + 1,
              g_c0 + int(seen_cols[0]), g_c0 + int(seen_cols[-1]) + 1)
    return int(seen.sum()), extent


def union_extent(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> (
        tuple[int, int, int, int]):
    """The bounding box of two ``(row0, row1, col0, col1)`` extents."""
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


def write_tiles_cog(path: Path, crs: pyproj.CRS, pixel_m: float,
                    extents: Mapping[tuple[int, int], tuple[int, int, int, int]],
                    read_tile: Callable[[tuple[int, int]], tuple[np.ndarray, np.ndarray]],
                    work_dir: Path) -> tuple[int, int, int, int]:
    """Write mosaic tiles into one COG with overviews and an alpha band, cropped to the cells
    seen (the union of ``extents``, global ``row0, row1, col0, col1`` per tile).

    ``read_tile(key)`` gives a tile's ``(colour (T, T, bands), alpha (T, T))``; tiles are read
    one at a time, row by row, into a tiled GeoTIFF in ``work_dir``, which GDAL converts into
    the COG (block by block: memory does not grow with the mosaic). Returns the crop.
    """
    T, p = TILE_PX, pixel_m
    row0, row1 = min(e[0] for e in extents.values()), max(e[1] for e in extents.values())
    col0, col1 = min(e[2] for e in extents.values()), max(e[3] for e in extents.values())
    transform = from_origin(col0 * p, -row0 * p, p, p)
    profile: dict[str, object] | None = None
    with atomic_path(work_dir / "mosaic_full.tif") as full:
        dst = None
        try:
            for tc, tr in sorted(extents, key=lambda t: (t[1], t[0])):
                colour, alpha = read_tile((tc, tr))
                if dst is None:
                    count = colour.shape[2] + 1
                    profile = {"driver": "GTiff", "width": col1 - col0, "height": row1 - row0,
                               "count": count, "dtype": colour.dtype.name, "tiled": True,
                               "blockxsize": T, "blockysize": T,
                               "crs": rasterio.crs.CRS.from_wkt(crs.to_wkt()),
                               "transform": transform, "sparse_ok": True,
                               "BIGTIFF": "IF_SAFER"}
                    dst = rasterio.open(full, "w", **profile)
                    dst.colorinterp = colorinterp_for(count, alpha=True)
                r0, r1 = max(tr * T, row0), min((tr + 1) * T, row1)
                c0, c1 = max(tc * T, col0), min((tc + 1) * T, col1)
                part = (slice(r0 - tr * T, r1 - tr * T), slice(c0 - tc * T, c1 - tc * T))
                data = np.concatenate([np.moveaxis(colour[part], 2, 0), alpha[part][None]])
                dst.write(data, window=Window(c0 - col0, r0 - row0, c1 - c0, r1 - r0))
        finally:
            if dst is not None:
                dst.close()
        gtiff_to_cog(full, path)
    return row0, row1, col0, col1


@dataclass(frozen=True, kw_only=True, eq=False)
class MosaicTile:
    """One mosaic tile: colour (T, T, bands), alpha (T, T), off-nadir tangent (T, T)."""

    colour: np.ndarray
    alpha: np.ndarray
    off: np.ndarray


def _blend(colour: np.ndarray, alpha: np.ndarray, off: np.ndarray, new: np.ndarray,
           seen: np.ndarray, new_off: np.ndarray, feather: float, opaque: int) -> None:
    """Merge one ortho window into a tile window in place.

    Where only the new image sees a cell it is taken; where both do, the weight of the new
    image is ``clip(0.5 + (off_old - off_new) / feather, 0, 1)`` (a hard choice of the more
    nadir view when ``feather`` is 0), so the blend spans about ``feather_px`` cells across
    the seamline where both are equally nadir (``cv2.blendLinear``). ``off`` keeps the better
    of the two.
    """
    old_seen = alpha > 0
    if feather > 0:
        with np.errstate(invalid="ignore"):
            w = off - new_off
            w *= np.float32(1.0 / feather)
            w += np.float32(0.5)
            np.clip(w, 0.0, 1.0, out=w)
    else:
        w = (new_off < off).astype(np.float32)
    w[~old_seen] = 1.0
    w[~seen] = 0.0
    if colour.dtype == np.uint8:  # cv2.blendLinear: 8-bit (and float) only
        cv2.blendLinear(new, colour, w, 1.0 - w, dst=colour)
    else:
        old = colour.astype(np.float32)
        old += w[:, :, None] * (new.astype(np.float32) - old)
        colour[:] = np.rint(old).astype(colour.dtype)
    alpha[seen] = opaque
    np.minimum(off, new_off, out=off, where=seen)
