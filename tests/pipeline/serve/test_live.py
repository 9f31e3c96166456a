"""The live map (issue 15): ``live/estimates.json`` on the page (estimated cameras, error
ellipses, footprints, tie points by precision, the stop criterion), and ``seqat watch --ortho
--serve`` end to end: a real server in the watch's process shows the live estimates and the
live mosaic's tiles while the watch goes on, and ``mosaic.tif`` once it has finished."""

from __future__ import annotations

import io
import json
import socket
import threading
import time
import urllib.request
from pathlib import Path

import morecantile
import numpy as np
import pyproj
import pytest
from PIL import Image
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.cli.run import watch_server
from pipeline.ortho.live import watch_ortho_factory
from pipeline.run.feed import feed_flight
from pipeline.run.store import read_eop_csv, read_json_object, read_points_csv
from pipeline.run.watch import WatchOptions, watch_flight
from pipeline.serve.app import serving

TMS = morecantile.tms.get("WebMercatorQuad")
SAMPLE = Path(__file__).resolve().parents[3] / "sample_data" / "autzen_rendered"


def doc(url: str, path: str) -> dict:
    with urllib.request.urlopen(url.rstrip("/") + path, timeout=10) as r:
        return json.loads(r.read())  # type: ignore[no-any-return]


def test_live_estimates_on_the_page(live_run: Path, mosaic_run: Path) -> None:
    eop = read_eop_csv(mosaic_run / "eop.csv")
    points = read_points_csv(mosaic_run / "points.csv")
    crs = pyproj.CRS.from_wkt(str(read_json_object(mosaic_run / "run.json")["crs"]))
    to_wgs84 = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    worst = points.sigma_m.max(axis=1)
    with serving(live_run) as served:
        status = doc(served.url, "/status.json")
        assert status["done"] is False and status["images"] == status["cameras"] == 6
        assert status["cameras_position"] == "live" and status["sigma0"] == 0.9
        assert status["last_image"] == eop.image_ids[5]
        assert status["latency_ms"]["tracking"] == 120.0 and status["latency_ms"]["at"] == 8.0
        assert status["last_latency_ms"] == 250.0 and status["crs_name"] == crs.name
        stop = status["stop"]
        assert stop["sigma_cm"] == 8.0 and stop["points_total"] == len(points)
        assert stop["points_done"] == int(np.sum(worst <= 0.08))
        assert stop["reached"] is False and 0 < stop["cells_total"]
        # the page's field overrides the run's criterion
        loose = doc(served.url, "/status.json?stop_sigma_cm=1e6")["stop"]
        assert loose["reached"] is True and loose["cells_done"] == loose["cells_total"]
        # cameras at their estimated EOP, not the nav
        cams = doc(served.url, "/cameras.geojson")["features"]
        lon, lat = to_wgs84.transform(eop.eop[:6, 0], eop.eop[:6, 1])
        np.testing.assert_allclose([f["geometry"]["coordinates"] for f in cams],
                                   np.column_stack([lon, lat]), rtol=0, atol=1e-12)
        assert all(f["properties"]["estimate"] == "live" for f in cams)
        assert [f["properties"]["in_window"] for f in cams] == [False] * 3 + [True] * 3
        # error ellipses: semi-axes σE, σN times the scale, around the camera
        ell = doc(served.url, "/ellipses.geojson")
        assert len(ell["features"]) == 6 and ell["scale"] > 1
        first = ell["features"][0]
        assert first["properties"]["sigma_e_m"] == pytest.approx(eop.sigma[0, 0])
        ring = np.array(first["geometry"]["coordinates"][0])
        x, y = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(
            ring[:, 0], ring[:, 1])
        assert (x.max() - x.min()) / 2 == pytest.approx(ell["scale"] * eop.sigma[0, 0],
                                                          rel=1e-3)
        assert (y.max() - y.min()) / 2 == pytest.approx(ell["scale"] * eop.sigma[0, 1],
                                                          rel=1e-3)
        assert len(doc(served.url, "/footprints.geojson")["features"]) == 6
        pts = doc(served.url, "/points.geojson")
        assert pts["total"] == len(points)
        assert all(f["properties"]["sigma_max_m"] > 0 for f in pts["features"])
        cells = doc(served.url, "/coverage.geojson")
        assert cells["stop_sigma_cm"] == 8.0
        assert sum(f["properties"]["done"] for f in cells["features"]) == stop["cells_done"]
        assert sum(f["properties"]["points"] for f in cells["features"]) == len(points)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _opaque_share(png: bytes) -> float:
    return float(np.mean(np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))[..., 3] > 0))


def test_watch_ortho_serve(tmp_path: Path) -> None:
    """4 images of the rendered Autzen flight: the watch with its live ortho and the server of
    ``--serve`` (a child process, as ``seqat watch --ortho --serve``; flat plane: its LiDAR is
    left out); while it goes on, the page's endpoints show the live estimates and the live
    mosaic; once stopped, mosaic.tif and no live tiles. The watch is stopped when both were
    seen, not by a timeout, so a loaded machine only makes the test slower."""
    flight, out = tmp_path / "flight", tmp_path / "out"
    feed_flight(SAMPLE, flight, rate_hz=100.0, limit=4)
    yaml = flight / "flight.yaml"  # no LiDAR: gridding it would take ~9 s
    yaml.write_text("".join(line for line in yaml.read_text().splitlines(keepends=True)
                            if not line.startswith("lidar:")))
    port = _free_port()
    stop = threading.Event()
    result: list[object] = []
    url = f"http://127.0.0.1:{port}"
    seen_live_cameras = seen_live_tile = seen_quicklook = False
    with watch_server(port, "127.0.0.1") as on_claimed:

        def watch() -> None:
            try:
                result.append(watch_flight(
                    flight, out, watch=WatchOptions(idle_timeout_s=120.0), stop=stop,
                    make_listeners=watch_ortho_factory(out), on_claimed=on_claimed,
                    stop_sigma_m=0.2, on_image=lambda live, update: None))
            except BaseException as err:  # noqa: BLE001 - re-raised below
                result.append(err)

        thread = threading.Thread(target=watch, daemon=True)
        thread.start()
        deadline = time.monotonic() + 120
        while thread.is_alive() and time.monotonic() < deadline and not (
                seen_live_cameras and seen_live_tile and seen_quicklook):
            try:
                status = doc(url, "/status.json")
            except OSError:
                time.sleep(0.05)
                continue
            if status["cameras_position"] == "live" and status["cameras"] > 0:
                cams = doc(url, "/cameras.geojson")["features"]
                assert all(f["properties"]["estimate"] == "live" for f in cams)
                assert status["stop"]["sigma_cm"] == 20.0
                seen_live_cameras = True
                for f in doc(url, "/footprints.geojson")["features"]:
                    if f["properties"]["quicklook"] and not seen_quicklook:
                        with urllib.request.urlopen(url + f["properties"]["quicklook"],
                                                    timeout=30) as r:
                            seen_quicklook = r.headers["Content-Type"] == "image/jpeg"
            mosaic = status["mosaic"]
            if mosaic is not None and mosaic["version"].startswith("live-"):
                west, south, east, north = mosaic["bounds_wgs84"]
                t = TMS.tile((west + east) / 2, (south + north) / 2, mosaic["maxzoom"] - 2)
                with urllib.request.urlopen(f"{url}/tiles/{t.z}/{t.x}/{t.y}.png",
                                            timeout=30) as r:
                    assert r.status == 200 and r.headers["Content-Type"] == "image/png"
                    seen_live_tile = seen_live_tile or _opaque_share(r.read()) > 0.1
            time.sleep(0.05)
        stop.set()
        thread.join(120)
        assert seen_live_cameras and seen_live_tile and seen_quicklook
        (res,) = result
        assert not isinstance(res, BaseException), res
        assert doc(url, "/status.json")["done"] is True  # the finished run, same server
    assert (out / "mosaic.tif").is_file()
    # the live mosaic's files are gone; the estimates and the quick-looks stay
    assert sorted(p.name for p in (out / "live").iterdir()) == ["estimates.json", "quicklook"]
    names = [c["quicklook"] for c in read_json_object(out / "live" / "estimates.json")[
        "cameras"]]
    assert names == [f"quicklook/{i}.jpg" for i in range(4)]
    assert sorted(p.name for p in (out / "live" / "quicklook").iterdir()) == [
        f"{i}.jpg" for i in range(4)]
    est = json.loads((out / "live" / "estimates.json").read_text())
    assert est["images"] == 4 and est["stop_sigma_m"] == 0.2
    assert all(c["footprint"] is not None and c["at_unix_s"] > 0 for c in est["cameras"])
    assert len(est["points"]["point"]) > 50
    with socket.socket() as again:  # the server stopped with the watch
        again.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        again.bind(("127.0.0.1", port))


def test_watch_serve_bad_options(tmp_path: Path) -> None:
    cli = CliRunner()
    flight = tmp_path / "flight"
    flight.mkdir()
    (flight / "flight.yaml").write_text((SAMPLE / "flight.yaml").read_text())
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        r = cli.invoke(app, ["watch", str(flight), "--out", str(tmp_path / "o"), "--serve",
                             str(port), "--idle-timeout-s", "1"])
    assert r.exit_code == 2 and f"127.0.0.1:{port}: cannot listen" in r.output
    assert not (tmp_path / "o").exists()
    r = cli.invoke(app, ["watch", str(flight), "--out", str(tmp_path / "o"), "--dsm", "x.tif"])
    assert r.exit_code == 2 and "--dsm and --ortho-options go with --ortho" in r.output
    r = cli.invoke(app, ["watch", str(flight), "--out", str(tmp_path / "o"), "--host",
                         "0.0.0.0"])
    assert r.exit_code == 2 and "--host goes with --serve" in r.output
    r = cli.invoke(app, ["watch", str(flight), "--out", str(tmp_path / "o"),
                         "--stop-sigma-cm", "-1"])
    assert r.exit_code == 2 and "--stop-sigma-cm" in r.output
