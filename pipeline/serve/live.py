"""What the page shows of a live run's ``OUT/live/estimates.json`` (and of a finished run's
``eop.csv`` / ``points.csv``): error ellipses, footprints, tie points by precision and the
coverage of the user's stop criterion (seed 003 §4.4, on-line precision monitoring).

All geometry is made in the run's working CRS (metres) and turned into WGS 84 by pyproj.

* **Error ellipses**: semi-axes σ_E and σ_N of the camera position (the a posteriori σ of X
  and Y; the E–N correlation is not published by the estimator, so the axes are the grid's),
  drawn ``scale`` times enlarged: centimetres would not show at the map's scale. ``scale`` is
  a 1-2-5 number making the largest ellipse about a third of the median camera spacing; it is
  in every feature's properties and in the legend.
* **Stop criterion**: a ground point is *done* when each of its σX, σY, σZ is at most
  ``stop_sigma_m``; the criterion is reached when every ground point is done. Coverage is
  shown on square cells of the working CRS (``cell_m``: a 1-2-5 number giving at most 20
  cells across the points' extent and about 8 points per cell): a cell is done when every
  point in it is done.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence

import numpy as np
import pyproj

FeatureCollection = dict[str, object]
#: Vertices of an ellipse polygon.
ELLIPSE_VERTICES = 36
#: At most this many coverage cells across the points' larger extent,
COVERAGE_CELLS_ACROSS = 20
#: ... and about this many points per cell at least.
POINTS_PER_CELL = 8
#: A quick-look's name in ``estimates.json`` (pipeline/run/live_view.py).
_QUICKLOOK = re.compile(r"quicklook/([0-9]{1,9})\.jpg")


def nice_number(value: float) -> float:
    """The 1-2-5 number nearest below ``value`` (> 0)."""
    if not (math.isfinite(value) and value > 0):
        return 1.0
    exp = math.floor(math.log10(value))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0 ** exp <= value:
            return m * 10.0 ** exp
    return 10.0 ** exp


def _collection(features: list[dict[str, object]], **extra: object) -> FeatureCollection:
    return {"type": "FeatureCollection", "features": features, **extra}


def _ring(transformer: pyproj.Transformer, xy: np.ndarray) -> list[list[float]] | None:
    lon, lat = transformer.transform(xy[:, 0], xy[:, 1])
    if not (np.all(np.isfinite(lon)) and np.all(np.isfinite(lat))):
        return None
    ring = np.column_stack([lon, lat])
    ring = np.vstack([ring, ring[:1]])
    return ring.tolist()  # type: ignore[no-any-return]


def ellipse_scale(xy: np.ndarray, sigma_en: np.ndarray) -> float:
    """Enlargement of the ellipses (module docstring)."""
    finite = np.all(np.isfinite(sigma_en), axis=1)
    if not finite.any():
        return 1.0
    largest = float(np.max(sigma_en[finite]))
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1) if len(xy) > 1 else np.zeros(0)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    spacing = float(np.median(steps)) if len(steps) else 10.0
    return nice_number(spacing / 3.0 / largest) if largest > 0 else 1.0


def ellipses(transformer: pyproj.Transformer, images: Sequence[str], xy: np.ndarray,
             sigma_en: np.ndarray) -> FeatureCollection:
    """Error ellipses of the camera positions (module docstring)."""
    scale = ellipse_scale(xy, sigma_en)
    t = np.linspace(0.0, 2.0 * np.pi, ELLIPSE_VERTICES, endpoint=False)
    ok = np.flatnonzero(np.all(np.isfinite(sigma_en), axis=1) & np.all(np.isfinite(xy), axis=1))
    # every ring in one transformation: (cameras, vertices) eastings and northings
    east = xy[ok, :1] + scale * sigma_en[ok, :1] * np.cos(t)
    north = xy[ok, 1:2] + scale * sigma_en[ok, 1:2] * np.sin(t)
    lon, lat = (np.asarray(v).reshape(east.shape)
                for v in transformer.transform(east.ravel(), north.ravel()))
    rings = np.stack([lon, lat], axis=2)
    rings = np.concatenate([rings, rings[:, :1]], axis=1)  # closed
    valid = np.all(np.isfinite(rings), axis=(1, 2)).tolist()
    features = []
    for k, (i, ring) in enumerate(zip(ok.tolist(), rings.tolist(), strict=True)):
        if not valid[k]:
            continue
        features.append({"type": "Feature", "geometry": {"type": "Polygon",
                                                         "coordinates": [ring]},
                         "properties": {"image": images[i],
                                        "sigma_e_m": float(sigma_en[i, 0]),
                                        "sigma_n_m": float(sigma_en[i, 1]), "scale": scale}})
    return _collection(features, scale=scale)


def quicklook_url(name: object) -> str | None:
    """The route of a quick-look named in ``estimates.json`` (``quicklook/<n>.jpg``), None
    for anything else (the route takes a number only: no file name reaches the server)."""
    match = _QUICKLOOK.fullmatch(name) if isinstance(name, str) else None
    return None if match is None else f"/quicklook/{int(match.group(1))}.jpg"


def footprints(transformer: pyproj.Transformer, cameras: Sequence[Mapping[str, object]],
               in_mosaic: frozenset[str] = frozenset()) -> FeatureCollection:
    """The cameras' footprints of ``estimates.json`` (corners on the mean ground height);
    each with its quick-look's route (``quicklook``, None without one), the corners in the
    order of the image's corners (``corners``: top-left, top-right, bottom-right,
    bottom-left, lon/lat) and whether the mosaic shows the image (``in_mosaic``)."""
    features = []
    for cam in cameras:
        corners = cam.get("footprint")
        if not isinstance(corners, list) or len(corners) != 4:
            continue
        try:
            xy = np.array(corners, dtype=np.float64).reshape(4, 2)
        except (TypeError, ValueError):
            continue
        ring = _ring(transformer, xy)
        if ring is None:
            continue
        image = cam.get("image")
        features.append({"type": "Feature", "geometry": {"type": "Polygon",
                                                         "coordinates": [ring]},
                         "properties": {"image": image,
                                        "in_window": bool(cam.get("in_window")),
                                        "quicklook": quicklook_url(cam.get("quicklook")),
                                        "corners": ring[:4],
                                        "in_mosaic": image in in_mosaic}})
    return _collection(features)


def point_sigma(sigma_m: np.ndarray) -> np.ndarray:
    """The σ a stop criterion compares: the largest of σX, σY, σZ (NaN when one is missing)."""
    if len(sigma_m) == 0:
        return np.zeros(0)
    with np.errstate(invalid="ignore"):
        worst = np.max(sigma_m, axis=1)
    worst[~np.all(np.isfinite(sigma_m), axis=1)] = np.nan
    return worst  # type: ignore[no-any-return]


def stop_summary(sigma_m: np.ndarray, xyz_m: np.ndarray,
                 stop_sigma_m: float | None) -> dict[str, object] | None:
    """``status.json`` ``stop``: counts of points and coverage cells done (None: no
    criterion)."""
    if stop_sigma_m is None:
        return None
    worst = point_sigma(sigma_m)
    done = worst <= stop_sigma_m
    cells = coverage_cells(xyz_m, done)
    n_cells_done = sum(1 for c in cells[1].values() if c[1] == c[0])
    return {"sigma_cm": round(stop_sigma_m * 100.0, 6), "points_total": int(len(worst)),
            "points_done": int(np.sum(done)), "cells_total": len(cells[1]),
            "cells_done": n_cells_done, "cell_m": cells[0],
            "reached": bool(len(worst) > 0 and bool(np.all(done)))}


def coverage_cells(xyz_m: np.ndarray, done: np.ndarray) -> tuple[
        float, dict[tuple[int, int], tuple[int, int]]]:
    """Cell size and, per cell ``(column, row)`` holding points: ``(points, points done)``."""
    ok = np.all(np.isfinite(xyz_m[:, :2]), axis=1) if len(xyz_m) else np.zeros(0, bool)
    xy, d = xyz_m[ok, :2], done[ok]
    if len(xy) == 0:
        return 1.0, {}
    span = np.maximum(np.ptp(xy, axis=0), 1.0)
    cell = nice_number(max(float(np.max(span)) / COVERAGE_CELLS_ACROSS,
                           math.sqrt(float(span[0] * span[1]) * POINTS_PER_CELL / len(xy))))
    keys = np.floor(xy / cell).astype(np.int64)
    cells: dict[tuple[int, int], tuple[int, int]] = {}
    for (c, r), is_done in zip(map(tuple, keys), d, strict=True):
        n, k = cells.get((c, r), (0, 0))
        cells[(c, r)] = (n + 1, k + int(is_done))
    return cell, cells


def coverage(transformer: pyproj.Transformer, xyz_m: np.ndarray, sigma_m: np.ndarray,
             stop_sigma_m: float | None) -> FeatureCollection:
    """The coverage cells done / not yet done of the stop criterion (empty without one)."""
    if stop_sigma_m is None:
        return _collection([], stop_sigma_cm=None)
    done = point_sigma(sigma_m) <= stop_sigma_m
    cell, cells = coverage_cells(xyz_m, done)
    features = []
    for (c, r), (n, k) in sorted(cells.items()):
        x0, y0 = c * cell, r * cell
        ring = _ring(transformer, np.array([[x0, y0], [x0 + cell, y0], [x0 + cell, y0 + cell],
                                            [x0, y0 + cell]]))
        if ring is None:
            continue
        features.append({"type": "Feature", "geometry": {"type": "Polygon",
                                                         "coordinates": [ring]},
                         "properties": {"points": n, "points_done": k, "done": n == k}})
    return _collection(features, stop_sigma_cm=stop_sigma_m * 100.0, cell_m=cell)
