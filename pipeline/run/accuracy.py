"""Accuracy of estimated EOPs and ground points against known truth (simulated flights)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common.rmse import Triple, rmse
from pipeline.common.tables import EopTable, GroundPoints, NavTable, PointTable
from seqat.geometry import wrap_angle
from seqat.types import FloatArray


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


def eop_differences(ids: tuple[str, ...], eop: FloatArray, ref_ids: tuple[str, ...],
                    ref_eop: FloatArray) -> tuple[np.ndarray, FloatArray, FloatArray]:
    """Differences ``estimate - reference`` of the EOPs of the images in both, by id.

    Parameters
    ----------
    ids : tuple[str, ...]
    eop : (n, 6) float
        Metres and radians.
    ref_ids : tuple[str, ...]
    ref_eop : (r, 6) float

    Returns
    -------
    rows : (k,) int
        Rows of ``eop`` matched, in their order.
    d_pos_m : (k, 3) float
    d_att_deg : (k, 3) float
        Wrapped to [-180, 180).
    """
    index = {iid: j for j, iid in enumerate(ref_ids)}
    pairs = [(i, index[iid]) for i, iid in enumerate(ids) if iid in index]
    rows = np.asarray([i for i, _ in pairs], dtype=np.int64)
    ref_rows = np.asarray([j for _, j in pairs], dtype=np.int64)
    d = np.asarray(eop, dtype=np.float64)[rows] - np.asarray(ref_eop, dtype=np.float64)[ref_rows]
    d = d.reshape(-1, 6)
    return rows, d[:, :3], np.degrees(wrap_angle(d[:, 3:]))


def point_differences(ids: tuple[str, ...], xyz: FloatArray, ref_ids: tuple[str, ...],
                      ref_xyz: FloatArray) -> FloatArray:
    """``estimate - reference`` of the points in both, by id, in the order of ``ids``: (k, 3)."""
    index = {pid: j for j, pid in enumerate(ref_ids)}
    pairs = [(i, index[pid]) for i, pid in enumerate(ids) if pid in index]
    a = np.asarray([i for i, _ in pairs], dtype=np.int64)
    b = np.asarray([j for _, j in pairs], dtype=np.int64)
    return (np.asarray(xyz, dtype=np.float64)[a] - np.asarray(ref_xyz)[b]).reshape(-1, 3)


def _eop_errors(ids: tuple[str, ...], eop: FloatArray,
                truth: NavTable) -> tuple[Triple, Triple, int]:
    rows, d_pos, d_att = eop_differences(ids, eop, truth.image_ids, truth.eop)
    return rmse(d_pos), rmse(d_att), int(rows.size)


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
    fix = np.all(np.isfinite(nav.eop), axis=1)  # GNSS dropouts have no input to compare
    nav_pos, nav_att, _ = _eop_errors(tuple(np.asarray(nav.image_ids)[fix]), nav.eop[fix],
                                      truth_eop)
    d = point_differences(points.point_ids, points.xyz_m, truth_points.point_ids,
                          truth_points.xyz_m)
    return Accuracy(n_images=n_img, n_points=d.shape[0], pos_rmse_m=pos, att_rmse_deg=att,
                    gp_rmse_m=rmse(d), nav_pos_rmse_m=nav_pos, nav_att_rmse_deg=nav_att)
