"""Seq-R on the paper strip with many more tie points: long tracks (each point in ~20 images,
~360 observations per image) and a window of ~85 images / ~5600 parameters. CPU time of
every sequential update (``time.process_time``), the window's size, and a checksum of the
real-time EOPs (to compare two versions of the code on the same flight).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=CHECKOUT python CHECKOUT/benchmarks/long_tracks.py \
        [--points 3000] [--images 160] [--seed 1]

``PYTHONPATH`` picks the checkout whose ``seqat`` runs (the installed one otherwise). Run two
checkouts one after the other: the machine is shared, only a pair of runs made together
compares (docs/benchmarks.md, *Long tracks*).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from pipeline.bench.common import load_sim_config
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import simulate_strip

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "paper_sim.yaml"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=3000)
    ap.add_argument("--images", type=int, default=160)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    cfg = dataclasses.replace(load_sim_config(CONFIG), n_points=a.points, n_images=a.images)
    flight = simulate_strip(cfg, a.seed)
    frames = list(flight.frames())
    est = SequentialAT(flight.camera, SequentialOptions(correlation_threshold=0.1))
    ms, images, params = [], [], []
    for frame in frames:
        t0 = time.process_time()
        upd = est.add_frame(frame)
        dt = (time.process_time() - t0) * 1e3
        if upd.stage == "sequential":
            ms.append(dt)
            images.append(upd.window_images)
            params.append(upd.window_params)
    eop = np.array([e.eop for e in est.solution(smoothed=False).eops])
    p50, p99, top = np.percentile(ms, [50, 99, 100])
    print(f"observations per image {np.mean([len(f.point_ids) for f in frames]):.1f}; "
          f"{len(ms)} sequential updates, CPU ms p50 {p50:.1f} p99 {p99:.1f} max {top:.1f}; "
          f"window median {np.median(images):.0f} images / {np.median(params):.0f} "
          f"parameters; EOP checksum {float(np.abs(eop).sum())!r}")


if __name__ == "__main__":
    main()
