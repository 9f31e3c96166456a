"""Live orthorectification of ``seqat run --ortho``: each image as soon as it is georeferenced.

:class:`LiveOrtho` is an :class:`pipeline.run.runner.ImageListener`. After each AT update it hands
the image and its EOP of that moment (``update.eop``) to one worker thread, which reads the
image, orthorectifies it (:class:`pipeline.ortho.orthorectifier.Orthorectifier`) and
pastes it into the tiles of the growing mosaic it touches (:class:`pipeline.ortho.mosaic.
MosaicBuilder`), while the runner goes on with the next image's tracking and update. At the
end (``on_finish``, with the final solution):

1. **Re-ortho rule.** An image is orthorectified again, with its final EOP, when that EOP
   moves its footprint by more than ``reortho_shift_px`` ortho pixels (default 0.5): the
   largest horizontal displacement of the ground points of the image's corners and centre on
   the plane at the DSM height under the camera
   (:meth:`pipeline.ortho.orthorectifier.Orthorectifier.footprint_shift_m`). Below that the live
   ortho differs from a new one by less than half a pixel and is kept. Images that could not be
   orthorectified live are tried again with their final EOP.
2. **Mosaic.** The tiles a re-orthorectified image touches (with its live and its final EOP)
   are emptied and recomposed from every image touching them, in acquisition order (images
   kept with their live EOP are orthorectified again for this, which writes their COG),
   so the mosaic is the one a post-run ``seqat ortho`` builds from the EOPs each image was
   kept with. With no image re-orthorectified the live mosaic is final as it is.
3. **Per-image COGs** ``ortho/<image>.tif`` are written now, each once, with the EOP its
   image is kept with (the live one or the final one): written live, nine in ten were
   written again here (the 196-image block), and a COG costs more CPU than its ortho.
4. The mosaic COG, ``cameras.gpkg`` (final EOPs) and ``ortho.json`` are written as
   :func:`pipeline.ortho.stage.orthorectify_run` writes them (:func:`pipeline.ortho.stage.
   finish_ortho`), with the live statistics (``live``).

Surface, chosen at the start by the rules of ``seqat ortho`` (:func:`pipeline.ortho.stage.
find_dsm`: ``--dsm``, ``OUT/dsm.tif``, the flight's ``lidar:``). Without one the fallback is
a flat plane at the median height of the estimator's ground points after the first update
that has any (Seq-R: the initial simultaneous window), under the whole nav's footprint;
images georeferenced before that wait for it, and the plane stays for the whole flight.

Errors: an image that cannot be orthorectified is skipped with a warning (as in ``seqat
ortho``). A :class:`~seqat.errors.SeqatError` at the end (no image could be orthorectified)
does not stop the run from publishing its results: :meth:`LiveOrtho.result` raises it
afterwards. Any other error of the worker stops the run at the next image.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pyproj

from pipeline.common.priority import MAX_NICE, lower_thread_priority
from pipeline.common.strict_yaml import build_dataclass
from pipeline.common.tables import NavTable
from pipeline.flight.folder import Flight, read_flight
from pipeline.flight.schema import CameraConfig
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.dsm import Dsm, DsmOptions
from pipeline.ortho.live_tiles import LiveTiles, seen_boxes
from pipeline.ortho.mosaic import FEATHER_PX, MosaicBuilder, tiles_of_bounds
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.ortho.stage import (
    MOSAIC_FILE,
    ORTHO_DIR,
    ImageOrtho,
    LiveOrthoStats,
    OrthoRunSummary,
    camera_warnings,
    find_dsm,
    finish_ortho,
    flat_plane,
    load_sections,
    ortho_image,
    ortho_mosaic_options,
    parse_out_crs,
)
from pipeline.run.store import TimingStats, eop_table, point_table
from seqat.errors import ConfigError, InputDataError, SeqatError
from seqat.types import FloatArray, Frame, ImageUpdate, Solution

#: Default of the re-ortho rule, ortho pixels.
REORTHO_SHIFT_PX = 0.5
#: Longest time between two publications of the live mosaic while the worker is behind, s.
PUBLISH_INTERVAL_S = 1.0
#: ``seqat watch``: the flat fallback plane reaches this far beyond the cameras known when it
#: is placed (the flight's extent is not known ahead), metres.
WATCH_FLAT_MARGIN_M = 10_000.0
#: Niceness of the ortho worker thread relative to the AT loop (Linux ``setpriority``).
WORKER_NICE = 10


@dataclass(frozen=True, kw_only=True)
class LiveOrthoOptions:
    """Options of the live ortho.

    Attributes
    ----------
    reortho_shift_px : float
        Orthorectify an image again at the end when its final EOP moves its footprint by
        more than this many ortho pixels (0: whenever it moves at all).
    background : bool
        Orthorectify on a worker thread (the AT loop only hands the image over); False: in
        the AT loop, before the next image.
    worker_nice : int
        The worker thread runs this much nicer than the AT loop (Linux: per-thread priority,
        inherited by the threads it starts: the projection pool, the COG writer and GDAL's
        compression threads), so the two cores go to tracking and AT first. 0: same priority.
    publish : bool
        Publish the mosaic's tiles while the run goes on (``OUT/live/``,
        :mod:`pipeline.ortho.live_tiles`; ``seqat watch --ortho`` turns it on): after each image
        when the worker has caught up, else at least every ``publish_interval_s``.
    publish_interval_s : float
    """

    reortho_shift_px: float = REORTHO_SHIFT_PX
    background: bool = True
    worker_nice: int = WORKER_NICE
    publish: bool = False
    publish_interval_s: float = PUBLISH_INTERVAL_S

    def __post_init__(self) -> None:
        if not (math.isfinite(self.reortho_shift_px) and self.reortho_shift_px >= 0):
            raise ConfigError(f"reortho_shift_px: expected a number >= 0, got "
                              f"{self.reortho_shift_px!r}")
        if not (math.isfinite(self.publish_interval_s) and self.publish_interval_s > 0):
            raise ConfigError(f"publish_interval_s: expected a number > 0, got "
                              f"{self.publish_interval_s!r}")
        if not 0 <= self.worker_nice <= MAX_NICE:
            raise ConfigError(f"worker_nice: expected 0 to {MAX_NICE}, got {self.worker_nice!r}")


@dataclass(kw_only=True, eq=False)
class _Kept:
    """What the live ortho keeps of one image (never its pixels)."""

    eop: FloatArray  # the EOP its ortho was made with
    tiles: frozenset[tuple[int, int]]
    record: ImageOrtho
    footprint_m: FloatArray


#: Make the calling thread ``nice`` steps nicer (the worker's initializer).
_lower_priority = lower_thread_priority


class LiveOrtho:
    """Image listener of ``seqat run --ortho`` (module docstring).

    Parameters
    ----------
    out_dir : Path
        The run's output folder (``ortho/``, ``mosaic.tif``, ``cameras.gpkg``, ``ortho.json``).
    crs : pyproj.CRS
        Working CRS.
    camera : CameraConfig
        Camera of the images (with distortion).
    images : Mapping[str, Path]
        Image file per image id.
    nav : NavTable
        The flight's nav (bounds of a flat fallback plane).
    dsm : Dsm or None
        The surface; None: the flat fallback, placed after the first update with ground points.
    dsm_warnings : tuple[str, ...]
    ortho_options : OrthoOptions, optional
    feather_px : int
    out_crs : str, optional
        As ``seqat ortho --crs``.
    options : LiveOrthoOptions, optional
    camera_approximate : bool
        The camera comes from EXIF (a warning in ``ortho.json``).
    """

    def __init__(self, out_dir: Path | str, *, crs: pyproj.CRS, camera: CameraConfig,
                 images: Mapping[str, Path], nav: NavTable, dsm: Dsm | None,
                 dsm_warnings: tuple[str, ...] = (), ortho_options: OrthoOptions | None = None,
                 feather_px: int = FEATHER_PX, out_crs: str | None = None,
                 options: LiveOrthoOptions | None = None,
                 camera_approximate: bool = False) -> None:
        self.t0 = time.perf_counter()
        self.out_dir = Path(out_dir)
        self.crs = crs
        self.camera = camera
        self.images = images  # not copied: a watch adds images as they arrive
        self.nav = nav
        self.options = options or LiveOrthoOptions()
        self._ortho_options = ortho_options
        self._out_crs = parse_out_crs(out_crs)
        self._mosaic = MosaicBuilder(self.out_dir / MOSAIC_FILE, crs, feather_px=feather_px)
        self._ortho: Orthorectifier | None = None
        self._dsm_source = ""
        self._warnings: list[str] = list(dsm_warnings) + list(camera_warnings(
            camera_approximate))
        self._surface_from: str | None = None
        if dsm is not None:
            self._start(dsm)
        self._waiting: list[tuple[str, FloatArray, float]] = []  # before the flat plane
        self._kept: dict[str, _Kept] = {}
        self._skipped: dict[str, str] = {}  # image -> warning
        self._listener_ms: list[float] = []
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="live-ortho",
                                          initializer=_lower_priority,
                                          initargs=(self.options.worker_nice,))
        self._futures: list[Future[None]] = []
        self._lock = threading.Lock()
        self._queued = 0  # images handed over and not yet done
        self._flat_margin_m = 0.0
        self._live_tiles = (LiveTiles(self.out_dir, self._mosaic, crs)
                            if self.options.publish else None)
        self._worker_error: BaseException | None = None
        self._error: SeqatError | None = None
        self._summary: OrthoRunSummary | None = None

    @classmethod
    def for_flight(cls, flight_dir: Path | str, out_dir: Path | str, *,
                   dsm_path: Path | str | None = None, ortho_options: OrthoOptions | None = None,
                   feather_px: int = FEATHER_PX, out_crs: str | None = None,
                   options: LiveOrthoOptions | None = None,
                   dsm_options: DsmOptions | None = None) -> LiveOrtho:
        """The live ortho of a flight folder, its surface chosen now (the flight's LiDAR
        gridded with ``dsm_options``).

        Raises
        ------
        InputDataError
            Not an image flight, a bad DSM or LiDAR.
        """
        flight = read_flight(flight_dir)
        if flight.images_dir is None:
            raise InputDataError(f"{flight.path}: --ortho needs an image flight (this one has "
                                 "observations only)")
        out = Path(out_dir)
        parse_out_crs(out_crs)  # a bad --crs fails before the LiDAR is gridded
        dsm, warnings = find_dsm(out, flight.crs, Path(dsm_path) if dsm_path else None,
                                 flight.path, dsm_options)
        paths = dict(zip(flight.nav.image_ids, flight.image_paths, strict=True))
        return cls(out, crs=flight.crs, camera=flight.camera_config, images=paths,
                   nav=flight.nav, dsm=dsm, dsm_warnings=warnings, ortho_options=ortho_options,
                   feather_px=feather_px, out_crs=out_crs, options=options,
                   camera_approximate=flight.camera_approximate)

    @classmethod
    def for_watch(cls, flight: Flight, out_dir: Path | str, images: Mapping[str, Path], *,
                  dsm_path: Path | str | None = None, ortho_options: OrthoOptions | None = None,
                  feather_px: int = FEATHER_PX, out_crs: str | None = None,
                  options: LiveOrthoOptions | None = None,
                  dsm_options: DsmOptions | None = None) -> LiveOrtho:
        """The live ortho of ``seqat watch --ortho``: made when the first image fixes the CRS
        and camera; ``images`` grows as images arrive; the live mosaic is published
        (``options.publish`` on). Without a DSM the flat plane reaches
        :data:`WATCH_FLAT_MARGIN_M` beyond the cameras known when it is placed.

        Raises
        ------
        InputDataError
            Not an image flight, a bad DSM or LiDAR.
        """
        if flight.images_dir is None:
            raise InputDataError(f"{flight.path}: --ortho needs an image flight (this one has "
                                 "observations only)")
        out = Path(out_dir)
        dsm, warnings = find_dsm(out, flight.crs, Path(dsm_path) if dsm_path else None,
                                 flight.path, dsm_options)
        live = cls(out, crs=flight.crs, camera=flight.camera_config, images=images,
                   nav=flight.nav, dsm=dsm, dsm_warnings=warnings,
                   ortho_options=ortho_options, feather_px=feather_px, out_crs=out_crs,
                   options=replace(options or LiveOrthoOptions(), publish=True),
                   camera_approximate=flight.camera_approximate)
        live._flat_margin_m = WATCH_FLAT_MARGIN_M
        return live

    # ------------------------------------------------------------------ ImageListener

    def on_image(self, frame: Frame, update: ImageUpdate, estimator: object) -> None:
        """Hand the image to the ortho worker with its EOP of this update."""
        t_submit = time.perf_counter()
        self._raise_worker_error()
        eop = np.array(update.eop.eop, dtype=np.float64)
        if self._ortho is None:
            self._waiting.append((frame.image_id, eop, t_submit))
            if update.n_points_total > 0:
                self._start_flat(frame.image_id, estimator)
                for waiting in self._waiting:
                    self._submit(*waiting)
                self._waiting.clear()
        else:
            self._submit(frame.image_id, eop, t_submit)
        self._listener_ms.append((time.perf_counter() - t_submit) * 1e3)

    def on_finish(self, solution: Solution) -> None:
        """Re-orthorectify what moved, finish the mosaic, write ``cameras.gpkg`` and
        ``ortho.json`` (module docstring). A SeqatError is kept for :meth:`result`."""
        t0 = time.perf_counter()
        try:
            self._drain()
            if self._ortho is None:  # flat fallback, and no update had ground points
                if not solution.points:
                    raise InputDataError(f"{self.out_dir}: no DSM (--dsm, dsm.tif, flight "
                                         "lidar:) and no tie points to place a flat plane")
                self._start_flat_at(np.array([p.xyz_m[2] for p in solution.points]),
                                    "the end of the run",
                                    np.array([e.eop[:3] for e in solution.eops]))
            self._summary = self._finish(solution, t0)
        except SeqatError as err:
            self._error = err
            self._mosaic.discard()
        finally:
            self.close()

    # ------------------------------------------------------------------ results

    def result(self) -> OrthoRunSummary:
        """The summary written to ``ortho.json``.

        Raises
        ------
        SeqatError
            What stopped the live ortho at the end (the run itself was published).
        """
        if self._error is not None:
            raise self._error
        if self._summary is None:
            raise InputDataError(f"{self.out_dir}: the live ortho did not finish")
        return self._summary

    def close(self) -> None:
        """Stop the worker (pending images are dropped) and the orthorectifier's threads."""
        for future in self._futures:
            future.cancel()
        self._worker.shutdown(wait=True)
        if self._ortho is not None:
            self._ortho.close()
        if self._live_tiles is not None:
            self._live_tiles.stop_renderer(0.0)

    def __enter__(self) -> LiveOrtho:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close()
        if exc_type is not None:
            self._mosaic.discard()

    # ------------------------------------------------------------------ internals

    def _start(self, dsm: Dsm) -> None:
        self._ortho = Orthorectifier(dsm, self.camera, self.crs, self.out_dir / ORTHO_DIR,
                                     self._ortho_options)
        self._dsm_source = dsm.source

    def _start_flat(self, image_id: str, estimator: object) -> None:
        window = getattr(estimator, "window_solution", None)
        solution = window() if window is not None else estimator.solution()  # type: ignore[attr-defined]
        heights = np.array([p.xyz_m[2] for p in solution.points])
        self._start_flat_at(heights, f"image {image_id} ({len(heights)} points)",
                            np.array([e.eop[:3] for e in solution.eops]))
        self._surface_from = image_id

    def _start_flat_at(self, points_z_m: FloatArray, when: str, cameras_xyz: FloatArray,
                       ) -> None:
        """The flat plane at the median tie point height (:func:`flat_plane`) under the
        flight's nav (a watch: under ``cameras_xyz``, the cameras known now, and
        :attr:`_flat_margin_m` beyond them)."""
        xyz = self.nav.eop[:, :3] if len(self.nav.image_ids) else cameras_xyz.reshape(-1, 3)
        if self._flat_margin_m > 0:
            m = self._flat_margin_m
            lo, hi = xyz.min(axis=0), xyz.max(axis=0)
            xyz = np.vstack([xyz, [lo[0] - m, lo[1] - m, hi[2]], [hi[0] + m, hi[1] + m, hi[2]]])
        plane, warning = flat_plane(points_z_m, xyz, self.crs,
                                    f"the median height of the tie points known after {when}:")
        self._warnings.append(warning)
        self._start(plane)

    def _submit(self, image_id: str, eop: FloatArray, t_submit: float) -> None:
        with self._lock:
            self._queued += 1
        if self.options.background:
            self._futures.append(self._worker.submit(self._ortho_live, image_id, eop, t_submit))
            self._futures = [f for f in self._futures if not f.done()]
        else:
            self._ortho_live(image_id, eop, t_submit)

    def _ortho_live(self, image_id: str, eop: FloatArray, t_submit: float) -> None:
        """Worker: orthorectify one image with its live EOP and update the mosaic."""
        try:
            t_start = time.perf_counter()
            assert self._ortho is not None
            try:
                # no COG yet: most images move before the end and are written then
                # (_finish), and a COG costs more CPU than the ortho (docs/architecture.md)
                record, result, update = ortho_image(self._ortho, self._mosaic, image_id,
                                                     self.images.get(image_id), eop, write=False)
            except InputDataError as err:
                self._skipped[image_id] = f"skipped: {err}"
                return
            t_end = time.perf_counter()
            record = replace(record, eop="live", queue_ms=(t_start - t_submit) * 1e3,
                             latency_ms=(t_end - t_submit) * 1e3)
            self._kept[image_id] = _Kept(eop=eop, tiles=update.tiles, record=record,
                                         footprint_m=result.footprint_m)
            if self._live_tiles is not None:
                self._live_tiles.touched(update.tiles, image_id, record.latency_ms,
                                         time.time() - (time.perf_counter() - t_submit),
                                         seen_boxes(result.raster))
        except BaseException as err:  # re-raised in the AT loop (on_image / on_finish)
            with self._lock:
                self._worker_error = self._worker_error or err
            raise
        finally:
            with self._lock:
                self._queued -= 1
                caught_up = self._queued == 0
            if self._live_tiles is not None and self._worker_error is None:
                try:
                    self._publish(caught_up)
                except BaseException as err:  # noqa: BLE001 - re-raised in the AT loop
                    with self._lock:
                        self._worker_error = self._worker_error or err

    def _publish(self, caught_up: bool) -> None:
        """Worker: publish the live mosaic when the worker has caught up, or when the last
        publication is ``publish_interval_s`` old."""
        tiles = self._live_tiles
        assert tiles is not None
        if tiles.pending and (caught_up or time.monotonic() - tiles.last_publish
                              >= self.options.publish_interval_s):
            tiles.publish()

    def _raise_worker_error(self) -> None:
        with self._lock:
            err = self._worker_error
        if err is not None:
            raise err

    def _drain(self) -> None:
        for future in self._futures:
            future.exception()  # wait; errors are kept by the worker itself
        self._futures.clear()
        self._raise_worker_error()

    def _finish(self, solution: Solution, t0: float) -> OrthoRunSummary:
        ortho = self._ortho
        assert ortho is not None
        eops = eop_table(solution.eops)
        final = dict(zip(eops.image_ids, eops.eop, strict=True))
        pixel_m = ortho.pixel_m
        moved: dict[str, float] = {}  # image -> shift in ortho pixels (inf: not orthorectified)
        new_tiles: dict[str, frozenset[tuple[int, int]]] = {}
        affected: set[tuple[int, int]] = set()
        for image_id, eop in final.items():
            kept = self._kept.get(image_id)
            if kept is not None and pixel_m is not None:
                shift = ortho.footprint_shift_m(image_id, kept.eop, eop) / pixel_m
                self._kept[image_id].record = replace(kept.record, shift_px=shift)
                if shift <= self.options.reortho_shift_px:
                    continue
            else:
                shift = math.inf
            moved[image_id] = shift
            try:
                window = ortho.ground_window(image_id, eop)
            except InputDataError:
                new_tiles[image_id] = frozenset()  # skipped again below, with its warning
            else:
                new_tiles[image_id] = (tiles_of_bounds(window, pixel_m) if pixel_m is not None
                                       else frozenset())
            affected |= new_tiles[image_id] | (kept.tiles if kept is not None else frozenset())
        self._mosaic.clear(affected)
        frozen = frozenset(affected)
        writes = ortho.out_dir is not None and ortho.options.write_images
        for image_id, eop in final.items():
            kept = self._kept.get(image_id)
            if image_id in moved:
                self._reortho(image_id, eop, frozen, kept)
            elif kept is not None and (writes or kept.tiles & frozen):
                # its COG, with the EOP it is kept with, and its part of the frozen tiles
                try:
                    record, _, _ = ortho_image(ortho, self._mosaic, image_id,
                                               self.images.get(image_id), kept.eop, tiles=frozen)
                except InputDataError as err:  # its file went away since
                    self._skipped[image_id] = f"skipped: {err}"
                    self._kept.pop(image_id)
                    continue
                self._kept[image_id].record = replace(kept.record, path=record.path,
                                                      write_ms=record.write_ms)
        ortho.flush()  # every COG complete before the mosaic, the warp and ortho.json
        records = [self._kept[i].record for i in final if i in self._kept]
        skipped = [i for i in final if i not in self._kept]
        warnings = self._warnings + [w for k in self._kept.values() for w in k.record.warnings]
        warnings += [self._skipped[i] for i in skipped if i in self._skipped]
        if not records:
            raise InputDataError(f"{self.out_dir}: no image could be orthorectified"
                                 + (f" ({self._skipped[skipped[-1]]})" if skipped
                                    and skipped[-1] in self._skipped else ""))

        def live_stats() -> LiveOrthoStats:
            return LiveOrthoStats(
                background=self.options.background, surface_from_image=self._surface_from,
                reortho_shift_px=self.options.reortho_shift_px,
                images_reorthorectified=tuple(i for i in moved if i in self._kept),
                tiles_rebuilt=len(affected),
                listener_ms=TimingStats.from_samples(self._listener_ms),
                queue_ms=TimingStats.from_samples([r.queue_ms for r in records]),
                latency_ms=TimingStats.from_samples([r.latency_ms for r in records]),
                finish_s=time.perf_counter() - t0,
                publish_ms=None if self._live_tiles is None or not self._live_tiles.publish_ms
                else TimingStats.from_samples(self._live_tiles.publish_ms),
                publications=0 if self._live_tiles is None else len(self._live_tiles.publish_ms),
                web_tiles_ms=None if self._live_tiles is None or not self._live_tiles.web_tiles_ms
                else TimingStats.from_samples(self._live_tiles.web_tiles_ms),
                web_tiles_cpu_ms=None if self._live_tiles is None
                or not self._live_tiles.web_tiles_cpu_ms
                else TimingStats.from_samples(self._live_tiles.web_tiles_cpu_ms),
                web_tiles=0 if self._live_tiles is None else sum(self._live_tiles.web_tiles))

        if self._live_tiles is not None:
            self._live_tiles.stop_renderer()  # its last publications, for the page and stats
        summary = finish_ortho(
            self.out_dir, self._mosaic, records, crs=self.crs, out_crs=self._out_crs, eops=eops,
            points=point_table(solution.points),
            footprints={i: self._kept[i].footprint_m for i in final if i in self._kept},
            eop_source="live", dsm_source=self._dsm_source,
            pixel_m=ortho.pixel_m, skipped=skipped, warnings=warnings, t0=self.t0,
            live=live_stats)
        if self._live_tiles is not None:
            self._live_tiles.remove()  # mosaic.tif is there
        return summary

    def _reortho(self, image_id: str, eop: FloatArray, tiles: frozenset[tuple[int, int]],
                 kept: _Kept | None) -> None:
        """Orthorectify a moved image again with its final EOP (its COG too)."""
        assert self._ortho is not None
        t0 = time.perf_counter()
        try:
            record, result, update = ortho_image(self._ortho, self._mosaic, image_id,
                                                 self.images.get(image_id), eop, tiles=tiles)
        except InputDataError as err:
            self._skipped[image_id] = f"skipped: {err}"
            self._kept.pop(image_id, None)
            return
        reortho_ms = (time.perf_counter() - t0) * 1e3
        if kept is not None:  # the live timings stay (latency); the products are the new ones
            record = replace(kept.record, path=record.path, seen_cells=record.seen_cells,
                             occluded_cells=record.occluded_cells, warnings=record.warnings)
        self._kept[image_id] = _Kept(eop=eop, tiles=update.tiles, footprint_m=result.footprint_m,
                                     record=replace(record, eop="final", reortho_ms=reortho_ms))
        self._skipped.pop(image_id, None)


def _options(options_path: Path | str | None) -> tuple[
        OrthoOptions, int, LiveOrthoOptions, DsmOptions | None]:
    ortho, feather_px, live = OrthoOptions(), FEATHER_PX, LiveOrthoOptions()
    dsm_options = None
    if options_path is not None:
        doc = load_sections(options_path, ("dsm", "live", "mosaic", "ortho"))
        ortho, feather_px = ortho_mosaic_options(options_path, doc)
        live = build_dataclass(LiveOrthoOptions, doc.get("live"), str(options_path), key="live")
        dsm_options = build_dataclass(DsmOptions, doc.get("dsm"), str(options_path), key="dsm")
    return ortho, feather_px, live, dsm_options


def open_live_ortho(flight_dir: Path | str, out_dir: Path | str, *,
                    dsm_path: Path | str | None = None,
                    options_path: Path | str | None = None) -> LiveOrtho:
    """``seqat run --ortho [--dsm D] [--ortho-options FILE]``: the live ortho of a flight.

    The options file has the sections ``ortho:`` (:class:`pipeline.ortho.base.OrthoOptions`),
    ``mosaic: {feather_px: N}``, ``live:`` (:class:`LiveOrthoOptions`) and ``dsm:``
    (:class:`pipeline.ortho.dsm.DsmOptions`, for the flight's LiDAR), all optional.
    """
    ortho, feather_px, live, dsm_options = _options(options_path)
    return LiveOrtho.for_flight(flight_dir, out_dir, dsm_path=dsm_path, ortho_options=ortho,
                                feather_px=feather_px, options=live, dsm_options=dsm_options)


def watch_ortho_factory(out_dir: Path | str, *, dsm_path: Path | str | None = None,
                        options_path: Path | str | None = None) -> Callable[
                            [Flight, Mapping[str, Path]], tuple[LiveOrtho]]:
    """``seqat watch --ortho``: the options file is read now (a bad one fails before the
    watch starts), the live ortho is made at the first image (:meth:`LiveOrtho.for_watch`)."""
    ortho, feather_px, live, dsm_options = _options(options_path)

    def make(flight: Flight, images: Mapping[str, Path]) -> tuple[LiveOrtho]:
        return (LiveOrtho.for_watch(flight, out_dir, images, dsm_path=dsm_path,
                                    ortho_options=ortho, feather_px=feather_px, options=live,
                                    dsm_options=dsm_options),)

    return make
