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

Each publication also hands the bounds of the cells the new images saw to the renderer
(:mod:`pipeline.ortho.live_render`, a child process), which renders the web tiles over them
(XYZ, Web Mercator, every zoom of the live mosaic) into the live tile cache
``OUT/live/xyz/{z}/{x}/{y}.png`` and then writes the index, so ``seqat serve`` answers tiles
with a file read rather than rendering them from the growing mosaic, under CPU contention,
when a browser asks. What an image changes lies inside its cells seen (the blend writes
nothing else), so the web tiles over their boxes (:func:`seen_boxes`) are the ones to render
again.

When the run's ``mosaic.tif`` is published, :meth:`LiveTiles.remove` deletes the tiles, the
cache and the index (``seqat serve`` shows ``mosaic.tif`` from then on).
"""

from __future__ import annotations

import contextlib
import json
import shutil
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pyproj

from pipeline.common import webtiles
from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import LIVE_DIR, LIVE_MOSAIC_INDEX, LIVE_TILES_DIR
from pipeline.ortho.base import OrthoRaster
from pipeline.ortho.live_render import STOP_WAIT_S, RendererProcess
from pipeline.ortho.mosaic import MosaicBuilder
from pipeline.ortho.raster import write_tiled_tiff

INDEX_FORMAT = "seqat-live-mosaic"


def tile_name(key: tuple[int, int]) -> str:
    return f"c{key[0]}_r{key[1]}.tif"


#: Rows of mosaic cells per band of :func:`seen_boxes`.
BAND_CELLS = 256


def seen_boxes(raster: OrthoRaster, band_cells: int = BAND_CELLS,
               ) -> list[tuple[float, float, float, float]]:
    """The cells an ortho sees (what it can change in the mosaic) as ``(west, south, east,
    north)`` boxes in the mosaic's CRS: one per band of ``band_cells`` rows of the mosaic's
    grid, the bounding box of the cells seen in it (a rotated footprint is a few bands, not
    its bounding box: fewer web tiles rendered and reloaded); none when it sees none."""
    seen_rows = raster.seen.any(axis=1)
    p = raster.pixel_m
    boxes = []
    first = raster.row0 - raster.row0 % band_cells  # bands on the global grid
    for top in range(first, raster.row0 + len(seen_rows), band_cells):
        r0, r1 = max(0, top - raster.row0), min(len(seen_rows), top + band_cells - raster.row0)
        rows = np.flatnonzero(seen_rows[r0:r1])
        if not len(rows):
            continue
        cols = np.flatnonzero(raster.seen[r0 + rows[0]:r0 + rows[-1] + 1].any(axis=0))
        boxes.append(((raster.col0 + int(cols[0])) * p,
                      -(raster.row0 + r0 + int(rows[-1]) + 1) * p,
                      (raster.col0 + int(cols[-1]) + 1) * p,
                      -(raster.row0 + r0 + int(rows[0])) * p))
    return boxes


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
    render : bool
        Render the live tile cache (a child process, :mod:`pipeline.ortho.live_render`,
        started at the first publication from the calling thread: it inherits its niceness).
    """

    def __init__(self, out_dir: Path, mosaic: MosaicBuilder, crs: pyproj.CRS,
                 render: bool = True) -> None:
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
        self._changed: list[tuple[float, float, float, float]] = []  # WGS 84, since last
        self._pending: set[tuple[int, int]] = set()
        self._waiting_images: list[dict[str, object]] = []
        self._published: dict[tuple[int, int], dict[str, object]] = {}
        self._images: list[dict[str, object]] = []
        self._version = 0
        self.last_publish = 0.0  # monotonic
        self.publish_ms: list[float] = []
        self._renderer: RendererProcess | None = None
        self._render = render

    def touched(self, tiles: Iterable[tuple[int, int]], image: str, ortho_ms: float,
                at_unix_s: float | None = None,
                changed: Iterable[tuple[float, float, float, float]] = ()) -> None:
        """An image went into these tiles (published by the next :meth:`publish`);
        ``changed``: boxes of the cells it changed in the mosaic's CRS (:func:`seen_boxes`),
        whose web tiles the publication renders."""
        for box in changed:
            self._changed.append(self._to_wgs84.transform_bounds(*box, densify_pts=5))
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
        now = round(time.time(), 3)
        for item in self._waiting_images:
            self._images.append({**item, "published_unix_s": now})
        self._waiting_images.clear()
        tiles = list(self._published.values())
        doc = {"format": INDEX_FORMAT, "version": 1, "updated_unix_s": now,
               "revision": self._version, "pixel_m": self.mosaic.pixel_m,
               "bounds_wgs84": _union([t["bounds_wgs84"] for t in tiles]),  # type: ignore[misc]
               "tiles": tiles, "images": self._images, "xyz": None}
        changed, self._changed = self._changed, []
        if self._render and self._renderer is None:
            self._renderer = RendererProcess(self.folder, self.crs.to_wkt())
        # the renderer writes the index once the web tiles are there; without it, now
        if self._renderer is None or not self._renderer.submit(changed, doc):
            atomic_write_text(self.folder / LIVE_MOSAIC_INDEX,
                              json.dumps(doc, separators=(",", ":")))
        self.last_publish = time.monotonic()
        self.publish_ms.append((time.perf_counter() - t0) * 1e3)

    @property
    def web_tiles_ms(self) -> list[float]:
        """The renderer's time per rendering (:mod:`pipeline.ortho.live_render`)."""
        return [] if self._renderer is None else list(self._renderer.ms)

    @property
    def web_tiles_cpu_ms(self) -> list[float]:
        """The renderer's CPU time per rendering."""
        return [] if self._renderer is None else list(self._renderer.cpu_ms)

    @property
    def web_tiles(self) -> list[int]:
        """Web tiles the renderer wrote, per rendering."""
        return [] if self._renderer is None else list(self._renderer.tiles)

    def wait_rendered(self, timeout: float | None = None) -> bool:
        """Wait until the renderer has written every publication handed to it (tests)."""
        return self._renderer is None or self._renderer.wait(timeout)

    def stop_renderer(self, wait_s: float = STOP_WAIT_S) -> None:
        """Let the renderer finish what it was handed (``wait_s`` at most), then end it."""
        if self._renderer is not None:
            self._renderer.stop(wait_s)

    def remove(self) -> None:
        """The run's ``mosaic.tif`` is published: end the renderer, drop the index, then the
        tiles."""
        if self._renderer is not None:
            self._renderer.stop(0.0)
        with contextlib.suppress(FileNotFoundError):
            (self.folder / LIVE_MOSAIC_INDEX).unlink()
        shutil.rmtree(self.tiles_dir, ignore_errors=True)
        shutil.rmtree(self.folder / webtiles.CACHE_DIR, ignore_errors=True)


def _union(bounds: list[list[float]]) -> list[float] | None:
    if not bounds:
        return None
    return [min(b[0] for b in bounds), min(b[1] for b in bounds),
            max(b[2] for b in bounds), max(b[3] for b in bounds)]
