"""``seqat simulate``: write a simulated flight as an ordinary flight folder (+ ``truth/``).

The folder is built in a temporary sibling folder and renamed into place, so a reader never
sees a half-written flight. An existing output folder is replaced only if it is empty or is
itself a flight folder (has ``flight.yaml``); anything else is refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from pipeline.common.atomic import building_folder, write_synced
from pipeline.common.columns import (
    FLIGHT_YAML,
    GROUND_POINT_COLUMNS,
    NAV_FILE,
    OBSERVATIONS_FILE,
    TRUTH_DIR,
)
from pipeline.common.csvio import format_csv_line
from pipeline.flight.folder import resolve_projected_crs
from pipeline.flight.nav_files import OBSERVATION_COLUMNS
from pipeline.run.store import fmt, format_nav_csv
from seqat.errors import InputDataError
from seqat.simulate import SimulatedFlight
from seqat.types import FloatArray

#: File names written into a simulated flight folder.
#: Sigmas in flight.yaml are rounded to this many significant digits (hides deg<->rad noise).
SIGMA_SIGNIFICANT_DIGITS = 12
#: Components of a position or attitude sigma.
AXES = 3


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
        write_synced(tmp / FLIGHT_YAML, _flight_yaml(flight, crs))
        write_synced(tmp / NAV_FILE,
                     format_nav_csv(flight.image_ids, flight.times_s, flight.nav_eop))
        write_synced(tmp / OBSERVATIONS_FILE, _observations_csv(flight))
        (tmp / TRUTH_DIR).mkdir()
        write_synced(tmp / TRUTH_DIR / "eop.csv", format_nav_csv(flight.image_ids, flight.times_s,
                                                     flight.truth_eop))
        write_synced(tmp / TRUTH_DIR / "points.csv",
                     _points_csv(flight.point_ids, flight.truth_xyz))
    return out
