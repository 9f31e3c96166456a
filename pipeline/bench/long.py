"""``seqat bench long``: memory and update time along a very long simulated strip (issue 7).

A strip of ``n`` images with the paper's camera and flight (seed 000 Table 2 scaled in
length) streams through Seq-R twice: with ``smoothing_lag`` (final parameters handed to a sink
that appends them to CSV files, as a long flight must) and without (every departure record
kept for the exact RTS pass). Every ``n / 20`` images the resident set size and the median
update time of the last chunk are sampled. Written to ``OUT/bench_long.json`` and
``OUT/long_memory.png``; the numbers go to docs/benchmarks.md.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.progress import (  # noqa: E402
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)

from pipeline.bench.common import load_average, machine  # noqa: E402
from pipeline.bench.report import Machine  # noqa: E402
from pipeline.common.atomic import atomic_write_text
from pipeline.run.store import to_jsonable  # noqa: E402
from seqat.sequential import SequentialAT, SequentialOptions  # noqa: E402
from seqat.simulate import StripSimConfig, simulate_strip  # noqa: E402
from seqat.types import EopEstimate, PointEstimate  # noqa: E402

#: Tie points per image of the paper strip (304 points over 384 images).
POINTS_PER_IMAGE = 304 / 384
#: Samples along the strip.
SAMPLES = 20


@dataclass(frozen=True, kw_only=True)
class Sample:
    """State after ``images`` images."""

    images: int
    rss_mb: float
    median_update_ms: float  # over the images since the previous sample
    window_params: int
    records_kept: int


@dataclass(frozen=True, kw_only=True)
class Variant:
    """One run along the strip."""

    name: str
    smoothing_lag: int | None
    samples: tuple[Sample, ...]
    wall_s: float
    rss_growth_kb_per_image: float  # slope over the second half of the strip


@dataclass(frozen=True, kw_only=True)
class LongBench:
    machine: Machine
    images: int
    points: int
    variants: tuple[Variant, ...]


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * 4096 / 2**20


class _CsvSink:
    """Appends final parameters to two CSV files as they arrive (constant memory)."""

    def __init__(self, out: Path) -> None:
        self._eop = (out / "final_eop.csv").open("w", newline="")
        self._pts = (out / "final_points.csv").open("w", newline="")
        self._we, self._wp = csv.writer(self._eop), csv.writer(self._pts)
        self._we.writerow(["image_id", "x_m", "y_m", "z_m", "omega_rad", "phi_rad", "kappa_rad"])
        self._wp.writerow(["point_id", "x_m", "y_m", "z_m", "n_obs"])

    def __call__(self, item: EopEstimate | PointEstimate) -> None:
        if isinstance(item, EopEstimate):
            self._we.writerow([item.image_id, *(f"{v:.6f}" for v in item.eop)])
        else:
            self._wp.writerow([item.point_id, *(f"{v:.4f}" for v in item.xyz_m), item.n_obs])

    def close(self) -> None:
        self._eop.close()
        self._pts.close()


def _run(name: str, config: StripSimConfig, seed: int, lag: int | None, out: Path,
         progress: Progress) -> Variant:
    flight = simulate_strip(config, seed)
    sink = _CsvSink(out) if lag is not None else None
    est = SequentialAT(flight.camera, SequentialOptions(smoothing_lag=lag), sink=sink)
    n = len(flight.image_ids)
    every = max(1, n // SAMPLES)
    samples, chunk = [], []
    task = progress.add_task(name, total=n)
    t0 = time.perf_counter()
    for k, frame in enumerate(flight.frames()):
        u = est.add_frame(frame)
        chunk.append(u.processing_ms)
        if (k + 1) % every == 0 or k + 1 == n:
            samples.append(Sample(images=k + 1, rss_mb=_rss_mb(),
                                  median_update_ms=float(np.median(chunk)),
                                  window_params=u.window_params,
                                  records_kept=sum(r is not None for r in est._departures)))
            chunk = []
            progress.update(task, completed=k + 1)
    wall = time.perf_counter() - t0
    if sink is not None:
        sink.close()
    half = [s for s in samples if s.images >= n / 2]
    slope = (float(np.polyfit([s.images for s in half], [s.rss_mb for s in half], 1)[0])
             * 1024 if len(half) >= 2 else float("nan"))
    return Variant(name=name, smoothing_lag=lag, samples=tuple(samples), wall_s=wall,
                   rss_growth_kb_per_image=slope)


def run_long_bench(out: Path | str, *, images: int = 10_000, lag: int = 200, seed: int = 1,
                   compare_full: bool = True) -> LongBench:
    """Stream a long strip through Seq-R with and without a smoothing lag; see the module."""
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    load_start = load_average()
    config = StripSimConfig(n_images=images, n_points=int(round(images * POINTS_PER_IMAGE)))
    console = Console(stderr=True, soft_wrap=True)
    variants = []
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True,
                  disable=not console.is_terminal) as progress:
        variants.append(_run(f"seq-r, lag {lag}", config, seed, lag, out_dir, progress))
        if compare_full:
            variants.append(_run("seq-r, no lag", config, seed, None, out_dir, progress))
    bench = LongBench(machine=machine(load_start), images=images,
                      points=config.n_points, variants=tuple(variants))
    atomic_write_text(out_dir / "bench_long.json",
                      json.dumps(to_jsonable(dataclasses.asdict(bench)), indent=2))
    _plot(bench, out_dir / "long_memory.png")
    return bench


def _plot(bench: LongBench, path: Path) -> None:
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for v in bench.variants:
        x = [s.images for s in v.samples]
        ax1.plot(x, [s.rss_mb for s in v.samples], marker="o", label=v.name)
        ax2.plot(x, [s.median_update_ms for s in v.samples], marker="o", label=v.name)
    ax1.set(xlabel="images", ylabel="resident memory (MB)", title="Memory along the strip")
    ax2.set(xlabel="images", ylabel="median update (ms)", title="Update time per chunk")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
