"""Seeded faults for the robustness benchmark (issue 7) and how they are scored.

Pure numpy, no I/O: :mod:`pipeline.bench.faults.suite` applies them to simulated flights and to
the observations and nav of a flight folder.

* :func:`inject_blunders` — gross errors of 10-100 px in a random direction on an exact
  share of the image observations (the blundered point stays inside the image: a wrong match
  is still a pixel of the image).
* :func:`pick_jump` — one GNSS position jump (a 3D offset of given length, random direction).
* :func:`pick_dropout` — the images of one dropout of given duration.
* :func:`detection` — precision and recall of the rejected observations against the injected
  ones; :func:`gap_stats` — dropout cameras' error against their neighbours'.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from seqat.errors import ConfigError
from seqat.types import FloatArray

#: Pixel centres of an image lie in ``[-0.5, size - 0.5]`` (OpenCV convention).
HALF_PIXEL = 0.5
#: Directions drawn for a blunder before it is pulled back into the image.
MAX_DIRECTION_DRAWS = 20


@dataclass(frozen=True, kw_only=True, eq=False)
class Blunders:
    """Gross errors added to some observations.

    Attributes
    ----------
    index : (b,) int
        Observations hit, ascending.
    offset_px : (b, 2) float
        What was added to each (length within the requested range).
    uv_px : (k, 2) float
        All observations after the injection.
    """

    index: np.ndarray
    offset_px: FloatArray
    uv_px: FloatArray


def inject_blunders(uv_px: FloatArray, width_px: int, height_px: int, fraction: float,
                    rng: np.random.Generator, *, min_px: float = 10.0,
                    max_px: float = 100.0) -> Blunders:
    """Add a gross error to ``round(fraction * k)`` observations chosen without replacement.

    Each error has a length uniform in ``[min_px, max_px]`` and a uniform direction; a
    direction that would leave the image is drawn again (up to
    :data:`MAX_DIRECTION_DRAWS` times, then the point is clipped to the image, which may
    shorten it; never below ``min_px`` on images larger than ``2 max_px``).

    Parameters
    ----------
    uv_px : (k, 2) float
        Observed pixels (u right, v down).
    width_px, height_px : int
    fraction : float
        In ``[0, 1]``.
    rng : numpy.random.Generator

    Returns
    -------
    Blunders

    Raises
    ------
    ConfigError
        ``fraction`` outside ``[0, 1]`` or ``0 < min_px <= max_px`` violated.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ConfigError(f"blunder fraction: expected a value in [0, 1], got {fraction!r}")
    if not 0.0 < min_px <= max_px:
        raise ConfigError(f"blunder size: expected 0 < min_px <= max_px, got {min_px!r}, "
                          f"{max_px!r}")
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2).copy()
    k = uv.shape[0]
    count = int(round(fraction * k))
    index = np.sort(rng.choice(k, size=count, replace=False)) if count else np.zeros(0, int)
    length = rng.uniform(min_px, max_px, size=count)
    lo = np.array([-HALF_PIXEL, -HALF_PIXEL])
    hi = np.array([width_px - HALF_PIXEL, height_px - HALF_PIXEL])
    offset = np.zeros((count, 2))
    for n, q in enumerate(index):
        for _ in range(MAX_DIRECTION_DRAWS):
            a = rng.uniform(0.0, 2.0 * math.pi)
            d = length[n] * np.array([math.cos(a), math.sin(a)])
            if np.all(uv[q] + d >= lo) and np.all(uv[q] + d <= hi):
                break
        offset[n] = np.clip(uv[q] + d, lo, hi) - uv[q]
    uv[index] += offset
    return Blunders(index=index, offset_px=offset, uv_px=uv)


def pick_jump(n_images: int, first: int, rng: np.random.Generator, length_m: float,
              *, last_margin: int = 5) -> tuple[int, FloatArray]:
    """One image (index in ``[first, n_images - last_margin)``) and a 3D position offset of
    ``length_m`` in a uniformly random direction."""
    hi = max(first + 1, n_images - last_margin)
    i = int(rng.integers(first, min(hi, n_images)))
    d = rng.normal(size=3)
    return i, length_m * d / np.linalg.norm(d)


def pick_dropout(times_s: FloatArray, first: int, duration_s: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Images of one dropout: those acquired in ``[t0, t0 + duration_s)``, ``t0`` uniform in
    ``[t[first], t[-1] - duration_s]`` (or ``t[first]`` when the flight is shorter).

    Returns
    -------
    (g,) int
        Image indices, ascending (never before ``first``).
    """
    t = np.asarray(times_s, dtype=np.float64)
    lo, hi = float(t[first]), float(t[-1]) - duration_s
    t0 = float(rng.uniform(lo, hi)) if hi > lo else lo
    return np.flatnonzero((t >= t0) & (t < t0 + duration_s) & (np.arange(t.size) >= first))


@dataclass(frozen=True, kw_only=True)
class Detection:
    """Rejected observations scored against the injected blunders.

    ``precision`` = true positives / rejected (NaN when nothing was rejected), ``recall`` =
    true positives / injected (NaN when nothing was injected).
    """

    injected: int
    rejected: int
    true_positives: int
    precision: float
    recall: float


def detection(injected: Iterable[tuple[str, str]],
              rejected: Iterable[tuple[str, str]]) -> Detection:
    """Precision and recall of ``rejected`` (image id, point id) against ``injected``."""
    bad, rej = set(injected), set(rejected)
    tp = len(bad & rej)
    return Detection(injected=len(bad), rejected=len(rej), true_positives=tp,
                     precision=tp / len(rej) if rej else math.nan,
                     recall=tp / len(bad) if bad else math.nan)


@dataclass(frozen=True, kw_only=True)
class GapStats:
    """Error of the dropout cameras against their neighbours (same unit as the input).

    ``neighbour_*`` over up to ``neighbours`` images on each side of the gap (those outside
    it); ``ratio_max`` = ``gap_max / neighbour_rms``, ``ratio_rms`` = ``gap_rms /
    neighbour_rms``.
    """

    images: int
    gap_max: float
    gap_rms: float
    neighbour_rms: float
    neighbour_max: float
    ratio_max: float
    ratio_rms: float


def gap_stats(error: FloatArray, gap: np.ndarray, neighbours: int) -> GapStats:
    """Statistics of per-image errors (``(n,)``, NaN = image not estimated) in a gap.

    Parameters
    ----------
    error : (n,) float
        E.g. the 3D position error of each image.
    gap : (g,) int
        Indices of the dropout images (contiguous or not).
    neighbours : int
        Images taken on each side of the gap.
    """
    e = np.asarray(error, dtype=np.float64)
    g = np.asarray(gap, dtype=np.int64)
    if g.size == 0:
        return GapStats(images=0, gap_max=math.nan, gap_rms=math.nan, neighbour_rms=math.nan,
                        neighbour_max=math.nan, ratio_max=math.nan, ratio_rms=math.nan)
    lo, hi = int(g.min()), int(g.max())
    around = np.r_[np.arange(max(0, lo - neighbours), lo),
                   np.arange(hi + 1, min(e.size, hi + 1 + neighbours))]
    around = around[~np.isin(around, g)]
    eg, en = e[g][np.isfinite(e[g])], e[around][np.isfinite(e[around])]
    gmax = float(eg.max()) if eg.size else math.nan
    grms = float(np.sqrt(np.mean(eg**2))) if eg.size else math.nan
    nrms = float(np.sqrt(np.mean(en**2))) if en.size else math.nan
    nmax = float(en.max()) if en.size else math.nan
    return GapStats(images=int(eg.size), gap_max=gmax, gap_rms=grms, neighbour_rms=nrms,
                    neighbour_max=nmax, ratio_max=gmax / nrms if nrms > 0 else math.nan,
                    ratio_rms=grms / nrms if nrms > 0 else math.nan)
