"""Accuracy of estimated EOPs and ground points against known truth (simulated flights)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.tables import EopTable, GroundPoints, NavTable, PointTable
from seqat.types import FloatArray

Triple = tuple[float, float, float]
_NAN3: Triple = (float("nan"), float("nan"), float("nan"))


@dataclass(frozen=True, kw_only=True)
class Accuracy:
    """Root-mean-square errors against truth, per axis.

    Attributes
    ----------
    n_images, n_points : int
        Images and points matched by id with the truth.
    pos_rmse_m : (x, y, z) float
        Projection centres, metres.
    att_rmse_deg : (omega, phi, kappa) float
        Attitude angles, degrees (differences wrapped to [-180, 180)).
    gp_rmse_m : (x, y, z) float
        Ground points, metres.
    nav_pos_rmse_m, nav_att_rmse_deg : (3,) float
        The same for the GPS/INS input, the baseline the adjustment should improve on.
    """

    n_images: int
    n_points: int
    pos_rmse_m: Triple
    att_rmse_deg: Triple
    gp_rmse_m: Triple
    nav_pos_rmse_m: Triple
    nav_att_rmse_deg: Triple


def _rmse(diff: FloatArray) -> Triple:
    if diff.shape[0] == 0:
        return _NAN3
    r = np.sqrt(np.mean(diff**2, axis=0))
    return (float(r[0]), float(r[1]), float(r[2]))


def _eop_errors(ids: tuple[str, ...], eop: FloatArray,
                truth: NavTable) -> tuple[Triple, Triple, int]:
    index = truth.index()
    rows = [(i, index[iid]) for i, iid in enumerate(ids) if iid in index]
    est = np.asarray([eop[i] for i, _ in rows]).reshape(-1, 6)
    ref = np.asarray([truth.eop[j] for _, j in rows]).reshape(-1, 6)
    d = est - ref
    d_ang = np.degrees((d[:, 3:] + np.pi) % (2 * np.pi) - np.pi)
    return _rmse(d[:, :3]), _rmse(d_ang), len(rows)


def compare_with_truth(eops: EopTable, points: PointTable, truth_eop: NavTable,
                       truth_points: GroundPoints, nav: NavTable) -> Accuracy:
    """Per-axis RMSE of estimates (and of the GPS/INS input) against truth, matched by id.

    Parameters
    ----------
    eops : EopTable
        Estimated EOPs.
    points : PointTable
        Estimated ground points.
    truth_eop : NavTable
        ``truth/eop.csv``.
    truth_points : GroundPoints
        ``truth/points.csv``.
    nav : NavTable
        The GPS/INS input (for the baseline errors).

    Returns
    -------
    Accuracy
        NaN triples where nothing matched.
    """
    pos, att, n_img = _eop_errors(eops.image_ids, eops.eop, truth_eop)
    nav_pos, nav_att, _ = _eop_errors(nav.image_ids, nav.eop, truth_eop)
    tindex = truth_points.index()
    rows = [(j, tindex[pid]) for j, pid in enumerate(points.point_ids) if pid in tindex]
    d = (np.asarray([points.xyz_m[j] for j, _ in rows]).reshape(-1, 3)
         - np.asarray([truth_points.xyz_m[k] for _, k in rows]).reshape(-1, 3))
    return Accuracy(n_images=n_img, n_points=len(rows), pos_rmse_m=pos, att_rmse_deg=att,
                    gp_rmse_m=_rmse(d), nav_pos_rmse_m=nav_pos, nav_att_rmse_deg=nav_att)
