"""``seqat bench live``: the live map's targets (issue 15) on a flight fed at the camera's rate.

Each *run* is what a field team does: ``seqat feed FLIGHT --rate R`` writes the flight into a
folder while ``seqat watch ... --ortho --serve PORT`` (a second process) georeferences it and
serves the map, and ``clients`` page-like HTTP clients (threads of this process) follow it as
the page does: ``--page sse`` (the default, the page since the live map's second pass)
listens to ``/events`` (server-sent events: ``status.json`` when its version changes),
``--page poll`` (the page before) polls ``/status.json`` every second; on a new ``version``
either fetches the cameras, ellipses, footprints, points and coverage (revalidated with their
ETags, as the page does since the live map's third pass) and, of the mosaic's tiles at the
zoom where at most 24 tiles cover it, those the new revision changed (``mosaic.changes``)
or newly in view, 6 at a time (niced to 19: real browsers run on their own devices).
Runs with different client counts are interleaved (``--clients 0 2 --repeat 3``: 0, 2, 0, 2,
0, 2) so the load of the shared machine falls on both alike; ``N:thread`` runs the server in
a thread of the watch instead of its child process (``--serve-in``).

Measured per run:

* **AT → page** (clients only): the time from an image's AT update (``at_unix_s`` in
  ``live/estimates.json``) to the end of the first client reload whose ``status.json``
  counts it in the mosaic (``mosaic_images``) and whose tiles were then loaded; for the
  cameras, to the first reload whose ``/cameras.geojson`` holds the image; for the *images*,
  to the end of the first reload that loaded its quick-look (``/footprints.geojson`` names
  it) or found it in the mosaic (``in_mosaic``);
* **tile serve time**: each tile request's duration at the clients, while the flight runs;
* **AT and ortho latency** from the published ``run.json`` (``live.update_ms``,
  ``latency_ms``: input complete → estimate) and ``ortho.json`` (``latency_ms``: AT update →
  image in the live mosaic), overall and for the first and last quarter of the images.

The flight's LiDAR is gridded once, before the runs (``--dsm``), so a run starts with it.
"""

from __future__ import annotations

import argparse
import http.client
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import morecantile
import numpy as np

from pipeline.bench.common import load_average, machine
from pipeline.bench.report import Machine
from pipeline.common.priority import lower_thread_priority_once
from pipeline.flight.folder import read_flight
from pipeline.ortho.dsm import build_dsm
from pipeline.ortho.stage import flight_lidar
from pipeline.run.store import read_json_object, to_jsonable

TMS = morecantile.tms.get("WebMercatorQuad")
#: The page's poll interval (pipeline/serve/static/serve.js), seconds.
PAGE_POLL_S = 1.0
#: At most this many tiles per reload (a 1280 x 800 window shows about 20).
MAX_TILES = 24
#: Tiles a browser loads at once from one host.
BROWSER_CONNECTIONS = 6
#: The clients' threads run this nice: a field team's browsers run on their own devices, so
#: the clients' own parsing should take as little as possible of the two cores measured.
CLIENT_NICE = 19


@dataclass
class Client:
    """One page-like client's records."""

    seen_mosaic: list[tuple[float, int]] = field(default_factory=list)  # (t, images in mosaic)
    seen_cameras: dict[str, float] = field(default_factory=dict)  # image -> t first seen
    #: image -> t its pixels were first on the page (its quick-look loaded, or the mosaic)
    seen_images: dict[str, float] = field(default_factory=dict)
    quicklook_ms: list[float] = field(default_factory=list)
    tile_ms: list[float] = field(default_factory=list)
    tile_ms_live: list[float] = field(default_factory=list)  # before the run finished
    requests: int = 0
    errors: int = 0
    events: int = 0  # status events received (page sse)
    reconnects: int = 0  # event streams that ended or failed after the first event
    #: live tile request times (ms) by the server's X-Seqat-Tile (where the tile came from)
    tile_sources: dict[str, list[float]] = field(default_factory=dict)
    #: the page's state: the layers' ETags and bodies (revalidated, as ``fetch`` with
    #: ``cache: "no-cache"``), the mosaic shown and the tiles loaded of it
    etags: dict[str, tuple[str, bytes]] = field(default_factory=dict)
    mosaic_shown: dict[str, object] | None = None
    tiles_shown: set[tuple[int, int, int]] = field(default_factory=set)


def _get(url: str) -> tuple[bytes, float]:
    body, ms, _ = _get_from(url)
    return body, ms


def _get_from(url: str) -> tuple[bytes, float, str]:
    """Body, duration (ms) and the server's ``X-Seqat-Tile`` (where a tile came from)."""
    t0 = time.perf_counter()
    with urllib.request.urlopen(url, timeout=30) as r:
        body = r.read()
        source = r.headers.get("X-Seqat-Tile", "")
    return body, (time.perf_counter() - t0) * 1e3, source


def _get_layer(url: str, rec: Client) -> bytes:
    """A layer as the page fetches it: revalidated with its ETag (a 304 reuses the body)."""
    req = urllib.request.Request(url)
    kept = rec.etags.get(url)
    if kept is not None:
        req.add_header("If-None-Match", kept[0])
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            body = r.read()
            tag = r.headers.get("ETag")
    except urllib.error.HTTPError as err:
        if err.code == 304 and kept is not None:
            return kept[1]
        raise
    if tag:
        rec.etags[url] = (tag, body)
    return body


def changed_boxes(shown: dict[str, object] | None,
                  cur: dict[str, object]) -> list[list[float]] | None:
    """The WGS 84 boxes the live mosaic changed from the ``shown`` revision to ``cur``'s
    (``status.mosaic.changes``), None when they do not reach back to it: the page's
    ``changedBoxes`` (pipeline/serve/static/serve.js)."""
    if shown is None:
        return None
    if shown.get("version") == cur.get("version"):
        return []
    rev, changes = shown.get("revision"), cur.get("changes")
    if rev is None or cur.get("revision") is None or not changes:
        return None
    if shown.get("maxzoom") != cur.get("maxzoom"):
        return None
    later = [c for c in changes if c[1] > rev]  # type: ignore[union-attr,index,operator]
    if not later or later[0][0] != rev:
        return None
    return [box for c in later for box in c[2]]


def _reaches(tile: morecantile.Tile, boxes: list[list[float]]) -> bool:
    b = TMS.bounds(tile)
    return any(b.left < e and b.right > w and b.bottom < n and b.top > so
               for w, so, e, n in boxes)


def _tiles_for(bounds: Sequence[float], maxzoom: int) -> list[morecantile.Tile]:
    """The tiles covering ``bounds`` at the highest zoom ≤ ``maxzoom`` with ≤ MAX_TILES."""
    west, south, east, north = bounds
    for z in range(maxzoom, -1, -1):
        tiles = list(TMS.tiles(west, south, east, north, [z]))
        if len(tiles) <= MAX_TILES:
            return tiles
    return []


def _reload(url: str, status: dict[str, object], rec: Client,
            pool: ThreadPoolExecutor) -> None:
    """What the page does on a new version: the cameras (then seen), the other layers, and
    the tiles, :data:`BROWSER_CONNECTIONS` at a time as a browser loads them (the mosaic is
    seen once they are all loaded)."""
    cams = json.loads(_get_layer(url + "cameras.geojson", rec))
    now = time.time()
    for f in cams.get("features", []):
        if f["properties"].get("position") != "nav":
            rec.seen_cameras.setdefault(f["properties"]["image"], now)
    footprints = json.loads(_get_layer(url + "footprints.geojson", rec))
    for path in ("ellipses.geojson", "points.geojson", "coverage.geojson"):
        _get_layer(url + path, rec)
    rec.requests += 5
    # the images themselves: a quick-look, loaded as the page does, or the mosaic
    looks = []
    for f in footprints.get("features", []):
        p = f["properties"]
        if p["image"] in rec.seen_images:
            continue
        if p.get("in_mosaic"):
            rec.seen_images[p["image"]] = time.time()
        elif p.get("quicklook"):
            looks.append((p["image"], url + p["quicklook"].lstrip("/")))
    for (image, _), (_, ms, _) in zip(looks, pool.map(_get_from, [u for _, u in looks]),
                                      strict=True):
        rec.seen_images.setdefault(image, time.time())
        rec.quicklook_ms.append(ms)
    rec.requests += len(looks)
    mosaic = status.get("mosaic")
    if isinstance(mosaic, dict):
        # the page's refreshTiles: the tiles the new revision changed, and the tiles newly
        # in view (the map follows the data)
        boxes = changed_boxes(rec.mosaic_shown, mosaic)
        shown = set() if boxes is None else rec.tiles_shown
        rec.mosaic_shown = mosaic
        tiles = _tiles_for(mosaic["bounds_wgs84"], int(mosaic["maxzoom"]))
        rec.tiles_shown = {(t.z, t.x, t.y) for t in tiles}
        tiles = [t for t in tiles if (t.z, t.x, t.y) not in shown or _reaches(t, boxes or [])]
        version = urllib.parse.quote(str(mosaic.get("version")))
        urls = [f"{url}tiles/{t.z}/{t.x}/{t.y}.png?v={version}" for t in tiles]
        got = list(pool.map(_get_from, urls))
        times = [ms for _, ms, _ in got]
        rec.requests += len(times)
        rec.tile_ms += times
        if not status.get("done"):
            rec.tile_ms_live += times
            for _, ms, source in got:
                rec.tile_sources.setdefault(source, []).append(ms)
    rec.seen_mosaic.append((time.time(), int(status.get("mosaic_images") or 0)))  # type: ignore[call-overload]


def _client(url: str, stop: threading.Event, rec: Client) -> None:
    """Poll as the page did before server-sent events until ``stop``: status every
    :data:`PAGE_POLL_S`, a reload (:func:`_reload`) on a new version."""
    version = None
    lower_thread_priority_once(CLIENT_NICE)
    with ThreadPoolExecutor(BROWSER_CONNECTIONS, initializer=lower_thread_priority_once,
                            initargs=(CLIENT_NICE,)) as pool:
        while not stop.is_set():
            t_poll = time.monotonic()
            try:
                body, _ = _get(url + "status.json")
                rec.requests += 1
                status = json.loads(body)
                if status.get("version") != version:
                    version = status.get("version")
                    _reload(url, status, rec, pool)
            except (OSError, ValueError):
                if rec.requests:  # not before the watch's server is up
                    rec.errors += 1
            stop.wait(max(0.0, PAGE_POLL_S - (time.monotonic() - t_poll)))


class _Stream:
    """The newest status of an ``/events`` stream, read by a thread (the page's EventSource:
    statuses that arrive during a reload are coalesced, the newest shown after it)."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.latest: dict[str, object] | None = None
        self.conn: http.client.HTTPConnection | None = None

    def read(self, url: str, stop: threading.Event, rec: Client) -> None:
        host, port = url.split("//", 1)[1].rstrip("/").rsplit(":", 1)
        while not stop.is_set():
            try:
                self.conn = http.client.HTTPConnection(host, int(port), timeout=60)
                self.conn.request("GET", "/events")
                response = self.conn.getresponse()
                kind, data = None, []
                while not stop.is_set():
                    line = response.readline()
                    if not line:
                        break
                    text = line.decode().rstrip("\n")
                    if text.startswith("event:"):
                        kind = text.split(":", 1)[1].strip()
                    elif text.startswith("data:"):
                        data.append(text.split(":", 1)[1].strip())
                    elif text == "" and data:
                        if kind == "status":
                            with self.cond:
                                self.latest = json.loads("\n".join(data))
                                rec.events += 1
                                self.cond.notify()
                        kind, data = None, []
            except (OSError, ValueError, http.client.HTTPException):
                pass
            if rec.events:
                rec.reconnects += 1
            stop.wait(0.1)  # the server is not up yet, or it stopped

    def next(self, stop: threading.Event) -> dict[str, object] | None:
        with self.cond:
            while self.latest is None and not stop.is_set():
                self.cond.wait(0.1)
            status, self.latest = self.latest, None
            return status


def _client_sse(url: str, stop: threading.Event, rec: Client) -> None:
    """Follow ``/events`` as the page does until ``stop``: a reload (:func:`_reload`) on each
    new version."""
    version = None
    lower_thread_priority_once(CLIENT_NICE)
    stream = _Stream()
    reader = threading.Thread(target=stream.read, args=(url, stop, rec), daemon=True)
    reader.start()
    with ThreadPoolExecutor(BROWSER_CONNECTIONS, initializer=lower_thread_priority_once,
                            initargs=(CLIENT_NICE,)) as pool:
        while not stop.is_set():
            status = stream.next(stop)
            if status is None or status.get("version") == version:
                continue
            version = status.get("version")
            try:
                _reload(url, status, rec, pool)
            except (OSError, ValueError):
                rec.errors += 1
    if stream.conn is not None:
        stream.conn.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stats(values: Sequence[float]) -> dict[str, float | int | None]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], float)
    if not len(v):
        return {"n": 0, "median": None, "p95": None, "max": None}
    return {"n": int(len(v)), "median": float(np.median(v)),
            "p95": float(np.percentile(v, 95)), "max": float(v.max())}


def _quarters(values: Sequence[float]) -> tuple[float | None, float | None]:
    v = [x for x in values if x is not None and math.isfinite(x)]
    if len(v) < 4:
        return None, None
    q = max(1, len(v) // 4)
    return float(np.median(v[:q])), float(np.median(v[-q:]))


def one_run(flight: Path, work: Path, *, clients: int, rate_hz: float, dsm: Path | None,
            idle_s: float, limit: int | None, serve_in: str = "process",
            page: str = "sse") -> dict[str, object]:
    """Feed + watch --ortho --serve with ``clients`` polling clients; the run's figures."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    fed, out = work / "flight", work / "run"
    port = _free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cli = [sys.executable, "-m", "pipeline.cli"]
    load0 = load_average()
    feed = subprocess.Popen([*cli, "feed", str(flight), "--out", str(fed), "--rate",
                             str(rate_hz), "--delay-s", "4",
                             *(["--limit", str(limit)] if limit else [])],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    while not (fed / "flight.yaml").exists():
        if feed.poll() is not None:
            raise RuntimeError(f"seqat feed failed: {feed.stderr.read().decode()}")  # type: ignore[union-attr]
        time.sleep(0.05)
    log = (work / "watch.log").open("w")
    watch = subprocess.Popen([*cli, "watch", str(fed), "--out", str(out), "--ortho",
                              *(["--dsm", str(dsm)] if dsm else []), "--serve", str(port),
                              "--serve-in", serve_in,
                              "--idle-timeout-s", str(idle_s)],
                             stdout=log, stderr=subprocess.STDOUT, env=env)
    stop = threading.Event()
    recs = [Client() for _ in range(clients)]
    url = f"http://127.0.0.1:{port}/"
    follow = _client_sse if page == "sse" else _client
    threads = [threading.Thread(target=follow, args=(url, stop, r), daemon=True)
               for r in recs]
    for t in threads:
        t.start()
    feed.wait()
    code = watch.wait()
    stop.set()
    for t in threads:
        t.join(30)
    log.close()
    if code != 0:
        raise RuntimeError(f"seqat watch exit {code}: see {work / 'watch.log'}")
    run = read_json_object(out / "run.json")
    ortho = read_json_object(out / "ortho.json")
    est = read_json_object(out / "live" / "estimates.json")
    lives = [im["live"] for im in run["images"]]  # type: ignore[union-attr,index]
    at_ms = [float(x["update_ms"]) for x in lives]
    track_ms = [float(x["prep_ms"]) for x in lives]
    latency_ms = [float(x["latency_ms"]) for x in lives if x.get("latency_ms") is not None]
    ortho_ms = [float(r["latency_ms"]) for r in ortho["images"]  # type: ignore[union-attr]
                if r.get("latency_ms") is not None]
    at_unix = {str(c["image"]): float(c["at_unix_s"]) for c in est["cameras"]}  # type: ignore[union-attr]
    order = [str(c["image"]) for c in est["cameras"]]  # type: ignore[union-attr]
    to_page_mosaic: list[float] = []
    to_page_cameras: list[float] = []
    to_page_images: list[float] = []
    for rec in recs:
        for k, image in enumerate(order):
            seen = next((t for t, n in rec.seen_mosaic if n >= k + 1), None)
            if seen is not None:
                to_page_mosaic.append((seen - at_unix[image]) * 1e3)
            if image in rec.seen_cameras:
                to_page_cameras.append((rec.seen_cameras[image] - at_unix[image]) * 1e3)
            if image in rec.seen_images:
                to_page_images.append((rec.seen_images[image] - at_unix[image]) * 1e3)
    q_lat, q_ortho = _quarters(latency_ms), _quarters(ortho_ms)
    ortho_work_ms = [float(r.get("read_ms") or 0) + float(r["compute_ms"])
                     + float(r.get("write_ms") or 0) + float(r["mosaic_ms"])
                     for r in ortho["images"]]  # type: ignore[union-attr]
    live_stats = ortho["live"]  # type: ignore[index]
    return {
        "clients": clients, "serve_in": serve_in, "page": page, "images": len(lives),
        "load_1m_start": load0,
        "load_1m_end": load_average(),
        "latency_budget": _budget_summary(run.get("latency_budget")),
        "threshold_first_last_quarter": _quarters([float(x["threshold"]) for x in lives
                                                   if x.get("threshold") is not None]),
        "tracking_ms": _stats(track_ms), "at_update_ms": _stats(at_ms),
        "latency_ms": _stats(latency_ms), "ortho_latency_ms": _stats(ortho_ms),
        "latency_first_last_quarter_ms": q_lat, "ortho_first_last_quarter_ms": q_ortho,
        "tracking_first_last_quarter_ms": _quarters(track_ms),
        "at_first_last_quarter_ms": _quarters(at_ms),
        "ortho_work_ms": _stats(ortho_work_ms),
        "ortho_work_first_last_quarter_ms": _quarters(ortho_work_ms),
        "publish_ms": live_stats.get("publish_ms"),  # type: ignore[union-attr]
        "publications": live_stats.get("publications"),  # type: ignore[union-attr]
        "web_tiles_ms": live_stats.get("web_tiles_ms"),  # type: ignore[union-attr]
        "web_tiles_cpu_ms": live_stats.get("web_tiles_cpu_ms"),  # type: ignore[union-attr]
        "web_tiles": live_stats.get("web_tiles"),  # type: ignore[union-attr]
        "at_to_page_mosaic_ms": _stats(to_page_mosaic),
        "at_to_page_cameras_ms": _stats(to_page_cameras),
        "at_to_page_images_ms": _stats(to_page_images),
        "quicklook_ms": _stats([ms for r in recs for ms in r.quicklook_ms]),
        "tile_ms_live": _stats([ms for r in recs for ms in r.tile_ms_live]),
        "tile_ms_all": _stats([ms for r in recs for ms in r.tile_ms]),
        "client_requests": sum(r.requests for r in recs),
        "client_errors": sum(r.errors for r in recs),
        "client_events": sum(r.events for r in recs),
        "client_reconnects": sum(r.reconnects for r in recs),
        "tile_ms_live_by_source": {
            k: _stats([ms for r in recs for ms in r.tile_sources.get(k, [])])
            for k in sorted({k for r in recs for k in r.tile_sources})},
        "reorthorectified": len(live_stats["images_reorthorectified"]),  # type: ignore[index]
        "finish_s": live_stats["finish_s"],  # type: ignore[index]
    }


@dataclass(frozen=True, kw_only=True)
class LiveMapBench:
    flight: str
    rate_hz: float
    machine: Machine
    date: str
    runs: tuple[dict[str, object], ...]


def _budget_summary(budget: object) -> dict[str, object] | None:
    """The watch's latency budget in brief (``run.json`` ``latency_budget``)."""
    if not isinstance(budget, dict):
        return None
    events = budget.get("events") or []
    return {k: budget.get(k) for k in ("mode", "budget_ms", "final_threshold",
                                       "final_features", "images_over_budget")} | {
        "events": len(events),
        "feature_changes": sum(1 for e in events if e.get("new_features") != e.get(
            "old_features"))}


def run_live_map_bench(flight: Path, out: Path, *, clients: Sequence[str] = ("0", "2"),
                       repeat: int = 1, rate_hz: float = 2.0, idle_s: float = 5.0,
                       limit: int | None = None, page: str = "sse") -> LiveMapBench:
    """Interleaved runs (module docstring)."""
    load0 = load_average()
    out.mkdir(parents=True, exist_ok=True)
    dsm = None
    lidar = flight_lidar(flight)
    if lidar:
        crs = read_flight(flight).crs
        dsm = build_dsm(lidar, out / "dsm.tif", crs=crs).path
    runs = []
    for r in range(repeat):
        for spec in clients:
            n, _, where = spec.partition(":")
            result = one_run(flight, out / f"run{r}_clients{n}{where}", clients=int(n),
                             rate_hz=rate_hz, dsm=dsm, idle_s=idle_s, limit=limit,
                             serve_in=where or "process", page=page)
            runs.append(result)
            print(json.dumps(to_jsonable(result)), file=sys.stderr, flush=True)
    return LiveMapBench(flight=str(flight), rate_hz=rate_hz, machine=machine(load0),
                        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                        runs=tuple(runs))


def main(argv: Sequence[str] | None = None) -> None:
    """``seqat bench live [--flight F] [--clients N ...] [--repeat K] [--rate-hz R]
    [--limit N] --out DIR``: print the runs as JSON (also ``DIR/live.json``)."""
    parser = argparse.ArgumentParser(prog=None if argv is None else "seqat bench live",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--flight", type=Path, default=Path("sample_data/autzen_rendered"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--clients", nargs="+", default=["0", "2"],
                        help="clients per run, in turn; N:thread serves from a thread of the "
                             "watch (--serve-in thread)")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--rate-hz", type=float, default=2.0)
    parser.add_argument("--idle-s", type=float, default=5.0)
    parser.add_argument("--limit", type=int)
    parser.add_argument("--page", choices=("sse", "poll"), default="sse",
                        help="the clients follow /events (the page now) or poll status.json "
                             "every second (the page before)")
    args = parser.parse_args(argv)
    result = run_live_map_bench(args.flight, args.out, clients=args.clients,
                                repeat=args.repeat, rate_hz=args.rate_hz, idle_s=args.idle_s,
                                limit=args.limit, page=args.page)
    text = json.dumps(to_jsonable(result), indent=1)
    (args.out / "live.json").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
