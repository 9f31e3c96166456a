"""Exports of a run for other tools (docs/formats.md, *Exports*): published with the run's own
files (:func:`pipeline.run.store.write_run_outputs`, atomically, all or none).

* ``shots.geojson`` — one GeoJSON Point per image (RFC 7946: WGS 84 longitude, latitude,
  ellipsoidal height), with the properties OpenDroneMap's ``odm_report/shots.geojson`` has
  (``filename``, ``focal``, ``width``, ``height``, ``translation``, ``rotation``) and ours
  (ω φ κ and the σ of ``eop.csv``);
* ``cameras_opk.csv`` + ``cameras_opk.prj`` — the omega-phi-kappa table Pix4D and Metashape
  import (label = image file name, X, Y, Z, ω, φ, κ, horizontal and vertical σ), its CRS
  named in the ``#`` header line and as WKT in the ``.prj`` sidecar;
* ``tie_points.laz`` — the tie points as a LAS 1.4 point cloud (laspy + lazrs), the CRS as
  a WKT VLR, extra dimensions ``sx_m``, ``sy_m``, ``sz_m`` and ``n_obs`` (rays).

Projections by pyproj, rotations by scipy, the point cloud by laspy: nothing hand-written.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping
from pathlib import Path

import laspy
import numpy as np
import pyproj
from pyproj.enums import WktVersion
from pyproj.exceptions import ProjError
from scipy.spatial.transform import Rotation

from pipeline.common.tables import EopTable, PointTable
from pipeline.flight.navigation import image_files
from pipeline.flight.schema import CameraConfig
from seqat.cvframe import cv_pose_from_eop
from seqat.types import FloatArray

SHOTS_GEOJSON = "shots.geojson"
CAMERAS_OPK_CSV = "cameras_opk.csv"
CAMERAS_OPK_PRJ = "cameras_opk.prj"
TIE_POINTS_LAZ = "tie_points.laz"
#: Columns of ``cameras_opk.csv`` (named in its ``#`` header line; Pix4D wants no header).
OPK_COLUMNS = ("label", "x_m", "y_m", "z_m", "omega_deg", "phi_deg", "kappa_deg",
               "sigma_horizontal_m", "sigma_vertical_m")
#: The σ columns of ``eop.csv``, as properties of each shot.
SIGMA_NAMES = ("sx_m", "sy_m", "sz_m", "somega_deg", "sphi_deg", "skappa_deg")
#: Coordinate resolution of ``tie_points.laz``, metres.
LAZ_SCALE_M = 0.001
#: WGS 84 with ellipsoidal heights (RFC 7946 coordinates).
WGS84_3D = "EPSG:4979"


def image_file_names(images_dir: Path | None, image_ids: tuple[str, ...]) -> dict[str, str]:
    """Image id -> file name in the images folder (the id where there is no file: an
    observations flight)."""
    files = {p.stem: p.name for p in image_files(images_dir)} if (
        images_dir is not None and images_dir.is_dir()) else {}
    return {iid: files.get(iid, iid) for iid in image_ids}


def crs_label(crs: pyproj.CRS) -> str:
    """``EPSG:32610`` when the CRS has an EPSG code, else its name."""
    code = crs.to_epsg()
    return f"EPSG:{code}" if code is not None else crs.name


def heights_of(crs: pyproj.CRS) -> str:
    """What the heights of a run CRS are (docs/formats.md, *Heights*)."""
    if crs.is_compound:
        vertical = next((s for s in crs.sub_crs_list if s.is_vertical), None)
        return f"orthometric ({vertical.name})" if vertical is not None else "as the CRS's"
    return f"ellipsoidal ({crs.ellipsoid.name if crs.ellipsoid else 'its ellipsoid'})"


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def format_shots_geojson(eops: EopTable, crs: pyproj.CRS, camera: CameraConfig,
                         names: Mapping[str, str]) -> str:
    """``shots.geojson`` (module docstring; docs/formats.md).

    ``rotation`` is OpenSfM's (ODM's): the rotation vector (axis x angle, radians) of
    ``R_cv_from_world``, world -> OpenCV camera frame (x right, y down, z forward), so
    ``p_cv = R (X - translation)``. Coordinates: longitude, latitude, ellipsoidal height
    (pyproj to EPSG:4979); where PROJ cannot give a WGS 84 height (a vertical datum without its
    grid), longitude and latitude only. An image without a finite EOP has ``"geometry":
    null`` (RFC 7946, 3.2) and null values.
    """
    xyz = eops.eop[:, :3]
    ok = np.all(np.isfinite(eops.eop), axis=1)  # an image without an estimate: no geometry
    lon, lat, h = (np.full(len(xyz), np.nan) for _ in range(3))
    src = crs if crs.is_compound else crs.to_3d()
    has_height = True
    try:
        to_wgs = pyproj.Transformer.from_crs(src, WGS84_3D, always_xy=True)
        lon[ok], lat[ok], h[ok] = to_wgs.transform(*xyz[ok].T, errcheck=True)
    except ProjError:
        to_wgs = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lon[ok], lat[ok] = to_wgs.transform(xyz[ok, 0], xyz[ok, 1], errcheck=True)
        has_height = False
    rotvec = np.full((len(xyz), 3), np.nan)
    if ok.any():
        R_cv, _ = cv_pose_from_eop(eops.eop[ok])
        rotvec[ok] = Rotation.from_matrix(R_cv).as_rotvec()
    angles = np.degrees(eops.eop[:, 3:])
    sigma = np.concatenate([eops.sigma[:, :3], np.degrees(eops.sigma[:, 3:])], axis=1)
    focal = camera.fx_px / max(camera.width_px, camera.height_px)
    features = []
    for i, iid in enumerate(eops.image_ids):
        coords = [float(lon[i]), float(lat[i])] + ([float(h[i])] if has_height else [])
        props: dict[str, object] = {
            "filename": names.get(iid, iid), "focal": focal, "width": camera.width_px,
            "height": camera.height_px, "translation": [_number(v) for v in xyz[i]],
            "rotation": [_number(v) for v in rotvec[i]], "image": iid,
            "translation_crs": crs_label(crs), "omega_deg": _number(angles[i, 0]),
            "phi_deg": _number(angles[i, 1]), "kappa_deg": _number(angles[i, 2]),
        }
        props.update({name: _number(sigma[i, k]) for k, name in enumerate(SIGMA_NAMES)})
        features.append({"type": "Feature", "properties": props,
                         "geometry": {"type": "Point", "coordinates": coords} if ok[i]
                         else None})
    body = ",\n".join(json.dumps(f, allow_nan=False) for f in features)
    return '{"type": "FeatureCollection", "features": [\n' + body + "\n]}\n"  # one per line


def format_cameras_opk_csv(eops: EopTable, crs: pyproj.CRS, names: Mapping[str, str]) -> str:
    """``cameras_opk.csv``: one ``#`` line (columns, CRS, heights, angle convention), then
    ``label,X,Y,Z,omega,phi,kappa,sigma_h,sigma_v`` per image (the 9-column form of Pix4D's
    image geolocation file; Metashape's *Import Reference* with these columns). X = easting,
    Y = northing of the run's CRS, angles in degrees (docs/conventions.md); σ_h =
    sqrt((sx² + sy²) / 2), σ_v = sz, ``nan`` where the run has none."""
    header = (f"# {','.join(OPK_COLUMNS)}; CRS {crs_label(crs)} ({crs.name}; WKT in "
              f"{CAMERAS_OPK_PRJ}); X easting, Y northing, Z {heights_of(crs)} heights, metres; "
              "omega phi kappa degrees, R_world_from_camera = Rx(omega) Ry(phi) Rz(kappa), "
              "camera x right, y up, looking along -z (seqat docs/conventions.md)\n")
    lines = [header]
    deg = np.degrees(eops.eop[:, 3:])
    for i, iid in enumerate(eops.image_ids):
        sx, sy, sz = eops.sigma[i, :3]
        values = [*eops.eop[i, :3], *deg[i], math.sqrt((sx * sx + sy * sy) / 2.0), sz]
        lines.append(",".join([names.get(iid, iid), *(repr(float(v)) for v in values)]) + "\n")
    return "".join(lines)


def format_prj(crs: pyproj.CRS) -> str:
    """The ``.prj`` sidecar: the CRS as ESRI WKT (GIS read it beside a table), else WKT2."""
    text = crs.to_wkt(WktVersion.WKT1_ESRI) or crs.to_wkt()
    return text + "\n"


def laz_scales(span_m: FloatArray) -> FloatArray:
    """LAS scale per axis: :data:`LAZ_SCALE_M`, or the smallest power of ten over it whose
    int32 range holds ``span_m`` (coordinates minus the offset, >= 0): a point the
    estimate left thousands of kilometres off (a blunder's intersection) coarsens its axis
    instead of failing the export."""
    top = np.max(span_m, axis=0) if len(span_m) else np.zeros(3)
    need = np.maximum(top / (np.iinfo(np.int32).max - 1), LAZ_SCALE_M)
    return LAZ_SCALE_M * 10.0 ** np.ceil(np.log10(need / LAZ_SCALE_M) - 1e-12)


def tie_points_laz(points: PointTable, crs: pyproj.CRS) -> bytes:
    """``tie_points.laz``: LAS 1.4, point format 6, millimetre coordinates, the CRS as a WKT
    VLR; extra dimensions ``sx_m``, ``sy_m``, ``sz_m`` (float32, NaN where none) and
    ``n_obs`` (uint16: the rays of the point)."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims([
        *(laspy.ExtraBytesParams(name=n, type=np.float32, description=f"sigma {n[1]}, m")
          for n in ("sx_m", "sy_m", "sz_m")),
        laspy.ExtraBytesParams(name="n_obs", type=np.uint16, description="rays (images)"),
    ])
    keep = np.all(np.isfinite(points.xyz_m), axis=1)  # a point without a position is left out
    xyz = points.xyz_m[keep]
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    header.scales = laz_scales(xyz - header.offsets)
    header.add_crs(crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for k, name in enumerate(("sx_m", "sy_m", "sz_m")):
        las[name] = points.sigma_m[keep, k].astype(np.float32)
    las["n_obs"] = np.minimum(points.n_obs[keep], np.iinfo(np.uint16).max).astype(np.uint16)
    buffer = io.BytesIO()
    las.write(buffer, do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
    return buffer.getvalue()


def export_files(eops: EopTable, points: PointTable, crs: pyproj.CRS, camera: CameraConfig,
                 images_dir: Path | None) -> dict[str, str | bytes]:
    """Every export of a run, by file name (text or bytes), for
    :func:`pipeline.common.atomic.write_files_atomically`."""
    names = image_file_names(images_dir, eops.image_ids)
    return {
        SHOTS_GEOJSON: format_shots_geojson(eops, crs, camera, names),
        CAMERAS_OPK_CSV: format_cameras_opk_csv(eops, crs, names),
        CAMERAS_OPK_PRJ: format_prj(crs),
        TIE_POINTS_LAZ: tie_points_laz(points, crs),
    }
