"""Timing of the ortho stage at full camera size (docs/benchmarks.md, *Orthorectification*).

``seqat bench ortho --images N --out DIR [--no-occlusion] [--no-write] [--sync-writes]``
(or ``python -m pipeline.bench.ortho`` with the same arguments) flies a strip of ``N``
images of a 2456 x 2058 px camera 100 m over a sloped DSM with box buildings,
orthorectifies each image, updates the mosaic and prints a JSON summary: per-image ortho
time (projection + occlusion + resampling), COG writing time, mosaic update time, the final
mosaic write, process CPU time, and the process's peak memory (run it with two flight
lengths to see that memory does not grow with the flight).

``seqat bench ortho --live MODE --images N --out DIR [--no-write] [--rate-hz R]``: the live
ortho of ``seqat run --ortho`` (:class:`pipeline.ortho.live.LiveOrtho`) behind the Seq-R
estimator on the paper strip (``configs/paper_sim.yaml``: the same 2456 x 2058 px camera, 200
m, 2 Hz), the frames paced at ``R`` Hz as in flight; each image is one decoded JPEG of a
synthetic texture, the surface the flat fallback. MODE ``none`` (no ortho), ``background`` (the
worker thread) or ``foreground`` (in the AT loop): the AT update times per mode show what the
ortho costs the estimator.

``seqat bench ortho --compare-occlusion --out DIR [--images N] [--run OUT]``: the two
occlusion methods of the orthorectifier (``zbuffer``, ``raycast``: open3d's
``RaycastingScene``) on the same images in one process, alternating per image: occlusion time
of each, their ratio, and how far their ``seen`` masks agree; on the benchmark strip, or on the
images, final EOPs and ``dsm.tif`` of a run folder ``OUT``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyproj
from rasterio.transform import from_origin

from pipeline.flight.schema import CameraConfig
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.dsm import Dsm
from pipeline.ortho.mosaic import MosaicBuilder
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.run.store import TimingStats, to_jsonable

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
#: Live benchmark: the paper strip (its camera is BENCH_CAMERA's size), seed, Seq-R threshold.
PAPER_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "paper_sim.yaml"
LIVE_SEED = 1
LIVE_THRESHOLD = 0.1
MIN_POINTS = 20
JPEG_QUALITY = 90


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
    cpu_ms_per_image: float  # process CPU time of the strip (all threads) / N
    load_start: float  # 1-minute load average before and after
    load_end: float


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
    load = os.getloadavg()[0]
    t_strip, cpu_strip = time.perf_counter(), time.process_time()
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
            updates.append(update.processing_ms)
            cells.append(result.raster.shape[0] * result.raster.shape[1])
        pixel_m = float(ortho.pixel_m or 0.0)
    strip_ms = (time.perf_counter() - t_strip) * 1e3 / n_images  # pending write included
    cpu_ms = (time.process_time() - cpu_strip) * 1e3 / n_images
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
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        cpu_ms_per_image=cpu_ms, load_start=load, load_end=os.getloadavg()[0])


@dataclass(frozen=True, kw_only=True)
class LiveBench:
    """Summary of the live benchmark (milliseconds, megabytes)."""

    mode: str  # none | background | foreground
    worker_nice: int | None  # None: the default
    images: int
    rate_hz: float
    write_images: bool
    at_update_ms: TimingStats  # SequentialAT.add_frame
    loop_ms: TimingStats  # AT update + on_image (what the AT loop spends per image)
    ortho_ms: TimingStats  # compute_ms of the live orthos
    latency_ms: TimingStats  # AT update -> mosaic
    queue_ms: TimingStats
    reorthorectified: int
    finish_s: float
    cpu_ms_per_image: float
    peak_rss_mb: float
    load_start: float
    load_end: float


def run_live_bench(n_images: int, out_dir: Path, mode: str, *, write: bool = True,
                   rate_hz: float = 2.0, nice: int | None = None) -> LiveBench:
    """Seq-R on the paper strip with the live ortho behind it (module docstring)."""
    from pipeline.bench.common import load_sim_config
    from pipeline.common.tables import NavTable
    from pipeline.ortho.live import LiveOrtho, LiveOrthoOptions
    from seqat.sequential import SequentialAT, SequentialOptions
    from seqat.simulate import simulate_strip

    if mode not in ("none", "background", "foreground"):
        raise ValueError(f"mode: none, background or foreground, got {mode!r}")
    paper = load_sim_config(PAPER_CONFIG)  # a shorter strip with the paper's point density
    config = dataclasses.replace(paper, n_images=n_images, n_points=max(
        MIN_POINTS, round(paper.n_points * n_images / paper.n_images)))
    flight = simulate_strip(config, LIVE_SEED)
    cam = flight.camera
    camera = CameraConfig(model="PINHOLE", width_px=config.width_px, height_px=config.height_px,
                          fx_px=cam.f_px, fy_px=cam.f_px, cx_px=cam.cx_px, cy_px=cam.cy_px)
    out_dir.mkdir(parents=True, exist_ok=True)
    jpeg = out_dir / "texture.jpg"
    image = cv2.resize(bench_image(), (config.width_px, config.height_px))
    cv2.imwrite(str(jpeg), cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    nav = NavTable(image_ids=flight.image_ids, times_s=flight.times_s, eop=flight.nav_eop)
    live = None if mode == "none" else LiveOrtho(
        out_dir, crs=BENCH_CRS, camera=camera, images=dict.fromkeys(flight.image_ids, jpeg),
        nav=nav, dsm=None, ortho_options=OrthoOptions(write_images=write),
        options=LiveOrthoOptions(background=mode == "background",
                                 **({} if nice is None else {"worker_nice": nice})))
    at = SequentialAT(cam, SequentialOptions(correlation_threshold=LIVE_THRESHOLD))
    at_ms, loop_ms = [], []
    load = os.getloadavg()[0]
    t0, cpu0 = time.perf_counter(), time.process_time()
    for k, frame in enumerate(flight.frames()):
        time.sleep(max(0.0, t0 + k / rate_hz - time.perf_counter()))  # the next frame arrives
        t = time.perf_counter()
        update = at.add_frame(frame)
        at_ms.append((time.perf_counter() - t) * 1e3)
        if live is not None:
            live.on_image(frame, update, at)
        loop_ms.append((time.perf_counter() - t) * 1e3)
    empty = TimingStats.from_samples([])
    ortho = latency = queue = empty
    again, finish_s = 0, 0.0
    if live is not None:
        with live:
            live.on_finish(at.solution())
        summary = live.result()
        assert summary.live is not None
        ortho = summary.compute_ms
        latency, queue = summary.live.latency_ms, summary.live.queue_ms
        again, finish_s = len(summary.live.images_reorthorectified), summary.live.finish_s
    return LiveBench(
        mode=mode, worker_nice=nice, images=n_images, rate_hz=rate_hz, write_images=write,
        at_update_ms=TimingStats.from_samples(at_ms), loop_ms=TimingStats.from_samples(loop_ms),
        ortho_ms=ortho, latency_ms=latency, queue_ms=queue, reorthorectified=again,
        finish_s=finish_s, cpu_ms_per_image=(time.process_time() - cpu0) * 1e3 / n_images,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        load_start=load, load_end=os.getloadavg()[0])


@dataclass(frozen=True, kw_only=True)
class OcclusionCompare:
    """Summary of ``--compare-occlusion`` (module docstring)."""

    source: str
    images: int
    image_px: tuple[int, int]
    pixel_m: float
    dsm_cells: int
    mesh_triangles: int
    mesh_build_ms: float
    zbuffer_ms: TimingStats
    raycast_ms: TimingStats
    ratio_median: float  # raycast / zbuffer, median of the per-image ratios
    cells: int  # footprint cells with a DSM height, all images
    hidden_zbuffer: int
    hidden_raycast: int
    disagree: int  # cells one method sees and the other hides
    agreement: float  # 1 - disagree / cells
    load_start: float
    load_end: float


def compare_occlusion(images: Sequence[tuple[str, np.ndarray, np.ndarray]], dsm: Dsm,
                      camera: CameraConfig, crs: pyproj.CRS, source: str,
                      pixel_m: float | None = None) -> OcclusionCompare:
    """Orthorectify each image with both occlusion methods (no writing) and compare."""
    load = os.getloadavg()[0]
    options = {m: OrthoOptions(occlusion_method=m, write_images=False, pixel_m=pixel_m)
               for m in ("zbuffer", "raycast")}
    times: dict[str, list[float]] = {"zbuffer": [], "raycast": []}
    cells = hidden_z = hidden_r = disagree = 0
    with Orthorectifier(dsm, camera, crs, None, options["zbuffer"]) as zb, \
            Orthorectifier(dsm, camera, crs, None, options["raycast"]) as rc:
        t0 = time.perf_counter()
        triangles = rc.prepare_occlusion()  # built here to time it apart
        build_ms = (time.perf_counter() - t0) * 1e3
        for image_id, image, eop in images:
            res = {}
            for m, ortho in (("zbuffer", zb), ("raycast", rc)):
                res[m] = ortho.add_image(image_id, image, eop)
                times[m].append(res[m].occlusion_ms)
            a, b = res["zbuffer"], res["raycast"]
            sa, sb = _on_grid(a.raster), _on_grid(b.raster)
            cells += a.seen_cells + a.occluded_cells
            hidden_z += a.occluded_cells
            hidden_r += b.occluded_cells
            disagree += len(sa ^ sb)
        pixel = float(zb.pixel_m or 0.0)
    ratios = [r / z for r, z in zip(times["raycast"], times["zbuffer"], strict=True) if z > 0]
    return OcclusionCompare(
        source=source, images=len(images), image_px=(camera.width_px, camera.height_px),
        pixel_m=pixel, dsm_cells=int(dsm.heights_m.size), mesh_triangles=triangles,
        mesh_build_ms=build_ms, zbuffer_ms=TimingStats.from_samples(times["zbuffer"]),
        raycast_ms=TimingStats.from_samples(times["raycast"]),
        ratio_median=float(np.median(ratios)) if ratios else float("nan"), cells=cells,
        hidden_zbuffer=hidden_z, hidden_raycast=hidden_r, disagree=disagree,
        agreement=1.0 - disagree / max(cells, 1), load_start=load, load_end=os.getloadavg()[0])


def _on_grid(raster: object) -> set[tuple[int, int]]:
    """Global (row, col) of the cells a cropped ortho raster sees."""
    r, c = np.nonzero(raster.seen)  # type: ignore[attr-defined]
    return set(zip((r + raster.row0).tolist(), (c + raster.col0).tolist(), strict=True))  # type: ignore[attr-defined]


def occlusion_on_strip(n_images: int) -> OcclusionCompare:
    """``--compare-occlusion`` on the benchmark strip (sloped DSM with box buildings)."""
    dsm = bench_dsm(n_images * SPACING_M + 200.0)
    image = bench_image()
    images = []
    for i in range(n_images):
        x = i * SPACING_M
        eop = np.array([ORIGIN_E + x, ORIGIN_N, BASE_M + SLOPE * (x + DSM_MARGIN_M) + HEIGHT_M,
                        np.radians(1.0), np.radians(-1.5), np.radians(3.0)])
        images.append((f"img_{i:04d}", image, eop))
    return compare_occlusion(images, dsm, BENCH_CAMERA, BENCH_CRS, "bench strip")


def occlusion_on_run(run_dir: Path) -> OcclusionCompare:
    """``--compare-occlusion --run OUT``: the run's images, final EOPs and ``dsm.tif``."""
    from pipeline.ortho.dsm import read_dsm
    from pipeline.ortho.stage import DSM_FILE, image_files, read_image
    from pipeline.run.store import read_run

    run = read_run(run_dir)
    if run.images_dir is None:
        raise SystemExit(f"{run_dir}: an observations flight has no images")
    files = image_files(run.images_dir)
    images = [(iid, read_image(files[iid]), eop)
              for iid, eop in zip(run.eop.image_ids, run.eop.eop, strict=True) if iid in files]
    return compare_occlusion(images, read_dsm(run_dir / DSM_FILE, run.crs), run.camera,
                             run.crs, str(run_dir))


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry (``seqat bench ortho ARGS``, or ``python -m`` on ``sys.argv``): print
    the benchmark summary as JSON."""
    parser = argparse.ArgumentParser(prog=None if argv is None else "seqat bench ortho",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--no-occlusion", action="store_true")
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--sync-writes", action="store_true")
    parser.add_argument("--live", choices=("none", "background", "foreground"), type=str.lower)
    parser.add_argument("--rate-hz", type=float, default=2.0)
    parser.add_argument("--nice", type=int, help="live: worker niceness (default: 10)")
    parser.add_argument("--compare-occlusion", action="store_true")
    parser.add_argument("--run", type=Path, help="--compare-occlusion on a run folder")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    result: OrthoBench | LiveBench | OcclusionCompare
    if args.compare_occlusion:
        result = (occlusion_on_run(args.run) if args.run is not None
                  else occlusion_on_strip(args.images))
    elif args.live is not None:
        result = run_live_bench(args.images, args.out, args.live, write=not args.no_write,
                                rate_hz=args.rate_hz, nice=args.nice)
    else:
        result = run_ortho_bench(args.images, args.out, occlusion=not args.no_occlusion,
                                 write=not args.no_write,
                                 background_writes=not args.sync_writes)
    print(json.dumps(to_jsonable(result), indent=1))


if __name__ == "__main__":
    main()
