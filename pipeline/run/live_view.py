"""``OUT/live/estimates.json``: the current estimates of a live run, for ``seqat serve``.

A run publishes its EOPs and ground points only at the end (``eop.csv``, ``points.csv``); the
journal holds each frame as the estimator received it, not what it made of it. During a
``seqat watch`` :class:`LiveEstimates` (an image listener) keeps, after every update, the
estimates of the window (``window_solution()``: O(window)) — every camera and ground point
at its latest estimate with its a posteriori σ, departed ones as they left the window; not
the points off the surface of the others (:func:`seqat.surface.off_surface_points`, tested
by the writer at every write, as the run's end leaves them out) — and a
writer thread replaces ``OUT/live/estimates.json`` atomically with them (docs/formats.md,
*Live run files*), at most every ``min_interval_s`` and always with the latest state, so the
AT loop only copies a window's worth of numbers per image and never waits for a write.

Each camera carries the wall-clock time of its first estimate (``at_unix_s``: the AT update
that georeferenced it) and its footprint on the plane at the median height of the window's
ground points (the four image corners' rays; the camera's distortion is ignored).

Given the image files, the writer also makes each georeferenced image's *quick-look*
(``OUT/live/quicklook/<n>.jpg``: the image at most :data:`QUICKLOOK_PX` pixels wide, ``n``
its position in the run) before the first ``estimates.json`` that names it, so the page can
show the image itself on its footprint as soon as it shows its camera, long before the
orthorectified mosaic has it (docs/formats.md, *Live run files*).
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.common import jsonio
from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import LIVE_DIR, LIVE_ESTIMATES_FILE, LIVE_QUICKLOOK_DIR
from seqat.geometry import rays_world
from seqat.surface import off_surface_points
from seqat.types import FloatArray, Frame, ImageUpdate, PinholeCamera, Solution

#: ``format`` of ``estimates.json``.
ESTIMATES_FORMAT = "seqat-live-estimates"
#: Default shortest time between two writes, seconds.
MIN_INTERVAL_S = 0.2
#: Quick-looks: at most this many pixels wide and high (the aspect ratio kept), JPEG quality.
QUICKLOOK_PX = 512
QUICKLOOK_JPEG_QUALITY = 80
#: OpenCV's reduced decoding (a JPEG decoded at 1/2, 1/4, 1/8 of its size: much less work).
_REDUCED = ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
            (2, cv2.IMREAD_REDUCED_COLOR_2))


def _round(values: FloatArray, digits: int) -> list[object]:
    """Rounded JSON numbers as nested lists of ``values``' shape; NaN/inf as null."""
    a = np.round(np.asarray(values, dtype=np.float64), digits)
    finite = np.isfinite(a)
    if finite.all():
        return a.tolist()  # type: ignore[no-any-return]
    return np.where(finite, a, None).tolist()  # type: ignore[no-any-return]


def footprint(eop: FloatArray, camera: PinholeCamera, ground_z_m: float) -> FloatArray | None:
    """The image corners' rays on the plane ``Z = ground_z_m``: (4, 2), or None when a corner
    ray does not point below the horizon or the camera is not above the plane."""
    w, h = camera.width_px, camera.height_px
    uv = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    eops = np.repeat(np.asarray(eop, dtype=np.float64)[None, :], 4, axis=0)
    rays = rays_world(eops, uv, camera)
    height = float(eop[2]) - ground_z_m
    if not height > 0 or np.any(rays[:, 2] > -0.05):
        return None
    scale = height / -rays[:, 2]
    return np.asarray(eop[:2], dtype=np.float64) + rays[:, :2] * scale[:, None]


def quicklook_name(n: int) -> str:
    """File name of the quick-look of the run's ``n``-th image (0-based), in
    ``live/quicklook/``."""
    return f"{n}.jpg"


def write_quicklook(image: Path, out: Path, width_px: int, max_px: int = QUICKLOOK_PX) -> bool:
    """Write a JPEG of ``image`` at most ``max_px`` wide and high to ``out`` (replaced
    atomically); ``width_px``: the image's width, for OpenCV's reduced decoding. False (and
    nothing written) when the file cannot be read as an image."""
    flag = cv2.IMREAD_COLOR
    for factor, reduced in _REDUCED:
        if width_px // factor >= max_px:
            flag = reduced
            break
    try:
        data = np.fromfile(image, dtype=np.uint8)
    except OSError:
        return False
    pixels = cv2.imdecode(data, flag) if data.size else None
    if pixels is None or pixels.size == 0:
        return False
    h, w = pixels.shape[:2]
    scale = min(1.0, max_px / max(h, w))
    if scale < 1.0:
        pixels = cv2.resize(pixels, (max(1, round(w * scale)), max(1, round(h * scale))),
                            interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, QUICKLOOK_JPEG_QUALITY])
    if not ok:
        return False
    # a preview: atomic (never seen half-written) but not fsynced
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(jpeg.tobytes())
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return True


@dataclass(kw_only=True, eq=False)
class _Camera:
    eop: FloatArray
    sigma: FloatArray
    at_unix_s: float
    footprint: FloatArray | None


class LiveEstimates:
    """Image listener writing ``OUT/live/estimates.json`` (module docstring).

    Parameters
    ----------
    out_dir : Path
        The run folder.
    crs_wkt : str
        The working CRS (the server turns positions into WGS 84).
    camera : PinholeCamera
        For the footprints.
    stop_sigma_m : float or None
        The user's stop criterion (every ground point σ ≤ this), recorded for the page.
    min_interval_s : float
    images : Mapping[str, Path], optional
        Image file per image id (a watch fills it as images arrive): a quick-look of each
        georeferenced image is written (module docstring). None: no quick-looks.
    """

    def __init__(self, out_dir: Path | str, *, crs_wkt: str, camera: PinholeCamera,
                 stop_sigma_m: float | None = None,
                 min_interval_s: float = MIN_INTERVAL_S,
                 images: Mapping[str, Path] | None = None) -> None:
        self.path = Path(out_dir) / LIVE_DIR / LIVE_ESTIMATES_FILE
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.images = images
        self._quicklooks: dict[str, str | None] = {}  # image -> file in live/ (None: none)
        #: image -> (its _Camera, its rounded row): departed cameras do not change, so only the
        #: window's are rounded again (the writer holds the GIL: O(window), not O(flight))
        self._rows: dict[str, tuple[_Camera, dict[str, object]]] = {}
        if images is not None:
            (self.path.parent / LIVE_QUICKLOOK_DIR).mkdir(exist_ok=True)
        self.crs_wkt = crs_wkt
        self.camera = camera
        self.stop_sigma_m = stop_sigma_m
        self.min_interval_s = min_interval_s
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._cameras: dict[str, _Camera] = {}
        self._order: list[str] = []
        self._window: set[str] = set()
        self._points: dict[str, tuple[FloatArray, FloatArray, int]] = {}
        self._sigma0: float | None = None
        self._stage: str | None = None
        self._latency: dict[str, float | None] = {}
        self._version = 0
        self._written = 0
        self._closed = False
        self.write_ms: list[float] = []
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._writer, name="live-estimates",
                                         daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ ImageListener
    def on_image(self, frame: Frame, update: ImageUpdate, estimator: object) -> None:
        """Keep the window's estimates after this update (AT loop: O(window))."""
        now = time.time()
        window = getattr(estimator, "window_solution", None)
        solution: Solution | None = window() if window is not None else None
        eops = list(solution.eops) if solution is not None else [update.eop]
        points = solution.points if solution is not None else ()
        ground_z = (float(np.median([p.xyz_m[2] for p in points])) if points else math.nan)
        with self._lock:
            for e in eops:
                old = self._cameras.get(e.image_id)
                fp = footprint(e.eop, self.camera, ground_z) if math.isfinite(ground_z) else (
                    None if old is None else old.footprint)
                if old is None:
                    self._order.append(e.image_id)
                self._cameras[e.image_id] = _Camera(
                    eop=np.array(e.eop, dtype=np.float64), sigma=np.array(e.sigma, np.float64),
                    at_unix_s=now if old is None else old.at_unix_s, footprint=fp)
            self._window = {e.image_id for e in eops}
            for p in points:
                self._points[p.point_id] = (np.array(p.xyz_m, np.float64),
                                            np.array(p.sigma_m, np.float64), int(p.n_obs))
            for pid in getattr(solution, "withheld", ()):
                self._points.pop(pid, None)  # shown before its rays came to disagree
            self._sigma0 = float(update.sigma0) if math.isfinite(update.sigma0) else None
            self._stage = update.stage

    def on_live(self, live: object) -> None:
        """The image's timings (``ImageLive``, after the journal record): publish."""
        with self._lock:
            self._latency = {k: getattr(live, k, None) for k in (
                "prep_ms", "update_ms", "processing_ms", "latency_ms")}
            self._latency["image"] = getattr(live, "image", None)  # type: ignore[assignment]
            self._version += 1
            self._wake.notify()

    def on_finish(self, solution: Solution) -> None:
        """Write the last state and stop the writer."""
        self.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._wake.notify()
        self._thread.join(30)

    # ------------------------------------------------------------------ writer
    def _writer(self) -> None:
        last = 0.0
        while True:
            with self._lock:
                while self._version == self._written and not self._closed:
                    self._wake.wait()
                if self._version == self._written and self._closed:
                    return
            wait = last + self.min_interval_s - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            try:
                t0 = time.perf_counter()
                with self._lock:  # a shallow copy: entries are replaced, never changed
                    version = self._version
                    state = (list(self._order), dict(self._cameras), set(self._window),
                             dict(self._points), self._sigma0, self._stage,
                             dict(self._latency))
                self._write_quicklooks(state[0])
                doc = self._document(*state)
                atomic_write_text(self.path, jsonio.dumps(doc))
                self.write_ms.append((time.perf_counter() - t0) * 1e3)
            except BaseException as err:  # noqa: BLE001 - kept; the run goes on without it
                self._error = err
                return
            finally:
                last = time.monotonic()
            with self._lock:
                self._written = version

    def _write_quicklooks(self, order: list[str]) -> None:
        """Writer: the quick-look of every image that has none yet (module docstring)."""
        if self.images is None:
            return
        for n, image in enumerate(order):
            if image in self._quicklooks:
                continue
            path = self.images.get(image)
            name = f"{LIVE_QUICKLOOK_DIR}/{quicklook_name(n)}"
            ok = path is not None and write_quicklook(
                Path(path), self.path.parent / name, self.camera.width_px)
            self._quicklooks[image] = name if ok else None

    def _document(self, order: list[str], cameras: dict[str, _Camera], window: set[str],
                  points: dict[str, tuple[FloatArray, FloatArray, int]], sigma0: float | None,
                  stage: str | None, latency: dict[str, float | None]) -> dict[str, object]:
        """The file's contents: plain lists, one row per camera / point."""
        cams = []
        for image in order:
            c = cameras[image]
            cached = self._rows.get(image)
            if cached is None or cached[0] is not c:  # entries are replaced, never changed
                row = {
                    "image": image, "eop": _round(c.eop[:3], 4) + _round(c.eop[3:], 8),
                    "sigma": _round(c.sigma[:3], 5) + _round(c.sigma[3:], 8),
                    "in_window": None, "at_unix_s": round(c.at_unix_s, 3),
                    "footprint": None if c.footprint is None else _round(c.footprint, 2),
                    "quicklook": None}
                self._rows[image] = cached = (c, row)
            row = cached[1]
            row["in_window"] = image in window
            row["quicklook"] = self._quicklooks.get(image)
            cams.append(row)
        ids = list(points)
        xyz = np.array([points[i][0] for i in ids]).reshape(-1, 3)
        sig = np.array([points[i][1] for i in ids]).reshape(-1, 3)
        off = off_surface_points(xyz, sig[:, 2])  # not shown: as the run will not publish them
        if off.size:
            keep = np.ones(len(ids), dtype=bool)
            keep[off] = False
            ids, xyz, sig = [i for i, k in zip(ids, keep, strict=True) if k], xyz[keep], sig[keep]
        return {
            "format": ESTIMATES_FORMAT, "version": 1, "updated_unix_s": round(time.time(), 3),
            "crs": self.crs_wkt, "images": len(order), "stage": stage,
            "sigma0": sigma0, "stop_sigma_m": self.stop_sigma_m, "last": latency,
            "cameras": cams,
            "points": {"point": ids, "xyz_m": _round(xyz, 4), "sigma_m": _round(sig, 5),
                       "n_obs": [points[i][2] for i in ids]}}


def is_estimates(doc: Mapping[str, object]) -> bool:
    """``doc`` looks like an ``estimates.json`` of this version."""
    return doc.get("format") == ESTIMATES_FORMAT and doc.get("version") == 1
