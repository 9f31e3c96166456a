"""The web map of ``seqat serve OUT``: a Starlette application on uvicorn.

Read-only and confined to fixed routes: no route takes a file name, so no request can reach
a path outside the run folder (the page's own files come from the package's ``static/``
folder through Starlette's ``StaticFiles``, which refuses paths leaving it).

Routes (docs/formats.md, *seqat serve*): ``/`` (the page), ``/tiles/{z}/{x}/{y}.png``
(``mosaic.tif`` as 256 x 256 Web Mercator tiles, transparent outside the data; before it
exists, the live mosaic a ``seqat watch --ortho`` publishes in ``live/``, from its live tile
cache; every tile with an ETag, ``If-None-Match`` answered 304), ``/status.json``,
``/events`` (server-sent events: ``status.json`` again whenever its ``version`` changes),
``/cameras.geojson``, ``/ellipses.geojson``, ``/footprints.geojson``, ``/points.geojson``,
``/coverage.geojson``, ``/quicklook/{n}.jpg`` (the quick-look of a live run's ``n``-th
image, ``live/quicklook/``), ``/static/...`` (the page's script and style, Leaflet).
``status.json``, ``events`` and ``coverage.geojson`` take ``?stop_sigma_cm=X`` (the page's
stop criterion field) instead of the run's ``--stop-sigma-cm``.

The event stream is the same files read again: the server looks at the run folder's files
(a ``stat`` each) every :data:`EVENT_POLL_S` and sends ``status.json`` when one changed and
the version with it, so a page learns of an image within that time instead of its poll
period, and a restarted server or a finished run behave as before.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import TypeVar

import uvicorn
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from pipeline.common import jsonio
from pipeline.common.columns import (
    EOP_FILE,
    LIVE_DIR,
    LIVE_ESTIMATES_FILE,
    LIVE_MOSAIC_INDEX,
    LIVE_QUICKLOOK_DIR,
    POINTS_FILE,
    RUN_FILE,
)
from pipeline.common.priority import lower_thread_priority_once
from pipeline.run.journal import JOURNAL_DIR, JOURNAL_FILE
from pipeline.run.live_view import quicklook_name
from pipeline.serve.runview import MOSAIC_FILE, ORTHO_JSON, RunView, check_run_folder
from pipeline.serve.tiles import (
    EMPTY_TILE,
    LiveMosaic,
    MosaicTiles,
    MosaicUnreadable,
    etag,
    tile_in_range,
)
from seqat.errors import InputDataError

T = TypeVar("T")
STATIC_DIR = Path(__file__).resolve().parent / "static"
#: Never used by the browser without asking: the run folder changes under a live run.
NO_CACHE = {"Cache-Control": "no-cache"}
GEOJSON = "application/geo+json"
#: Answers (``status.json`` and the layers, per stop criterion) kept for the files' state.
ANSWERS_KEPT = 32
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
#: ``seqat watch --serve``: the request threads run this much nicer than the AT loop, and
#: nicer than the live ortho's worker (10): browsers must not slow the AT or the ortho
#: (docs/benchmarks.md, *Keeping up on the 196-image block*: at 10, two clients made the
#: ortho latency +88 %; at 15, +3 %).
WATCH_SERVE_NICE = 15
#: Where a tile came from (``mosaic``: mosaic.tif; ``cache``, ``memory``, ``rendered``,
#: ``empty``: the live mosaic, :meth:`LiveMosaic.tile_from`), for benchmarks and the curious.
TILE_SOURCE_HEADER = "X-Seqat-Tile"
#: How often ``/events`` looks at the run folder's files, s.
EVENT_POLL_S = 0.1
#: An event-stream comment at least this often keeps proxies and browsers connected, s.
EVENT_KEEPALIVE_S = 15.0
#: Before reconnecting, a browser waits this long (the stream's ``retry:``), ms.
EVENT_RETRY_MS = 1000
#: Seconds uvicorn waits for open connections (event streams) when it stops.
GRACEFUL_SHUTDOWN_S = 1


def not_modified(request: Request, tag: str) -> bool:
    """The request's ``If-None-Match`` names ``tag`` (answer 304)."""
    return tag in (t.strip() for t in request.headers.get("if-none-match", "").split(","))


def build_app(out: Path, nice: int = 0) -> Starlette:
    """The application serving the run folder ``out`` (checked by the caller); ``nice``: the
    threads answering requests run that much nicer (``seqat watch --serve``: the server
    shares the process with the AT loop and the live ortho)."""
    view = RunView(out)
    tiles = MosaicTiles(out / MOSAIC_FILE)
    live_tiles = LiveMosaic(out / LIVE_DIR / LIVE_MOSAIC_INDEX)

    def mosaic_info() -> tuple[dict[str, object] | None, str | None]:
        try:
            info = tiles.info()
            if info is None:
                info = live_tiles.info()
        except MosaicUnreadable as err:
            return None, str(err)
        return (None if info is None else dataclasses.asdict(info)), None

    def stop_param(request: Request) -> float | None:
        """``?stop_sigma_cm=X`` (X > 0), else None (a bad value is ignored)."""
        raw = request.query_params.get("stop_sigma_cm")
        try:
            value = float(raw) if raw else None
        except ValueError:
            return None
        return value if value is not None and math.isfinite(value) and value > 0 else None

    def niced(endpoint: Callable[[Request], Response]) -> Callable[[Request], Response]:
        def run(request: Request) -> Response:
            lower_thread_priority_once(nice)
            return endpoint(request)

        return run

    def index(request: Request) -> Response:
        return FileResponse(STATIC_DIR / "index.html", headers=NO_CACHE)

    def tile(request: Request) -> Response:
        z, x, y = (request.path_params[k] for k in ("z", "x", "y"))
        if not tile_in_range(z, x, y):
            return Response("no such tile", status_code=404, media_type="text/plain")
        try:
            png, source = tiles.tile(z, x, y), "mosaic"
            if png is EMPTY_TILE and not (out / MOSAIC_FILE).exists():
                png, source = live_tiles.tile_from(z, x, y)
        except MosaicUnreadable as err:
            return Response(str(err), status_code=503, media_type="text/plain",
                            headers=NO_CACHE)
        tag = etag(png)
        headers = {**NO_CACHE, "ETag": tag, TILE_SOURCE_HEADER: source}
        if not_modified(request, tag):
            return Response(status_code=304, headers=headers)
        return Response(png, media_type="image/png", headers=headers)

    # every answer is made of these files: one state of them, one answer (cached below)
    watched = [out / n for n in (RUN_FILE, EOP_FILE, POINTS_FILE, ORTHO_JSON, MOSAIC_FILE)] + [
        out / LIVE_DIR / LIVE_ESTIMATES_FILE, out / LIVE_DIR / LIVE_MOSAIC_INDEX,
        out / JOURNAL_DIR / JOURNAL_FILE]

    def files_key() -> tuple[tuple[int, int, int] | None, ...]:
        keys = []
        for path in watched:
            try:
                st = os.stat(path)
                keys.append((st.st_ino, st.st_mtime_ns, st.st_size))
            except OSError:
                keys.append(None)
        return tuple(keys)

    answers: dict[object, tuple[object, object]] = {}
    #: The last encoding of each layer, with the object encoded: :class:`RunView` returns
    #: the same object while the file it comes from is unchanged, so a change of another
    #: file (the mosaic's index, the journal) costs an identity check, not an encoding.
    encodings: dict[object, tuple[object, bytes, str]] = {}
    answers_lock = threading.Lock()

    def answer(name: object, build: Callable[[], T]) -> T:
        """``build()``, made once per state of the files (every page asks for the same
        answers after a change); at most :data:`ANSWERS_KEPT` kept (criteria typed into
        pages)."""
        key = files_key()
        with answers_lock:
            hit = answers.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]  # type: ignore[return-value]
        value = build()
        with answers_lock:
            if len(answers) >= ANSWERS_KEPT:
                answers.clear()
            answers[name] = (key, value)
        return value

    def status_doc(stop: float | None) -> dict[str, object]:
        """``status.json`` for a stop criterion."""
        return answer(("status", stop), lambda: view.status(*mosaic_info(), stop_sigma_cm=stop))

    def status(request: Request) -> Response:
        return JSONResponse(status_doc(stop_param(request)), headers=NO_CACHE)

    def niced_status(stop: float | None) -> dict[str, object]:
        lower_thread_priority_once(nice)
        return status_doc(stop)

    async def events(request: Request) -> Response:
        stop = stop_param(request)

        async def stream() -> AsyncIterator[str]:
            yield f"retry: {EVENT_RETRY_MS}\n\n"
            key: object = object()
            version = None
            sent = time.monotonic()
            while not app.state.closing:
                now_key = files_key()
                if now_key != key:
                    key = now_key
                    doc = await run_in_threadpool(niced_status, stop)
                    if doc["version"] != version:
                        version = doc["version"]
                        sent = time.monotonic()
                        yield f"event: status\ndata: {jsonio.dumps(doc).decode()}\n\n"
                if time.monotonic() - sent >= EVENT_KEEPALIVE_S:
                    sent = time.monotonic()
                    yield ": keep-alive\n\n"
                await asyncio.sleep(EVENT_POLL_S)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={**NO_CACHE, "X-Accel-Buffering": "no"})

    def encoded(request: Request, name: object, build: Callable[[], object],
                media_type: str = GEOJSON) -> Response:
        """``build()`` as JSON (:func:`answer`: encoded once per state of the files) with an
        ETag of its bytes (``If-None-Match`` answered 304)."""

        def encode() -> tuple[bytes, str]:
            doc = build()
            with answers_lock:
                hit = encodings.get(name)
            if hit is not None and hit[0] is doc:  # RunView's cached layer: same bytes
                return hit[1], hit[2]
            body = jsonio.dumps(doc)
            tag = etag(body)
            with answers_lock:
                if len(encodings) >= ANSWERS_KEPT:
                    encodings.clear()
                encodings[name] = (doc, body, tag)
            return body, tag

        body, tag = answer(name, encode)
        headers = {**NO_CACHE, "ETag": tag}
        if not_modified(request, tag):
            return Response(status_code=304, headers=headers)
        return Response(body, media_type=media_type, headers=headers)

    def cameras(request: Request) -> Response:
        return encoded(request, "cameras", view.cameras)

    def points(request: Request) -> Response:
        return encoded(request, "points", view.points)

    def ellipses(request: Request) -> Response:
        return encoded(request, "ellipses", view.ellipses)

    def footprints(request: Request) -> Response:
        return encoded(request, "footprints", view.footprints)

    def coverage(request: Request) -> Response:
        stop = stop_param(request)
        return encoded(request, ("coverage", stop), lambda: view.coverage(stop))

    def quicklook(request: Request) -> Response:
        path = out / LIVE_DIR / LIVE_QUICKLOOK_DIR / quicklook_name(request.path_params["n"])
        if not path.is_file():
            return Response("no such quick-look", status_code=404, media_type="text/plain",
                            headers=NO_CACHE)
        return FileResponse(path, media_type="image/jpeg", headers=NO_CACHE)

    get = ["GET", "HEAD"]
    app = Starlette(routes=[
        Route("/", niced(index), methods=get),
        Route("/tiles/{z:int}/{x:int}/{y:int}.png", niced(tile), methods=get),
        Route("/status.json", niced(status), methods=get),
        Route("/events", events, methods=["GET"]),
        Route("/cameras.geojson", niced(cameras), methods=get),
        Route("/points.geojson", niced(points), methods=get),
        Route("/ellipses.geojson", niced(ellipses), methods=get),
        Route("/footprints.geojson", niced(footprints), methods=get),
        Route("/coverage.geojson", niced(coverage), methods=get),
        Route("/quicklook/{n:int}.jpg", niced(quicklook), methods=get),
        Mount("/static", StaticFiles(directory=STATIC_DIR), name="static"),
    ])
    app.state.tiles = tiles
    app.state.live_tiles = live_tiles
    app.state.closing = False  # set when the server stops: the event streams end
    return app


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: a free one).

    Raises
    ------
    InputDataError
        The host is unknown, or the port in use or not allowed, naming them.
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as err:
        raise InputDataError(f"--host {host}: unknown host ({err.strerror})") from err
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
    except OSError as err:
        sock.close()
        why = ("the port is in use (choose another with --port)"
               if err.errno == errno.EADDRINUSE else err.strerror or str(err))
        raise InputDataError(f"{host}:{port}: cannot listen: {why}") from err
    sock.set_inheritable(True)
    return sock


@dataclasses.dataclass
class Served:
    """A server running on ``url`` (see :func:`serving`)."""

    url: str
    server: uvicorn.Server
    sock: socket.socket
    app: Starlette

    def stop(self) -> None:
        """Ask the server to stop (its event streams end at once)."""
        self.app.state.closing = True
        self.server.should_exit = True


def make_server(out: Path | str, host: str = DEFAULT_HOST,
                port: int = DEFAULT_PORT) -> Served:
    """Check ``out``, bind the socket and build the (not yet started) server."""
    out = Path(out)
    check_run_folder(out)
    return server_on(out, bind(host, port), host)


def server_on(out: Path, sock: socket.socket, host: str, nice: int = 0) -> Served:
    """The (not yet started) server of ``out`` on a bound socket (``seqat watch --serve``
    binds first, so a busy port fails before the watch starts)."""
    real_port = sock.getsockname()[1]
    app = build_app(out, nice)
    config = uvicorn.Config(app, log_level="warning", access_log=False,
                            lifespan="off", timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S)
    shown = f"[{host}]" if ":" in host else host
    return Served(url=f"http://{shown}:{real_port}/", server=uvicorn.Server(config), sock=sock,
                  app=app)


def run_server(served: Served) -> None:
    """Serve until interrupted (Ctrl-C) in this thread."""
    try:
        served.server.run(sockets=[served.sock])
    finally:
        served.sock.close()


def start_thread(served: Served, nice: int = 0) -> threading.Thread:
    """Run the server in a daemon thread (``nice`` steps nicer: its event loop and the
    threads it starts); returns once it accepts connections (≤ 5 s)."""

    def run() -> None:
        lower_thread_priority_once(nice)
        run_server(served)

    thread = threading.Thread(target=run, name="seqat-serve", daemon=True)
    thread.start()
    for _ in range(500):
        if served.server.started:
            break
        thread.join(0.01)
    return thread


def serve_child(out: str, fd: int, host: str, nice: int) -> None:
    """The server process of ``seqat watch --serve``: serve ``out`` on the inherited listening
    socket ``fd``, ``nice`` steps nicer, until terminated or the parent process is gone."""
    if nice > 0 and hasattr(os, "nice"):
        os.nice(nice)
    parent = os.getppid()
    served = server_on(Path(out), socket.socket(fileno=fd), host)

    def orphaned() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        served.stop()

    threading.Thread(target=orphaned, daemon=True).start()
    run_server(served)


def start_process(out: Path, sock: socket.socket, host: str,
                  nice: int = WATCH_SERVE_NICE) -> subprocess.Popen[bytes]:
    """Run the server of ``out`` in a child process on the bound socket ``sock``
    (:func:`serve_child`); stop it with :func:`stop_process`."""
    fd = sock.fileno()
    code = ("import sys; from pipeline.serve.app import serve_child; "
            "serve_child(sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]))")
    return subprocess.Popen([sys.executable, "-c", code, str(out), str(fd), host, str(nice)],
                            pass_fds=(fd,))


def stop_process(child: subprocess.Popen[bytes]) -> None:
    child.terminate()
    try:
        child.wait(10)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


def stop_thread(served: Served, thread: threading.Thread) -> None:
    served.stop()
    thread.join(10)


@contextlib.contextmanager
def serving(out: Path | str, host: str = DEFAULT_HOST, port: int = 0) -> Iterator[Served]:
    """Serve ``out`` in a background thread for the ``with`` block (tests, scripts)."""
    served = make_server(out, host, port)
    thread = start_thread(served)
    try:
        yield served
    finally:
        stop_thread(served, thread)
