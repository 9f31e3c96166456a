"""``seqat serve``: the HTTP endpoints on a real uvicorn server, read-only, confined."""

from __future__ import annotations

import http.client
import io
import json
import os
import shutil
import socket
import urllib.error
import urllib.request
from pathlib import Path
from urllib.parse import urlsplit

import morecantile
import numpy as np
import pyproj
import pytest
from PIL import Image
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.run.journal import encode_record, read_journal
from pipeline.run.store import read_eop_csv, read_json_object
from pipeline.serve.app import Served, serving
from pipeline.serve.runview import MAX_POINTS, RunView

from .conftest import write_mosaic

TMS = morecantile.tms.get("WebMercatorQuad")


def get(served: Served, path: str) -> tuple[int, str, bytes]:
    """Status, content type and body of a GET (errors included)."""
    try:
        with urllib.request.urlopen(served.url.rstrip("/") + path, timeout=10) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers.get("Content-Type", ""), err.read()


def raw_status(served: Served, path: str) -> int:
    """The status of a request sent with its path exactly as given (no normalisation)."""
    parts = urlsplit(served.url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)
    try:
        conn.putrequest("GET", path, skip_accept_encoding=True)
        conn.endheaders()
        response = conn.getresponse()
        response.read()
        return response.status
    finally:
        conn.close()


def tile_rgba(served: Served, z: int, x: int, y: int) -> np.ndarray:
    status, kind, body = get(served, f"/tiles/{z}/{x}/{y}.png")
    assert status == 200 and kind == "image/png"
    img = Image.open(io.BytesIO(body))
    assert img.size == (256, 256)
    return np.asarray(img.convert("RGBA"))


def centre_tile(served: Served) -> morecantile.Tile:
    mosaic = json.loads(get(served, "/status.json")[2])["mosaic"]
    west, south, east, north = mosaic["bounds_wgs84"]
    return TMS.tile((west + east) / 2, (south + north) / 2, mosaic["maxzoom"])


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.stat().st_size)
            for p in folder.rglob("*")}


def test_status_of_a_finished_run(served: Served, mosaic_run: Path) -> None:
    status, kind, body = get(served, "/status.json")
    assert status == 200 and kind.startswith("application/json")
    doc = json.loads(body)
    run = read_json_object(mosaic_run / "run.json")
    assert doc["done"] is True
    assert doc["images"] == run["totals"]["images"] == len(read_eop_csv(mosaic_run / "eop.csv"))
    assert doc["cameras"] == doc["images"]
    assert doc["sigma0"] == pytest.approx(run["totals"]["sigma0"])
    last = run["images"][-1]
    assert doc["last_image"] == last["image_id"]
    assert doc["last_latency_kind"] == "processing_ms"  # `seqat run`: no watch latency
    assert doc["last_latency_ms"] == pytest.approx(last["live"]["processing_ms"])
    assert isinstance(doc["warnings"], list) and doc["method"] == "seq-r"
    assert doc["mosaic"]["maxzoom"] >= doc["mosaic"]["minzoom"]


def test_tiles_inside_and_outside_the_data(served: Served) -> None:
    tile = centre_tile(served)
    rgba = tile_rgba(served, tile.z, tile.x, tile.y)
    opaque = rgba[..., 3] == 255
    assert opaque.mean() > 0.5
    assert np.all(rgba[opaque][:, :3] == (200, 120, 40))
    # a tile of the same zoom far away, and one at zoom 2: fully transparent
    assert not tile_rgba(served, tile.z, tile.x + 50, tile.y).any()
    assert not tile_rgba(served, 2, 0, 0)[..., 3].any()
    # indices outside the tile matrix: 404
    assert get(served, f"/tiles/{tile.z}/{2 ** tile.z}/0.png")[0] == 404
    assert get(served, "/tiles/25/0/0.png")[0] == 404
    assert get(served, "/tiles/3/-1/0.png")[0] == 404


def test_cameras_and_points_geojson(served: Served, mosaic_run: Path) -> None:
    status, kind, body = get(served, "/cameras.geojson")
    assert status == 200 and kind == "application/geo+json"
    features = json.loads(body)["features"]
    eop = read_eop_csv(mosaic_run / "eop.csv")
    crs = pyproj.CRS.from_wkt(str(read_json_object(mosaic_run / "run.json")["crs"]))
    lon, lat = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(
        eop.eop[:, 0], eop.eop[:, 1])
    assert [f["properties"]["image"] for f in features] == list(eop.image_ids)
    got = np.array([f["geometry"]["coordinates"] for f in features])
    np.testing.assert_allclose(got, np.column_stack([lon, lat]), rtol=0, atol=1e-12)
    sigma = np.array([f["properties"]["sigma_position_m"] for f in features])
    np.testing.assert_allclose(sigma, np.linalg.norm(eop.sigma[:, :3], axis=1))
    doc = json.loads(get(served, "/points.geojson")[2])
    assert doc["total"] == json.loads(get(served, "/status.json")[2])["points"] > 0
    assert doc["shown"] == len(doc["features"]) == min(doc["total"], 5000)
    assert all(f["properties"]["sigma_m"] > 0 for f in doc["features"])


def test_page_and_vendored_leaflet(served: Served) -> None:
    status, kind, body = get(served, "/")
    assert status == 200 and kind.startswith("text/html")
    assert b"/static/leaflet.js" in body and b"http" not in body  # nothing from a CDN
    status, _, body = get(served, "/static/leaflet.js")
    assert status == 200 and b"Leaflet 1.9.4" in body
    assert get(served, "/static/images/marker-icon.png")[0] == 200


@pytest.mark.parametrize("path", [
    "/tiles/../../etc/passwd", "/tiles/%2e%2e/%2e%2e/etc/passwd",
    "/static/../../../../etc/passwd", "/static/%2e%2e/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
    "/static/..%2f..%2f..%2f..%2fetc%2fpasswd", "/static/../app.py", "/static/%2e%2e/app.py",
    "/eop.csv", "/run.json", "/mosaic.tif", "/tiles/1/0/0.png/../../../run.json",
])
def test_no_path_outside_the_fixed_routes(served: Served, path: str) -> None:
    assert raw_status(served, path) in (400, 404)


def test_read_only(served: Served, mosaic_run: Path) -> None:
    before = snapshot(mosaic_run)
    tile = centre_tile(served)
    for path in ("/", "/status.json", "/cameras.geojson", "/points.geojson",
                 f"/tiles/{tile.z}/{tile.x}/{tile.y}.png"):
        assert get(served, path)[0] == 200
    assert snapshot(mosaic_run) == before
    status, _, _ = get(served, "/status.json")
    req = urllib.request.Request(served.url + "status.json", method="POST")
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=10)
    assert err.value.code == 405


def test_live_folder_and_replaced_mosaic(mosaic_run: Path, tmp_path: Path) -> None:
    """A run still going: only its journal; then the mosaic appears and is replaced."""
    out = tmp_path / "live"
    out.mkdir()
    shutil.copy(mosaic_run / ".seqat-run", out)
    shutil.copytree(mosaic_run / "journal", out / "journal")
    with serving(out) as served:
        doc = json.loads(get(served, "/status.json")[2])
        assert doc["done"] is False and doc["mosaic"] is None
        n = len(read_eop_csv(mosaic_run / "eop.csv"))
        assert doc["images"] == n and doc["cameras"] == 0
        assert doc["sigma0"] is not None and doc["last_latency_ms"] is not None
        assert json.loads(get(served, "/cameras.geojson")[2])["features"] == []
        assert not tile_rgba(served, 2, 1, 1).any()
        # the run publishes its files, then a new mosaic replaces the first
        for name in ("run.json", "eop.csv", "points.csv", "mosaic.tif"):
            shutil.copy(mosaic_run / name, out / name)
        tile = centre_tile(served)
        first = json.loads(get(served, "/status.json")[2])
        assert first["done"] is True and first["cameras"] == n
        assert tuple(tile_rgba(served, tile.z, tile.x, tile.y)[128, 128]) == (200, 120, 40, 255)
        write_mosaic(out, (10, 20, 30))  # atomic replace, as a live run does
        assert tuple(tile_rgba(served, tile.z, tile.x, tile.y)[128, 128]) == (10, 20, 30, 255)
        assert json.loads(get(served, "/status.json")[2])["version"] != first["version"]
        # a damaged mosaic: 503 for its tiles, a warning naming it, the rest still served
        (out / "mosaic.tif").write_bytes(b"II*\0 not a tiff")
        status, _, body = get(served, f"/tiles/{tile.z}/{tile.x}/{tile.y}.png")
        assert status == 503 and b"mosaic.tif: cannot read" in body
        doc = json.loads(get(served, "/status.json")[2])
        assert doc["mosaic"] is None and doc["done"] is True
        assert any(w.startswith("mosaic.tif: cannot read") for w in doc["warnings"])


def test_live_watch_cameras_at_their_nav_position(mosaic_run: Path, tmp_path: Path) -> None:
    """A live ``seqat watch`` journal (its ``setup`` record names the CRS): the cameras at
    their nav position with the σ of their update, until the run publishes eop.csv."""
    out = tmp_path / "watch"
    (out / "journal").mkdir(parents=True)
    shutil.copy(mosaic_run / ".seqat-run", out)
    run = read_json_object(mosaic_run / "run.json")
    lines = (mosaic_run / "journal" / "journal.log").read_bytes().splitlines(keepends=True)
    setup = encode_record({"kind": "setup", "crs": run["crs"], "camera": run["camera"],
                           "camera_approximate": False})
    (out / "journal" / "journal.log").write_bytes(lines[0] + setup + b"".join(lines[1:4]))
    journal = read_journal(out)
    assert journal is not None and len(journal.images) == 3
    with serving(out) as served:
        features = json.loads(get(served, "/cameras.geojson")[2])["features"]
        assert [f["properties"]["image"] for f in features] == [
            r.frame.image_id for r in journal.images]
        crs = pyproj.CRS.from_wkt(str(run["crs"]))
        nav = np.array([r.frame.nav_eop[:2] for r in journal.images])
        lon, lat = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(
            nav[:, 0], nav[:, 1])
        np.testing.assert_allclose([f["geometry"]["coordinates"] for f in features],
                                   np.column_stack([lon, lat]), rtol=0, atol=1e-12)
        assert all(f["properties"]["position"] == "nav" for f in features)
        np.testing.assert_allclose(
            [f["properties"]["sigma_position_m"] for f in features],
            [np.linalg.norm(r.live["sigma_position_m"]) for r in journal.images])
        status = json.loads(get(served, "/status.json")[2])
        assert status["images"] == status["cameras"] == 3 and status["done"] is False
        assert status["last_image"] == journal.images[-1].frame.image_id


def test_cli_bad_input(tmp_path: Path, mosaic_run: Path) -> None:
    cli = CliRunner()
    (tmp_path / "plain").mkdir()
    result = cli.invoke(app, ["serve", str(tmp_path / "plain")])
    assert result.exit_code == 2
    assert "not a seqat run folder" in result.output and "plain" in result.output
    result = cli.invoke(app, ["serve", str(tmp_path / "missing")])
    assert result.exit_code == 2 and "no such run folder" in result.output
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        result = cli.invoke(app, ["serve", str(mosaic_run), "--port", str(port)])
    assert result.exit_code == 2
    assert f"127.0.0.1:{port}: cannot listen: the port is in use" in result.output
    assert len(result.output.strip().splitlines()) == 1
    result = cli.invoke(app, ["serve", str(mosaic_run), "--host", "no-such-host.invalid"])
    assert result.exit_code == 2 and "--host no-such-host.invalid" in result.output


def test_served_folder_is_not_left_open(mosaic_run: Path) -> None:
    """The server of a ``with serving(...)`` block stops at its end (port released)."""
    with serving(mosaic_run) as served:
        port = urlsplit(served.url).port
        assert get(served, "/status.json")[0] == 200
    with socket.socket() as again:
        again.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        again.bind(("127.0.0.1", port))
    assert os.path.isdir(mosaic_run)


def test_points_subsampled_evenly(mosaic_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "many"
    out.mkdir()
    shutil.copy(mosaic_run / "run.json", out)
    rows = [f"p{i:05d},{500000 + i * 0.01},{4090000 + i * 0.01},100.0,0.1,0.1,0.2,3"
            for i in range(12001)]
    (out / "points.csv").write_text("point,x_m,y_m,z_m,sx_m,sy_m,sz_m,n_obs\n"
                                    + "\n".join(rows) + "\n")
    doc = RunView(out).points()
    ids = [f["properties"]["point"] for f in doc["features"]]  # type: ignore[union-attr]
    assert doc["total"] == 12001 and doc["shown"] == len(ids) == MAX_POINTS
    assert ids[0] == "p00000" and ids[-1] == "p12000" and ids == sorted(set(ids))
