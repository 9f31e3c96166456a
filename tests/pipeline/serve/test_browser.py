"""The page of ``seqat serve`` in headless chromium (selenium + Debian's chromium-driver):
the mosaic's tiles and the camera markers appear, and the status panel is filled. Skipped
when chromium or chromedriver is absent (``.ci/run`` installs both)."""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from pipeline.run.store import read_eop_csv
from pipeline.serve.app import Served, serving

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")

pytestmark = pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None,
                                reason="chromium and chromedriver are absent "
                                       "(apt-get install chromium chromium-driver)")


@pytest.fixture(scope="module")
def chromium() -> Iterator[Any]:
    """One headless chromium for the module's tests (a start costs ~2 s of CPU)."""
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM  # type: ignore[assignment]
    with tempfile.TemporaryDirectory() as profile:
        for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                    "--disable-background-networking", "--disable-component-update",
                    "--no-first-run", f"--user-data-dir={profile}", "--window-size=1280,800"):
            options.add_argument(arg)
        driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER),
                                  options=options)
        try:
            yield driver
        finally:
            driver.quit()


@pytest.fixture
def browser(chromium: Any) -> Any:
    """The module's chromium on a blank page, its browser log emptied: each test sees only
    its own page and log messages (every server is on its own port: its own origin)."""
    chromium.get("about:blank")
    chromium.get_log("browser")
    return chromium


def test_page_shows_tiles_cameras_and_status(browser: Any, served: Served,
                                             mosaic_run: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    n_images = len(read_eop_csv(mosaic_run / "eop.csv"))
    browser.get(served.url)
    wait = WebDriverWait(browser, 20)
    wait.until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "path.seqat-camera"))
               == n_images)
    wait.until(lambda d: d.execute_script(
        "return Array.from(document.querySelectorAll('img.leaflet-tile-loaded'))"
        ".filter(i => i.src.includes('/tiles/') && i.naturalWidth === 256).length") > 0)
    # the points come from their own request (/points.geojson), after or before the cameras
    wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "path.seqat-point"),
               "no tie point drawn")
    assert browser.find_element(By.ID, "state").text == "finished"
    assert browser.find_element(By.ID, "images").text == str(n_images)
    logs = [e for e in browser.get_log("browser") if e.get("level") == "SEVERE"]
    assert logs == []


def test_page_follows_a_live_run_without_reload(browser: Any, mosaic_run: Path,
                                                tmp_path: Path) -> None:
    """A run folder with only its journal; the run then publishes its files: the page,
    told by the server-sent events of /events, shows the cameras and the finished state
    without a reload."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    out = tmp_path / "live"
    out.mkdir()
    shutil.copy(mosaic_run / ".seqat-run", out)
    shutil.copytree(mosaic_run / "journal", out / "journal")
    n_images = len(read_eop_csv(mosaic_run / "eop.csv"))
    with serving(out) as served:
        browser.get(served.url)
        wait = WebDriverWait(browser, 20)
        wait.until(lambda d: d.find_element(By.ID, "state").text == "live")
        assert browser.find_element(By.ID, "images").text == str(n_images)
        assert not browser.find_elements(By.CSS_SELECTOR, "path.seqat-camera")
        browser.execute_script("window.seqatNotReloaded = true;")
        wait.until(lambda d: d.execute_script("return window.seqatEventState();") == 1)
        for name in ("run.json", "eop.csv", "points.csv", "mosaic.tif"):
            shutil.copy(mosaic_run / name, out / name)
        WebDriverWait(browser, 20, poll_frequency=0.05).until(
            lambda d: len(d.find_elements(By.CSS_SELECTOR, "path.seqat-camera")) == n_images)
        wait.until(lambda d: d.find_element(By.ID, "state").text == "finished")
        assert browser.execute_script("return window.seqatNotReloaded === true;")


def test_page_shows_live_estimates_ellipses_and_stop_criterion(browser: Any,
                                                               live_run: Path) -> None:
    """A live watch's ``live/estimates.json``: cameras at their estimates with error
    ellipses and footprints, tie points and coverage coloured by the stop criterion, which
    the page's field changes."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    with serving(live_run) as served:
        browser.get(served.url)
        wait = WebDriverWait(browser, 20)
        for css in ("path.seqat-camera-live", "path.seqat-ellipse", "path.seqat-footprint"):
            wait.until(lambda d, css=css: len(d.find_elements(By.CSS_SELECTOR, css)) == 6)
        assert browser.find_element(By.ID, "cameras_position").text == "live estimates"
        assert browser.find_element(By.ID, "lat_at").text == "8 ms"
        _check_quicklooks(browser, wait, 6)
        assert "points" in browser.find_element(By.ID, "stop").text
        # the coverage comes from its own request (/coverage.geojson)
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "path.seqat-cell-todo"),
                   "no coverage cell drawn")
        field = browser.find_element(By.ID, "stop_cm")
        field.clear()
        field.send_keys("100000", Keys.ENTER)
        wait.until(lambda d: d.find_element(By.ID, "stop").text.endswith("reached"))
        wait.until(lambda d: not d.find_elements(By.CSS_SELECTOR, "path.seqat-cell-todo"))
        logs = [e for e in browser.get_log("browser") if e.get("level") == "SEVERE"]
        assert logs == []


def _check_quicklooks(browser: Any, wait: Any, n: int) -> None:
    """Each image's quick-look is placed on its footprint (the image's bounding box is the
    footprint's), and shows the picture the right way round: the source is red on its left
    half, blue on its right (conftest.quicklook_source) and the footprints' left corners are
    west (conftest.write_live_estimates), so the newest image, drawn on top, is red on the
    footprint's west side and blue on its east side."""
    import io

    from PIL import Image
    from selenium.webdriver.common.by import By

    wait.until(lambda d: len(d.find_elements(By.CSS_SELECTOR,
                                             "img.seqat-quicklook-placed")) == n)
    boxes = browser.execute_script("""
        const r = e => { const b = e.getBoundingClientRect();
                         return [b.left, b.top, b.right, b.bottom]; };
        return [Array.from(document.querySelectorAll('img.seqat-quicklook')).map(r),
                Array.from(document.querySelectorAll('path.seqat-footprint')).map(r)];""")
    for img, foot in zip(*boxes, strict=True):
        assert img == pytest.approx(foot, abs=2.0)  # pixels
    left, top, right, bottom = boxes[0][-1]
    ratio = browser.execute_script("return window.devicePixelRatio;")
    shot = Image.open(io.BytesIO(browser.get_screenshot_as_png())).convert("RGB")
    y = int((top + 0.3 * (bottom - top)) * ratio)

    def colour(fx: float) -> tuple[int, ...]:
        x = int((left + fx * (right - left)) * ratio)
        return tuple(int(v) for v in shot.getpixel((x, y)))

    west, east = colour(0.15), colour(0.85)  # under the coverage cells' 30 % tint
    assert west[0] > west[2] + 60, west
    assert east[2] > east[0] + 60, east


def test_page_reloads_only_the_tiles_a_new_revision_changed(browser: Any,
                                                            tmp_path: Path) -> None:
    """A live mosaic grows by one image while the page shows it (the map held still): the
    page reloads the tiles over the boxes the revision changed (``mosaic.changes``), at the
    new revision, and no other."""
    import time

    from selenium.webdriver.support.ui import WebDriverWait

    from pipeline.common import webtiles
    from pipeline.ortho.live_tiles import LiveTiles, seen_boxes
    from pipeline.ortho.mosaic import MosaicBuilder
    from tests.pipeline.serve.test_live_cache import COL0, CRS, ROW0, ortho

    out = tmp_path / "run"
    out.mkdir()
    (out / ".seqat-run").write_text("")
    mosaic = MosaicBuilder(out / "mosaic.tif", CRS)
    live = LiveTiles(out, mosaic, CRS)

    def add(k: int) -> None:
        result = ortho(f"img_{k}", COL0 + 150 * k, ROW0 + 40 * k, 500, 700, seed=k)
        live.touched(mosaic.add(result).tiles, result.image_id, 10.0, time.time(),
                     seen_boxes(result.raster))
        live.publish()
        assert live.wait_rendered(120)

    shown = ("return typeof mosaicShown !== 'undefined' && mosaicShown && !tiles.isLoading()"
             " ? mosaicShown.revision : null;")
    tile_urls = ("return performance.getEntriesByType('resource').map(e => e.name)"
                 ".filter(n => n.includes('/tiles/'));")
    settled = "return Object.values(tiles._tiles).every(t => t.el.complete);"
    try:
        add(0)
        add(1)
        with serving(out) as served:
            browser.get(served.url)
            browser.execute_script("performance.setResourceTimingBufferSize(10000);")
            wait = WebDriverWait(browser, 30, poll_frequency=0.05)
            rev = json.loads((out / "live" / "mosaic.json").read_text())["revision"]
            wait.until(lambda d: d.execute_script(shown) == rev)
            browser.execute_script("userMoved = true;")  # the map stays where it is
            time.sleep(0.5)
            wait.until(lambda d: d.execute_script(shown) == rev)
            before = len(browser.execute_script(tile_urls))
            on_map = browser.execute_script("return Object.keys(tiles._tiles).length;")
            add(2)
            doc = json.loads((out / "live" / "mosaic.json").read_text())
            # the page sets the changed tiles' src itself (Leaflet's isLoading() does not see
            # them) and a resource is listed once loaded: wait for the new requests to end
            wait.until(lambda d: d.execute_script(shown) == doc["revision"]
                       and d.execute_script(settled)
                       and len(d.execute_script(tile_urls)) > before,
                       "no tile was reloaded for the new revision")
            frm, to, boxes = doc["xyz"]["changes"][-1]
            assert (frm, to) == (rev, doc["revision"])
            reloaded = browser.execute_script(tile_urls)[before:]
            assert reloaded and len(reloaded) < on_map
            for url in reloaded:
                path, _, query = url.split("/tiles/", 1)[1].partition("?")
                z, x, y = (int(v) for v in path.removesuffix(".png").split("/"))
                assert query == f"v=live-{doc['revision']}"
                assert any(webtiles.reaches(b, webtiles.tile_bounds_wgs84(z, x, y))
                           for b in boxes)
            logs = [e for e in browser.get_log("browser") if e.get("level") == "SEVERE"]
            assert logs == []
    finally:
        live.stop_renderer()
