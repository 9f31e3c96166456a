"""One gross blunder in one random observation row of the paper strip: Seq-R with every
default, EOP position and GP RMSE against truth as a ratio to the clean run (issue 12's
target: within 10 % and 25 %).

    OPENBLAS_NUM_THREADS=1 python benchmarks/one_blunder.py [--seed S ...] [--rows N]

Each case moves one observation row by 30-400 px in a random direction, kept in the image
(:func:`pipeline.bench.faults.injection.inject_blunders` with one row: a wrong but in-image
match), and streams the strip again.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from pipeline.bench.common import load_sim_config
from pipeline.bench.faults.injection import inject_blunders
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, simulate_strip

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "paper_sim.yaml"


def rmse(flight: SimulatedFlight) -> tuple[float, float]:
    """EOP position and GP RMSE (m, r.m.s. over the components) of Seq-R's real-time values."""
    est = SequentialAT(flight.camera, SequentialOptions())
    for f in flight.frames():
        est.add_frame(f)
    sol = est.solution(smoothed=False)
    eop = np.array([e.eop for e in sol.eops])
    index = {p: j for j, p in enumerate(flight.point_ids)}
    xyz = np.array([p.xyz_m for p in sol.points])
    truth = flight.truth_xyz[[index[p.point_id] for p in sol.points]]
    return (float(np.sqrt(np.mean((eop[:, :3] - flight.truth_eop[: len(eop), :3]) ** 2))),
            float(np.sqrt(np.mean((xyz - truth) ** 2))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, action="append")
    ap.add_argument("--rows", type=int, default=8, help="blundered cases per seed")
    args = ap.parse_args()
    cfg = load_sim_config(CONFIG)
    for seed in args.seed or [1]:
        flight = simulate_strip(cfg, seed)
        e0, g0 = rmse(flight)
        rng = np.random.default_rng(100 + seed)
        cam, rows = flight.camera, flight.obs_uv.shape[0]
        worst = [0.0, 0.0]
        for _ in range(args.rows):
            b = inject_blunders(flight.obs_uv, cam.width_px, cam.height_px, 1.0 / rows, rng,
                                min_px=30.0, max_px=400.0)
            e, g = rmse(dataclasses.replace(flight, obs_uv=b.uv_px))
            k = int(b.index[0])
            worst = [max(worst[0], e / e0), max(worst[1], g / g0)]
            size = float(np.hypot(*b.offset_px[0]))
            print(f"seed {seed} row {k} (image {flight.obs_image[k]}, {size:.0f} px): "
                  f"EOP {e / e0:.3f} GP {g / g0:.3f}", flush=True)
        print(f"seed {seed}: clean EOP {e0:.4f} m GP {g0:.4f} m; worst ratio EOP {worst[0]:.3f} "
              f"GP {worst[1]:.3f}")


if __name__ == "__main__":
    main()
