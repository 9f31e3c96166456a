"""Products of a rendered flight against its truth (docs/benchmarks.md, issues 5 and 6).

``seqat bench rendered OUT --config CONFIG.yaml [--json FILE]`` (or ``python -m
pipeline.bench.rendered`` with the same arguments) on the run folder
of ``seqat run FLIGHT --out OUT --ortho`` (FLIGHT rendered by ``seqat simulate CONFIG.yaml``):

* **mosaic check points**: the planimetric error of ``OUT/mosaic.tif`` at the flight's check
  points, measured against the texture the renderer draped (:func:`pipeline.bench.mosaic_accuracy.
  mosaic_shifts`), as RMSE_x, RMSE_y, RMSE_H (ASPRS 2023) and in ground pixels; the same for
  a mosaic made with the GPS/INS EOPs (direct georeferencing) and, when ``OUT/reference/``
  exists, with the COLMAP reference's, both by ``seqat ortho`` on a copy of the run folder
  (``OUT/bench_<eops>/``, same DSM and pixel, no per-image COGs);
* **DSM vs truth**: ``OUT/dsm.tif`` minus the rendering surface (highest LiDAR point per
  ``source.cell_m`` cell of the source clouds, gaps filled, :func:`pipeline.simulate.render_scene.
  lidar_surface`) at the DSM's valid cell centres: mean, RMSE, median and 95th percentile
  of the absolute difference;
* **latency** per image by stage (:mod:`pipeline.run.latency`).

Prints the summary as JSON (and writes it to ``--json``).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio

from pipeline.bench.mosaic_accuracy import mosaic_shifts
from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import (
    EOP_FILE,
    NAV_FILE,
    OBSERVATIONS_FILE,
    POINTS_FILE,
    REFERENCE_DIR,
    RUN_FILE,
)
from pipeline.flight.nav_files import read_ground_points
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.dsm import parse_crs, read_dsm
from pipeline.ortho.stage import DSM_FILE, MOSAIC_FILE, orthorectify_run
from pipeline.report.model import find_checkpoints
from pipeline.run.latency import LatencyTable, latency_table, read_ortho_json
from pipeline.run.store import RunFolder, format_eop_csv, read_run, to_jsonable
from pipeline.simulate.config import RenderSimulateConfig, load_simulate_config
from pipeline.simulate.render_scene import lidar_surface, read_texture
from seqat.errors import ConfigError, InputDataError
from seqat.types import EopEstimate

#: Files of a run folder copied for a mosaic with other EOPs.
RUN_FILES = (EOP_FILE, POINTS_FILE, RUN_FILE, NAV_FILE, OBSERVATIONS_FILE)


@dataclass(frozen=True, kw_only=True)
class MosaicCheck:
    """Planimetric errors of one mosaic at the check points."""

    eops: str  # seq-r (the run's), direct, colmap
    measured: int
    skipped: int
    rmse_x_m: float
    rmse_y_m: float
    rmse_h_m: float
    rmse_h_gsd: float  # RMSE_H / pixel
    max_abs_dx_m: float
    max_abs_dy_m: float


@dataclass(frozen=True, kw_only=True)
class DsmCheck:
    """``dsm.tif`` minus the rendering surface over the DSM's valid cells."""

    cell_m: float
    truth_cell_m: float
    cells: int
    nodata_fraction: float
    mean_m: float
    rmse_m: float
    median_abs_m: float
    p95_abs_m: float


@dataclass(frozen=True, kw_only=True)
class RenderedBench:
    run: str
    pixel_m: float
    mosaics: tuple[MosaicCheck, ...]
    dsm: DsmCheck
    latency: LatencyTable


def _mosaic_check(label: str, mosaic: Path, ids: tuple[str, ...], xy: np.ndarray,
                  texture: object, pixel_m: float) -> MosaicCheck:
    s = mosaic_shifts(mosaic, ids, xy, texture)  # type: ignore[arg-type]
    d = s.dxy_m
    rx, ry = (float(np.sqrt(np.mean(d[:, i] ** 2))) if len(d) else math.nan for i in (0, 1))
    return MosaicCheck(eops=label, measured=len(s.point_ids), skipped=len(s.skipped),
                       rmse_x_m=rx, rmse_y_m=ry, rmse_h_m=s.rmse_h_m,
                       rmse_h_gsd=s.rmse_h_m / pixel_m,
                       max_abs_dx_m=float(np.abs(d[:, 0]).max()) if len(d) else math.nan,
                       max_abs_dy_m=float(np.abs(d[:, 1]).max()) if len(d) else math.nan)


def _mosaic_with(run_dir: Path, label: str, eop_text: str, pixel_m: float) -> Path:
    """``seqat ortho`` on a copy of the run folder whose ``eop.csv`` is ``eop_text``."""
    folder = run_dir / f"bench_{label}"
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir()
    for name in RUN_FILES:
        shutil.copy(run_dir / name, folder / name)
    atomic_write_text(folder / EOP_FILE, eop_text)
    summary = orthorectify_run(folder, dsm_path=run_dir / DSM_FILE, progress=False,
                               options=OrthoOptions(pixel_m=pixel_m, write_images=False))
    return summary.mosaic


def _nav_eop_text(run: RunFolder) -> str:
    """The GPS/INS EOPs (``nav.csv``) as an ``eop.csv`` without sigmas."""
    return format_eop_csv([EopEstimate(image_id=i, eop=e, sigma=np.full(6, np.nan))
                           for i, e in zip(run.nav.image_ids, run.nav.eop, strict=True)])


def dsm_check(run_dir: Path, config: RenderSimulateConfig, config_dir: Path) -> DsmCheck:
    """``OUT/dsm.tif`` against the rendering surface (module docstring)."""
    run = read_run(run_dir)
    dsm = read_dsm(run_dir / DSM_FILE, run.crs)
    src = config.source
    las = [p if p.is_absolute() else config_dir / p for p in map(Path, src.lidar)]
    las_crs = parse_crs(src.las_crs, "source.las_crs", config_dir) if src.las_crs else None
    truth = lidar_surface(las, run.crs, las_crs, src.cell_m, dsm.bounds)
    rows, cols = dsm.heights_m.shape
    cw, ch = dsm.cell_m
    x = dsm.transform.c + (np.arange(cols) + 0.5) * cw
    y = dsm.transform.f - (np.arange(rows) + 0.5) * ch
    X, Y = np.meshgrid(x, y)
    valid = np.isfinite(dsm.heights_m)
    d = dsm.heights_m[valid] - truth.sample(X[valid], Y[valid])
    return DsmCheck(cell_m=cw, truth_cell_m=src.cell_m, cells=int(valid.sum()),
                    nodata_fraction=float(1.0 - valid.mean()), mean_m=float(d.mean()),
                    rmse_m=float(np.sqrt(np.mean(d**2))),
                    median_abs_m=float(np.median(np.abs(d))),
                    p95_abs_m=float(np.percentile(np.abs(d), 95)))


def run_rendered_bench(run_dir: Path | str, config_path: Path | str) -> RenderedBench:
    """Measure a rendered flight's products against truth (module docstring)."""
    run_dir, config_path = Path(run_dir), Path(config_path)
    config = load_simulate_config(config_path)
    if not isinstance(config, RenderSimulateConfig):
        raise ConfigError(f"{config_path}: not a rendered flight config (kind: rendered)")
    run = read_run(run_dir)
    found = find_checkpoints(run.flight_dir)
    if found is None or not (run_dir / MOSAIC_FILE).is_file():
        raise InputDataError(f"{run_dir}: needs a mosaic (seqat run --ortho) of a flight with "
                             "check points")
    known = read_ground_points(found[0])
    config_dir = config_path.parent
    texture = read_texture(config_dir / config.source.texture, run.crs,
                           parse_crs(config.source.texture_crs, "source.texture_crs",
                                     config_dir))
    with rasterio.open(run_dir / MOSAIC_FILE) as src:
        pixel_m = float(src.transform.a)
    xy = known.xyz_m[:, :2]
    checks = [_mosaic_check("seq-r", run_dir / MOSAIC_FILE, known.point_ids, xy, texture,
                            pixel_m)]
    others = {"direct": _nav_eop_text(run)}
    if (run_dir / REFERENCE_DIR / EOP_FILE).is_file():
        others["colmap"] = (run_dir / REFERENCE_DIR / EOP_FILE).read_text(encoding="utf-8")
    for label, text in others.items():
        mosaic = _mosaic_with(run_dir, label, text, pixel_m)
        checks.append(_mosaic_check(label, mosaic, known.point_ids, xy, texture, pixel_m))
    return RenderedBench(run=str(run_dir), pixel_m=pixel_m, mosaics=tuple(checks),
                         dsm=dsm_check(run_dir, config, config_dir),
                         latency=latency_table(run.record, read_ortho_json(run_dir)))


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry (``seqat bench rendered ARGS``, or ``python -m`` on ``sys.argv``):
    print (and write) the summary as JSON."""
    parser = argparse.ArgumentParser(prog=None if argv is None else "seqat bench rendered",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--config", type=Path, required=True)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    text = json.dumps(to_jsonable(run_rendered_bench(args.run, args.config)), indent=1,
                      allow_nan=False) + "\n"
    if args.json is not None:
        atomic_write_text(args.json, text)
    print(text, end="")


if __name__ == "__main__":
    main()
