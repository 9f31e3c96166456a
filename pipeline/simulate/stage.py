"""The ``seqat simulate`` stage: a simulation config in, a flight folder (+ ``truth/``) out."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.flight.folder import resolve_projected_crs
from pipeline.simulate.config import RenderSimulateConfig, load_simulate_config
from pipeline.simulate.folder import check_replaceable, write_simulated_flight
from pipeline.simulate.rendered import render_to_folder
from seqat.simulate import simulate_strip


@dataclass(frozen=True, kw_only=True)
class SimulateSummary:
    """What ``seqat simulate`` wrote."""

    out_dir: Path
    crs: str
    seed: int
    n_images: int
    n_points: int
    n_observations: int
    duration_s: float


def simulate_to_folder(config_path: Path | str, out_dir: Path | str, seed: int) -> SimulateSummary:
    """The ``seqat simulate`` stage: read a simulation config, simulate, write the folder.

    Parameters
    ----------
    config_path : Path or str
        ``configs/*_sim.yaml`` (:class:`pipeline.simulate.config.SimulateConfig`).
    out_dir : Path or str
    seed : int
        Random seed; the same config and seed give the same flight.

    Raises
    ------
    ConfigError
        Bad config.
    InputDataError
        Unusable CRS or an output folder that cannot be replaced (checked before simulating).
    """
    config = load_simulate_config(config_path)
    if isinstance(config, RenderSimulateConfig):
        rendered = render_to_folder(config, Path(config_path).parent, out_dir, seed)
        return SimulateSummary(out_dir=rendered.out_dir, crs=rendered.crs, seed=seed,
                               n_images=rendered.n_images, n_points=rendered.n_points,
                               n_observations=rendered.n_observations,
                               duration_s=rendered.duration_s)
    resolve_projected_crs(config.crs, f"{config_path}")
    out = Path(out_dir)
    check_replaceable(out)
    flight = simulate_strip(config.simulation, seed)
    write_simulated_flight(flight, config.crs, out)
    times = np.asarray(flight.times_s, dtype=np.float64)
    duration = float(times[-1] - times[0]) if times.size else math.nan
    return SimulateSummary(out_dir=out, crs=config.crs, seed=seed,
                           n_images=len(flight.image_ids), n_points=len(flight.point_ids),
                           n_observations=int(np.asarray(flight.obs_image).size),
                           duration_s=duration)
