"""Quick-looks of a live run (issue 15): each georeferenced image, small, written by the
estimates writer before ``estimates.json`` names it, served at ``/quicklook/{n}.jpg`` and
placed by the page on its footprint until the mosaic shows the image."""

from __future__ import annotations

import json
import shutil
import urllib.error
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from pipeline.run.live_view import LiveEstimates, quicklook_name, write_quicklook
from pipeline.serve.app import serving
from pipeline.serve.live import quicklook_url
from pipeline.serve.runview import RunView
from seqat.types import PinholeCamera
from tests.pipeline.serve.conftest import quicklook_source


def _get(url: str) -> tuple[int, bytes, str]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as err:
        return err.code, b"", ""


@pytest.mark.parametrize("width, height, expected", [(800, 600, (512, 384)),
                                                     (4000, 3000, (512, 384)),
                                                     (300, 500, (300, 500)),
                                                     (600, 3000, (102, 512))])
def test_quicklook_size_and_content(tmp_path: Path, width: int, height: int,
                                    expected: tuple[int, int]) -> None:
    """At most 512 px wide and high, the aspect ratio kept, never enlarged, the picture's
    content (left half red, right half blue) in place; reduced decoding for large JPEGs."""
    pixels = np.zeros((height, width, 3), np.uint8)
    pixels[:, : width // 2, 2] = 230
    pixels[:, width // 2:, 0] = 230
    src = tmp_path / "in.jpg"
    assert cv2.imwrite(str(src), pixels)
    out = tmp_path / "q.jpg"
    assert write_quicklook(src, out, width)
    small = cv2.imread(str(out))
    assert (small.shape[1], small.shape[0]) == expected
    w = small.shape[1]
    left, right = small[:, : w // 2 - 3].mean(axis=(0, 1)), small[:, w // 2 + 3:].mean(axis=(0, 1))
    assert left[2] > 200 and left[0] < 30 and right[0] > 200 and right[2] < 30
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp


def test_quicklook_of_unreadable_files(tmp_path: Path) -> None:
    for name, data in (("empty.jpg", b""), ("text.jpg", b"not an image")):
        (tmp_path / name).write_bytes(data)
        assert not write_quicklook(tmp_path / name, tmp_path / "q.jpg", 800)
    assert not write_quicklook(tmp_path / "absent.jpg", tmp_path / "q.jpg", 800)
    assert not (tmp_path / "q.jpg").exists()


def test_live_estimates_write_quicklooks_before_naming_them(tmp_path: Path) -> None:
    """The writer makes each image's quick-look before the first ``estimates.json`` that
    names it; an image whose file cannot be read has none (``quicklook`` null)."""
    camera = PinholeCamera(f_px=800.0, cx_px=400.0, cy_px=300.0, width_px=800,
                           height_px=600)
    images = {"a": quicklook_source(tmp_path / "a.jpg"), "b": tmp_path / "missing.jpg"}
    out = tmp_path / "out"
    est = LiveEstimates(out, crs_wkt="LOCAL_CS[\"m\"]", camera=camera, images=images,
                        min_interval_s=0.0)
    try:
        for k, image in enumerate(("a", "b")):
            eop = SimpleNamespace(image_id=image, eop=np.array([10.0 * k, 0, 500, 0, 0, 0]),
                                  sigma=np.full(6, 0.01))
            update = SimpleNamespace(eop=eop, sigma0=1.0, stage="sequential")
            est.on_image(None, update, None)  # type: ignore[arg-type]
            est.on_live(None)
    finally:
        est.close()
    doc = json.loads((out / "live" / "estimates.json").read_text())
    names = {c["image"]: c["quicklook"] for c in doc["cameras"]}
    assert names == {"a": f"quicklook/{quicklook_name(0)}", "b": None}
    assert cv2.imread(str(out / "live" / names["a"])).shape == (384, 512, 3)


def test_quicklooks_served_with_footprints(live_run: Path, tmp_path: Path) -> None:
    """``footprints.geojson`` names each quick-look's route with the footprint's corners in
    the image's corner order; the route serves the JPEG, nothing else; an image the
    mosaic shows is marked ``in_mosaic``."""
    assert quicklook_url("quicklook/3.jpg") == "/quicklook/3.jpg"
    for bad in ("../run.json", "quicklook/3.png", "quicklook/../3.jpg", "/etc/passwd", 3, None):
        assert quicklook_url(bad) is None
    with serving(live_run) as served:
        with urllib.request.urlopen(served.url + "footprints.geojson", timeout=10) as r:
            fp = json.loads(r.read())
        props = [f["properties"] for f in fp["features"]]
        assert [p["quicklook"] for p in props] == [f"/quicklook/{i}.jpg" for i in range(6)]
        assert not any(p["in_mosaic"] for p in props)
        for f in fp["features"]:
            ring = f["geometry"]["coordinates"][0]
            assert f["properties"]["corners"] == ring[:4]
        status, body, kind = _get(served.url + "quicklook/0.jpg")
        assert status == 200 and kind == "image/jpeg"
        assert cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR).shape[1] == 512
        for path in ("quicklook/6.jpg", "quicklook/-1.jpg", "quicklook/x.jpg",
                     "quicklook/..%2Fsource.jpg"):
            assert _get(served.url + path)[0] == 404
    out = tmp_path / "run"
    shutil.copytree(live_run, out)
    first = props[0]["image"]
    (out / "ortho.json").write_text(json.dumps({"images": [{"image": first}]}))
    marked = [f["properties"]["in_mosaic"] for f in RunView(out).footprints()["features"]]
    assert marked == [True] + [False] * 5


def test_live_estimates_rows_follow_every_change(tmp_path: Path) -> None:
    """Rows of cameras that did not change are reused (O(window) per write); a camera
    estimated again, or leaving the window, is written with its new values."""
    camera = PinholeCamera(f_px=800.0, cx_px=400.0, cy_px=300.0, width_px=800,
                           height_px=600)
    est = LiveEstimates(tmp_path / "out", crs_wkt="LOCAL_CS[\"m\"]", camera=camera,
                        min_interval_s=0.0)

    def update(*cams: tuple[str, float]) -> dict[str, dict[str, object]]:
        eops = [SimpleNamespace(image_id=i, eop=np.array([x, 0, 500, 0, 0, 0]),
                                sigma=np.full(6, 0.01)) for i, x in cams]
        window = SimpleNamespace(eops=eops, points=())
        est.on_image(None, SimpleNamespace(eop=eops[-1], sigma0=1.0, stage="sequential"),
                     SimpleNamespace(window_solution=lambda: window))  # type: ignore[arg-type]
        doc = est._document(*_state(est))  # what the writer does (not woken: no on_live)
        return {c["image"]: c for c in doc["cameras"]}  # type: ignore[index,union-attr]

    try:
        first = update(("a", 1.0), ("b", 2.0))
        assert first["a"]["eop"][0] == 1.0 and first["a"]["in_window"]
        second = update(("b", 2.5), ("c", 3.0))  # a left the window, b moved
        assert second["a"]["eop"][0] == 1.0 and not second["a"]["in_window"]
        assert second["b"]["eop"][0] == 2.5 and second["c"]["in_window"]
        est.on_live(None)  # the writer's file: the same rows
    finally:
        est.close()
    doc = json.loads((tmp_path / "out" / "live" / "estimates.json").read_text())
    rows = {c["image"]: c for c in doc["cameras"]}
    assert rows["b"]["eop"][0] == 2.5 and not rows["a"]["in_window"]


def _state(est: LiveEstimates) -> tuple[object, ...]:
    with est._lock:
        return (list(est._order), dict(est._cameras), set(est._window), dict(est._points),
                est._sigma0, est._stage, dict(est._latency))


def _one_image(tmp_path: Path) -> tuple[LiveEstimates, SimpleNamespace]:
    """A live-estimates writer (the tests read its ``_document``, as the writer does) and
    one image's EOP."""
    camera = PinholeCamera(f_px=800.0, cx_px=400.0, cy_px=300.0, width_px=800,
                           height_px=600)
    est = LiveEstimates(tmp_path / "out", crs_wkt="LOCAL_CS[\"m\"]", camera=camera,
                        min_interval_s=0.0)
    eop = SimpleNamespace(image_id="a", eop=np.array([0.0, 0, 500, 0, 0, 0]),
                          sigma=np.full(6, 0.01))
    return est, eop


def _shown(est: LiveEstimates, eop: SimpleNamespace, points: list[SimpleNamespace],
           withheld: tuple[str, ...] = ()) -> dict[str, list[object]]:
    """The points of the document after an update whose window holds ``points``."""
    window = SimpleNamespace(eops=[eop], points=points, withheld=withheld)
    est.on_image(None, SimpleNamespace(eop=eop, sigma0=1.0, stage="sequential"),
                 SimpleNamespace(window_solution=lambda: window))  # type: ignore[arg-type]
    return est._document(*_state(est))["points"]  # type: ignore[return-value]


def test_live_estimates_drop_a_point_once_its_rays_disagree(tmp_path: Path) -> None:
    """A ground point shown after one update and withheld by the next (its rays came to
    disagree: ``Solution.withheld``) leaves the live estimates; the others stay."""
    est, eop = _one_image(tmp_path)
    point = {pid: SimpleNamespace(point_id=pid, xyz_m=np.array([x, 0.0, 0.0]),
                                  sigma_m=np.full(3, 0.1), n_obs=2)
             for pid, x in (("t1", 1.0), ("t2", 2.0))}
    try:
        assert _shown(est, eop, [point["t1"], point["t2"]])["point"] == ["t1", "t2"]
        assert _shown(est, eop, [point["t2"]], withheld=("t1",))["point"] == ["t2"]
    finally:
        est.close()


def test_live_estimates_do_not_show_a_point_off_the_surface(tmp_path: Path) -> None:
    """A ground point 60 m under the others (a wrong match along the epipolar line) is not
    in the live estimates, as the run's end will not publish it; the ground's points are."""
    est, eop = _one_image(tmp_path)
    rng = np.random.default_rng(1)
    xyz = [(f"g{k}", x, y, 100.0 + rng.normal(0.0, 0.05))
           for k, (x, y) in enumerate((x, y) for x in range(0, 50, 10) for y in range(0, 50, 10))]
    xyz.append(("wrong", 21.0, 21.0, 40.0))
    points = [SimpleNamespace(point_id=pid, xyz_m=np.array([x, y, z]), sigma_m=np.full(3, 0.1),
                              n_obs=2) for pid, x, y, z in xyz]
    try:
        shown = _shown(est, eop, points)
    finally:
        est.close()
    assert shown["point"] == [p[0] for p in xyz[:-1]]
    assert len(shown["xyz_m"]) == len(shown["sigma_m"]) == len(shown["n_obs"]) == 25
