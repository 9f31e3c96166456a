"""GIS export beside the rasters: ``cameras.gpkg`` (GeoPackage, written by GDAL via pyogrio).

Layers, all in the working CRS:

* ``cameras`` (Point Z): one projection centre per image with the OPK table's columns
  (``image, x_m, y_m, z_m, omega_deg, phi_deg, kappa_deg, sx_m, ..., skappa_deg``);
* ``footprints`` (Polygon): the ground outline of each orthorectified image;
* ``tie_points`` (Point Z): the estimated ground points with ``sx_m, sy_m, sz_m, n_obs``.

Geometries are built with shapely and written as WKB by pyogrio (GDAL's GPKG driver); the
file is written to a temporary name and renamed, so QGIS never sees half a GeoPackage.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pyogrio.raw
import pyproj
import shapely

from pipeline.common.columns import EOP_COLUMNS
from pipeline.common.tables import EopTable, PointTable
from pipeline.ortho.raster import atomic_path
from pipeline.run.store import XYZ
from seqat.types import FloatArray

#: Layer names of ``cameras.gpkg``.
CAMERAS_LAYER = "cameras"
FOOTPRINTS_LAYER = "footprints"
TIE_POINTS_LAYER = "tie_points"


def _opk_fields(eops: EopTable) -> dict[str, np.ndarray]:
    values = np.concatenate([eops.eop[:, :XYZ], np.degrees(eops.eop[:, XYZ:]),
                             eops.sigma[:, :XYZ], np.degrees(eops.sigma[:, XYZ:])], axis=1)
    fields = {"image": np.asarray(eops.image_ids, dtype=object)}
    fields.update({name: values[:, i] for i, name in enumerate(EOP_COLUMNS[1:])})
    return fields


def _write_layer(path: Path, layer: str, geometry: np.ndarray, fields: Mapping[str, np.ndarray],
                 geometry_type: str, crs: pyproj.CRS, append: bool) -> None:
    pyogrio.raw.write(str(path), geometry=shapely.to_wkb(geometry, output_dimension=3),
                      field_data=list(fields.values()), fields=list(fields), layer=layer,
                      driver="GPKG", geometry_type=geometry_type, crs=crs.to_wkt(),
                      append=append, nan_as_null=True)


def write_cameras_gpkg(path: Path | str, crs: pyproj.CRS, eops: EopTable,
                       footprints: Mapping[str, FloatArray] | None = None,
                       points: PointTable | None = None) -> Path:
    """Write ``cameras.gpkg`` (atomically).

    Parameters
    ----------
    path : Path or str
    crs : pyproj.CRS
        Working CRS of every coordinate.
    eops : EopTable
        Camera positions, attitudes and sigmas (metres, radians; written in degrees).
    footprints : mapping image id -> (k, 2) float, optional
        Closed ground rings, east/north metres.
    points : PointTable, optional
        Tie points.

    Returns
    -------
    Path
    """
    path = Path(path)
    with atomic_path(path, suffix=".gpkg") as tmp:
        tmp.unlink()  # GDAL creates the file
        cams = shapely.points(eops.eop[:, :XYZ])
        _write_layer(tmp, CAMERAS_LAYER, cams, _opk_fields(eops), "Point Z", crs, False)
        if footprints:
            ids = [i for i in eops.image_ids if i in footprints]
            polys = shapely.polygons([np.asarray(footprints[i], dtype=np.float64)
                                      for i in ids])
            _write_layer(tmp, FOOTPRINTS_LAYER, shapely.force_2d(polys),
                         {"image": np.asarray(ids, dtype=object)}, "Polygon", crs, True)
        if points is not None and len(points.point_ids):
            fields = {"point": np.asarray(points.point_ids, dtype=object),
                      "x_m": points.xyz_m[:, 0], "y_m": points.xyz_m[:, 1],
                      "z_m": points.xyz_m[:, 2], "sx_m": points.sigma_m[:, 0],
                      "sy_m": points.sigma_m[:, 1], "sz_m": points.sigma_m[:, 2],
                      "n_obs": points.n_obs.astype(np.int64)}
            _write_layer(tmp, TIE_POINTS_LAYER, shapely.points(points.xyz_m), fields,
                         "Point Z", crs, True)
    return path
