"""XYZ Web Mercator tiles of the live mosaic: one renderer for the writer and the server.

A live ``seqat watch --ortho`` publishes the growing mosaic's work tiles (512 x 512 cells of
the global ortho grid, :mod:`pipeline.ortho.live_tiles`), and its renderer process
(:mod:`pipeline.ortho.live_render`) renders the web tiles the new images changed into the
live tile cache ``OUT/live/xyz/{z}/{x}/{y}.png``; ``seqat serve`` answers from that cache (a
file read) and renders on request only the tiles not in it (:mod:`pipeline.serve.tiles`,
rio-tiler's ``mosaic_reader``). The cache is rendered by :func:`render_tile`: the work tiles
the web tiles of one rendering reach are pasted into one in-memory raster (:func:`region`:
they lie on one grid and never overlap, so this is a copy at integer offsets), and GDAL's
warper (a rasterio ``WarpedVRT``, nearest neighbour, as rio-tiler's ``Reader.tile``) reads
each tile's 256 x 256 pixels on the grid of its bounds in morecantile's ``WebMercatorQuad``:
no tile maths here. A cached tile is what rio-tiler renders of the published work tiles on
request, pixel for pixel (tests/pipeline/serve/test_live_cache.py), and both are encoded by
:func:`encode_tile`; one raster serves every web tile of a rendering, and without rio-tiler's
per-tile bounds check and default-transform search, and its reading of every work tile per
web tile, a tile costs 3-7x less CPU than on request (docs/benchmarks.md).

The cache's zoom range is the live mosaic's (:func:`live_zooms`): from two zooms below the
one a work tile fits in to the first zoom finer than the mosaic's cells.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import morecantile
import numpy as np
import rasterio
from affine import Affine
from PIL import Image
from rasterio.enums import ColorInterp, Resampling
from rasterio.io import MemoryFile
from rasterio.transform import from_bounds
from rasterio.vrt import WarpedVRT
from rio_tiler.errors import NoOverviewWarning
from rio_tiler.io import Reader
from rio_tiler.utils import render as rio_render

# the regions are in memory and read at one zoom each: overviews would cost more than they save
warnings.filterwarnings("ignore", category=NoOverviewWarning)

#: Edge of a tile, pixels.
TILE_PX = 256
#: The tile matrix set of the XYZ tiles Leaflet and OpenLayers request.
TMS = morecantile.tms.get("WebMercatorQuad")
#: Zooms below the one a work tile fits in that the live mosaic still offers.
ZOOMS_BELOW = 2
#: zlib level of the PNGs: 1 encodes 256 x 256 RGBA in ~5 ms instead of ~10 ms at the default
#: 6, for ~20 % more bytes (docs/benchmarks.md, *Live map*, second pass).
PNG_LEVEL = 1
#: Folder of the live tile cache in ``OUT/live/``.
CACHE_DIR = "xyz"
_INTERP = {2: [ColorInterp.gray, ColorInterp.alpha],
           4: [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]}


def encode_png(rgba: np.ndarray) -> bytes:
    """A ``(TILE_PX, TILE_PX, 4)`` uint8 array as PNG bytes (Pillow, :data:`PNG_LEVEL`)."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba, dtype=np.uint8), "RGBA").save(
        buf, "PNG", compress_level=PNG_LEVEL)
    return buf.getvalue()


#: The tile outside the data.
EMPTY_TILE = encode_png(np.zeros((TILE_PX, TILE_PX, 4), np.uint8))


@dataclass(frozen=True)
class WorkTile:
    """One published work tile: ``(bands + alpha, rows, cols)`` uint8 and its geotransform."""

    data: np.ndarray
    transform: Affine


def tile_in_range(z: int, x: int, y: int) -> bool:
    """A tile index of ``WebMercatorQuad`` (zoom 0..24)."""
    return 0 <= z <= 24 and 0 <= x < 2 ** z and 0 <= y < 2 ** z


def tiles_over(bounds_wgs84: Sequence[float], zooms: Iterable[int]) -> list[morecantile.Tile]:
    """The web tiles of ``zooms`` that ``(west, south, east, north)`` reaches."""
    west, south, east, north = bounds_wgs84
    return list(TMS.tiles(west, south, east, north, list(zooms)))


def tile_bounds_wgs84(z: int, x: int, y: int) -> tuple[float, float, float, float]:
    b = TMS.bounds(morecantile.Tile(x, y, z))
    return b.left, b.bottom, b.right, b.top


def reaches(bounds_wgs84: Sequence[float], tile_bounds: Sequence[float]) -> bool:
    """Whether two WGS 84 boxes overlap (a work tile and a web tile)."""
    return (bounds_wgs84[0] < tile_bounds[2] and bounds_wgs84[2] > tile_bounds[0]
            and bounds_wgs84[1] < tile_bounds[3] and bounds_wgs84[3] > tile_bounds[1])


@contextlib.contextmanager
def region(tiles: Sequence[WorkTile], crs: rasterio.crs.CRS,
           ) -> Iterator[rasterio.io.DatasetReader]:
    """``tiles`` pasted at their places on their common grid into one in-memory raster (an
    uncompressed GeoTIFF in a ``MemoryFile``), transparent elsewhere, opened for reading."""
    if not tiles:
        raise ValueError("a region of no tiles")
    p = tiles[0].transform.a
    west = min(t.transform.c for t in tiles)
    north = max(t.transform.f for t in tiles)
    cols = max(round((t.transform.c - west) / p) + t.data.shape[2] for t in tiles)
    rows = max(round((north - t.transform.f) / p) + t.data.shape[1] for t in tiles)
    bands, dtype = tiles[0].data.shape[0], tiles[0].data.dtype
    if bands not in _INTERP:
        raise ValueError(f"a region of {bands} bands (expected colour or gray, and alpha)")
    data = np.zeros((bands, rows, cols), dtype)
    for t in tiles:
        c0, r0 = round((t.transform.c - west) / p), round((north - t.transform.f) / p)
        data[:, r0:r0 + t.data.shape[1], c0:c0 + t.data.shape[2]] = t.data
    # band interleaved, as the array: GDAL copies it (pixel interleaved: 4-5x the time)
    profile = {"driver": "GTiff", "width": cols, "height": rows, "count": bands,
               "dtype": dtype, "crs": crs, "transform": Affine(p, 0.0, west, 0.0, -p, north),
               "interleave": "band"}
    with MemoryFile() as mem:
        with mem.open(**profile) as dst:
            dst.colorinterp = _INTERP[bands]
            dst.write(data)
        with mem.open() as ds:
            yield ds


def read_tile(dataset: rasterio.io.DatasetReader, z: int, x: int, y: int) -> np.ndarray:
    """Web tile ``z/x/y`` read from ``dataset`` (:func:`region`: colour or gray bands and
    alpha) on the tile's 256 x 256 grid in ``WebMercatorQuad`` (nearest neighbour, as
    rio-tiler's ``Reader.tile``): ``(bands + alpha, 256, 256)``, alpha 0 outside the data."""
    b = TMS.xy_bounds(morecantile.Tile(x, y, z))
    with WarpedVRT(dataset, crs=TMS.rasterio_crs,
                   transform=from_bounds(b.left, b.bottom, b.right, b.top, TILE_PX, TILE_PX),
                   width=TILE_PX, height=TILE_PX, resampling=Resampling.nearest) as vrt:
        return vrt.read()


def encode_tile(data: np.ndarray) -> bytes:
    """:func:`read_tile`'s pixels as the tile's PNG (:data:`EMPTY_TILE` without data)."""
    alpha = data[-1]
    if not alpha.any():
        return EMPTY_TILE
    if data.dtype != np.uint8:
        return rio_render(data[:-1], (alpha > 0).astype(np.uint8) * 255, img_format="PNG",
                          ZLEVEL=PNG_LEVEL)
    if len(data) == 2:  # gray
        data = np.concatenate([data[:1], data[:1], data])
    return encode_png(data.transpose(1, 2, 0))


def render_tile(dataset: rasterio.io.DatasetReader, z: int, x: int, y: int) -> bytes:
    """The PNG of web tile ``z/x/y`` from ``dataset`` (:func:`read_tile`, :func:`encode_tile`)."""
    return encode_tile(read_tile(dataset, z, x, y))


def live_zooms(dataset: rasterio.io.DatasetReader) -> tuple[int, int]:
    """The live mosaic's zoom range from one work tile (:func:`region`): rio-tiler's zooms of
    it, the lowest :data:`ZOOMS_BELOW` lower (a whole flight on the screen)."""
    with Reader(dataset.name, dataset=dataset, tms=TMS) as reader:
        return max(0, int(reader.minzoom) - ZOOMS_BELOW), int(reader.maxzoom)


def cache_path(live_dir: Path, z: int, x: int, y: int) -> Path:
    """Where the live tile cache holds tile ``z/x/y``."""
    return live_dir / CACHE_DIR / str(z) / str(x) / f"{y}.png"


def write_cached(live_dir: Path, z: int, x: int, y: int, png: bytes) -> None:
    """Replace tile ``z/x/y`` of the live tile cache (a temporary file renamed: a reader sees
    the old tile or the new one, never part of one; not fsynced: a cache)."""
    path = cache_path(live_dir, z, x, y)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(png)
    os.replace(tmp, path)
