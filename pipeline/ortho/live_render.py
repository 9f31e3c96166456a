"""The live tile cache's renderer: a child process of ``seqat watch --ortho``.

:class:`pipeline.ortho.live_tiles.LiveTiles` publishes the work tiles an image touched and
hands the renderer one *job* per publication: the bounds of the cells the new images saw and
the index it would have written. The renderer renders the web tiles over those bounds, every
zoom of the live mosaic, from the published GeoTIFFs (:mod:`pipeline.common.webtiles`) into
``OUT/live/xyz/``, and only then writes the index, so a revision is announced with its tiles
ready (the cache is complete). Jobs waiting when it is free are rendered as one (the union of
their bounds, the newest index). The index also keeps the bounds each of the last
:data:`CHANGES_KEPT` renderings changed (``xyz.changes``: ``[from revision, to revision,
[[west, south, east, north], ...]]``), so a page reloads only the web tiles a new revision
changed (``seqat serve``'s ``status.json``, ``mosaic.changes``).

A process, not a thread of the watch: rendering is Python around GDAL, and a niced thread
holding the GIL while descheduled stalls the AT loop (the server moved to a child process for
the same reason, docs/architecture.md). It inherits the ortho worker's niceness (it is started
from the worker thread) and reads the GeoTIFFs back (the same bytes the server reads).

Protocol (JSON lines): the parent writes ``{"folder", "crs"}``, then a job per publication
``{"changed": [[west, south, east, north] WGS 84, ...], "index": {...}}``; the child answers
each rendering with ``{"jobs", "tiles" (written), "ms", "cpu_ms"}``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import select
import subprocess
import sys
import threading
import time
from collections import OrderedDict, deque
from pathlib import Path

import rasterio

from pipeline.common import webtiles
from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import LIVE_MOSAIC_INDEX

#: Seconds :meth:`RendererProcess.stop` waits for pending jobs before terminating.
STOP_WAIT_S = 10.0
#: Work tiles the renderer keeps read (1 MB each at 512 x 512 RGBA).
PARTS_KEPT = 64
#: Renderings whose changed bounds the index keeps (``xyz.changes``): a page that showed one
#: of the last this many revisions reloads only the web tiles they changed.
CHANGES_KEPT = 32


class TileRenderer:
    """The child's state: zooms, the digest of every tile written (a tile whose pixels did
    not change is not written again), when each image was first published."""

    def __init__(self, folder: Path, crs_wkt: str) -> None:
        self.folder = folder
        self.crs = rasterio.crs.CRS.from_wkt(crs_wkt)
        self.zooms: tuple[int, int] | None = None
        self._digests: dict[tuple[int, int, int], bytes] = {}
        self._published: dict[str, float] = {}
        self._parts: OrderedDict[tuple[Path, object], webtiles.WorkTile] = OrderedDict()
        self._changes: deque[list[object]] = deque(maxlen=CHANGES_KEPT)
        self._revision: object = None  # of the index written last

    def _part(self, path: Path, version: object) -> webtiles.WorkTile:
        """A published work tile, read once per version (:data:`PARTS_KEPT` kept)."""
        key = (path, version)
        part = self._parts.get(key)
        if part is None:
            with rasterio.open(path) as src:
                part = webtiles.WorkTile(src.read(), src.transform)
            self._parts[key] = part
            while len(self._parts) > PARTS_KEPT:
                self._parts.popitem(last=False)
        self._parts.move_to_end(key)
        return part

    def render(self, changed: list[list[float]], index: dict[str, object]) -> int:
        """Render the web tiles over ``changed``, then write ``index``; tiles written."""
        tiles = [(self.folder / str(t["file"]), [float(b) for b in t["bounds_wgs84"]],
                  t.get("version")) for t in index["tiles"]]  # type: ignore[union-attr,index]
        written = 0
        if tiles and changed:
            if self.zooms is None:
                with webtiles.region([self._part(tiles[0][0], tiles[0][2])], self.crs) as ds:
                    self.zooms = webtiles.live_zooms(ds)
            zooms = range(self.zooms[0], self.zooms[1] + 1)
            todo = sorted({t for b in changed for t in webtiles.tiles_over(b, zooms)},
                          key=lambda t: (t.z, t.x, t.y))
            bounds = [webtiles.tile_bounds_wgs84(t.z, t.x, t.y) for t in todo]
            reach = [(p, v) for p, b, v in tiles
                     if any(webtiles.reaches(b, tb) for tb in bounds)]
            if reach:
                # one raster for every zoom: the warper reads only the window a tile needs
                with webtiles.region([self._part(p, v) for p, v in reach], self.crs) as ds:
                    for t in todo:
                        data = webtiles.read_tile(ds, t.z, t.x, t.y)
                        digest = hashlib.blake2b(data.tobytes(), digest_size=16).digest()
                        key = (t.z, t.x, t.y)
                        if self._digests.get(key) == digest:
                            continue  # the new cells are elsewhere in its bounds
                        self._digests[key] = digest
                        webtiles.write_cached(self.folder, t.z, t.x, t.y,
                                              webtiles.encode_tile(data))
                        written += 1
        now = round(time.time(), 3)
        for image in index.get("images", []):  # type: ignore[union-attr]
            image["published_unix_s"] = self._published.setdefault(image["image"], now)
        index["updated_unix_s"] = now
        revision = index.get("revision")
        if revision != self._revision:
            self._changes.append([self._revision, revision,
                                  [[round(b, 9) for b in box] for box in changed]])
        self._revision = revision
        index["xyz"] = None if self.zooms is None else {
            "dir": webtiles.CACHE_DIR, "minzoom": self.zooms[0], "maxzoom": self.zooms[1],
            "complete": True, "changes": list(self._changes)}
        atomic_write_text(self.folder / LIVE_MOSAIC_INDEX, json.dumps(index,
                                                                     separators=(",", ":")))
        return written


def _lines(fd: int) -> tuple[list[str], bool]:
    """The complete lines on ``fd`` now (blocking for the first); and whether it ended."""
    buf = b""
    lines: list[bytes] = []
    while True:
        chunk = os.read(fd, 1 << 16)
        if not chunk:
            return [line.decode() for line in lines], True
        buf += chunk
        *done, buf = buf.split(b"\n")
        lines += done
        if not buf and lines and not select.select([fd], [], [], 0)[0]:
            return [line.decode() for line in lines], False


def render_child() -> None:
    """The renderer process: jobs from stdin (module docstring) until stdin closes."""
    fd = sys.stdin.fileno()
    renderer: TileRenderer | None = None
    ended = False
    while not ended:
        lines, ended = _lines(fd)
        jobs = [json.loads(line) for line in lines if line.strip()]
        if renderer is None and jobs:
            head = jobs.pop(0)
            renderer = TileRenderer(Path(head["folder"]), head["crs"])
        if not jobs or renderer is None:
            continue
        t0, c0 = time.perf_counter(), time.thread_time()
        written = renderer.render([b for job in jobs for b in job["changed"]], jobs[-1]["index"])
        print(json.dumps({"jobs": len(jobs), "tiles": written,
                          "ms": (time.perf_counter() - t0) * 1e3,
                          "cpu_ms": (time.thread_time() - c0) * 1e3}), flush=True)


class RendererProcess:
    """The parent's handle of the renderer (started by the calling thread: it inherits its
    niceness). Thread-safe for one sender."""

    def __init__(self, folder: Path, crs_wkt: str) -> None:
        code = "from pipeline.ortho.live_render import render_child; render_child()"
        self._child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                       stdout=subprocess.PIPE)
        self._cond = threading.Condition()
        self.sent = 0
        self.done = 0
        self.ms: list[float] = []
        self.cpu_ms: list[float] = []
        self.tiles: list[int] = []
        self._reader = threading.Thread(target=self._read, name="seqat-live-render",
                                        daemon=True)
        self._reader.start()
        self._send({"folder": str(folder), "crs": crs_wkt})

    @property
    def alive(self) -> bool:
        return self._child.poll() is None

    def _send(self, doc: dict[str, object]) -> None:
        assert self._child.stdin is not None
        self._child.stdin.write((json.dumps(doc, separators=(",", ":")) + "\n").encode())
        self._child.stdin.flush()

    def submit(self, changed: list[tuple[float, float, float, float]],
               index: dict[str, object]) -> bool:
        """Hand a publication to the renderer; False when it is gone (the caller writes the
        index itself)."""
        if not self.alive:
            return False
        try:
            self._send({"changed": [list(b) for b in changed], "index": index})
        except (BrokenPipeError, OSError):
            return False
        with self._cond:
            self.sent += 1
        return True

    def _read(self) -> None:
        assert self._child.stdout is not None
        for line in self._child.stdout:
            with contextlib.suppress(ValueError):
                reply = json.loads(line)
                with self._cond:
                    self.done += int(reply["jobs"])
                    self.ms.append(float(reply["ms"]))
                    self.cpu_ms.append(float(reply["cpu_ms"]))
                    self.tiles.append(int(reply["tiles"]))
                    self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until every job sent is rendered (True) or the child is gone (False)."""
        with self._cond:
            return self._cond.wait_for(lambda: self.done >= self.sent or not self.alive,
                                       timeout) and self.done >= self.sent

    def stop(self, wait_s: float = STOP_WAIT_S) -> None:
        """Let the renderer finish the jobs sent (at most ``wait_s``), then end it."""
        with contextlib.suppress(OSError):
            if self._child.stdin is not None:
                self._child.stdin.close()
        try:
            self._child.wait(wait_s)
        except subprocess.TimeoutExpired:
            self._child.terminate()
            try:
                self._child.wait(5)
            except subprocess.TimeoutExpired:
                self._child.kill()
                self._child.wait()
        self._reader.join(5)
