"""What ``seqat bench fuzz`` calls an absurd published output.

A command that exited 0 published its files; they must be strict (no ``NaN`` / ``Infinity``
in JSON, every coordinate finite, every sigma finite and non-negative or ``nan`` = "no
precision") and plausible: no coordinate beyond :data:`MAX_XY_M` / :data:`MAX_Z_M` (no
projected CRS in metres reaches them: the equator is 4e7 m long), no angle beyond
:data:`MAX_ANGLE_DEG`, every camera within :func:`reach_m` of its own nav position and every
ground point within it of the nav's bounding box. The files are read with the standard
library, not with seqat's readers, so a file those would refuse is still looked at.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

#: Largest plausible easting / northing, metres.
MAX_XY_M = 1e8
#: Largest plausible height, metres (above or below the datum).
MAX_Z_M = 1e5
#: Largest plausible angle, degrees.
MAX_ANGLE_DEG = 720.0
#: Smallest distance that is absurd however small the flight.
MIN_REACH_M = 1000.0

_XYZ = ("x_m", "y_m", "z_m")
_ANGLES = ("omega_deg", "phi_deg", "kappa_deg")


def reach_m(span_m: float) -> float:
    """Distance from the nav beyond which an estimate is absurd: 3 x the nav's extent, at
    least :data:`MIN_REACH_M`."""
    return max(MIN_REACH_M, 3.0 * span_m)


def _strict_json(path: Path) -> tuple[object, list[str]]:
    def refuse(token: str) -> float:
        raise ValueError(f"non-finite number {token}")

    try:
        return json.loads(path.read_text(encoding="utf-8"), parse_constant=refuse), []
    except (OSError, UnicodeDecodeError, ValueError) as err:
        return None, [f"{path.name}: {err}"]


def check_json_file(path: Path) -> list[str]:
    if not path.is_file():
        return [f"{path.name}: missing after exit 0"]
    return _strict_json(path)[1]


def _rows(path: Path) -> tuple[list[dict[str, str]], list[str]]:
    if not path.is_file():
        return [], [f"{path.name}: missing after exit 0"]
    try:
        with path.open(encoding="utf-8", newline="") as f:
            return list(csv.DictReader(f)), []
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        return [], [f"{path.name}: unreadable: {err}"]


def _num(text: str | None) -> float:
    try:
        return float(text) if text is not None else math.nan
    except ValueError:
        return math.nan


def _check_values(name: str, key: str, row: dict[str, str], problems: list[str],
                  allow_nan_position: bool = False) -> tuple[float, float, float]:
    xyz = tuple(_num(row.get(c)) for c in _XYZ)
    for c, v in zip(_XYZ, xyz, strict=True):
        limit = MAX_Z_M if c == "z_m" else MAX_XY_M
        if math.isnan(v) and allow_nan_position:
            continue
        if not math.isfinite(v) or abs(v) > limit:
            problems.append(f"{name}: {key} {c} = {row.get(c)}")
    for c in _ANGLES:
        if c in row:
            v = _num(row[c])
            if math.isnan(v) and allow_nan_position:
                continue
            if not math.isfinite(v) or abs(v) > MAX_ANGLE_DEG:
                problems.append(f"{name}: {key} {c} = {row[c]}")
    for c, text in row.items():
        if c and c.startswith("s") and c.endswith(("_m", "_deg")):
            v = _num(text)
            if not math.isnan(v) and (not math.isfinite(v) or v < 0):
                problems.append(f"{name}: {key} {c} = {text}")
    return xyz  # type: ignore[return-value]


def check_run_outputs(out: Path) -> list[str]:
    """Problems of a run folder published by an exit-0 ``seqat run`` (empty: none)."""
    problems: list[str] = []
    nav, p = _rows(out / "nav.csv")
    problems += p
    eop, p = _rows(out / "eop.csv")
    problems += p
    points, p = _rows(out / "points.csv")
    problems += p
    run, p = _strict_json(out / "run.json") if (out / "run.json").is_file() else (
        None, ["run.json: missing after exit 0"])
    problems += p
    nav_xyz: dict[str, tuple[float, float, float]] = {}
    for row in nav:
        nav_xyz[row.get("image", "")] = _check_values("nav.csv", row.get("image", "?"), row,
                                                      problems, allow_nan_position=True)
    finite = [v for v in nav_xyz.values() if all(math.isfinite(c) for c in v)]
    if finite:
        lo = [min(v[i] for v in finite) for i in range(3)]
        hi = [max(v[i] for v in finite) for i in range(3)]
        reach = reach_m(max(h - low for h, low in zip(hi, lo, strict=True)))
    else:
        lo = hi = []
        reach = math.inf
    for row in eop:
        key = row.get("image", "?")
        xyz = _check_values("eop.csv", key, row, problems)
        ref = nav_xyz.get(key)
        if ref is not None and all(math.isfinite(c) for c in ref + xyz):
            d = math.dist(ref, xyz)
            if d > reach:
                problems.append(f"eop.csv: {key} lies {d:.4g} m from its nav position")
    for row in points:
        key = row.get("point", "?")
        xyz = _check_values("points.csv", key, row, problems)
        if lo and all(math.isfinite(c) for c in xyz):
            d = math.hypot(*(max(low - c, 0.0, c - h)
                             for c, low, h in zip(xyz, lo, hi, strict=True)))
            if d > reach:
                problems.append(f"points.csv: {key} lies {d:.4g} m from the nav's extent")
    if isinstance(run, dict):
        for rec in run.get("images") or ():
            e = rec.get("eop") if isinstance(rec, dict) else None
            if isinstance(e, dict):
                _check_values("run.json images[].eop", str(rec.get("image", "?")),
                              {k: ("nan" if v is None else str(v)) for k, v in e.items()},
                              problems)
        s0 = (run.get("totals") or {}).get("sigma0")
        if s0 is not None and (not isinstance(s0, int | float) or s0 < 0):
            problems.append(f"run.json: totals.sigma0 = {s0}")
    return problems[:20]


def check_dsm(path: Path) -> list[str]:
    """A DSM written by an exit-0 ``seqat dsm``: readable, heights finite or nodata and
    plausible."""
    if not path.is_file():
        return [f"{path.name}: missing after exit 0"]
    import numpy as np
    import rasterio

    try:
        with rasterio.open(path) as ds:
            a = ds.read(1, masked=True)
    except Exception as err:  # noqa: BLE001 - any failure to read it back is the finding
        return [f"{path.name}: unreadable: {err}"]
    values = np.ma.compressed(a)
    values = values[~np.isnan(values)] if values.dtype.kind == "f" else values
    if not values.size:
        return [f"{path.name}: no valid height (every cell is nodata)"]
    if values.size and (not np.all(np.isfinite(values)) or np.abs(values).max() > MAX_Z_M):
        return [f"{path.name}: heights out of range ({values.min():.4g} to {values.max():.4g})"]
    return []
