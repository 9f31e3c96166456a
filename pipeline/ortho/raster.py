"""Cloud Optimized GeoTIFF writing and checking (rasterio / GDAL's ``COG`` driver).

Every raster seqat writes (``dsm.tif``, ``ortho/*.tif``, ``mosaic.tif``) goes through
:func:`write_cog` or :func:`gtiff_to_cog`: GDAL's COG driver lays the file out (ghost header,
IFDs first, overviews before full-resolution data, 512 px tiles) and the file is published
atomically (temporary file in the same folder, then rename). :func:`cog_problems` checks that
layout the way GDAL's ``validate_cloud_optimized_geotiff.py`` does, through rasterio's TIFF
metadata domain.

Raster conventions (docs/conventions.md, *Rasters*): north-up, pixel-is-area, the geotransform
``from_origin(west, north, pixel_m, pixel_m)`` maps the *outer corner* of the top-left pixel.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np
import pyproj
import rasterio
import rasterio.shutil
import rasterio.vrt
from affine import Affine
from rasterio.enums import ColorInterp

from pipeline.common.atomic import fsync_dir
from pipeline.common.outdir import output_errors
from seqat.errors import InputDataError

#: Tile size of every COG, pixels (GDAL's COG default).
COG_BLOCK_PX = 512
#: Compression of the COGs: lossless, fast to write, read by every GDAL-based GIS.
COG_COMPRESS = "DEFLATE"
#: DEFLATE level: 1 writes about 3x faster than the default 6 for ~10 % larger files.
COG_DEFLATE_LEVEL = 1
#: Overview resampling (averaging; alpha-aware in GDAL).
COG_OVERVIEW_RESAMPLING = "AVERAGE"
#: GDAL compresses the tiles on this many threads; the environment variable
#: ``SEQAT_COG_THREADS`` overrides it (a campaign's workers, one per core, set it to 1).
COG_THREADS = "ALL_CPUS"
COG_THREADS_ENV = "SEQAT_COG_THREADS"
#: GDAL block cache while writing a COG, MB: bounds the memory of the mosaic's conversion
#: (GDAL's default is 5 % of the RAM and grows with the mosaic).
COG_CACHE_MB = 256


def cog_options(dtype: str) -> dict[str, str | int]:
    """Creation options of the COG driver for a band type.

    Floating-point bands get the floating-point predictor (``PREDICTOR=3``), integer bands
    the horizontal one (``PREDICTOR=2``). DEFLATE is read by every GDAL build (ZSTD level 1
    writes about twice as fast at the same size but is missing from some GIS builds).
    """
    return {
        "BLOCKSIZE": COG_BLOCK_PX,
        "COMPRESS": COG_COMPRESS,
        "LEVEL": COG_DEFLATE_LEVEL,
        "PREDICTOR": 3 if np.dtype(dtype).kind == "f" else 2,
        "OVERVIEWS": "AUTO",
        "RESAMPLING": COG_OVERVIEW_RESAMPLING,
        "BIGTIFF": "IF_SAFER",
        "NUM_THREADS": os.environ.get(COG_THREADS_ENV, COG_THREADS),
    }


@contextlib.contextmanager
def atomic_path(path: Path, suffix: str = ".tif", *, durable: bool = True) -> Iterator[Path]:
    """A temporary path beside ``path``, renamed onto it when the block succeeds.

    On failure the temporary file is removed and ``path`` is left as it was. Errors of the
    file system (read-only folder, ``path`` a folder) are InputDataErrors naming ``path``.
    ``durable``: fsync the folder after the rename (not for a live cache replaced at the end:
    readers still see the old file or the new one, never part of one).
    """
    if path.is_dir():
        raise InputDataError(f"{path}: is a folder; give the name of the file to write")
    with output_errors(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with output_errors(path):
            os.chmod(tmp, _file_mode())  # mkstemp makes 0600; published: 0666 & ~umask
            os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    if durable:
        fsync_dir(path.parent)


def _file_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def colorinterp_for(count: int, alpha: bool) -> list[ColorInterp]:
    """Colour interpretation of ``count`` bands: RGB or grey, plus alpha last."""
    colour = count - 1 if alpha else count
    base = ([ColorInterp.red, ColorInterp.green, ColorInterp.blue] if colour == 3
            else [ColorInterp.gray] * colour)
    return base + ([ColorInterp.alpha] if alpha else [])


def write_cog(path: Path | str, data: np.ndarray, *, transform: Affine, crs: pyproj.CRS,
              nodata: float | None = None, alpha: bool = False,
              tags: Mapping[str, str] | None = None) -> Path:
    """Write a north-up raster as a Cloud Optimized GeoTIFF, atomically.

    Parameters
    ----------
    path : Path or str
    data : (bands, rows, cols) array
        Band-sequential pixels; with ``alpha`` the last band is the alpha band (0 = outside).
    transform : Affine
        Pixel-is-area geotransform (``rasterio.transform.from_origin(west, north, px, px)``).
    crs : pyproj.CRS
    nodata : float, optional
        Nodata value of every band (not with ``alpha``).
    alpha : bool
        The last band is an alpha band (``ExtraSamples`` = unassociated alpha).
    tags : mapping, optional
        GDAL metadata items of the dataset (``gdalinfo`` lists them; ``src.tags()``).

    Returns
    -------
    Path
    """
    path = Path(path)
    if data.ndim != 3:
        raise ValueError(f"write_cog needs (bands, rows, cols), got shape {data.shape}")
    count, rows, cols = data.shape
    profile = {"driver": "MEM", "width": cols, "height": rows, "count": count,
               "dtype": data.dtype.name, "crs": rasterio.crs.CRS.from_wkt(crs.to_wkt()),
               "transform": transform, "nodata": nodata}
    # The COG driver does all its work when the dataset closes, and rasterio closes it
    # holding the GIL (every other Python thread stops for the whole write); GDAL's
    # CreateCopy from an in-memory dataset runs with the GIL released.
    with atomic_path(path) as tmp, rasterio.Env(GDAL_CACHEMAX=COG_CACHE_MB), \
            rasterio.MemoryFile() as memfile, memfile.open(**profile) as mem:
        mem.colorinterp = colorinterp_for(count, alpha)
        if tags:
            mem.update_tags(**tags)
        mem.write(data)
        rasterio.shutil.copy(mem, tmp, driver="COG", **cog_options(data.dtype.name))
    return path


def write_tiled_tiff(path: Path, data: np.ndarray, *, transform: Affine, crs: pyproj.CRS,
                     alpha: bool = False) -> Path:
    """Write a small north-up raster as a tiled (256 px), uncompressed GeoTIFF without
    overviews, atomically (not fsynced: a live cache, replaced by the mosaic COG at the end):
    the live mosaic's tiles (:mod:`pipeline.ortho.live_tiles`), where
    the write time matters more than the size."""
    count, rows, cols = data.shape
    profile = {"driver": "GTiff", "width": cols, "height": rows, "count": count,
               "dtype": data.dtype.name, "crs": rasterio.crs.CRS.from_wkt(crs.to_wkt()),
               "transform": transform, "tiled": True, "blockxsize": 256, "blockysize": 256}
    with atomic_path(path, durable=False) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        dst.colorinterp = colorinterp_for(count, alpha)
        dst.write(data)
    return path


def gtiff_to_cog(src_path: Path, dst_path: Path) -> Path:
    """Convert a (tiled) GeoTIFF into a COG with overviews, atomically.

    GDAL reads the source block by block, so memory stays bounded however large it is.
    """
    with rasterio.open(src_path) as src:
        dtype = src.dtypes[0]
    with atomic_path(dst_path) as tmp, rasterio.Env(GDAL_CACHEMAX=COG_CACHE_MB):
        rasterio.shutil.copy(src_path, tmp, driver="COG", **cog_options(dtype))
    return dst_path


def reproject_cog(path: Path, crs: pyproj.CRS) -> Path:
    """Warp a COG into another CRS in place (bilinear, alpha and nodata respected), atomically.

    GDAL's warper reads and writes in chunks through a ``WarpedVRT``, so memory stays bounded.
    The pixel size is GDAL's suggestion for the target CRS (about the same ground size).
    """
    target = rasterio.crs.CRS.from_wkt(crs.to_wkt())
    with rasterio.open(path) as src:
        dtype = src.dtypes[0]
        with rasterio.vrt.WarpedVRT(src, crs=target,
                                    resampling=rasterio.enums.Resampling.bilinear) as vrt, \
                atomic_path(path) as tmp, rasterio.Env(GDAL_CACHEMAX=COG_CACHE_MB):
            rasterio.shutil.copy(vrt, tmp, driver="COG", **cog_options(dtype))
    return path


def cog_problems(path: Path | str) -> tuple[str, ...]:
    """Check the Cloud Optimized GeoTIFF layout of a file; empty when it is valid.

    The checks of GDAL's ``validate_cloud_optimized_geotiff.py``: a tiled GeoTIFF; overviews
    when larger than one tile, each tiled; the main IFD first and the overview IFDs after it
    in decreasing size; the image data of the smallest overview first and of the full
    resolution last; plus GDAL's ``LAYOUT=COG`` marker (written by the COG driver).

    Returns
    -------
    tuple[str, ...]
        One message per problem.
    """
    problems: list[str] = []
    try:
        src = rasterio.open(path)
    except rasterio.errors.RasterioIOError as err:
        raise InputDataError(f"{path}: cannot open raster: {err}") from err
    with src:
        if src.driver != "GTiff":
            return (f"driver is {src.driver}, not GTiff",)
        if src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") != "COG":
            problems.append("no LAYOUT=COG marker (not written by GDAL's COG driver)")
        block_rows, block_cols = src.block_shapes[0]
        if block_cols == src.width and src.width > COG_BLOCK_PX or block_rows == 1:
            problems.append(f"not tiled (blocks {block_cols} x {block_rows})")
        overviews = src.overviews(1)
        if max(src.width, src.height) > block_cols and not overviews:
            problems.append("no overviews although larger than one tile")

        def tiff_item(name: str, ovr: int | None) -> int | None:
            value = src.get_tag_item(name, "TIFF", bidx=1, ovr=ovr)
            return int(value) if value not in (None, "") else None

        ifd = [tiff_item("IFD_OFFSET", None)] + [tiff_item("IFD_OFFSET", i)
                                                 for i in range(len(overviews))]
        if any(o is None for o in ifd):
            problems.append("IFD offsets unavailable")
        elif ifd != sorted(ifd):
            problems.append(f"IFDs not in order main, overviews by decreasing size: {ifd}")
        data = [tiff_item("BLOCK_OFFSET_0_0", None)] + [tiff_item("BLOCK_OFFSET_0_0", i)
                                                        for i in range(len(overviews))]
        present = [d for d in data if d]  # a sparse (empty) first block has offset 0
        if present != sorted(present, reverse=True):
            problems.append(f"image data not ordered smallest overview first: {data}")
        if all(o is not None for o in ifd) and present and max(ifd) > min(present):  # type: ignore[type-var]
            problems.append("an IFD lies after image data (IFDs must come first)")
    return tuple(problems)
