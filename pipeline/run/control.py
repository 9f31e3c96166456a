"""Ground control in the run folder: ``control.csv`` and ``run.json`` ``control``.

``control.csv`` holds the control points as the estimator received them (point id
``gcp:NAME``, surveyed coordinates in the working CRS, prior σ; ``inf`` = that coordinate
free), so the later stages (``seqat reference``, ``seqat report``) read them from the run
folder alone. ``run.json`` ``control`` compares the adjusted points with the surveyed ones:
residual = adjusted − surveyed, per point and as RMSE, mean and σ per axis (docs/formats.md).
Control residuals show how well the adjustment fits its control, not its accuracy: that is
the independent check points' job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.common.csvio import read_csv
from pipeline.flight.gcp import GCP_PREFIX, GroundControl
from seqat.types import FloatArray, Solution

#: File of the run folder and its columns.
CONTROL_FILE = "control.csv"
CONTROL_COLUMNS = ("point", "x_m", "y_m", "z_m", "sx_m", "sy_m", "sz_m")


@dataclass(frozen=True, kw_only=True, eq=False)
class ControlTable:
    """``control.csv`` read back: ids (``gcp:NAME``), surveyed xyz (k, 3), prior σ (k, 3)."""

    point_ids: tuple[str, ...]
    xyz_m: FloatArray
    sigma_m: FloatArray

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p[len(GCP_PREFIX):] for p in self.point_ids)

    def __len__(self) -> int:
        return len(self.point_ids)


def _num(value: float) -> str:
    return "inf" if math.isinf(value) else repr(float(value))


def format_control_csv(control: GroundControl) -> str:
    """Text of ``control.csv``."""
    lines = [",".join(CONTROL_COLUMNS)]
    for p in control.points:
        lines.append(",".join([p.point_id, *(repr(float(v)) for v in p.xyz_m),
                               *(_num(s) for s in p.sigma_m)]))
    return "\n".join(lines) + "\n"


def read_control_csv(path: Path | str) -> ControlTable | None:
    """``control.csv`` of a run folder, or None when the run had no ground control."""
    path = Path(path)
    if not path.is_file():
        return None
    ids, xyz, sig = [], [], []
    for row in read_csv(path, CONTROL_COLUMNS):
        ids.append(row.ident("point"))
        xyz.append([row.number(f) for f in ("x_m", "y_m", "z_m")])
        sig.append([math.inf if row.values[f] == "inf" else row.number(f)
                    for f in ("sx_m", "sy_m", "sz_m")])
    return ControlTable(point_ids=tuple(ids), xyz_m=np.array(xyz, dtype=np.float64).reshape(-1, 3),
                        sigma_m=np.array(sig, dtype=np.float64).reshape(-1, 3))


def _f(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def axis_statistics(d: FloatArray) -> dict[str, float | None]:
    """RMSE per axis, RMSE_H / RMSE_V, mean and σ (n − 1) per axis of ``(n, 3)`` residuals
    (NaN entries left out per axis); ``None`` where not defined."""
    out: dict[str, float | None] = {}
    for k, axis in enumerate("xyz"):
        col = d[:, k][np.isfinite(d[:, k])] if d.size else np.zeros(0)
        out[f"rmse_{axis}_m"] = _f(float(np.sqrt(np.mean(col**2)))) if col.size else None
        out[f"mean_{axis}_m"] = _f(float(np.mean(col))) if col.size else None
        out[f"std_{axis}_m"] = _f(float(np.std(col, ddof=1))) if col.size > 1 else None
    rx, ry = out["rmse_x_m"], out["rmse_y_m"]
    out["rmse_h_m"] = None if rx is None or ry is None else math.hypot(rx, ry)
    out["rmse_v_m"] = out["rmse_z_m"]
    return out


def control_residuals(table: ControlTable, point_ids: tuple[str, ...], xyz_m: FloatArray
                      ) -> tuple[list[dict[str, object]], FloatArray]:
    """Per control point: surveyed, adjusted − surveyed (``None`` for a free axis or a point
    the solution lacks). Returns the rows and the ``(n, 3)`` residuals of adjusted points."""
    index = {p: k for k, p in enumerate(point_ids)}
    rows: list[dict[str, object]] = []
    res = []
    for pid, known, sig in zip(table.point_ids, table.xyz_m, table.sigma_m, strict=True):
        row: dict[str, object] = {"point": pid[len(GCP_PREFIX):], "point_id": pid,
                                  "x_m": float(known[0]), "y_m": float(known[1]),
                                  "z_m": float(known[2]),
                                  "sigma_m": [_f(float(s)) for s in sig], "adjusted": False,
                                  "dx_m": None, "dy_m": None, "dz_m": None}
        k = index.get(pid)
        if k is not None:
            d = np.where(np.isfinite(sig), xyz_m[k] - known, np.nan)
            row.update({"adjusted": True, "dx_m": _f(d[0]), "dy_m": _f(d[1]), "dz_m": _f(d[2])})
            res.append(d)
        rows.append(row)
    return rows, np.array(res, dtype=np.float64).reshape(-1, 3)


def control_summary(table: ControlTable, point_ids: tuple[str, ...], xyz_m: FloatArray,
                    *, file: str | None = None, n_observations: int | None = None
                    ) -> dict[str, object]:
    """The ``control`` section (run.json, report.json) of one set of adjusted points."""
    rows, d = control_residuals(table, point_ids, xyz_m)
    return {"file": file, "count": len(table), "adjusted": int(d.shape[0]),
            "observations": n_observations,
            "not_adjusted": [r["point"] for r in rows if not r["adjusted"]],
            **axis_statistics(d), "residuals": rows,
            "note": "residual = adjusted - surveyed; control points fit the adjustment, "
                    "they do not check it (see the check points)"}


def control_table(control: GroundControl) -> ControlTable:
    """The control points of a flight as :class:`ControlTable`."""
    return ControlTable(point_ids=tuple(p.point_id for p in control.points),
                        xyz_m=np.array([p.xyz_m for p in control.points]).reshape(-1, 3),
                        sigma_m=np.array([p.sigma_m for p in control.points]).reshape(-1, 3))


def control_record(control: GroundControl, solution: Solution) -> dict[str, object]:
    """``run.json`` ``control`` of a run with ground control."""
    ids = tuple(p.point_id for p in solution.points)
    xyz = np.array([p.xyz_m for p in solution.points]).reshape(-1, 3)
    return control_summary(control_table(control), ids, xyz, file=str(control.path),
                           n_observations=control.n_observations)
