"""Check point statistics as the ASPRS Positional Accuracy Standards for Digital Geospatial
Data, Edition 2 (2023) state them, and the report's verdict in words.

``RMSE_H = sqrt(RMSE_x^2 + RMSE_y^2)``, ``RMSE_V = RMSE_z``; the accuracy class is the
smallest of :data:`ASPRS_CLASSES_CM` the RMSE meets (Edition 2 allows any X-cm class); at
least :data:`ASPRS_MIN_CHECKPOINTS` check points support an accuracy statement. Beside the
RMSEs: the mean (systematic part, bias) and the standard deviation (``n - 1``, the random
part) per axis, so a bias is seen as one (docs/formats.md, *Report*).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.common.rmse import rmse
from seqat.types import FloatArray

#: ASPRS Edition 2 (2023): fewer check points than this do not support an accuracy statement.
ASPRS_MIN_CHECKPOINTS = 30
#: Accuracy classes (cm) offered: Edition 2 allows any X-cm class; these are the common ones.
ASPRS_CLASSES_CM = (0.63, 1.25, 2.5, 5.0, 7.5, 10.0, 12.5, 15.0, 20.0, 25.0, 30.0, 50.0,
                    100.0, 150.0, 200.0, 300.0, 500.0, 1000.0)
CM_PER_M = 100.0
#: An axis whose |mean| exceeds this many standard deviations is called mostly systematic.
BIAS_SIGMAS = 1.0


@dataclass(frozen=True, kw_only=True)
class PointResidual:
    """One ground point of a table: its known coordinates and estimated − known (check
    points: intersected − known; control points: adjusted − surveyed, NaN on a free axis)."""

    point: str
    n_images: int
    x_m: float
    y_m: float
    z_m: float
    dx_m: float
    dy_m: float
    dz_m: float


@dataclass(frozen=True, kw_only=True)
class AsprsTable:
    """ASPRS Edition 2 (2023) summary of check point residuals (metres).

    ``mean_*``: the systematic part (bias); ``std_*``: sample standard deviation (``n - 1``;
    NaN for fewer than 2 points); ``RMSE^2 = mean^2 + std^2 (n - 1) / n``.
    """

    count: int
    rmse_x_m: float
    rmse_y_m: float
    rmse_z_m: float
    rmse_h_m: float
    rmse_v_m: float
    mean_x_m: float
    mean_y_m: float
    mean_z_m: float
    std_x_m: float
    std_y_m: float
    std_z_m: float
    horizontal_class_cm: float | None  # smallest class of ASPRS_CLASSES_CM with RMSE_H <= X
    vertical_class_cm: float | None
    warning: str | None

    def figures(self) -> dict[str, float]:
        """``report.json``'s RMSE, mean and σ per axis (``checkpoints``, ``control``)."""
        return {"rmse_x_m": self.rmse_x_m, "rmse_y_m": self.rmse_y_m,
                "rmse_h_m": self.rmse_h_m, "rmse_v_m": self.rmse_v_m,
                "mean_x_m": self.mean_x_m, "mean_y_m": self.mean_y_m,
                "mean_z_m": self.mean_z_m, "std_x_m": self.std_x_m,
                "std_y_m": self.std_y_m, "std_z_m": self.std_z_m}


def asprs_class_cm(rmse_m: float) -> float | None:
    """Smallest class of :data:`ASPRS_CLASSES_CM` that ``rmse_m`` meets (None: none, or NaN)."""
    if not math.isfinite(rmse_m):
        return None
    return next((c for c in ASPRS_CLASSES_CM if rmse_m * CM_PER_M <= c + 1e-12), None)


def asprs_table(residuals_m: FloatArray) -> AsprsTable:
    """ASPRS Edition 2 summary of check point residuals ``(k, 3)`` (x, y, z metres)."""
    d = np.asarray(residuals_m, dtype=np.float64).reshape(-1, 3)
    n = d.shape[0]
    rx, ry, rz = rmse(d)
    rh = float(math.hypot(rx, ry)) if n else float("nan")
    mean = d.mean(axis=0) if n else np.full(3, np.nan)
    std = d.std(axis=0, ddof=1) if n >= 2 else np.full(3, np.nan)
    warning = None
    if n < ASPRS_MIN_CHECKPOINTS:
        warning = (f"only {n} check points; ASPRS (2023) asks for at least "
                   f"{ASPRS_MIN_CHECKPOINTS} for an accuracy statement")
    return AsprsTable(count=int(n), rmse_x_m=rx, rmse_y_m=ry, rmse_z_m=rz, rmse_h_m=rh,
                      rmse_v_m=rz, mean_x_m=float(mean[0]), mean_y_m=float(mean[1]),
                      mean_z_m=float(mean[2]), std_x_m=float(std[0]), std_y_m=float(std[1]),
                      std_z_m=float(std[2]), horizontal_class_cm=asprs_class_cm(rh),
                      vertical_class_cm=asprs_class_cm(rz), warning=warning)


def cm(value_m: float | None, digits: int = 1) -> str:
    """Metres as centimetres for a sentence ("6.0 cm"; "–" when unknown)."""
    if value_m is None or not math.isfinite(value_m):
        return "–"
    return f"{value_m * CM_PER_M:.{digits}f} cm"


def class_words(class_cm: float | None, rmse_m: float, axis: str) -> str:
    """The ASPRS (2023) class statement for one direction (``axis``: horizontal, vertical)."""
    symbol = "RMSE_H" if axis == "horizontal" else "RMSE_V"
    if class_cm is None:
        return (f"{axis.capitalize()}: {symbol} = {cm(rmse_m)} meets none of the classes up "
                f"to {ASPRS_CLASSES_CM[-1]:g} cm.")
    return (f"{axis.capitalize()}: meets the {class_cm:g} cm {axis} accuracy class "
            f"({symbol} = {cm(rmse_m)} ≤ {class_cm:g} cm).")


def bias_words(t: AsprsTable) -> str | None:
    """A sentence naming the axes whose residuals are mostly a systematic offset, or None."""
    axes = [(a, m, s) for a, m, s in (("x", t.mean_x_m, t.std_x_m), ("y", t.mean_y_m, t.std_y_m),
                                      ("z", t.mean_z_m, t.std_z_m))
            if math.isfinite(m) and math.isfinite(s) and abs(m) > BIAS_SIGMAS * s]
    if not axes:
        return None
    parts = ", ".join(f"d{a} mean {m * CM_PER_M:+.1f} cm vs σ {s * CM_PER_M:.1f} cm"
                      for a, m, s in axes)
    return (f"Mostly a systematic offset ({parts}): look for a datum, geoid or antenna "
            "offset, or a shift of the check point survey, before blaming the adjustment.")


def verdict_lines(t: AsprsTable | None, method: str, has_truth: bool) -> tuple[str, ...]:
    """The report's first box in sentences: what the check points say, or that there are none.

    Parameters
    ----------
    t : AsprsTable or None
        Of the run's method; None when the flight has no check points.
    method : str
        The run's method label.
    has_truth : bool
        The flight is simulated or rendered (``truth/``): its accuracy table is against truth.
    """
    if t is None or t.count == 0:
        lines = ["No check points: nothing in this report measures accuracy on the ground."
                 if t is None else "No check point could be intersected (none is seen in two "
                 "images): nothing in this report measures accuracy on the ground."]
        if has_truth:
            lines.append("The flight is simulated: 'Accuracy against truth' compares with the "
                         "simulation's exact values.")
        lines.append("The figures are precision (a-posteriori σ of the adjustment) and "
                     "agreement with other estimates of the same data (direct georeferencing, "
                     "the COLMAP reference), not accuracy. Add checkpoints.csv and "
                     "checkpoint_obs.csv to the flight folder (docs/formats.md) for an "
                     "accuracy statement.")
        return tuple(lines)
    lines = [f"{t.count} check points, intersected with the {method} orientations "
             f"(never used in the adjustment): RMSE_H = {cm(t.rmse_h_m)}, "
             f"RMSE_V = {cm(t.rmse_v_m)}."]
    if t.count < ASPRS_MIN_CHECKPOINTS:
        lines.append(f"Only {t.count} check points: ASPRS (2023) asks for at least "
                     f"{ASPRS_MIN_CHECKPOINTS} for an accuracy statement; the classes below "
                     "are indicative.")
    lines.append(class_words(t.horizontal_class_cm, t.rmse_h_m, "horizontal"))
    lines.append(class_words(t.vertical_class_cm, t.rmse_v_m, "vertical"))
    bias = bias_words(t)
    if bias is not None:
        lines.append(bias)
    lines.append("ASPRS Positional Accuracy Standards, Edition 2 (2023); the check points' own "
                 "survey accuracy is not included (not known to seqat).")
    return tuple(lines)
