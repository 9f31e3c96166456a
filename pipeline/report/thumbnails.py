"""Small pictures of a run's rasters for the report: ``mosaic.tif`` and ``dsm.tif`` read at a
reduced size (their COG overviews), with their extent in the working CRS.

The report never needs the full raster: a few hundred pixels across, read through
``rasterio``'s decimated read (GDAL picks the overview), is what a page shows.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj

#: Files of a run folder (pipeline.ortho.stage's names; the report reads them, never imports
#: the ortho stage).
MOSAIC_FILE = "mosaic.tif"
DSM_FILE = "dsm.tif"
#: Longest side of a thumbnail, pixels.
THUMBNAIL_PX = 900


@dataclass(frozen=True, kw_only=True, eq=False)
class Thumbnail:
    """A raster read small.

    ``image``: ``(h, w, 4)`` uint8 RGBA for a mosaic, ``(h, w)`` float64 heights with NaN for
    nodata for a DSM; ``extent``: (left, right, bottom, top) in the raster's CRS, as
    matplotlib's ``imshow`` takes it; ``same_crs``: the raster is in the run's working CRS
    (else it cannot be drawn under the run's coordinates).
    """

    path: Path
    image: np.ndarray
    extent: tuple[float, float, float, float]
    same_crs: bool


def _to_rgba(bands: np.ndarray) -> np.ndarray:
    """``(bands, h, w)`` of a mosaic (grey or RGB, + alpha) as ``(h, w, 4)`` uint8."""
    data = bands.astype(np.float64)
    if bands.dtype != np.uint8:
        top = float(np.nanmax(data[:-1])) if data.shape[0] > 1 else float(np.nanmax(data))
        data = data * (255.0 / top) if top > 0 else data
    n = data.shape[0]
    colour = data[:3] if n >= 4 else np.repeat(data[:1], 3, axis=0)
    alpha = data[-1] if n in (2, 4) else np.full(data.shape[1:], 255.0)
    alpha = np.where(alpha > 0, 255.0, 0.0)
    rgba = np.concatenate([colour, alpha[None]], axis=0)
    return np.clip(np.moveaxis(rgba, 0, -1), 0, 255).astype(np.uint8)


def read_thumbnail(path: Path, crs: pyproj.CRS, *, heights: bool = False,
                   max_px: int = THUMBNAIL_PX) -> Thumbnail | None:
    """``path`` read at most ``max_px`` pixels across (None when absent or unreadable).

    Parameters
    ----------
    path : Path
        ``mosaic.tif`` or ``dsm.tif`` of a run folder.
    crs : pyproj.CRS
        The run's working CRS.
    heights : bool
        A DSM (one band of heights, nodata masked) rather than a mosaic.
    """
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import RasterioError

    if not path.is_file():
        return None
    try:
        with rasterio.open(path) as src:
            step = max(1.0, max(src.width, src.height) / max_px)
            shape = (max(1, round(src.height / step)), max(1, round(src.width / step)))
            b = src.bounds
            extent = (b.left, b.right, b.bottom, b.top)
            same = src.crs is not None and pyproj.CRS.from_wkt(src.crs.to_wkt()).equals(
                crs, ignore_axis_order=True)
            if heights:
                band = src.read(1, out_shape=shape, masked=True,
                                resampling=Resampling.average)
                image = np.ma.filled(band.astype(np.float64), np.nan)
            else:
                image = _to_rgba(src.read(out_shape=(src.count, *shape),
                                          resampling=Resampling.nearest))
    except (OSError, RasterioError, pyproj.exceptions.CRSError):
        return None
    return Thumbnail(path=path, image=image, extent=extent, same_crs=bool(same))
