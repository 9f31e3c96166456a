"""Stage function of ``seqat ortho``: files in, files out (``seqat dsm``:
:mod:`pipeline.ortho.dsm_stage`; both read the ``--options`` file of :func:`load_stage_options`).

:func:`orthorectify_run` reads a run folder (:func:`pipeline.run.store.read_run`), picks the EOPs
(Seq-R ``eop.csv`` or ``reference/eop.csv``) and the surface, streams every image through
:class:`pipeline.ortho.orthorectifier.Orthorectifier` and
:class:`pipeline.ortho.mosaic.MosaicBuilder` and writes

* ``OUT/ortho/<image>.tif`` — one COG per image,
* ``OUT/mosaic.tif`` — the mosaic COG,
* ``OUT/cameras.gpkg`` — camera positions with σ and OPK, footprints, tie points,
* ``OUT/ortho.json`` — the per-image timings and warnings (:class:`OrthoRunSummary`).

Surface, first found: ``--dsm``; ``OUT/dsm.tif``; the flight's ``lidar:`` (a DSM GeoTIFF is
used as is, LAS/LAZ files are gridded into ``OUT/dsm.tif``); else a flat plane at the median
height of the tie points (a wild point does not move it), with a warning.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pyproj
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import EOP_FILE, REFERENCE_DIR
from pipeline.common.paths import exists_as_anything, file_problem
from pipeline.common.strict_yaml import build_dataclass, load_yaml
from pipeline.common.tables import EopTable, PointTable
from pipeline.flight.navigation import image_files as flight_image_files
from pipeline.flight.schema import load_flight_config
from pipeline.ortho.base import OrthoOptions, OrthoResult
from pipeline.ortho.dsm import Dsm, DsmOptions, build_dsm, flat_dsm, read_dsm
from pipeline.ortho.gis_export import write_cameras_gpkg
from pipeline.ortho.mosaic import FEATHER_PX, MosaicBuilder, MosaicResult, MosaicUpdate
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.ortho.raster import reproject_cog
from pipeline.run.store import TimingStats, read_eop_csv, to_jsonable
from seqat.errors import ConfigError, InputDataError, SeqatError

#: Outputs inside a run folder.
DSM_FILE = "dsm.tif"
ORTHO_DIR = "ortho"
MOSAIC_FILE = "mosaic.tif"
CAMERAS_GPKG = "cameras.gpkg"
ORTHO_JSON = "ortho.json"
#: Image file suffixes looked for in the images folder (any case).
IMAGE_SUFFIXES = (".jpg", ".jpeg")
#: Suffixes of a DSM GeoTIFF given as the flight's ``lidar:``.
GEOTIFF_SUFFIXES = (".tif", ".tiff")
#: Cell of the flat fallback plane, metres (a plane needs no resolution).
FLAT_CELL_M = 10.0
#: Margin of the flat plane around the cameras, in flying heights.
FLAT_MARGIN_HEIGHTS = 4.0

#: ``--eop`` of ``seqat ortho``: ``run`` = the run's own ``OUT/eop.csv`` (the estimates of its
#: method, seq-r, seq-f or sim), ``reference`` = ``OUT/reference/eop.csv``; the name of the run's
#: own method is accepted for ``run`` (``--eop seq-r`` on a seq-r run, as before).
EopSource = Literal["run", "reference", "seq-r", "seq-f", "sim"]
#: The values ``--eop`` accepts.
EOP_SOURCES = ("run", "reference", "seq-r", "seq-f", "sim")


# --------------------------------------------------------------------------------------------
# Stage options (seqat dsm and seqat ortho)
# --------------------------------------------------------------------------------------------


def load_stage_options(path: Path | str | None) -> tuple[DsmOptions, OrthoOptions, int]:
    """``--options FILE``: sections ``dsm:`` (DsmOptions), ``ortho:`` (OrthoOptions) and
    ``mosaic: {feather_px: N}``; absent sections keep their defaults."""
    if path is None:
        return DsmOptions(), OrthoOptions(), FEATHER_PX
    doc = load_sections(path, ("dsm", "mosaic", "ortho"))
    dsm = build_dataclass(DsmOptions, doc.get("dsm"), str(path), key="dsm")
    ortho, feather_px = ortho_mosaic_options(path, doc)
    return dsm, ortho, feather_px


def load_sections(path: Path | str, allowed: tuple[str, ...]) -> dict[str, object]:
    """An options YAML whose top-level keys must be among ``allowed`` (sorted)."""
    doc = load_yaml(path)
    unknown = set(doc) - set(allowed)
    if unknown:
        raise ConfigError(f"{path}: {sorted(unknown)[0]}: unknown key (expected one of: "
                          f"{', '.join(allowed)})")
    return doc


def ortho_mosaic_options(path: Path | str, doc: Mapping[str, object]) -> (
        tuple[OrthoOptions, int]):
    """Sections ``ortho:`` and ``mosaic: {feather_px: N}`` of an options file."""
    ortho = build_dataclass(OrthoOptions, doc.get("ortho"), str(path), key="ortho")
    mosaic = build_dataclass(_MosaicOptions, doc.get("mosaic"), str(path), key="mosaic")
    return ortho, mosaic.feather_px


@dataclass(frozen=True, kw_only=True)
class _MosaicOptions:
    feather_px: int = FEATHER_PX


# --------------------------------------------------------------------------------------------
# seqat ortho
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class ImageOrtho:
    """One image's line in ``ortho.json``.

    ``read_ms`` is the colour decode of the image; ``compute_ms``, ``write_ms`` as in
    :class:`pipeline.ortho.base.OrthoResult`; ``mosaic_ms`` the mosaic update. Live runs
    (``seqat run --ortho``, :mod:`pipeline.ortho.live`) add ``eop`` (``live``: the ortho was
    made with the estimate at the image's own update and kept; ``final``: made again at the
    end with the final EOP), ``shift_px`` (how far the final EOP moves the footprint, ortho
    pixels), ``queue_ms`` (waiting for the ortho worker), ``latency_ms`` (from the end of
    the image's AT update to its mosaic update: queue + read + ortho + COG write wait +
    mosaic) and ``reortho_ms`` (the ortho again at the end). The timings of a live run are
    those of the live ortho; path, cells and warnings those of the final product.
    """

    image: str
    path: str | None
    seen_cells: int
    occluded_cells: int
    compute_ms: float
    write_ms: float
    mosaic_ms: float
    warnings: tuple[str, ...]
    read_ms: float = math.nan
    eop: str = "final"
    shift_px: float = math.nan
    queue_ms: float = math.nan
    latency_ms: float = math.nan
    reortho_ms: float = math.nan


@dataclass(frozen=True, kw_only=True)
class LiveOrthoStats:
    """What the live ortho of ``seqat run --ortho`` adds to ``ortho.json`` (``live``).

    Attributes
    ----------
    background : bool
        Orthorectified on a worker thread while the AT went on.
    surface_from_image : str or None
        Flat fallback only: the image after whose update the plane's height was known
        (images before it waited for it); None with a DSM, or when no update had ground
        points and the plane was placed at the end (then the warning says so).
    reortho_shift_px : float
        Rule: an image is orthorectified again at the end when its final EOP moves its
        footprint by more than this (ortho pixels).
    images_reorthorectified : tuple[str, ...]
    tiles_rebuilt : int
        Mosaic tiles recomposed because a re-orthorectified image touches them.
    listener_ms : TimingStats
        Time ``on_image`` held the AT loop per image (handing the image to the worker).
    queue_ms, latency_ms : TimingStats
        See :class:`ImageOrtho`.
    finish_s : float
        ``on_finish``: waiting for the worker, re-orthorectification, mosaic rebuild and
        the final writes (mosaic COG, ``cameras.gpkg``, ``ortho.json``).
    publish_ms : TimingStats or None
        ``seqat watch --ortho``: each publication of the live mosaic (touched tiles, the web
        tiles they changed and the index, ``OUT/live/``); None when it is not published.
    publications : int
    web_tiles_ms, web_tiles_cpu_ms : TimingStats or None
        Each rendering of the live tile cache (:mod:`pipeline.ortho.live_render`, a child
        process: one or more publications), wall and CPU time.
    web_tiles : int
        Web tiles written into the live tile cache over all publications (a tile whose
        pixels did not change is read, compared and left).
    """

    background: bool
    surface_from_image: str | None
    reortho_shift_px: float
    images_reorthorectified: tuple[str, ...]
    tiles_rebuilt: int
    listener_ms: TimingStats
    queue_ms: TimingStats
    latency_ms: TimingStats
    finish_s: float
    publish_ms: TimingStats | None = None
    publications: int = 0
    web_tiles_ms: TimingStats | None = None
    web_tiles_cpu_ms: TimingStats | None = None
    web_tiles: int = 0


@dataclass(frozen=True, kw_only=True)
class OrthoRunSummary:
    """What :func:`orthorectify_run` did (also written as ``ortho.json``)."""

    out_dir: Path
    eop_source: str
    dsm_source: str
    crs: str
    pixel_m: float
    images: tuple[ImageOrtho, ...]
    skipped: tuple[str, ...]
    compute_ms: TimingStats
    mosaic_ms: TimingStats
    mosaic: Path
    cameras_gpkg: Path
    wall_s: float
    warnings: tuple[str, ...]
    live: LiveOrthoStats | None = None


def _eops(run_dir: Path, source: str, method: str, default: EopTable) -> tuple[EopTable, str]:
    """The EOPs ``--eop`` names and how ``ortho.json`` records them (the run's method, or
    ``reference``)."""
    if source in ("run", method):
        return default, method
    if source == "reference":
        path = run_dir / REFERENCE_DIR / EOP_FILE
        if not path.is_file():
            raise InputDataError(f"{path}: no such file (run `seqat reference {run_dir}` first)")
        return read_eop_csv(path), source
    if source in EOP_SOURCES:
        raise ConfigError(f"--eop {source}: {run_dir} is a {method} run (its eop.csv holds the "
                          f"{method} estimates); use --eop run or --eop reference")
    raise ConfigError(f"--eop: expected one of {', '.join(EOP_SOURCES[:2])}, got {source!r}")


def image_files(images_dir: Path) -> dict[str, Path]:
    """The JPEGs of an image folder by image id (file stem)."""
    if not images_dir.is_dir():
        raise InputDataError(f"{images_dir}: no such image folder")
    return {p.stem: p for p in flight_image_files(images_dir)}


def camera_warnings(camera_approximate: bool) -> tuple[str, ...]:
    """The ortho's warning about a camera taken from EXIF."""
    return (("camera from EXIF (approximate): the ortho is only as good as it",)
            if camera_approximate else ())


def flight_lidar(flight_dir: Path) -> tuple[Path, ...]:
    """The flight's ``lidar:`` files (none when the flight folder is gone or has none; what
    ``seqat run --ortho`` grids into OUT/dsm.tif, and what makes ``seqat process`` ortho)."""
    yaml_path = flight_dir / "flight.yaml"
    if not yaml_path.is_file():
        if exists_as_anything(yaml_path):
            raise InputDataError(f"{yaml_path}: {file_problem(yaml_path)}")
        return ()
    lidar = load_flight_config(yaml_path).lidar
    if lidar is None:
        return ()
    names = (lidar,) if isinstance(lidar, str) else lidar
    return tuple(p if p.is_absolute() else flight_dir / p for p in map(Path, names))


def find_dsm(run_dir: Path, crs: pyproj.CRS, dsm_path: Path | None, flight_dir: Path,
             dsm_options: DsmOptions | None = None) -> tuple[Dsm | None, tuple[str, ...]]:
    """The measured surface, first found: ``dsm_path``; ``run_dir/dsm.tif``; the flight's
    ``lidar:`` (a GeoTIFF as is, LAS/LAZ gridded into ``run_dir/dsm.tif`` with
    ``dsm_options``, the ``dsm:`` section of the options file); else None."""
    if dsm_path is not None:
        return read_dsm(dsm_path, crs), ()
    if (run_dir / DSM_FILE).is_file():
        return read_dsm(run_dir / DSM_FILE, crs), ()
    lidar = flight_lidar(flight_dir)
    if lidar and all(p.suffix.lower() in GEOTIFF_SUFFIXES for p in lidar):
        return read_dsm(lidar[0], crs), ()
    if lidar:
        result = build_dsm(lidar, run_dir / DSM_FILE, crs=crs, options=dsm_options)
        return read_dsm(result.path, crs), result.warnings
    return None, ()


def flat_plane(points_z_m: np.ndarray, cameras_xyz_m: np.ndarray, crs: pyproj.CRS,
               what: str) -> tuple[Dsm, str]:
    """The flat fallback surface at the median of the tie point heights ``points_z_m`` under
    the cameras (``FLAT_MARGIN_HEIGHTS`` flying heights around them) and its warning;
    ``what`` says where the height comes from. The median, not the mean: a tie point that
    blunders sent kilometres under the ground (2 rays, one down-weighted: σ of hundreds of
    metres) moves a mean by metres."""
    z_m = float(np.median(points_z_m))
    xy = cameras_xyz_m[:, :2]
    margin = FLAT_MARGIN_HEIGHTS * float(np.max(cameras_xyz_m[:, 2]) - z_m)
    bounds = (xy[:, 0].min() - margin, xy[:, 1].min() - margin, xy[:, 0].max() + margin,
              xy[:, 1].max() + margin)
    return flat_dsm(z_m, bounds, crs, FLAT_CELL_M), (
        f"no DSM: orthorectified on a flat plane at {what} {z_m:.2f} m "
        "(relief displaces the ortho; give --dsm or the flight's lidar)")


def choose_dsm(run_dir: Path, crs: pyproj.CRS, dsm_path: Path | None, flight_dir: Path,
               eops: EopTable, points_z_m: np.ndarray,
               dsm_options: DsmOptions | None = None) -> tuple[Dsm, tuple[str, ...]]:
    """The surface of ``seqat ortho`` (module docstring) and warnings."""
    dsm, warnings = find_dsm(run_dir, crs, dsm_path, flight_dir, dsm_options)
    if dsm is not None:
        return dsm, warnings
    if len(points_z_m) == 0:
        raise InputDataError(f"{run_dir}: no DSM (--dsm, {DSM_FILE}, flight lidar:) and no tie "
                             "points to place a flat plane")
    plane, warning = flat_plane(points_z_m, eops.eop[:, :3], crs, "the median tie point height")
    return plane, (warning,)


def parse_out_crs(value: str | None) -> pyproj.CRS | None:
    if value is None:
        return None
    try:
        crs = pyproj.CRS.from_user_input(value)
    except pyproj.exceptions.CRSError as err:
        raise ConfigError(f"--crs: unknown CRS {value!r}: {err}") from err
    if not (crs.is_projected or crs.is_geographic):
        raise ConfigError(f"--crs: {value!r} ({crs.name}) is not a horizontal CRS")
    return crs


def read_image(path: Path) -> np.ndarray:
    """An image as RGB (8 or 16 bit as stored)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputDataError(f"{path}: cannot read the image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def ortho_image(ortho: Orthorectifier, mosaic: MosaicBuilder, image_id: str,
                path: Path | None, eop: np.ndarray, *, write: bool = True,
                tiles: frozenset[tuple[int, int]] | None = None) -> tuple[
                    ImageOrtho, OrthoResult, MosaicUpdate]:
    """Read one image, orthorectify it with ``eop`` and paste it into the mosaic.

    ``write``: write ``ortho/<image>.tif``; ``tiles``: paste only into these mosaic tiles.

    Raises
    ------
    InputDataError
        No image file, or the image cannot be orthorectified (the caller skips it).
    """
    if path is None:
        raise InputDataError(f"no image {image_id}.jpg")
    t0 = time.perf_counter()
    rgb = read_image(path)
    read_ms = (time.perf_counter() - t0) * 1e3
    result = ortho.add_image(image_id, rgb, eop, write=write)
    update = mosaic.add(result, tiles=tiles)
    record = ImageOrtho(
        image=image_id, path=str(result.path) if result.path else None,
        seen_cells=result.seen_cells, occluded_cells=result.occluded_cells,
        compute_ms=result.compute_ms, write_ms=result.write_ms, mosaic_ms=update.update_ms,
        warnings=result.warnings, read_ms=read_ms)
    return record, result, update


def finish_ortho(run_dir: Path, mosaic: MosaicBuilder | MosaicResult,
                 records: Sequence[ImageOrtho], *,
                 crs: pyproj.CRS, out_crs: pyproj.CRS | None, eops: EopTable,
                 points: PointTable, footprints: Mapping[str, np.ndarray],
                 eop_source: str, dsm_source: str, pixel_m: float | None,
                 skipped: Sequence[str], warnings: Sequence[str], t0: float,
                 live: Callable[[], LiveOrthoStats] | None = None) -> OrthoRunSummary:
    """Write the mosaic COG (then warp everything to ``out_crs``), ``cameras.gpkg`` and
    ``ortho.json``; ``live`` gives the live statistics once the rest is written. ``mosaic``:
    the builder to finish, or the mosaic already written (by the campaign's tile tasks)."""
    mosaic_result = mosaic if isinstance(mosaic, MosaicResult) else mosaic.finish()
    raster_crs = crs
    if out_crs is not None and not out_crs.equals(crs, ignore_axis_order=True):
        for record in records:
            if record.path is not None:
                reproject_cog(Path(record.path), out_crs)
        reproject_cog(mosaic_result.path, out_crs)
        raster_crs = out_crs
    gpkg = write_cameras_gpkg(run_dir / CAMERAS_GPKG, crs, eops, footprints, points)
    summary = OrthoRunSummary(
        out_dir=run_dir, eop_source=eop_source, dsm_source=dsm_source, crs=raster_crs.name,
        pixel_m=float(pixel_m if pixel_m is not None else math.nan), images=tuple(records),
        skipped=tuple(skipped),
        compute_ms=TimingStats.from_samples([r.compute_ms for r in records]),
        mosaic_ms=TimingStats.from_samples([r.mosaic_ms for r in records]),
        mosaic=mosaic_result.path, cameras_gpkg=gpkg, wall_s=time.perf_counter() - t0,
        warnings=tuple(warnings), live=live() if live is not None else None)
    atomic_write_text(run_dir / ORTHO_JSON,
                      json.dumps(to_jsonable(summary), indent=1, allow_nan=False) + "\n")
    return summary


def orthorectify_run(out_dir: Path | str, *, dsm_path: Path | str | None = None,
                     eop_source: EopSource = "run", options: OrthoOptions | None = None,
                     feather_px: int = FEATHER_PX, out_crs: str | None = None,
                     progress: bool = True,
                     dsm_options: DsmOptions | None = None) -> OrthoRunSummary:
    """Orthorectify every image of a run and build the mosaic and ``cameras.gpkg``.

    Parameters
    ----------
    out_dir : Path or str
        Output folder of ``seqat run``.
    dsm_path : Path or str, optional
        DSM GeoTIFF (any CRS; reprojected).
    eop_source : {"run", "reference"}
        ``OUT/eop.csv`` (the estimates of the run's own method; that method's name, e.g.
        ``"seq-r"`` for a seq-r run, is accepted too) or ``OUT/reference/eop.csv``.
    options : OrthoOptions, optional
    feather_px : int
        Seamline feather of the mosaic, cells.
    out_crs : str, optional
        Write the orthos and the mosaic in this CRS (``EPSG:XXXX``, anything pyproj reads):
        they are computed in the working CRS and then warped (bilinear, a second resampling).
        ``cameras.gpkg`` stays in the working CRS (GIS reproject vectors on the fly).
    progress : bool
        Transient progress bar on a terminal.
    dsm_options : DsmOptions, optional
        How the flight's LiDAR is gridded when there is no DSM yet (``dsm:`` section).

    Returns
    -------
    OrthoRunSummary

    Raises
    ------
    InputDataError
        No images (an observations-only flight), no EOP file, a DSM that covers no image.
        An image that cannot be orthorectified (missing file, EOP above the horizon, outside
        the DSM) is skipped with a warning; when none can be, the error is raised.
    """
    from pipeline.run.store import read_run

    t0 = time.perf_counter()
    run_dir = Path(out_dir)
    target_crs = parse_out_crs(out_crs)
    run = read_run(run_dir)
    eops, eops_from = _eops(run_dir, eop_source, run.method, run.eop)
    if run.images_dir is None:
        raise InputDataError(f"{run_dir}: the flight has no images (observations only); "
                             "nothing to orthorectify")
    files = image_files(run.images_dir)
    dsm, warnings_dsm = choose_dsm(run_dir, run.crs, Path(dsm_path) if dsm_path else None,
                                   run.flight_dir, eops, run.points.xyz_m[:, 2], dsm_options)
    warnings = list(warnings_dsm) + list(camera_warnings(run.inputs.camera_approximate))
    records: list[ImageOrtho] = []
    skipped: list[str] = []
    footprints: dict[str, np.ndarray] = {}
    mosaic = MosaicBuilder(run_dir / MOSAIC_FILE, run.crs, feather_px=feather_px)
    console = Console(stderr=True, soft_wrap=True)
    last_error: SeqatError | None = None
    with Orthorectifier(dsm, run.camera, run.crs, run_dir / ORTHO_DIR, options) as ortho, \
            Progress(TextColumn("[bold]ortho"), BarColumn(), MofNCompleteColumn(),
                     TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console,
                     transient=True, disable=not (progress and console.is_terminal)) as bar:
        task = bar.add_task("ortho", total=len(eops.image_ids), info="")
        for image_id, eop in zip(eops.image_ids, eops.eop, strict=True):
            bar.update(task, advance=1, info=image_id)
            try:
                record, result, _ = ortho_image(ortho, mosaic, image_id, files.get(image_id),
                                                eop)
            except InputDataError as err:
                skipped.append(image_id)
                warnings.append(f"skipped: {run.images_dir}: {err}" if image_id not in files
                                else f"skipped: {err}")
                last_error = err
                continue
            footprints[image_id] = result.footprint_m
            warnings.extend(result.warnings)
            records.append(record)
        pixel_m = ortho.pixel_m
    if not records:
        mosaic.discard()
        raise InputDataError(f"{run_dir}: no image could be orthorectified"
                             + (f" ({last_error})" if last_error else ""))
    return finish_ortho(run_dir, mosaic, records, crs=run.crs, out_crs=target_crs, eops=eops,
                        points=run.points, footprints=footprints, eop_source=eops_from,
                        dsm_source=dsm.source, pixel_m=pixel_m, skipped=skipped,
                        warnings=warnings, t0=t0)
