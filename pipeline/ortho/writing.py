"""Writing one ortho as a COG: cropped to its valid pixels, alpha band from the mask."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyproj

from pipeline.ortho.base import ALPHA_OPAQUE, OrthoRaster
from pipeline.ortho.raster import write_cog


def cropped(raster: OrthoRaster) -> OrthoRaster:
    """The raster cut to the bounding box of its seen cells."""
    rows = np.flatnonzero(raster.seen.any(axis=1))
    cols = np.flatnonzero(raster.seen.any(axis=0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    if (r0, c0) == (0, 0) and (r1, c1) == raster.shape:
        return raster
    return OrthoRaster(image_id=raster.image_id, col0=raster.col0 + int(c0),
                       row0=raster.row0 + int(r0), pixel_m=raster.pixel_m,
                       pixels=raster.pixels[r0:r1, c0:c1], seen=raster.seen[r0:r1, c0:c1],
                       off_nadir=raster.off_nadir[r0:r1, c0:c1],
                       height_agl_m=raster.height_agl_m)


def write_ortho(path: Path, raster: OrthoRaster, crs: pyproj.CRS) -> Path:
    """Write an ortho as a COG: the image bands plus an alpha band (0 = not seen)."""
    alpha = raster.seen.astype(raster.pixels.dtype) * raster.pixels.dtype.type(
        ALPHA_OPAQUE[raster.pixels.dtype])
    data = np.concatenate([np.moveaxis(raster.pixels, 2, 0), alpha[None]])
    return write_cog(path, data, transform=raster.transform, crs=crs, alpha=True)
