"""``OUT/mosaic.tif`` (or, during a ``seqat watch --ortho``, the live mosaic's tiles) as XYZ
Web Mercator tiles (rio-tiler, as TiTiler does).

The tile maths is rio-tiler's and morecantile's (``WebMercatorQuad``); this module only keeps
one open reader and re-opens it when the file is replaced (a live run publishes the mosaic by
an atomic rename: a new inode, a new mtime), so a tile always shows the file as it is when it
is requested. Tiles outside the data are fully transparent 256 x 256 PNGs, as is every tile
while the run folder has no mosaic yet.

Before ``mosaic.tif`` exists, :class:`LiveMosaic` serves the live ortho's publication
(``OUT/live/mosaic.json``, :mod:`pipeline.ortho.live_tiles`): a web tile is read from the
live tile cache ``OUT/live/xyz/{z}/{x}/{y}.png`` the watch renders when it publishes (a file
read, whatever the CPU load; a tile missing from a ``complete`` cache holds no data); a tile
not in it (another zoom, a folder without a cache) is rendered on request: the published
work tiles its bounds (morecantile) reach, merged by rio-tiler's ``mosaic_reader``, which
gives the cached tiles' pixels (tests/pipeline/serve/test_live_cache.py), encoded by the same
function. Such PNGs are kept (:data:`PNG_CACHE` of them, least recently used out) by web
tile and the versions of the files they were made of. Every tile carries an ETag of its
bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.errors import RasterioIOError
from rio_tiler.errors import TileOutsideBounds
from rio_tiler.io import Reader
from rio_tiler.models import ImageData
from rio_tiler.mosaic import mosaic_reader

from pipeline.common import webtiles
from pipeline.common.webtiles import EMPTY_TILE, TILE_PX, TMS, tile_in_range

__all__ = ["EMPTY_TILE", "TILE_PX", "TMS", "LiveMosaic", "MosaicInfo", "MosaicTiles",
           "MosaicUnreadable", "etag", "tile_in_range"]


def etag(png: bytes) -> str:
    """A strong ETag of a tile's bytes (the same tile from the cache or rendered on request
    has the same one)."""
    return '"' + hashlib.blake2b(png, digest_size=8).hexdigest() + '"'


@dataclass(frozen=True)
class MosaicInfo:
    """What the page needs to place the mosaic: WGS 84 bounds and the zoom range."""

    version: str
    bounds_wgs84: tuple[float, float, float, float]
    minzoom: int
    maxzoom: int
    #: The live mosaic's revision, and the WGS 84 boxes each of its last renderings changed
    #: (``[from revision, to revision, [[west, south, east, north], ...]]``, oldest first,
    #: :mod:`pipeline.ortho.live_render`): a page that shows ``from`` reloads only the tiles
    #: over the boxes up to ``to``. None for ``mosaic.tif`` and a live mosaic without them.
    revision: int | None = None
    changes: tuple[object, ...] | None = None


class MosaicUnreadable(Exception):
    """``mosaic.tif`` exists but cannot be read (damaged, or not a raster)."""


class MosaicTiles:
    """Tiles of one COG, read through one rio-tiler ``Reader`` re-opened on change.

    Thread-safe: the reader is used under a lock (a GDAL dataset handle is not thread-safe).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._reader: Reader | None = None
        self._key: tuple[int, int, int] | None = None
        self._info: MosaicInfo | None = None

    def _stat_key(self) -> tuple[int, int, int] | None:
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def _current(self) -> Reader | None:
        """The reader of the file as it is now (call with the lock held)."""
        key = self._stat_key()
        if key != self._key:
            self.close_locked()
            if key is not None:
                self._reader = Reader(str(self.path), tms=TMS)
                self._key = key
                r = self._reader
                self._info = MosaicInfo(
                    version=f"{key[0]}-{key[1]}-{key[2]}",
                    bounds_wgs84=tuple(float(v) for v in r.get_geographic_bounds(
                        "EPSG:4326")),  # type: ignore[arg-type]
                    minzoom=int(r.minzoom), maxzoom=int(r.maxzoom))
        return self._reader

    def _current_or_raise(self) -> Reader | None:
        try:
            return self._current()
        except Exception as err:  # noqa: BLE001 - rasterio's and rio-tiler's errors alike
            self.close_locked()
            raise MosaicUnreadable(f"{self.path.name}: cannot read: {err}") from err

    def info(self) -> MosaicInfo | None:
        """Bounds and zooms of the mosaic as it is now; None without a mosaic.

        Raises
        ------
        MosaicUnreadable
        """
        with self._lock:
            self._current_or_raise()
            return self._info

    def tile(self, z: int, x: int, y: int) -> bytes:
        """The PNG of tile ``z/x/y``; :data:`EMPTY_TILE` outside the data or without a
        mosaic.

        Raises
        ------
        MosaicUnreadable
        """
        with self._lock:
            reader = self._current_or_raise()
            if reader is None or not reader.tile_exists(x, y, z):
                return EMPTY_TILE
            try:
                img = reader.tile(x, y, z, tilesize=TILE_PX)
            except TileOutsideBounds:
                return EMPTY_TILE
            except Exception as err:  # noqa: BLE001 - a damaged block
                raise MosaicUnreadable(f"{self.path.name}: cannot read: {err}") from err
        if not img.mask.any():
            return EMPTY_TILE
        mask = img.mask[None]
        return webtiles.encode_tile(np.concatenate([np.where(mask > 0, img.data, 0), mask]))

    def close_locked(self) -> None:
        if self._reader is not None:
            self._reader.close()
        self._reader, self._key, self._info = None, None, None

    def close(self) -> None:
        with self._lock:
            self.close_locked()


#: Rendered live-mosaic PNGs kept by :class:`LiveMosaic`.
PNG_CACHE = 512


class LiveMosaic:
    """The live ortho's published tiles (module docstring); thread-safe."""

    def __init__(self, index: Path) -> None:
        self.index = index
        self._lock = threading.Lock()
        self._key: tuple[int, int, int] | None = None
        self._doc: dict[str, object] | None = None
        self._tiles: list[tuple[Path, tuple[float, float, float, float], object]] = []
        self._png: OrderedDict[tuple[object, ...], bytes] = OrderedDict()
        self._zooms: tuple[int, int] | None = None
        self._cached_zooms: tuple[int, int] | None = None  # the live tile cache's
        self._cache_complete = False  # every tile with data at its zooms is in it
        self._info: MosaicInfo | None = None
        #: Tiles answered from the live tile cache and rendered on request.
        self.served_cached = 0
        self.rendered = 0

    def _load(self) -> None:
        """Read the index if it changed (lock held)."""
        try:
            st = os.stat(self.index)
        except OSError:
            self._key, self._doc, self._tiles, self._info = None, None, [], None
            self._cached_zooms = None
            return
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if key == self._key:
            return
        try:
            doc = json.loads(self.index.read_text(encoding="utf-8"))
            tiles = [(self.index.parent / str(t["file"]),
                      tuple(float(b) for b in t["bounds_wgs84"]), t.get("version"))
                     for t in doc["tiles"]]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise MosaicUnreadable(f"live/{self.index.name}: cannot read: {err}") from err
        self._key, self._doc = key, doc
        self._tiles = tiles  # type: ignore[assignment]
        self._info = None
        xyz = doc.get("xyz")
        self._cached_zooms = (int(xyz["minzoom"]), int(xyz["maxzoom"])) if isinstance(
            xyz, dict) and xyz.get("dir") == webtiles.CACHE_DIR else None
        self._cache_complete = isinstance(xyz, dict) and xyz.get("complete") is True
        if self._cached_zooms is not None:
            self._zooms = (self._cached_zooms[0] + webtiles.ZOOMS_BELOW, self._cached_zooms[1])
        if tiles:
            if self._zooms is None:
                with Reader(str(tiles[0][0]), tms=TMS) as r:
                    self._zooms = (int(r.minzoom), int(r.maxzoom))
            west = min(b[0] for _, b, _ in tiles)
            south = min(b[1] for _, b, _ in tiles)
            east = max(b[2] for _, b, _ in tiles)
            north = max(b[3] for _, b, _ in tiles)
            revision = doc.get("revision")
            changes = xyz.get("changes") if isinstance(xyz, dict) else None
            self._info = MosaicInfo(version=f"live-{revision}",
                                    bounds_wgs84=(west, south, east, north),
                                    minzoom=max(0, self._zooms[0] - 2), maxzoom=self._zooms[1],
                                    revision=revision if isinstance(revision, int) else None,
                                    changes=tuple(changes) if isinstance(changes, list) else None)

    def info(self) -> MosaicInfo | None:
        """Bounds and zooms of the published tiles; None without any."""
        with self._lock:
            self._load()
            return self._info

    def document(self) -> dict[str, object] | None:
        """The index as read last (images published, ...)."""
        with self._lock:
            self._load()
            return self._doc

    def tile(self, z: int, x: int, y: int) -> bytes:
        """The PNG of tile ``z/x/y`` (:data:`EMPTY_TILE` outside the published tiles): from
        the live tile cache, else rendered now (module docstring).

        Raises
        ------
        MosaicUnreadable
        """
        return self.tile_from(z, x, y)[0]

    def tile_from(self, z: int, x: int, y: int) -> tuple[bytes, str]:
        """:meth:`tile` and where it came from: ``cache`` (the live tile cache), ``memory``
        (rendered earlier), ``rendered`` (now) or ``empty`` (outside the published tiles)."""
        bounds = webtiles.tile_bounds_wgs84(z, x, y)
        with self._lock:
            self._load()
            hits = [(str(p), v) for p, b, v in self._tiles if webtiles.reaches(b, bounds)]
            cached, complete = self._cached_zooms, self._cache_complete
            key = (z, x, y, *hits)
            png = self._png.get(key)
            if png is not None:
                self._png.move_to_end(key)
                return png, "memory"
        if not hits:
            return EMPTY_TILE, "empty"
        if cached is not None and cached[0] <= z <= cached[1]:
            try:
                png = webtiles.cache_path(self.index.parent, z, x, y).read_bytes()
            except FileNotFoundError:
                png = None
            if png is not None:
                with self._lock:
                    self.served_cached += 1
                return png, "cache"
            if complete:  # no image put data there (docs/formats.md, *Live run files*)
                return EMPTY_TILE, "empty"
        png = self._render([a for a, _ in hits], z, x, y)
        with self._lock:
            self.rendered += 1
            self._png[key] = png
            while len(self._png) > PNG_CACHE:
                self._png.popitem(last=False)
        return png, "rendered"

    def _render(self, assets: list[str], z: int, x: int, y: int) -> bytes:

        def read(asset: str, x: int, y: int, z: int) -> ImageData:
            with Reader(asset, tms=TMS) as r:
                return r.tile(x, y, z, tilesize=TILE_PX)

        try:
            img, _ = mosaic_reader(assets, read, x, y, z, threads=1,
                                   allowed_exceptions=(TileOutsideBounds, RasterioIOError))
        except Exception as err:  # noqa: BLE001 - a tile replaced or removed meanwhile, ...
            if type(err).__name__ == "EmptyMosaicError":
                return EMPTY_TILE
            raise MosaicUnreadable(f"live mosaic: cannot read: {err}") from err
        if not img.mask.any():
            return EMPTY_TILE
        mask = img.mask[None]
        return webtiles.encode_tile(np.concatenate([np.where(mask > 0, img.data, 0), mask]))
