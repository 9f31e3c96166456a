"""The growing mosaic published while the flight goes on: ``OUT/live/mosaic.json`` + tiles.

``mosaic.tif`` is written once, at the end (a COG of the whole mosaic: its cost grows with
the flight). While the run goes on, the live ortho publishes instead the mosaic's work tiles
an image touched (:class:`pipeline.ortho.mosaic.MosaicBuilder`'s 512 x 512 cell tiles of the
global ortho grid) as small GeoTIFFs ``OUT/live/tiles/c<col>_r<row>.tif`` (each written
atomically; tiled, uncompressed, no overviews: half the time of a COG, and a 1 MB tile read
whole at a low zoom costs little), then the index ``OUT/live/mosaic.json`` (atomically replaced)
naming every published tile with its WGS 84 bounds and a version, and the images in the
mosaic so far with the time each was published. The cost per image is the tiles it touched,
not the mosaic's size; ``seqat serve`` reads the tiles through rio-tiler's mosaic reader
(docs/formats.md, *Live run files*).

Before the index, each publication renders the web tiles (XYZ, Web Mercator, every zoom of
the live mosaic) that the new images changed into the live tile cache
``OUT/live/xyz/{z}/{x}/{y}.png`` (:mod:`pipeline.common.webtiles`: GDAL's warper on one
in-memory raster per zoom of the work tiles the web tiles reach; a tile whose pixels did not
change is not written again), so ``seqat serve`` answers tiles with
a file read rather than rendering them from the growing mosaic, under CPU contention, when a
browser asks. What an image changes lies inside its cells seen (the blend writes nothing
else), so the web tiles over their bounding box are the ones to render again.

When the run's ``mosaic.tif`` is published, :meth:`LiveTiles.remove` deletes the tiles, the
cache and the index (``seqat serve`` shows ``mosaic.tif`` from then on).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pyproj
import rasterio

from pipeline.common import webtiles
from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import LIVE_DIR, LIVE_MOSAIC_INDEX, LIVE_TILES_DIR
from pipeline.ortho.base import OrthoRaster
from pipeline.ortho.mosaic import MosaicBuilder
from pipeline.ortho.raster import write_tiled_tiff

INDEX_FORMAT = "seqat-live-mosaic"


def tile_name(key: tuple[int, int]) -> str:
    return f"c{key[0]}_r{key[1]}.tif"


def seen_bounds(raster: OrthoRaster) -> tuple[float, float, float, float] | None:
    """``(west, south, east, north)`` of the cells an ortho sees (what it can change in the
    mosaic), in the mosaic's CRS; None when it sees none."""
    rows = np.flatnonzero(raster.seen.any(axis=1))
    cols = np.flatnonzero(raster.seen.any(axis=0))
    if not len(rows):
        return None
    p = raster.pixel_m
    return ((raster.col0 + int(cols[0])) * p, -(raster.row0 + int(rows[-1]) + 1) * p,
            (raster.col0 + int(cols[-1]) + 1) * p, -(raster.row0 + int(rows[0])) * p)


class LiveTiles:
    """Publishes the tiles of a growing mosaic (module docstring). Used from one thread (the
    live ortho's worker: the one that changes the mosaic).

    Parameters
    ----------
    out_dir : Path
        The run folder.
    mosaic : MosaicBuilder
    crs : pyproj.CRS
        The mosaic's CRS.
    """

    def __init__(self, out_dir: Path, mosaic: MosaicBuilder, crs: pyproj.CRS) -> None:
        self.folder = out_dir / LIVE_DIR
        self.tiles_dir = self.folder / LIVE_TILES_DIR
        if self.tiles_dir.exists():
            shutil.rmtree(self.tiles_dir)
        shutil.rmtree(self.folder / webtiles.CACHE_DIR, ignore_errors=True)
        (self.folder / LIVE_MOSAIC_INDEX).unlink(missing_ok=True)
        self.tiles_dir.mkdir(parents=True)
        self.mosaic = mosaic
        self.crs = crs
        self._to_wgs84 = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        self._rio_crs = rasterio.crs.CRS.from_wkt(crs.to_wkt())
        self._zooms: tuple[int, int] | None = None
        self._changed: list[tuple[float, float, float, float]] = []  # WGS 84, since last
        self._rendered: dict[object, bytes] = {}  # web tile -> digest of its pixels
        self._pending: set[tuple[int, int]] = set()
        self._waiting_images: list[dict[str, object]] = []
        self._published: dict[tuple[int, int], dict[str, object]] = {}
        self._images: list[dict[str, object]] = []
        self._version = 0
        self.last_publish = 0.0  # monotonic
        self.publish_ms: list[float] = []
        self.web_tiles_ms: list[float] = []
        self.web_tiles: list[int] = []

    def touched(self, tiles: Iterable[tuple[int, int]], image: str, ortho_ms: float,
                at_unix_s: float | None = None,
                changed: tuple[float, float, float, float] | None = None) -> None:
        """An image went into these tiles (published by the next :meth:`publish`);
        ``changed``: the bounds of the cells it changed in the mosaic's CRS
        (:func:`seen_bounds`), whose web tiles the publication renders."""
        if changed is not None:
            self._changed.append(self._to_wgs84.transform_bounds(*changed, densify_pts=5))
        self._pending.update(tiles)
        self._waiting_images.append({"image": image, "ortho_ms": round(ortho_ms, 1),
                                     "at_unix_s": at_unix_s})

    @property
    def pending(self) -> bool:
        return bool(self._pending or self._waiting_images)

    def publish(self) -> None:
        """Write the pending tiles, then the index."""
        if not self.pending:
            return
        t0 = time.perf_counter()
        self._version += 1
        for key in sorted(self._pending):
            raster = self.mosaic.tile_raster(key)
            path = self.tiles_dir / tile_name(key)
            if raster is None:
                self._published.pop(key, None)
                path.unlink(missing_ok=True)
                continue
            data, transform = raster
            write_tiled_tiff(path, data, transform=transform, crs=self.crs, alpha=True)
            rows, cols = data.shape[1:]
            west, north = transform.c, transform.f
            east, south = west + cols * transform.a, north + rows * transform.e
            bounds = self._to_wgs84.transform_bounds(west, south, east, north, densify_pts=5)
            self._published[key] = {"file": f"{LIVE_TILES_DIR}/{tile_name(key)}",
                                    "bounds_wgs84": [round(b, 9) for b in bounds],
                                    "version": self._version}
        self._pending.clear()
        self._render_web_tiles()
        now = round(time.time(), 3)
        for item in self._waiting_images:
            self._images.append({**item, "published_unix_s": now})
        self._waiting_images.clear()
        tiles = list(self._published.values())
        doc = {"format": INDEX_FORMAT, "version": 1, "updated_unix_s": now,
               "revision": self._version, "pixel_m": self.mosaic.pixel_m,
               "bounds_wgs84": _union([t["bounds_wgs84"] for t in tiles]),  # type: ignore[misc]
               "tiles": tiles, "images": self._images,
               "xyz": None if self._zooms is None else {
                   "dir": webtiles.CACHE_DIR, "minzoom": self._zooms[0],
                   "maxzoom": self._zooms[1], "complete": True}}
        atomic_write_text(self.folder / LIVE_MOSAIC_INDEX, json.dumps(doc, separators=(",", ":")))
        self.last_publish = time.monotonic()
        self.publish_ms.append((time.perf_counter() - t0) * 1e3)

    def _render_web_tiles(self) -> None:
        """Render the web tiles over the changed cells into the live tile cache, every zoom
        of the live mosaic, one in-memory raster per zoom."""
        t0 = time.perf_counter()
        changed, self._changed = self._changed, []
        if not changed or not self._published:
            return
        if self._zooms is None:
            key = next(iter(self._published))
            raster = self.mosaic.tile_raster(key)
            if raster is None:
                return
            with webtiles.region([webtiles.WorkTile(*raster)], self._rio_crs) as ds:
                self._zooms = webtiles.live_zooms(ds)
        zooms = range(self._zooms[0], self._zooms[1] + 1)
        written = 0
        todo = sorted({t for b in changed for t in webtiles.tiles_over(b, zooms)},
                      key=lambda t: (t.z, t.x, t.y))
        for z in zooms:
            level = [t for t in todo if t.z == z]
            bounds = [webtiles.tile_bounds_wgs84(t.z, t.x, t.y) for t in level]
            keys = [k for k, info in self._published.items()
                    if any(webtiles.reaches(info["bounds_wgs84"], b)  # type: ignore[arg-type]
                           for b in bounds)]
            rasters = [r for r in (self.mosaic.tile_raster(k) for k in sorted(keys))
                       if r is not None]
            if not rasters:
                continue
            with webtiles.region([webtiles.WorkTile(*r) for r in rasters],
                                 self._rio_crs) as ds:
                for t in level:
                    data = webtiles.read_tile(ds, t.z, t.x, t.y)
                    digest = hashlib.blake2b(data.tobytes(), digest_size=16).digest()
                    if self._rendered.get(t) == digest:
                        continue  # the new cells are elsewhere in its bounds
                    self._rendered[t] = digest
                    webtiles.write_cached(self.folder, t.z, t.x, t.y,
                                          webtiles.encode_tile(data))
                    written += 1
        self.web_tiles.append(written)
        self.web_tiles_ms.append((time.perf_counter() - t0) * 1e3)

    def remove(self) -> None:
        """The run's ``mosaic.tif`` is published: drop the index, then the tiles."""
        with contextlib.suppress(FileNotFoundError):
            (self.folder / LIVE_MOSAIC_INDEX).unlink()
        shutil.rmtree(self.tiles_dir, ignore_errors=True)
        shutil.rmtree(self.folder / webtiles.CACHE_DIR, ignore_errors=True)


def _union(bounds: list[list[float]]) -> list[float] | None:
    if not bounds:
        return None
    return [min(b[0] for b in bounds), min(b[1] for b in bounds),
            max(b[2] for b in bounds), max(b[3] for b in bounds)]
