"""Task bodies of a campaign (:mod:`pipeline.campaign.job`): plain functions of files and small
values, run on any Dask worker.

Every task reads its inputs from the output folder or the flight folders (shared storage: a
worker holds nothing between tasks but caches) and publishes its outputs atomically, so a task
run twice (a worker killed after it wrote, before it reported) writes the same files again
and nothing is half written. What the driver needs back is small: image ids, tile keys,
extents, timings. The work itself is the stages' own functions: ``run_flight``,
:meth:`Orthorectifier.add_image`, :func:`pipeline.ortho.mosaic.paste_into_tile` (the step
:class:`MosaicBuilder` composes its tiles with), ``write_tiles_cog``, ``finish_ortho``,
``run_reference``, ``make_report``.

Work files (``<OUT>/.campaign-work/``, removed when the job ends):
``<flight>/orthos/<image>.npz`` the ortho raster with its off-nadir tangent (what the mosaic
composes), ``<flight>/tiles/<col>_<row>.npz`` the flight mosaic's tiles.
"""

from __future__ import annotations

import contextlib
import functools
import os
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ParamSpec, TypeVar

import numpy as np
import pyproj
import rasterio
from rasterio.windows import Window

from pipeline.common.tables import EopTable
from pipeline.flight.schema import CameraConfig
from pipeline.ortho.base import OrthoOptions, OrthoRaster
from pipeline.ortho.dsm import Dsm, DsmOptions, read_dsm
from pipeline.ortho.mosaic import (
    TILE_PX,
    MosaicResult,
    new_tile,
    paste_into_tile,
    raster_tiles,
    union_extent,
    write_tiles_cog,
)
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.ortho.raster import write_cog
from pipeline.ortho.stage import (
    MOSAIC_FILE,
    ORTHO_DIR,
    ImageOrtho,
    OrthoRunSummary,
    camera_warnings,
    choose_dsm,
    finish_ortho,
    image_files,
    read_image,
)
from seqat.errors import InputDataError, SeqatError

TileKey = tuple[int, int]
Extent = tuple[int, int, int, int]
P = ParamSpec("P")
R = TypeVar("R")


@dataclass(frozen=True)
class Refused:
    """What a task returns instead of raising when its input is bad (a :class:`SeqatError`):
    the flight is reported failed with this one line, and no worker logs a traceback."""

    message: str


def refusing(task: Callable[P, R]) -> Callable[P, R | Refused]:
    """A task body that returns :class:`Refused` for bad input (anything else raises)."""

    @functools.wraps(task)
    def body(*args: P.args, **kwargs: P.kwargs) -> R | Refused:
        try:
            return task(*args, **kwargs)
        except SeqatError as err:
            return Refused(str(err))

    return body


# --------------------------------------------------------------------------------------------
# Per flight: the run, the surface, the reference and the report
# --------------------------------------------------------------------------------------------


@refusing
def run_task(flight_dir: Path, out_dir: Path, method: str) -> int:
    """``seqat run`` of one flight (one sequential stream); the number of images adjusted."""
    from pipeline.run.runner import Method, run_flight

    return run_flight(flight_dir, out_dir, method=Method(method), progress=False).n_images


@refusing
def reference_task(out_dir: Path) -> str:
    """``seqat reference`` of one run folder; one line for the summary."""
    from pipeline.reference.stage import run_reference

    rec = run_reference(out_dir).record
    return f"{rec.n_images_adjusted} images, sigma0 {rec.sigma0:.4f}"


@refusing
def report_task(out_dir: Path) -> str:
    """``seqat report`` of one run folder; the HTML report's path."""
    from pipeline.report.stage import make_report

    files = make_report(out_dir).files
    return next((str(f) for f in files if f.suffix == ".html"), str(out_dir))


@dataclass(frozen=True, kw_only=True, eq=False)
class FlightOrtho:
    """What the ortho tasks of one flight need (from :func:`prepare_task`).

    ``surface`` is the DSM file (read once per worker) or the flat fallback plane itself (a
    few cells: shipped with the task); ``pixel_m`` the GSD of its first image (what
    ``seqat ortho`` would fix), before the campaign fixes one for all flights.
    """

    name: str
    run_dir: Path
    crs: pyproj.CRS
    camera: CameraConfig
    eops: EopTable
    files: dict[str, Path]
    surface: Path | Dsm
    dsm_source: str
    eop_source: str
    pixel_m: float
    warnings: tuple[str, ...]


@refusing
def prepare_task(name: str, run_dir: Path, dsm_options: DsmOptions | None) -> FlightOrtho:
    """The run's EOPs, image files and surface (the flight's LiDAR gridded into
    ``dsm.tif`` here when there is none yet), as ``seqat ortho`` chooses them."""
    from pipeline.run.store import read_run

    run = read_run(run_dir)
    if run.images_dir is None:
        raise InputDataError(f"{run_dir}: the flight has no images (observations only); "
                             "nothing to orthorectify")
    files = image_files(run.images_dir)
    dsm, warnings = choose_dsm(run_dir, run.crs, None, run.flight_dir, run.eop,
                               run.points.xyz_m[:, 2], dsm_options)
    surface: Path | Dsm = Path(dsm.source) if Path(dsm.source).is_file() else dsm
    pixel_m = float("nan")
    with Orthorectifier(dsm, run.camera, run.crs, None, OrthoOptions(threads=1)) as ortho:
        for image_id, eop in zip(run.eop.image_ids, run.eop.eop, strict=True):
            with contextlib.suppress(InputDataError):
                pixel_m = ortho.auto_pixel_m(image_id, eop)
                break
    return FlightOrtho(name=name, run_dir=run_dir, crs=run.crs, camera=run.camera,
                       eops=run.eop, files=files, surface=surface, dsm_source=dsm.source,
                       eop_source=run.method, pixel_m=pixel_m,
                       warnings=(*warnings, *camera_warnings(run.inputs.camera_approximate)))


# --------------------------------------------------------------------------------------------
# Per image: the ortho
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class OrthoDone:
    """One image's ortho task: its ``ortho.json`` line, footprint, the mosaic tiles it
    reaches and the work file of its raster (None: skipped, ``error`` says why)."""

    image_id: str
    record: ImageOrtho | None
    footprint_m: np.ndarray | None
    tiles: tuple[TileKey, ...]
    raster_file: Path | None
    error: str | None = None


_local = threading.local()  # per worker thread: Orthorectifiers and DSMs (not thread-safe)


def _orthorectifier(flight: FlightOrtho, options: OrthoOptions) -> Orthorectifier:
    cache: dict[tuple[object, ...], Orthorectifier] = _local.__dict__.setdefault("ortho", {})
    key = (str(flight.run_dir), str(flight.surface) if isinstance(flight.surface, Path)
           else id(flight.surface), options)
    ortho = cache.get(key)
    if ortho is None:
        while len(cache) >= 2:  # noqa: PLR2004 - a worker serves one or two flights at a time
            cache.pop(next(iter(cache))).close()
        dsm = (read_dsm(flight.surface, flight.crs) if isinstance(flight.surface, Path)
               else flight.surface)
        ortho = cache[key] = Orthorectifier(dsm, flight.camera, flight.crs,
                                            flight.run_dir / ORTHO_DIR, options)
    return ortho


@refusing
def ortho_task(flight: FlightOrtho, image_id: str, options: OrthoOptions,
               work_dir: Path) -> OrthoDone:
    """Orthorectify one image: ``ortho/<image>.tif`` and the raster's work file (both
    atomic); an image that cannot be orthorectified is skipped with the reason, as in
    ``seqat ortho``."""
    path = flight.files.get(image_id)
    if path is None:
        return OrthoDone(image_id=image_id, record=None, footprint_m=None, tiles=(),
                         raster_file=None, error=f"no image {image_id}.jpg")
    eop = flight.eops.eop[flight.eops.image_ids.index(image_id)]
    try:
        t0 = time.perf_counter()
        rgb = read_image(path)
        read_ms = (time.perf_counter() - t0) * 1e3
        result = _orthorectifier(flight, options).add_image(image_id, rgb, eop)
    except InputDataError as err:
        return OrthoDone(image_id=image_id, record=None, footprint_m=None, tiles=(),
                         raster_file=None, error=str(err))
    raster_file = work_dir / f"{image_id}.npz"
    save_raster(raster_file, result.raster)
    record = ImageOrtho(image=image_id, path=str(result.path) if result.path else None,
                        seen_cells=result.seen_cells, occluded_cells=result.occluded_cells,
                        compute_ms=result.compute_ms, write_ms=result.write_ms, mosaic_ms=0.0,
                        warnings=result.warnings, read_ms=read_ms)
    return OrthoDone(image_id=image_id, record=record, footprint_m=result.footprint_m,
                     tiles=raster_tiles(result.raster), raster_file=raster_file)


def save_raster(path: Path, raster: OrthoRaster) -> None:
    """An ortho raster as an ``.npz`` work file, atomically."""
    meta = np.array([raster.col0, raster.row0, raster.pixel_m, raster.height_agl_m])
    _atomic_npz(path, meta=meta, image_id=np.array(raster.image_id), pixels=raster.pixels,
                seen=raster.seen, off_nadir=raster.off_nadir)


def load_raster(path: Path) -> OrthoRaster:
    with np.load(path) as npz:
        col0, row0, pixel_m, height = npz["meta"]
        return OrthoRaster(image_id=str(npz["image_id"]), col0=int(col0), row0=int(row0),
                           pixel_m=float(pixel_m), pixels=npz["pixels"], seen=npz["seen"],
                           off_nadir=npz["off_nadir"], height_agl_m=float(height))


def _atomic_npz(path: Path, **arrays: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            np.savez(handle, **arrays)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


# --------------------------------------------------------------------------------------------
# Per tile: the mosaic
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class TileDone:
    """One composed tile: its extent (global ``row0, row1, col0, col1``; None: nothing seen)
    and its file (``.npz`` work file or per-tile COG)."""

    key: TileKey
    extent: Extent | None
    path: Path | None
    images: int = 0


def compose_tile(key: TileKey, raster_files: Sequence[Path], feather_px: int) -> (
        tuple[np.ndarray, np.ndarray, Extent | None]):
    """Compose one tile from the orthos touching it, in the order given (acquisition order,
    flights in campaign order): :func:`paste_into_tile`, as :class:`MosaicBuilder` does."""
    tile = None
    extent: Extent | None = None
    for path in raster_files:
        raster = load_raster(path)
        if tile is None:
            tile = new_tile(raster.pixels.shape[2], raster.pixels.dtype)
        pasted = paste_into_tile(tile, key, raster, feather_px)
        if pasted is not None:
            extent = pasted[1] if extent is None else union_extent(extent, pasted[1])
    if tile is None:
        raise InputDataError(f"tile {key}: no ortho to compose")
    return tile.colour, tile.alpha, extent


@refusing
def flight_tile_task(key: TileKey, raster_files: Sequence[Path], feather_px: int,
                     work_dir: Path) -> TileDone:
    """A flight mosaic's tile as a work file (``<col>_<row>.npz``)."""
    colour, alpha, extent = compose_tile(key, raster_files, feather_px)
    path = work_dir / f"{key[0]}_{key[1]}.npz"
    if extent is not None:
        _atomic_npz(path, colour=colour, alpha=alpha)
    return TileDone(key=key, extent=extent, path=path if extent else None,
                    images=len(raster_files))


@refusing
def campaign_tile_task(key: TileKey, raster_files: Sequence[Path], feather_px: int,
                       tiles_dir: Path, pixel_m: float, crs: pyproj.CRS) -> TileDone:
    """A campaign mosaic's tile as a COG (``tiles/<col>_<row>.tif``, cropped to its seen
    cells, alpha band): a product of its own (a GIS opens any of them)."""
    colour, alpha, extent = compose_tile(key, raster_files, feather_px)
    if extent is None:
        return TileDone(key=key, extent=None, path=None, images=len(raster_files))
    r0, r1, c0, c1 = extent
    tc, tr = key
    part = (slice(r0 - tr * TILE_PX, r1 - tr * TILE_PX), slice(c0 - tc * TILE_PX,
                                                               c1 - tc * TILE_PX))
    data = np.concatenate([np.moveaxis(colour[part], 2, 0), alpha[part][None]])
    path = write_cog(tiles_dir / f"{tc}_{tr}.tif", data,
                     transform=rasterio.transform.from_origin(c0 * pixel_m, -r0 * pixel_m,
                                                              pixel_m, pixel_m),
                     crs=crs, alpha=True)
    return TileDone(key=key, extent=extent, path=path, images=len(raster_files))


def _read_tile(done: TileDone) -> tuple[np.ndarray, np.ndarray]:
    """A tile's ``(colour, alpha)`` on the full T x T tile, from its work file or COG."""
    assert done.path is not None and done.extent is not None
    if done.path.suffix == ".npz":
        with np.load(done.path) as npz:
            return npz["colour"], npz["alpha"]
    with rasterio.open(done.path) as src:
        data = src.read()
    colour = np.zeros((TILE_PX, TILE_PX, data.shape[0] - 1), data.dtype)
    alpha = np.zeros((TILE_PX, TILE_PX), data.dtype)
    r0, r1, c0, c1 = done.extent
    tc, tr = done.key
    part = (slice(r0 - tr * TILE_PX, r1 - tr * TILE_PX), slice(c0 - tc * TILE_PX,
                                                               c1 - tc * TILE_PX))
    colour[part] = np.moveaxis(data[:-1], 0, 2)
    alpha[part] = data[-1]
    return colour, alpha


@refusing
def mosaic_task(path: Path, tiles: Sequence[TileDone], crs: pyproj.CRS, pixel_m: float,
                images: int, work_dir: Path) -> MosaicResult:
    """The campaign mosaic: :func:`write_mosaic` as a task."""
    return write_mosaic(path, tiles, crs, pixel_m, images, work_dir)


def write_mosaic(path: Path, tiles: Sequence[TileDone], crs: pyproj.CRS, pixel_m: float,
                 images: int, work_dir: Path) -> MosaicResult:
    """One mosaic COG (overviews, alpha) from composed tiles (``write_tiles_cog``, as
    :meth:`MosaicBuilder.finish`), atomically."""
    t0 = time.perf_counter()
    done = {t.key: t for t in tiles if t.extent is not None}
    if not done:
        raise InputDataError(f"{path}: no ortho was added to the mosaic")
    extents = {k: t.extent for k, t in done.items() if t.extent is not None}
    work_dir.mkdir(parents=True, exist_ok=True)
    row0, row1, col0, col1 = write_tiles_cog(path, crs, pixel_m, extents,
                                             lambda key: _read_tile(done[key]), work_dir)
    p = pixel_m
    return MosaicResult(path=path, images=images, tiles=len(done), rows=row1 - row0,
                        cols=col1 - col0, bounds=(col0 * p, -row1 * p, col1 * p, -row0 * p),
                        finish_s=time.perf_counter() - t0)


@dataclass(frozen=True, kw_only=True)
class FlightMosaic:
    """What the flight's finish task needs besides its tiles."""

    flight: FlightOrtho
    done: tuple[OrthoDone, ...]
    pixel_m: float
    elapsed_s: float = 0.0  # ortho time before the finish task (the driver's clock)


@refusing
def finish_flight_task(job: FlightMosaic, tiles: Sequence[TileDone],
                       work_dir: Path) -> OrthoRunSummary:
    """The flight's ``mosaic.tif`` from its tiles, then ``cameras.gpkg`` and ``ortho.json``
    (``finish_ortho``, as ``seqat ortho``)."""
    from pipeline.run.store import read_run

    flight = job.flight
    ok = [d for d in job.done if d.record is not None]
    mosaic = write_mosaic(flight.run_dir / MOSAIC_FILE, tiles, flight.crs, job.pixel_m,
                         len(ok), work_dir)
    run = read_run(flight.run_dir)
    warnings = [*flight.warnings]
    for d in job.done:
        if d.record is None:
            warnings.append(f"skipped: {d.error}")
        else:
            warnings.extend(d.record.warnings)
    return finish_ortho(flight.run_dir, mosaic, [d.record for d in ok if d.record is not None],
                        crs=flight.crs, out_crs=None, eops=flight.eops, points=run.points,
                        footprints={d.image_id: d.footprint_m for d in ok
                                    if d.footprint_m is not None},
                        eop_source=flight.eop_source, dsm_source=flight.dsm_source,
                        pixel_m=job.pixel_m, skipped=[d.image_id for d in job.done
                                                      if d.record is None],
                        warnings=warnings, t0=time.perf_counter() - job.elapsed_s)


def read_cog_pixels(path: Path) -> tuple[np.ndarray, tuple[float, ...]]:
    """A raster's bands and geotransform (for comparisons: the benchmark and the tests)."""
    with rasterio.open(path) as src:
        return src.read(window=Window(0, 0, src.width, src.height)), tuple(src.transform)[:6]

