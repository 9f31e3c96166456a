"""A 7-parameter similarity between two sets of camera poses, and the poses' agreement after it.

Used by the independent SfM check (:mod:`pipeline.reference.sfm_stage`): the SfM model has its
own datum (arbitrary scale, rotation, translation), so it is compared with a method's EOPs
only after the similarity ``method_from_sfm`` fitted on the camera centres.

The fit is pycolmap's least-squares similarity (``pycolmap.estimate_sim3d``, Umeyama's
closed form) inside an outlier rejection: images whose centre misfits by more than
``k`` robust sigmas (1.4826 x the median misfit, with a floor) are left out of the fit and the
fit repeated until the inlier set no longer changes. It is deterministic (pycolmap's
``estimate_sim3d_robust`` is LO-RANSAC with a random seed and a fixed threshold, which would
have to be guessed before the misfit's size is known: metres for a wrong camera model,
centimetres for a good one). Every image is reported, inlier or not.

Centres are fitted in local coordinates (target minus its mean): UTM coordinates of 4e6 m
would cost ~1e-9 relative precision in the closed form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.common.rmse import rmse
from seqat.cvframe import cv_pose_from_eop, eop_from_cv_pose
from seqat.errors import EstimationError
from seqat.geometry import wrap_angle
from seqat.types import FloatArray

#: Fewest images a similarity is fitted on (7 parameters from 3 per centre: 3 images are the
#: minimum; 5 leave some redundancy to reject outliers with).
MIN_ALIGN_IMAGES = 5
#: Outlier rejection: misfits beyond this many robust sigmas leave the fit ...
REJECT_SIGMAS = 3.0
#: ... but never one below this (metres), so a near-perfect fit keeps all its images.
REJECT_FLOOR_M = 0.05
#: The robust sigma of a misfit length from its median (normal distribution).
MAD_TO_SIGMA = 1.4826
#: Iterations of the rejection loop (it stops as soon as the inlier set repeats).
MAX_REJECT_ITERATIONS = 20


@dataclass(frozen=True, kw_only=True, eq=False)
class Similarity:
    """``x_target = scale * R @ x_source + t`` (world metres)."""

    scale: float
    rotation: FloatArray  # (3, 3)
    translation: FloatArray  # (3,)

    def apply(self, points: FloatArray) -> FloatArray:
        """Transform ``(n, 3)`` points from the source to the target frame."""
        x = np.asarray(points, dtype=np.float64)
        return self.scale * x @ self.rotation.T + self.translation

    def rotate_cam_from_world(self, R_cam_from_world: FloatArray) -> FloatArray:
        """Camera rotations ``(n, 3, 3)`` (camera from source world) as camera from target
        world: ``R_cw R^T``."""
        return np.einsum("nij,kj->nik", R_cam_from_world, self.rotation)


@dataclass(frozen=True, kw_only=True, eq=False)
class PoseAgreement:
    """Agreement of a source's poses with a target's after the similarity.

    Attributes
    ----------
    similarity : Similarity
        ``target_from_source``.
    inlier : (n,) bool
        Images the final fit used.
    d_xyz_m : (n, 3) float
        Transformed source centre minus target centre (metres, target axes).
    d_angles_rad : (n, 3) float
        Transformed source ω, φ, κ minus the target's (wrapped to (-π, π]).
    d_rotation_rad : (n,) float
        Angle of the relative rotation between the two attitudes.
    """

    similarity: Similarity
    inlier: np.ndarray
    d_xyz_m: FloatArray
    d_angles_rad: FloatArray
    d_rotation_rad: FloatArray

    @property
    def d_position_m(self) -> FloatArray:
        return np.linalg.norm(self.d_xyz_m, axis=1)


def _fit(src: FloatArray, tgt: FloatArray) -> Similarity:
    import pycolmap

    sim = pycolmap.estimate_sim3d(src, tgt)
    if sim is None:
        raise EstimationError(f"no similarity fits {len(src)} camera centres (degenerate "
                              "geometry: all on one point?)")
    return Similarity(scale=float(sim.scale),
                      rotation=np.asarray(sim.rotation.matrix(), dtype=np.float64),
                      translation=np.asarray(sim.translation, dtype=np.float64).reshape(3))


def fit_similarity(src: FloatArray, tgt: FloatArray, *, reject_sigmas: float = REJECT_SIGMAS,
                   floor_m: float = REJECT_FLOOR_M) -> tuple[Similarity, np.ndarray]:
    """Least-squares similarity ``tgt ≈ s R src + t`` with iterative outlier rejection.

    Parameters
    ----------
    src, tgt : (n, 3) float
        Corresponding points (camera centres), finite.
    reject_sigmas, floor_m : float
        Rejection threshold ``max(reject_sigmas * 1.4826 * median(misfit), floor_m)``.

    Returns
    -------
    Similarity
    inlier : (n,) bool

    Raises
    ------
    EstimationError
        Fewer than :data:`MIN_ALIGN_IMAGES` points, or no similarity (degenerate).
    """
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    n = src.shape[0]
    if n < MIN_ALIGN_IMAGES:
        raise EstimationError(f"a similarity needs >= {MIN_ALIGN_IMAGES} common images, got {n}")
    s0, t0 = src.mean(axis=0), tgt.mean(axis=0)
    a, b = src - s0, tgt - t0
    inlier = np.ones(n, dtype=bool)
    sim = _fit(a, b)
    for _ in range(MAX_REJECT_ITERATIONS):
        misfit = np.linalg.norm(sim.apply(a) - b, axis=1)
        threshold = max(reject_sigmas * MAD_TO_SIGMA * float(np.median(misfit[inlier])),
                        floor_m)
        new = misfit <= threshold
        if np.count_nonzero(new) < MIN_ALIGN_IMAGES or np.array_equal(new, inlier):
            break
        inlier = new
        sim = _fit(a[inlier], b[inlier])
    # back to the original frames: tgt = s R (src - s0) + t + t0
    world = Similarity(scale=sim.scale, rotation=sim.rotation,
                       translation=sim.translation + t0 - sim.scale * sim.rotation @ s0)
    return world, inlier


def pose_agreement(src_centres: FloatArray, src_R_cam_from_world: FloatArray,
                   tgt_eop: FloatArray, **fit_options: float) -> PoseAgreement:
    """Fit ``target_from_source`` on the centres and compare the poses after it.

    Parameters
    ----------
    src_centres : (n, 3) float
    src_R_cam_from_world : (n, 3, 3) float
        Source attitudes as COLMAP's ``cam_from_world`` rotations (OpenCV camera frame).
    tgt_eop : (n, 6) float
        Target EOPs ``[X0, Y0, Z0, ω, φ, κ]`` (metres, radians), same images in the same order.
    fit_options
        Passed to :func:`fit_similarity`.
    """
    tgt_eop = np.asarray(tgt_eop, dtype=np.float64)
    sim, inlier = fit_similarity(src_centres, tgt_eop[:, :3], **fit_options)
    centres = sim.apply(src_centres)
    R_src = sim.rotate_cam_from_world(np.asarray(src_R_cam_from_world, dtype=np.float64))
    R_tgt, _ = cv_pose_from_eop(tgt_eop)
    src_eop = eop_from_cv_pose(R_src, -np.einsum("nij,nj->ni", R_src, centres))
    relative = Rotation.from_matrix(np.einsum("nij,nkj->nik", R_src, R_tgt))
    return PoseAgreement(similarity=sim, inlier=inlier, d_xyz_m=centres - tgt_eop[:, :3],
                         d_angles_rad=wrap_angle(src_eop[:, 3:] - tgt_eop[:, 3:]),
                         d_rotation_rad=relative.magnitude())


@dataclass(frozen=True, kw_only=True)
class AgreementStats:
    """Summary of a :class:`PoseAgreement` (metres, degrees)."""

    n_images: int
    n_inliers: int
    scale: float
    position_rms_m: float  # 3D: sqrt(mean |d|^2)
    position_max_m: float
    position_rms_xyz_m: tuple[float, float, float]
    attitude_rms_deg: float  # angle of the relative rotation
    attitude_max_deg: float
    attitude_rms_opk_deg: tuple[float, float, float]  # ω, φ, κ


def agreement_stats(agreement: PoseAgreement) -> AgreementStats:
    """RMS and maximum over every image compared (inliers and outliers alike)."""
    d = agreement.d_xyz_m
    ang = np.degrees(agreement.d_rotation_rad)
    pos = agreement.d_position_m
    xyz = rmse(d)
    opk = rmse(np.degrees(agreement.d_angles_rad))
    return AgreementStats(
        n_images=int(d.shape[0]), n_inliers=int(np.count_nonzero(agreement.inlier)),
        scale=agreement.similarity.scale,
        position_rms_m=float(np.sqrt(np.mean(pos ** 2))), position_max_m=float(pos.max()),
        position_rms_xyz_m=(float(xyz[0]), float(xyz[1]), float(xyz[2])),
        attitude_rms_deg=float(np.sqrt(np.mean(ang ** 2))), attitude_max_deg=float(ang.max()),
        attitude_rms_opk_deg=(float(opk[0]), float(opk[1]), float(opk[2])))
