"""Tie points off the surface their neighbours define: wrong matches that no ray test sees.

A wrong match that lies along the epipolar line of a good ray fits the rays exactly: two
such rays meet at the wrong depth, and a third ray that agrees with the wrong one outvotes
the good one. No test on the rays alone can catch them (:mod:`seqat.robust`), but the
point they make is metres to hundreds of metres above or below the ground its neighbours
lie on. The estimators keep such a point in the adjustment (along the epipolar line its
rays carry next to no information on the EOPs); :func:`off_surface_points` names the
points the run does not publish (docs/algorithm.md, *Points off the surface*).

The test, for each tie point ``i`` among its :data:`SURFACE_NEIGHBOURS` nearest points in
plan (X, Y):

* the local surface is the median height ``m`` of the neighbours, its roughness their
  median absolute deviation ``s`` (scaled to a σ);
* the point departs from it by ``d = z − m``, against ``σ = hypot(s, σ_z)`` (σ_z: the
  point's own published σ);
* it is off the surface when ``|d| > k σ`` (:data:`SURFACE_SIGMAS`) and no neighbour
  lies within half that departure of its height (``|z_j − z| < |d| / 2``): two points
  on one roof or one tree top hold each other up; a wrong match has no partner.

A real tie point can fail it: one point alone on a pole or a tree top, high above flat
ground. The cost is one tie point not published; the EOPs are not affected.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Container

import numpy as np
from scipy.spatial import cKDTree

from seqat.types import FloatArray, Solution

#: Neighbours (nearest in plan) that define the local surface of a tie point.
SURFACE_NEIGHBOURS = 8
#: A point this many σ (roughness and own σ_z combined) above or below the local surface,
#: with no neighbour at its height, is off the surface.
SURFACE_SIGMAS = 10.0
#: Normal-consistent σ of a median absolute deviation.
_MAD_SIGMA = 1.4826


def off_surface_points(xyz_m: FloatArray, sigma_z_m: FloatArray,
                       exempt: np.ndarray | None = None) -> np.ndarray:
    """Indices (sorted) of the tie points off the local surface of their neighbours.

    Parameters
    ----------
    xyz_m : (n, 3) float
        The points (a projected CRS or a local frame: metres, Z up).
    sigma_z_m : (n,) float
        Each point's standard deviation in Z (non-finite: treated as 0).
    exempt : (n,) bool, optional
        Points never flagged (ground control); they still define the surface.

    Returns
    -------
    (m,) int64
        Nothing when there are too few points to define a surface (fewer than
        ``SURFACE_NEIGHBOURS + 1`` with finite coordinates; the others are not tested).
    """
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    sz = np.asarray(sigma_z_m, dtype=np.float64).reshape(xyz.shape[0])
    sz = np.where(np.isfinite(sz), np.abs(sz), 0.0)
    ok = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))  # the others are not tested
    n, k = ok.size, SURFACE_NEIGHBOURS
    if n <= k:
        return np.zeros(0, dtype=np.int64)
    xyz, sz = xyz[ok], sz[ok]
    plan = xyz[:, :2] - xyz[:, :2].mean(axis=0)  # conditioned: UTM northings are 4e6 m
    _, nb = cKDTree(plan).query(plan, k + 1)
    # drop the point itself (not always the first: points may coincide in plan)
    keep = nb != np.arange(n)[:, None]
    keep[keep.all(axis=1), -1] = False
    nb = nb[keep].reshape(n, k)
    z = xyz[:, 2]
    zn = z[nb]
    m = np.median(zn, axis=1)
    s = _MAD_SIGMA * np.median(np.abs(zn - m[:, None]), axis=1)
    d = z - m
    off = np.abs(d) > SURFACE_SIGMAS * np.hypot(s, sz)  # the roughness and the point's σ_z
    partner = np.any(np.abs(zn - z[:, None]) < 0.5 * np.abs(d)[:, None], axis=1)
    off &= ~partner
    if exempt is not None:
        off &= ~np.asarray(exempt, dtype=bool).reshape(-1)[ok]
    return ok[off].astype(np.int64)


def without_off_surface(solution: Solution,
                        control: Container[str] = ()) -> tuple[Solution, tuple[str, ...]]:
    """``solution`` without its tie points off the surface (:func:`off_surface_points`;
    the ids in ``control`` exempt), and their ids, which ``withheld`` names too."""
    pts = solution.points
    off = off_surface_points(np.array([p.xyz_m for p in pts]).reshape(-1, 3),
                             np.array([p.sigma_m[2] for p in pts]),
                             exempt=np.array([p.point_id in control for p in pts], bool))
    if not off.size:
        return solution, ()
    ids = tuple(pts[i].point_id for i in off)
    out = set(off.tolist())
    return dataclasses.replace(solution, points=tuple(p for i, p in enumerate(pts)
                                                      if i not in out),
                               withheld=(*solution.withheld, *ids)), ids
