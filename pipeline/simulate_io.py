"""``seqat simulate``: write a simulated flight as an ordinary flight folder (+ ``truth/``).

The folder is built in a temporary sibling folder and renamed into place, so a reader never
sees a half-written flight. An existing output folder is replaced only if it is empty or is
itself a flight folder (has ``flight.yaml``); anything else is refused.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pipeline.config import RenderSimulateConfig, load_simulate_config
from pipeline.csvio import format_csv_line
from pipeline.flight import (
    FLIGHT_YAML,
    GROUND_POINT_COLUMNS,
    OBSERVATION_COLUMNS,
    TRUTH_DIR,
    resolve_projected_crs,
)
from pipeline.store import fmt, format_nav_csv, fsync_dir
from seqat.errors import InputDataError
from seqat.simulate import SimulatedFlight, simulate_strip
from seqat.types import FloatArray

#: File names written into a simulated flight folder.
NAV_FILE = "nav.csv"
OBSERVATIONS_FILE = "observations.csv"
#: Sigmas in flight.yaml are rounded to this many significant digits (hides deg<->rad noise).
SIGMA_SIGNIFICANT_DIGITS = 12
#: Components of a position or attitude sigma.
AXES = 3


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


def _round_sig(value: float) -> float:
    return float(f"{value:.{SIGMA_SIGNIFICANT_DIGITS}g}")


def _sigma_value(values: FloatArray) -> float | list[float]:
    """A scalar when the three components agree, else a list (flight.yaml style)."""
    rounded = [_round_sig(float(v)) for v in values]
    return rounded[0] if len(set(rounded)) == 1 else rounded


def _flight_yaml(flight: SimulatedFlight, crs: str) -> str:
    cam = flight.camera
    sigma = np.asarray(flight.nav_sigma, dtype=np.float64)
    doc = {
        "crs": crs,
        "camera": {"model": "PINHOLE", "width_px": int(cam.width_px),
                   "height_px": int(cam.height_px), "fx_px": float(cam.f_px),
                   "fy_px": float(cam.f_px), "cx_px": float(cam.cx_px),
                   "cy_px": float(cam.cy_px)},
        "nav": {"file": NAV_FILE, "frame": "projected",
                "sigma_position_m": _sigma_value(sigma[:AXES]),
                "sigma_attitude_deg": _sigma_value(np.degrees(sigma[AXES:]))},
        "sigma_image_px": float(flight.sigma_px),
        "observations": OBSERVATIONS_FILE,
    }
    header = ("# Simulated flight written by `seqat simulate` (docs/formats.md).\n"
              "# Exact truth in truth/; never used by the adjustment.\n")
    return header + str(yaml.safe_dump(doc, sort_keys=False))


def _observations_csv(flight: SimulatedFlight) -> str:
    obs_image = np.asarray(flight.obs_image)
    if obs_image.size and np.any(np.diff(obs_image) < 0):
        # Group by image in acquisition order (stable: keeps each image's point order).
        order = np.argsort(obs_image, kind="stable")
    else:
        order = np.arange(obs_image.size)
    lines = [format_csv_line(OBSERVATION_COLUMNS)]
    for k in order:
        u, v = flight.obs_uv[k]
        lines.append(format_csv_line([flight.image_ids[flight.obs_image[k]],
                                      flight.point_ids[flight.obs_point[k]], fmt(u), fmt(v)]))
    return "".join(lines)


def _points_csv(ids: tuple[str, ...], xyz_m: FloatArray) -> str:
    lines = [format_csv_line(GROUND_POINT_COLUMNS)]
    lines += [format_csv_line([pid, *(fmt(v) for v in p)]) for pid, p in zip(ids, xyz_m,
                                                                             strict=True)]
    return "".join(lines)


def _write(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8", newline="") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())


def check_replaceable(out_dir: Path) -> None:
    """Refuse to replace anything but an absent or empty folder or an earlier flight folder.

    Raises
    ------
    InputDataError
        ``out_dir`` is a file, or a non-empty folder without ``flight.yaml``.
    """
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise InputDataError(f"{out_dir}: exists and is not a folder")
    if (out_dir / FLIGHT_YAML).is_file() or not any(out_dir.iterdir()):
        return
    raise InputDataError(f"{out_dir}: exists and is not a flight folder (no {FLIGHT_YAML}); "
                         "refusing to replace it")


def write_simulated_flight(flight: SimulatedFlight, crs: str, out_dir: Path | str) -> Path:
    """Write a simulated flight as a flight folder with ``truth/``.

    Writes ``flight.yaml`` (PINHOLE camera, projected nav, sigmas), ``nav.csv``,
    ``observations.csv`` (grouped by image in acquisition order), ``truth/eop.csv`` and
    ``truth/points.csv``. The folder appears complete or not at all.

    Parameters
    ----------
    flight : SimulatedFlight
    crs : str
        Projected CRS of the world coordinates, e.g. ``EPSG:32652``.
    out_dir : Path or str
        Replaced if it is empty or an earlier flight folder (:func:`check_replaceable`).

    Returns
    -------
    Path
        ``out_dir``.
    """
    out = Path(out_dir)
    resolve_projected_crs(crs, "crs")
    check_replaceable(out)
    with building_folder(out) as tmp:
        _write(tmp / FLIGHT_YAML, _flight_yaml(flight, crs))
        _write(tmp / NAV_FILE, format_nav_csv(flight.image_ids, flight.times_s, flight.nav_eop))
        _write(tmp / OBSERVATIONS_FILE, _observations_csv(flight))
        (tmp / TRUTH_DIR).mkdir()
        _write(tmp / TRUTH_DIR / "eop.csv", format_nav_csv(flight.image_ids, flight.times_s,
                                                     flight.truth_eop))
        _write(tmp / TRUTH_DIR / "points.csv", _points_csv(flight.point_ids, flight.truth_xyz))
    return out


@contextlib.contextmanager
def building_folder(out: Path) -> Iterator[Path]:
    """Build a folder in a temporary sibling and publish it as ``out`` atomically.

    Yields the temporary folder (mode as a new folder gets under the umask). When the block
    succeeds, every sub-folder and the folder are fsynced and it replaces ``out`` (a
    previous ``out`` is moved aside first and removed after); when it fails, the temporary
    folder is removed and a previous ``out`` is put back.
    """
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    old: Path | None = None
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        for sub in tmp.iterdir():
            if sub.is_dir():
                fsync_dir(sub)
        fsync_dir(tmp)
        if out.exists():
            old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
            os.replace(out, old / out.name)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and (old / out.name).exists() and not out.exists():
            os.replace(old / out.name, out)  # put the previous folder back
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    fsync_dir(out.parent)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def simulate_to_folder(config_path: Path | str, out_dir: Path | str, seed: int) -> SimulateSummary:
    """The ``seqat simulate`` stage: read a simulation config, simulate, write the folder.

    Parameters
    ----------
    config_path : Path or str
        ``configs/*_sim.yaml`` (:class:`pipeline.config.SimulateConfig`).
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
        from pipeline.render_flight import render_to_folder  # imports this module

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
