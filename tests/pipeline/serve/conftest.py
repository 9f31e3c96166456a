"""A run folder with a mosaic for the ``seqat serve`` tests, and a server on a free port.

The run is the session's ``strip_run`` (``sample_data/strip_demo``, Seq-R, ~5 s), copied,
with a synthetic ``mosaic.tif`` (a COG in the run's CRS over the cameras' area, alpha 0 in
a border) instead of a live ortho of the rendered flight (~20 s).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pyproj
import pytest
from affine import Affine

from pipeline.ortho.raster import write_cog
from pipeline.run.live_view import quicklook_name, write_quicklook
from pipeline.run.store import read_eop_csv, read_json_object, read_points_csv
from pipeline.serve.app import Served, serving

#: Mosaic cell, metres, and the border without data, cells.
PIXEL_M = 0.5
BORDER = 40


def write_mosaic(out: Path, rgb: tuple[int, int, int]) -> Path:
    """A uniform-colour RGBA COG over the run's cameras, transparent in a border."""
    crs = pyproj.CRS.from_wkt(str(read_json_object(out / "run.json")["crs"]))
    xy = read_eop_csv(out / "eop.csv").eop[:, :2]
    west, south = np.floor(xy.min(axis=0) - 50.0)
    east, north = np.ceil(xy.max(axis=0) + 50.0)
    cols, rows = int((east - west) / PIXEL_M), int((north - south) / PIXEL_M)
    data = np.zeros((4, rows, cols), np.uint8)
    for band, value in enumerate(rgb):
        data[band] = value
    data[3, BORDER:-BORDER, BORDER:-BORDER] = 255
    return write_cog(out / "mosaic.tif", data,
                     transform=Affine(PIXEL_M, 0.0, west, 0.0, -PIXEL_M, north), crs=crs,
                     alpha=True)


@pytest.fixture(scope="session")
def mosaic_run(strip_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of ``strip_run`` with ``mosaic.tif`` (read-only for the tests)."""
    out = tmp_path_factory.mktemp("serve") / "out"
    shutil.copytree(strip_run, out)
    write_mosaic(out, (200, 120, 40))
    return out


@pytest.fixture(scope="session")
def served(mosaic_run: Path) -> Iterator[Served]:
    """``seqat serve`` of ``mosaic_run`` on a free port of 127.0.0.1, in a thread."""
    with serving(mosaic_run) as served:
        yield served


def quicklook_source(path: Path) -> Path:
    """An 800 x 600 JPEG, red on the left half, blue on the right (what a quick-look of it
    shows is checkable), at ``path``."""
    pixels = np.zeros((600, 800, 3), np.uint8)
    pixels[:, :400, 2] = 230  # BGR: red
    pixels[:, 400:, 0] = 230  # blue
    assert cv2.imwrite(str(path), pixels)
    return path


def write_live_estimates(out: Path, source: Path, images: int,
                         stop_sigma_m: float | None = None,
                         quicklooks: bool = False) -> dict[str, object]:
    """``out/live/estimates.json`` as a live watch writes it, from the first ``images``
    cameras and all points of a finished run ``source``; ``quicklooks``: with a quick-look
    of :func:`quicklook_source` for each camera."""
    run = read_json_object(source / "run.json")
    eop = read_eop_csv(source / "eop.csv")
    points = read_points_csv(source / "points.csv")
    cams = []
    if quicklooks:
        (out / "live" / "quicklook").mkdir(parents=True, exist_ok=True)
        jpeg = quicklook_source(out / "live" / "source.jpg")
    for i in range(images):
        x, y = eop.eop[i, :2]
        name = None
        if quicklooks:
            name = f"quicklook/{quicklook_name(i)}"
            assert write_quicklook(jpeg, out / "live" / name, 800)
        cams.append({"image": eop.image_ids[i], "eop": eop.eop[i].tolist(),
                     "sigma": eop.sigma[i].tolist(), "in_window": i >= images - 3,
                     "at_unix_s": 1.0e9 + i,
                     "footprint": [[x - 40, y - 30], [x + 40, y - 30], [x + 40, y + 30],
                                   [x - 40, y + 30]], "quicklook": name})
    doc = {"format": "seqat-live-estimates", "version": 1, "updated_unix_s": 1.0e9,
           "crs": run["crs"], "images": images, "stage": "sequential", "sigma0": 0.9,
           "stop_sigma_m": stop_sigma_m,
           "last": {"image": eop.image_ids[images - 1], "prep_ms": 120.0, "update_ms": 8.0,
                    "processing_ms": 130.0, "latency_ms": 250.0},
           "cameras": cams,
           "points": {"point": list(points.point_ids), "xyz_m": points.xyz_m.tolist(),
                      "sigma_m": points.sigma_m.tolist(), "n_obs": points.n_obs.tolist()}}
    (out / "live").mkdir(parents=True, exist_ok=True)
    (out / "live" / "estimates.json").write_text(json.dumps(doc))
    return doc


@pytest.fixture(scope="session")
def live_run(mosaic_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live watch's folder: marker, journal and ``live/estimates.json`` (6 cameras with
    quick-looks, a stop criterion of 8 cm), no published results."""
    out = tmp_path_factory.mktemp("serve_live") / "live"
    out.mkdir()
    shutil.copy(mosaic_run / ".seqat-run", out)
    shutil.copytree(mosaic_run / "journal", out / "journal")
    write_live_estimates(out, mosaic_run, 6, stop_sigma_m=0.08, quicklooks=True)
    return out
