"""Timing of the ortho stage at full camera size (docs/benchmarks.md, *Orthorectification*).

``python -m pipeline.ortho_bench --images N --out DIR [--no-occlusion] [--no-write]
[--sync-writes]`` flies a
strip of ``N`` images of a 2456 x 2058 px camera 100 m over a sloped DSM with box buildings,
orthorectifies each image, updates the mosaic and prints a JSON summary: per-image ortho
time (projection + occlusion + resampling), COG writing time, mosaic update time, the final
mosaic write, and the process's peak memory (run it with two flight lengths to see that
memory does not grow with the flight).
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyproj
from rasterio.transform import from_origin

from pipeline.config import CameraConfig
from pipeline.dsm import Dsm
from pipeline.mosaic import MosaicBuilder
from pipeline.ortho import OrthoOptions, Orthorectifier
from pipeline.store import TimingStats, to_jsonable

#: The benchmark camera: 2456 x 2058 px (5 Mpx machine-vision sensor), f = 3000 px.
BENCH_CAMERA = CameraConfig(model="OPENCV", width_px=2456, height_px=2058, fx_px=3000.0,
                            fy_px=3000.0, cx_px=1227.5, cy_px=1028.5, k1=-0.05, k2=0.01,
                            p1=2e-4, p2=-1e-4)
BENCH_CRS = pyproj.CRS.from_epsg(32652)
#: Flying height above the DSM's base, metres (GSD 3.3 cm), and image spacing along the strip.
HEIGHT_M = 100.0
SPACING_M = 25.0
#: DSM of the benchmark: cell, base height, slope, buildings.
DSM_CELL_M = 0.5
BASE_M = 50.0
SLOPE = 0.02
N_BUILDINGS_PER_100M = 4
ORIGIN_E, ORIGIN_N = 500000.0, 4090000.0
#: The DSM starts this far west of the first image.
DSM_MARGIN_M = 60.0


@dataclass(frozen=True, kw_only=True)
class OrthoBench:
    """Benchmark summary (milliseconds, megabytes)."""

    images: int
    image_px: tuple[int, int]
    pixel_m: float
    occlusion: bool
    cells_per_image: float
    compute_ms: TimingStats
    occlusion_ms: TimingStats
    write_ms: TimingStats
    mosaic_ms: TimingStats
    strip_ms_per_image: float  # wall time of the strip (everything but the final mosaic) / N
    mosaic_finish_s: float
    mosaic_px: tuple[int, int]
    peak_rss_strip_mb: float  # peak resident memory before the mosaic is written
    peak_rss_mb: float  # peak resident memory of the whole run


def bench_dsm(length_m: float, seed: int = 0) -> Dsm:
    """Sloped ground with box buildings (10-20 m tall) along the strip."""
    rng = np.random.default_rng(seed)
    width_m = 200.0
    cols, rows = int(length_m / DSM_CELL_M), int(width_m / DSM_CELL_M)
    x = np.arange(cols) * DSM_CELL_M
    heights = np.repeat((BASE_M + SLOPE * x)[None, :], rows, axis=0).astype(np.float32)
    for _ in range(int(N_BUILDINGS_PER_100M * length_m / 100.0)):
        c0, r0 = rng.integers(0, cols - 60), rng.integers(0, rows - 60)
        w, h = rng.integers(16, 60, 2)
        heights[r0:r0 + h, c0:c0 + w] += rng.uniform(10.0, 20.0)
    west, north = ORIGIN_E - DSM_MARGIN_M, ORIGIN_N + width_m / 2
    return Dsm(heights_m=heights, transform=from_origin(west, north, DSM_CELL_M, DSM_CELL_M),
               crs=BENCH_CRS, source="bench")


def bench_image(seed: int = 0) -> np.ndarray:
    """A natural-looking RGB image (smooth shapes plus fine grain), uint8."""
    rng = np.random.default_rng(seed)
    h, w = BENCH_CAMERA.height_px, BENCH_CAMERA.width_px
    coarse = rng.uniform(0, 255, (h // 32, w // 32, 3)).astype(np.float32)
    image = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    image += rng.normal(0, 8, (h, w, 3)).astype(np.float32)
    return np.clip(image, 0, 255).astype(np.uint8)


def run_ortho_bench(n_images: int, out_dir: Path, *, occlusion: bool = True,
                    write: bool = True, background_writes: bool = True) -> OrthoBench:
    """Fly the strip and time every step (module docstring)."""
    length = n_images * SPACING_M + 200.0
    dsm = bench_dsm(length)
    image = bench_image()
    ortho_dir = out_dir / "ortho" if write else None
    options = OrthoOptions(occlusion=occlusion, write_images=write,
                           background_writes=background_writes)
    mosaic = MosaicBuilder(out_dir / "mosaic.tif", BENCH_CRS)
    compute, occlusion_ms, writing, updates, cells = [], [], [], [], []
    t_strip = time.perf_counter()
    with Orthorectifier(dsm, BENCH_CAMERA, BENCH_CRS, ortho_dir, options) as ortho:
        for i in range(n_images):
            x = i * SPACING_M  # the strip follows the sloped ground at HEIGHT_M
            eop = np.array([ORIGIN_E + x, ORIGIN_N, BASE_M + SLOPE * (x + DSM_MARGIN_M) + HEIGHT_M,
                            np.radians(1.0), np.radians(-1.5), np.radians(3.0)])
            result = ortho.add_image(f"img_{i:04d}", image, eop)
            update = mosaic.add(result)
            compute.append(result.compute_ms)
            occlusion_ms.append(result.occlusion_ms)
            writing.append(result.write_ms)
            updates.append(update.update_ms)
            cells.append(result.raster.shape[0] * result.raster.shape[1])
        pixel_m = float(ortho.pixel_m or 0.0)
    strip_ms = (time.perf_counter() - t_strip) * 1e3 / n_images  # pending write included
    rss_strip = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    t0 = time.perf_counter()
    final = mosaic.finish()
    finish_s = time.perf_counter() - t0
    return OrthoBench(
        images=n_images, image_px=(BENCH_CAMERA.width_px, BENCH_CAMERA.height_px),
        pixel_m=pixel_m, occlusion=occlusion, cells_per_image=float(np.mean(cells)),
        compute_ms=TimingStats.from_samples(compute),
        occlusion_ms=TimingStats.from_samples(occlusion_ms),
        write_ms=TimingStats.from_samples(writing),
        mosaic_ms=TimingStats.from_samples(updates), strip_ms_per_image=strip_ms,
        mosaic_finish_s=finish_s,
        mosaic_px=(final.cols, final.rows), peak_rss_strip_mb=rss_strip,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


def main() -> None:
    """Command-line entry: print the benchmark summary as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--no-occlusion", action="store_true")
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--sync-writes", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    result = run_ortho_bench(args.images, args.out, occlusion=not args.no_occlusion,
                             write=not args.no_write, background_writes=not args.sync_writes)
    print(json.dumps(to_jsonable(result), indent=1))


if __name__ == "__main__":
    main()
