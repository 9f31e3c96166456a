"""The report's ground control: adjusted − surveyed of each control point, per method.

Control points (``OUT/control.csv``, :mod:`pipeline.run.control`) entered the adjustment, so
their residuals show how well it fits its control, not its accuracy; the verdict stays on the
independent check points, and a point that is both is control (left out of the check
statistics). Methods: the run in ``OUT``, ``--compare`` runs with the same control, and the
COLMAP reference (which adjusts the same GCPs, ``seqat reference``); direct georeferencing
uses no control.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.common.tables import PointTable
from pipeline.report.asprs import AsprsTable, PointResidual, asprs_table
from pipeline.run.control import CONTROL_FILE, ControlTable, read_control_csv


@dataclass(frozen=True, kw_only=True)
class ControlReport:
    """The control points of one method (``table``: the figures of the check points'
    table, on the control residuals)."""

    method: str
    table: AsprsTable
    residuals: tuple[PointResidual, ...]
    not_adjusted: tuple[str, ...]


def read_run_control(run_path: Path) -> ControlTable | None:
    """``OUT/control.csv``, or None (a run without ground control)."""
    return read_control_csv(run_path / CONTROL_FILE)


def control_report(method: str, control: ControlTable, points: PointTable) -> ControlReport:
    """Residuals (adjusted − surveyed) of the control points ``points`` holds, largest first."""
    index = points.index()
    residuals, missing = [], []
    for pid, name, known, sig in zip(control.point_ids, control.names, control.xyz_m,
                                     control.sigma_m, strict=True):
        k = index.get(pid)
        if k is None:
            missing.append(name)
            continue
        d = np.where(np.isfinite(sig), points.xyz_m[k] - known, np.nan)
        residuals.append(PointResidual(point=name, n_images=int(points.n_obs[k]),
                                       x_m=float(known[0]), y_m=float(known[1]),
                                       z_m=float(known[2]), dx_m=float(d[0]),
                                       dy_m=float(d[1]), dz_m=float(d[2])))
    residuals.sort(key=lambda r: (-math.sqrt(np.nansum([r.dx_m**2, r.dy_m**2, r.dz_m**2])),
                                  r.point))
    d = np.array([[r.dx_m, r.dy_m, r.dz_m] for r in residuals]).reshape(-1, 3)
    full = d[np.all(np.isfinite(d), axis=1)]  # the ASPRS figures on 3D control points
    return ControlReport(method=method, table=asprs_table(full), residuals=tuple(residuals),
                         not_adjusted=tuple(missing))


def control_reports(control: ControlTable | None,
                    methods: Sequence[tuple[str, PointTable | None]]) -> tuple[ControlReport,
                                                                                ...]:
    """One :class:`ControlReport` per method that adjusted the control points."""
    if control is None:
        return ()
    out = []
    for label, points in methods:
        if points is None or not any(p in points.index() for p in control.point_ids):
            continue
        out.append(control_report(label, control, points))
    return tuple(out)


def control_json(main: ControlReport | None, control: ControlTable | None
                 ) -> dict[str, object] | None:
    """``report.json`` ``control``: the run in OUT (``None`` without ground control)."""
    if control is None:
        return None
    t = main.table if main is not None else None
    figures: dict[str, object] = {} if t is None else {**t.figures(),
                                                       "rmse_z_m": t.rmse_z_m}
    return {"method": None if main is None else main.method, "count": len(control),
            "adjusted": 0 if main is None else len(main.residuals),
            "points": list(control.names), **figures,
            "note": "control points entered the adjustment: their residuals (adjusted - "
                    "surveyed) show the fit to the control, not the accuracy"}


def control_verdict(main: ControlReport | None, excluded: Sequence[str]) -> list[str]:
    """The verdict's sentences on the control (after the check points')."""
    if main is None:
        return []
    t = main.table
    line = (f"{len(main.residuals)} ground control point(s) were used in the adjustment "
            f"(fit to the control: RMSE_H {t.rmse_h_m:.3f} m, RMSE_V {t.rmse_v_m:.3f} m; not "
            "an accuracy).")
    if excluded:
        line += (f" {len(excluded)} of the check points are control points and are left out "
                 f"of the check statistics: {', '.join(excluded)}.")
    return [line]
