"""The live map's second pass (issue 15): the live tile cache a publication renders, served as a
file with an ETag and equal, pixel for pixel, to the tile the server renders on request; and
``/events``, the server-sent events that push ``status.json`` when its version changes."""

from __future__ import annotations

import http.client
import io
import json
import os
import shutil
import time
import urllib.error
import urllib.request
from email.message import Message
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pyproj
import pytest
from PIL import Image
from rio_tiler.errors import TileOutsideBounds
from rio_tiler.io import Reader
from rio_tiler.models import ImageData
from rio_tiler.mosaic import mosaic_reader

from pipeline.common import webtiles
from pipeline.ortho.base import OrthoRaster, OrthoResult
from pipeline.ortho.live_tiles import LiveTiles, seen_boxes
from pipeline.ortho.mosaic import MosaicBuilder
from pipeline.serve.app import Served, serving

CRS = pyproj.CRS.from_epsg(32610)
#: Cell size of the synthetic mosaic, metres, and its first cell (UTM 10N, near Autzen).
PIXEL_M = 0.3
COL0, ROW0 = 1_650_000, -16_000_000


def ortho(image: str, col0: int, row0: int, rows: int, cols: int, seed: int) -> OrthoResult:
    """A synthetic ortho: random colours, a round seen area, nadir at its centre."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:rows, 0:cols]
    off = np.hypot(r - rows / 2, c - cols / 2).astype(np.float32) / max(rows, cols)
    seen = off < 0.45
    pixels = rng.integers(1, 255, (rows, cols, 3), dtype=np.uint8) * seen[..., None]
    raster = OrthoRaster(image_id=image, col0=col0, row0=row0, pixel_m=PIXEL_M, pixels=pixels,
                         seen=seen, off_nadir=off, height_agl_m=100.0)
    return OrthoResult(image_id=image, path=None, raster=raster,
                       footprint_m=np.zeros((0, 2)), seen_cells=int(seen.sum()),
                       occluded_cells=0, off_dsm_cells=0, compute_ms=0.0, write_ms=0.0)


def publish_images(out: Path, n: int) -> LiveTiles:
    """``n`` overlapping orthos along a strip into a live mosaic, published after each."""
    mosaic = MosaicBuilder(out / "mosaic.tif", CRS)
    live = LiveTiles(out, mosaic, CRS)
    for k in range(n):
        result = ortho(f"img_{k}", COL0 + 150 * k, ROW0 + 40 * k, 500, 700, seed=k)
        update = mosaic.add(result)
        live.touched(update.tiles, result.image_id, 10.0, time.time(), seen_boxes(result.raster))
        live.publish()
    assert live.wait_rendered(120)
    live.stop_renderer()
    return live


@pytest.fixture(scope="module")
def live_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("live_cache") / "run"
    out.mkdir()
    (out / ".seqat-run").write_text("")
    publish_images(out, 3)
    return out


def rgba(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))


def get(served: Served, path: str, headers: dict[str, str] | None = None
        ) -> tuple[int, Message, bytes]:
    """Status, headers (names in any case) and body of a GET."""
    req = urllib.request.Request(served.url.rstrip("/") + path, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers, err.read()


def test_publication_renders_the_changed_web_tiles(live_folder: Path) -> None:
    doc = json.loads((live_folder / "live" / "mosaic.json").read_text())
    zmin, zmax = doc["xyz"]["minzoom"], doc["xyz"]["maxzoom"]
    assert doc["xyz"]["dir"] == webtiles.CACHE_DIR and zmin < zmax
    cached = {tuple(int(v) for v in p.with_suffix("").relative_to(
        live_folder / "live" / "xyz").parts) for p in (live_folder / "live" / "xyz").rglob("*.png")}
    # every zoom, and every web tile over the published mosaic that holds data is cached
    assert {z for z, _, _ in cached} == set(range(zmin, zmax + 1))
    expected = {(t.z, t.x, t.y) for t in webtiles.tiles_over(doc["bounds_wgs84"],
                                                             range(zmin, zmax + 1))}
    assert cached <= expected
    with serving(live_folder) as served:
        for z, x, y in sorted(expected - cached):
            assert not rgba(get(served, f"/tiles/{z}/{x}/{y}.png")[2])[..., 3].any()


def test_cached_tile_equals_the_tile_rendered_on_request(live_folder: Path,
                                                         tmp_path: Path) -> None:
    """The same folder without its cache (as a watch without one published it): the server
    renders every tile on request, and each equals the cached one pixel for pixel (and byte
    for byte: one encoder)."""
    bare = tmp_path / "bare"
    shutil.copytree(live_folder, bare)
    shutil.rmtree(bare / "live" / "xyz")
    index = bare / "live" / "mosaic.json"
    index.write_text(json.dumps({**json.loads(index.read_text()), "xyz": None}))
    cache = live_folder / "live" / "xyz"
    files = sorted(cache.rglob("*.png"))
    assert len(files) > 10
    with serving(live_folder) as cached, serving(bare) as bare_served:
        opaque = 0
        for path in files:
            z, x, y = (int(v) for v in path.with_suffix("").relative_to(cache).parts)
            status, headers, body = get(cached, f"/tiles/{z}/{x}/{y}.png")
            assert status == 200 and body == path.read_bytes()
            status, bare_headers, rendered = get(bare_served, f"/tiles/{z}/{x}/{y}.png")
            assert status == 200
            np.testing.assert_array_equal(rgba(rendered), rgba(body))
            assert headers["ETag"] == bare_headers["ETag"]
            opaque += int(rgba(body)[..., 3].any())
        assert opaque > 10
        live = cached.app.state.live_tiles
        assert live.served_cached == len(files) and live.rendered == 0
        assert bare_served.app.state.live_tiles.rendered > 0


def rio_tiler_tile(live: Path, z: int, x: int, y: int) -> np.ndarray:
    """The tile as rio-tiler makes it of the published work tiles (``mosaic_reader`` over
    ``Reader.tile``, TiTiler's way), RGBA."""
    doc = json.loads((live / "mosaic.json").read_text())
    bounds = webtiles.tile_bounds_wgs84(z, x, y)
    assets = [str(live / t["file"]) for t in doc["tiles"]
              if webtiles.reaches(t["bounds_wgs84"], bounds)]

    def read(asset: str, x: int, y: int, z: int) -> ImageData:
        with Reader(asset, tms=webtiles.TMS) as r:
            return r.tile(x, y, z, tilesize=webtiles.TILE_PX)

    img, _ = mosaic_reader(assets, read, x, y, z, threads=1,
                           allowed_exceptions=(TileOutsideBounds,))
    rgb = np.where(img.mask[None] > 0, img.data, 0)
    return np.concatenate([rgb, img.mask[None]]).transpose(1, 2, 0)


def test_cached_tiles_are_what_rio_tiler_renders(live_folder: Path) -> None:
    """Every cached tile with data equals rio-tiler's rendering of the published work tiles,
    pixel for pixel (the cache warps them itself, without rio-tiler's per-tile overhead)."""
    cache = live_folder / "live" / "xyz"
    checked = 0
    for path in sorted(cache.rglob("*.png")):
        z, x, y = (int(v) for v in path.with_suffix("").relative_to(cache).parts)
        ours = rgba(path.read_bytes())
        if not ours[..., 3].any():
            continue
        theirs = rio_tiler_tile(live_folder / "live", z, x, y)
        np.testing.assert_array_equal(ours[..., 3] > 0, theirs[..., 3] > 0)
        np.testing.assert_array_equal(np.where(ours[..., 3:] > 0, ours, 0), theirs)
        checked += 1
    assert checked > 10


def test_tile_etag_and_not_modified(live_folder: Path) -> None:
    path = next((live_folder / "live" / "xyz").rglob("*.png"))
    z, x, y = (int(v) for v in path.with_suffix("").relative_to(
        live_folder / "live" / "xyz").parts)
    with serving(live_folder) as served:
        status, headers, body = get(served, f"/tiles/{z}/{x}/{y}.png")
        assert status == 200 and headers["Cache-Control"] == "no-cache"
        tag = headers["ETag"]
        assert tag.startswith('"') and len(body) > 0
        status, headers, body = get(served, f"/tiles/{z}/{x}/{y}.png",
                                    {"If-None-Match": tag})
        assert status == 304 and body == b"" and headers["ETag"] == tag
        status, _, body = get(served, f"/tiles/{z}/{x}/{y}.png", {"If-None-Match": '"other"'})
        assert status == 200 and body


def read_event(response: http.client.HTTPResponse, deadline: float) -> dict[str, object]:
    """The next ``status`` event of an event stream (comments and ``retry:`` skipped)."""
    kind, data = None, []
    while time.monotonic() < deadline:
        line = response.readline().decode()
        if not line:
            raise AssertionError("the event stream ended")
        line = line.rstrip("\n")
        if line.startswith("event:"):
            kind = line.split(":", 1)[1].strip()
        elif line.startswith("data:"):
            data.append(line.split(":", 1)[1].strip())
        elif line == "" and data:
            if kind == "status":
                return json.loads("\n".join(data))  # type: ignore[no-any-return]
            kind, data = None, []
    raise AssertionError("no event in time")


def test_events_push_a_new_version(mosaic_run: Path, tmp_path: Path) -> None:
    """A live folder (journal only): the stream sends its status at once, then a new status
    as soon as the run publishes its files, well within the page's old 1 s poll."""
    out = tmp_path / "live"
    out.mkdir()
    shutil.copy(mosaic_run / ".seqat-run", out)
    shutil.copytree(mosaic_run / "journal", out / "journal")
    conn = None
    try:
        with serving(out) as served:
            parts = urlsplit(served.url)
            conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=30)
            conn.request("GET", "/events?stop_sigma_cm=5")
            response = conn.getresponse()
            assert response.status == 200
            assert response.headers["Content-Type"].startswith("text/event-stream")
            first = read_event(response, time.monotonic() + 20)
            assert first["done"] is False and first["stop"]["sigma_cm"] == 5.0  # type: ignore[index]
            for name in ("run.json", "eop.csv", "points.csv", "mosaic.tif"):
                shutil.copy(mosaic_run / name, out / name)
            t0 = time.monotonic()
            doc = read_event(response, t0 + 20)
            while doc["done"] is not True:
                doc = read_event(response, t0 + 20)
            assert doc["version"] != first["version"] and doc["mosaic"] is not None
            assert get(served, "/status.json")[0] == 200  # other requests meanwhile
            t_stop = time.monotonic()
        # the server stops although the stream is still open
        assert time.monotonic() - t_stop < 5
    finally:
        if conn is not None:
            conn.close()


def cache_bytes(live: Path) -> dict[tuple[int, int, int], bytes]:
    cache = live / "xyz"
    return {tuple(int(v) for v in p.with_suffix("").relative_to(cache).parts):  # type: ignore[misc]
            p.read_bytes() for p in cache.rglob("*.png")}


def test_changes_name_every_web_tile_a_revision_changed(tmp_path: Path) -> None:
    """After each publication the index's ``xyz.changes`` ends with ``[previous revision,
    revision, boxes]``, the entries chain, and every cached tile whose bytes changed (or that
    appeared) lies over one of the new entry's boxes: a page that reloads only those shows
    the new revision exactly. ``status.json`` passes them on."""
    out = tmp_path / "run"
    out.mkdir()
    (out / ".seqat-run").write_text("")
    mosaic = MosaicBuilder(out / "mosaic.tif", CRS)
    live = LiveTiles(out, mosaic, CRS)
    before: dict[tuple[int, int, int], bytes] = {}
    revisions: list[object] = [None]
    reloaded = kept = 0
    try:
        for k in range(4):
            result = ortho(f"img_{k}", COL0 + 150 * k, ROW0 + 40 * k, 500, 700, seed=k)
            update = mosaic.add(result)
            live.touched(update.tiles, result.image_id, 10.0, time.time(),
                         seen_boxes(result.raster))
            live.publish()
            assert live.wait_rendered(120)
            doc = json.loads((out / "live" / "mosaic.json").read_text())
            changes = doc["xyz"]["changes"]
            assert [c[1] for c in changes] == [r for r in revisions[1:]] + [doc["revision"]]
            assert all(c[0] == p[1] for p, c in zip(changes, changes[1:], strict=False))
            frm, to, boxes = changes[-1]
            assert frm == revisions[-1] and to == doc["revision"] and boxes
            after = cache_bytes(out / "live")
            changed = {t for t, b in after.items() if before.get(t) != b}
            assert changed and not set(before) - set(after)
            for z, x, y in after:
                over = any(webtiles.reaches(box, webtiles.tile_bounds_wgs84(z, x, y))
                           for box in boxes)
                assert over or (z, x, y) not in changed
                reloaded += over
                kept += not over
            before = after
            revisions.append(doc["revision"])
        with serving(out) as served:
            status = json.loads(get(served, "/status.json")[2])
        mosaic_doc = status["mosaic"]
        assert mosaic_doc["revision"] == revisions[-1]
        assert [c[1] for c in mosaic_doc["changes"]] == revisions[1:]
        assert kept > 0  # a revision leaves most of a growing mosaic's tiles as they were
    finally:
        live.stop_renderer()


def test_layers_are_encoded_once_and_revalidated(mosaic_run: Path, tmp_path: Path) -> None:
    """The layers carry an ETag of their bytes: the same files give the same bytes (a 304 to
    a page that has them), a change of the files a new answer."""
    out = tmp_path / "run"
    shutil.copytree(mosaic_run, out)
    with serving(out) as served:
        for path in ("/cameras.geojson", "/points.geojson", "/ellipses.geojson",
                     "/footprints.geojson", "/coverage.geojson?stop_sigma_cm=5"):
            status, headers, body = get(served, path)
            assert status == 200 and headers["Cache-Control"] == "no-cache"
            assert json.loads(body)["type"] == "FeatureCollection"
            tag = headers["ETag"]
            again = get(served, path)
            assert again[2] == body and again[1]["ETag"] == tag
            status, headers, body = get(served, path, {"If-None-Match": tag})
            assert status == 304 and body == b"" and headers["ETag"] == tag
        status, headers, body = get(served, "/cameras.geojson")
        tag, n = headers["ETag"], len(json.loads(body)["features"])
        assert n > 1
        eop = out / "eop.csv"
        lines = eop.read_text().splitlines(keepends=True)
        eop.write_text("".join(lines[:-1]))  # one camera fewer
        status, headers, body = get(served, "/cameras.geojson", {"If-None-Match": tag})
        assert status == 200 and headers["ETag"] != tag
        assert len(json.loads(body)["features"]) == n - 1


def test_seen_boxes_cover_the_seen_cells_band_by_band() -> None:
    """A diagonal footprint: one box per 256-row band of the global grid it reaches, every
    seen cell inside a box of its band, far less area than the footprint's bounding box."""
    rows, cols = 900, 900
    r, c = np.mgrid[0:rows, 0:cols]
    seen = np.abs(r - c) < 120  # a diagonal strip
    raster = OrthoRaster(image_id="d", col0=1000, row0=-1000 + 37, pixel_m=0.5,
                         pixels=np.zeros((rows, cols, 3), np.uint8), seen=seen,
                         off_nadir=np.zeros((rows, cols), np.float32), height_agl_m=100.0)
    boxes = seen_boxes(raster)
    bands = {(raster.row0 + i) // 256 for i in range(rows)}
    assert len(boxes) == len(bands)
    p = raster.pixel_m
    i, j = np.nonzero(seen)
    x, y = (raster.col0 + j + 0.5) * p, -(raster.row0 + i + 0.5) * p
    b = np.asarray(boxes)[:, :, None]
    inside = (b[:, 0] < x) & (x < b[:, 2]) & (b[:, 1] < y) & (y < b[:, 3])
    assert (inside.sum(axis=0) == 1).all()  # in one box: bands do not overlap
    area = sum((b[2] - b[0]) * (b[3] - b[1]) for b in boxes)
    assert area < 0.6 * (rows * p) * (cols * p)
    blank = OrthoRaster(image_id="b", col0=0, row0=0, pixel_m=0.5,
                        pixels=np.zeros((4, 4, 3), np.uint8), seen=np.zeros((4, 4), bool),
                        off_nadir=np.zeros((4, 4), np.float32), height_agl_m=100.0)
    assert seen_boxes(blank) == []


def test_a_layer_is_encoded_again_only_when_its_own_file_changed(
        live_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A live watch changes one file of the run folder after another (journal, mosaic
    index, estimates): the points layer is encoded again only when ``live/estimates.json``
    changed, with the same bytes and ETag otherwise."""
    from pipeline.serve import app as app_module

    out = tmp_path / "live"
    shutil.copytree(live_run, out)
    encodes: list[int] = []
    dumps = app_module.jsonio.dumps

    def counting(doc: object) -> bytes:
        encodes.append(1)
        return dumps(doc)

    monkeypatch.setattr(app_module.jsonio, "dumps", counting)
    with serving(out) as served:
        _, headers, body = get(served, "/points.geojson")
        tag, first = headers["ETag"], len(encodes)
        assert first == 1
        journal = out / "journal" / "journal.log"
        stamp = time.time() + 5
        os.utime(journal, (stamp, stamp))  # another file of the folder changed
        _, headers, again = get(served, "/points.geojson")
        assert again == body and headers["ETag"] == tag and len(encodes) == first
        est = out / "live" / "estimates.json"
        doc = json.loads(est.read_text())
        doc["points"]["sigma_m"][0] = [0.5, 0.5, 0.5]
        est.write_text(json.dumps(doc))
        _, headers, changed = get(served, "/points.geojson")
        assert headers["ETag"] != tag and len(encodes) == first + 1
        assert json.loads(changed)["features"][0]["properties"]["sx_m"] == 0.5


def test_pages_asking_together_parse_a_changed_file_once(tmp_path: Path) -> None:
    """Several request threads asking for one changed file: one parses it, the others wait
    for its value (not one parse per page)."""
    import threading

    from pipeline.serve.runview import RunView

    view = RunView(tmp_path)
    loads: list[int] = []
    barrier = threading.Barrier(4)

    def load() -> str:
        loads.append(1)
        time.sleep(0.2)
        return "parsed"

    def ask(results: list[str]) -> None:
        barrier.wait()
        results.append(view._cached("estimates", ("ino", 1), load))

    results: list[str] = []
    threads = [threading.Thread(target=ask, args=(results,)) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert results == ["parsed"] * 4 and len(loads) == 1
    assert view._cached("estimates", ("ino", 2), lambda: "again") == "again"
