"""COLMAP bundle adjustment of a run's observations with GPS/INS priors (pycolmap + Ceres).

The algorithm of the reference stage (``pipeline/reference/stage.py``).

The run's observations become a :class:`pycolmap.Reconstruction` (one ``OPENCV`` camera, the
images with their poses as COLMAP's ``cam_from_world``, every tie point seen in at least two
images as a 3D point with its track). COLMAP's Ceres bundle adjuster
(``create_default_ceres_bundle_adjuster``) sets up the reprojection residuals; we add one
GPS/INS prior residual block per image ourselves (``AbsolutePosePriorCost`` with the full 6x6
covariance, or ``AbsolutePosePositionPriorCost``) and check the residual count. We do *not* use
``create_pose_prior_bundle_adjuster``: it first RANSAC-aligns the model to the prior positions
and, when that fails (collinear camera centres of a single strip), logs a warning and drops
every prior.

Same stochastic model as Sim (``seqat/simultaneous.py``):

* COLMAP's reprojection residuals are in pixels, unweighted. Sim minimises
  ``sum(v_img^2) / sigma_px^2 + sum(v_nav^2 / sigma_nav^2)``; multiplying by ``sigma_px^2``
  gives the same minimiser, so each prior gets the covariance ``Sigma_prior / sigma_px^2``.
* Sim's nav prior is on ``[X0, Y0, Z0, omega, phi, kappa]`` with a diagonal covariance.
  COLMAP's 6-DoF prior residual is ``[log(R_cv R_cv,prior^T), R_cv (C_prior - C)]``
  (rotation in the camera frame, then translation). To first order
  ``rho = -R_cv A dtheta`` and ``tau = -R_cv dC`` (``A``: world axes of the angle rotations,
  :func:`seqat.geometry.attitude_axes`), so the prior covariance is
  ``J diag(sigma^2) J^T`` with ``J = [[0, -R_cv A], [-R_cv, 0]]``, evaluated at the prior.
  The two objectives then agree to second order in the nav error (0.1 deg ~ 2e-3 rad), which
  is what the agreement test measures (docs/benchmarks.md).

Ground control points (``OUT/control.csv``): their image observations are image points like
any tie point's (they are in ``observations.csv``); their surveyed coordinates are a prior on
the 3D point, ``sigma_px / sigma`` times the coordinate difference per axis (a small
:class:`pyceres.CostFunction`: COLMAP has no point prior), the weight Sim gives them times
``sigma_px^2``. A GCP seen in fewer than two images is not in the model (as any point).

Coordinates: the adjustment runs in local coordinates (world minus the rounded first nav
position, as the estimators); every file holds world coordinates. Pixels: COLMAP puts the
centre of the top-left pixel at (0.5, 0.5), OpenCV (ours) at (0, 0): ``u_colmap = u + 0.5``
for observations and the principal point alike.
"""

from __future__ import annotations

import dataclasses
import enum
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipeline.flight.schema import CameraConfig
from pipeline.run.robustness import final_robust_scale
from seqat.catalogue import free_nav_sigma
from seqat.cvframe import (
    cv_pose_from_eop,
    eop_covariance_from_tangent,
    eop_from_cv_pose,
    pose_prior_covariance,
)
from seqat.errors import ConfigError, EstimationError
from seqat.geometry import wrap_angle
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray

if TYPE_CHECKING:
    import pycolmap

#: COLMAP's pixel coordinates minus OpenCV's (centre of the top-left pixel: 0.5 vs 0).
COLMAP_PIXEL_OFFSET = 0.5
#: The single camera of a reference model.
CAMERA_ID = 1
#: Number of parameters of COLMAP's ``OPENCV`` model (fx, fy, cx, cy, k1, k2, p1, p2).
OPENCV_PARAMS = 8
#: ``FULL_OPENCV`` (used when k3 != 0): the 8 above plus k3, k4, k5, k6 (k4-k6 stay 0).
FULL_OPENCV_PARAMS = 12
#: Indices of k4, k5, k6 in ``FULL_OPENCV``: held at 0 when self-calibrating.
FULL_OPENCV_RATIONAL_IDX = (9, 10, 11)
#: Residuals per image observation and per prior.
OBS_RESIDUALS = 2
POSE_PRIOR_RESIDUALS = 6
POSITION_PRIOR_RESIDUALS = 3


class PriorKind(enum.StrEnum):
    """GPS/INS prior of each image."""

    POSE = "pose"  # 6-DoF, AbsolutePosePriorCost with the full covariance (Sim's model)
    POSITION = "position"  # AbsolutePosePositionPriorCost: attitude left free


class RobustLoss(enum.StrEnum):
    """Loss on the reprojection residuals (priors always use the squared loss)."""

    TRIVIAL = "trivial"
    HUBER = "huber"
    CAUCHY = "cauchy"
    SOFT_L1 = "soft_l1"


@dataclass(frozen=True, kw_only=True)
class ReferenceOptions:
    """Options of the reference adjustment.

    Attributes
    ----------
    prior : PriorKind
    self_calibrate : bool
        Also estimate fx, fy, cx, cy, k1, k2, p1, p2 (and k3 for a ``FULL_OPENCV`` camera).
    robust_loss : RobustLoss or None
        Loss of the reprojection residuals. ``None`` (the default): the run's own
        (:func:`loss_of_run`): Huber at the run's final robust scale (:func:`run_loss_scale`)
        when the run was robust (least squares within that many σ, as the run's loss;
        docs/algorithm.md, *Robust loss*), least squares (``trivial``) when it was not.
    loss_scale_sigmas : float
        Scale of the robust loss in units of the image sigma.
    max_iterations : int
        Ceres' limit. The tolerances below take the 70 Seneca images 169 iterations: at
        COLMAP's 100 the solve stopped 0.3 mm short and reported ``NO_CONVERGENCE``.
    function_tolerance, gradient_tolerance, parameter_tolerance : float
        Ceres' stopping rules (tighter than COLMAP's defaults: the reference must converge
        as far as Sim does, < 1 um).
    covariance : bool
        Posterior pose and point covariances (``pycolmap.estimate_ba_covariance``).
    """

    prior: PriorKind = PriorKind.POSE
    self_calibrate: bool = False
    robust_loss: RobustLoss | None = None
    loss_scale_sigmas: float = 3.0
    max_iterations: int = 1000
    function_tolerance: float = 1e-15
    gradient_tolerance: float = 1e-12
    parameter_tolerance: float = 1e-12
    covariance: bool = True

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ConfigError(f"max_iterations: expected >= 1, got {self.max_iterations}")
        if not self.loss_scale_sigmas > 0:
            raise ConfigError(f"loss_scale_sigmas: expected > 0, got {self.loss_scale_sigmas}")


@dataclass(frozen=True, kw_only=True, eq=False)
class ReferenceInput:
    """Everything the reference adjustment needs, in world coordinates.

    Attributes
    ----------
    camera : CameraConfig
        The camera of the observed pixels (distortion included).
    image_ids : tuple[str, ...]
        Acquisition order.
    nav_eop : (n, 6) float
        GPS/INS EOPs (metres, radians): the priors. NaN (a GNSS dropout) takes Sim's free
        prior: ``eop0`` with σ 1 km / 1 rad (:func:`seqat.catalogue.free_nav_sigma`).
    nav_sigma : (6,) float
        Their standard deviations (metres, radians).
    sigma_px : float
        Standard deviation of an image coordinate.
    point_ids : tuple[str, ...]
    obs_image, obs_point : (k,) int
        Image and point index of each observation.
    obs_uv_px : (k, 2) float
        Observed OpenCV pixels (distorted).
    eop0 : (n, 6) float
        Initial EOPs (the run's estimates).
    xyz0 : (m, 3) float
        Initial points, finite (the run's estimates, else intersections).
    control_ids : tuple[str, ...]
        Ground control points among ``point_ids`` (``gcp:NAME``).
    control_xyz : (c, 3) float
        Their surveyed coordinates (world).
    control_sigma : (c, 3) float
        Their σ, metres (``inf``: that coordinate free).
    """

    camera: CameraConfig
    image_ids: tuple[str, ...]
    nav_eop: FloatArray
    nav_sigma: FloatArray
    sigma_px: float
    point_ids: tuple[str, ...]
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_uv_px: FloatArray
    eop0: FloatArray
    xyz0: FloatArray
    control_ids: tuple[str, ...] = ()
    control_xyz: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    control_sigma: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        n, m, k = len(self.image_ids), len(self.point_ids), self.obs_image.shape[0]
        shapes = {"nav_eop": (self.nav_eop, (n, EOP_SIZE)), "eop0": (self.eop0, (n, EOP_SIZE)),
                  "nav_sigma": (self.nav_sigma, (EOP_SIZE,)), "xyz0": (self.xyz0, (m, GP_SIZE)),
                  "obs_point": (self.obs_point, (k,)), "obs_uv_px": (self.obs_uv_px, (k, 2))}
        for name, (array, shape) in shapes.items():
            if array.shape != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {array.shape}")
        if not np.all(np.isfinite(self.xyz0)):
            raise ValueError("xyz0: initial points must be finite")


@dataclass(frozen=True, kw_only=True, eq=False)
class ReferenceResult:
    """Typed result of :func:`adjust_reference`.

    Attributes
    ----------
    image_ids : tuple[str, ...]
    eop : (n, 6) float
        World metres, radians. Images without tie points keep their nav (``in_adjustment``).
    eop_sigma : (n, 6) float
        A posteriori standard deviations (``sigma0 * sqrt(q)``, as Sim); NaN where the
        covariance was not computed.
    in_adjustment : (n,) bool
        Image has tie points (a pose parameter in the adjustment).
    point_ids : tuple[str, ...]
        Points adjusted (seen in >= 2 images).
    xyz : (m, 3) float
    xyz_sigma : (m, 3) float
        NaN: COLMAP gives point covariances conditioned on the poses only (see
        ``_covariances``).
    n_obs : (m,) int
    camera : CameraConfig
        Adjusted camera (the input one without self-calibration).
    converged : bool
    termination : str
        Ceres' termination type.
    iterations : int
    n_residuals : int
        Residuals in the problem (checked: ``2 * observations + prior residuals``).
    n_prior_residuals : int
    n_control_points, n_control_residuals : int
        Ground control points in the model and their prior residuals (3 each).
    sigma0, redundancy, rms_px : float, int, float
        With Sim's definitions (``seqat/simultaneous.py``): each image point in ``sigma0``
        at its final weight under the loss (:func:`loss_weight`), ``rms_px`` over every
        image point unweighted.
    ba_s : float
        Wall time of the Ceres solve.
    linear_solver : str
        Ceres' linear solver (COLMAP chooses it by the number of images).
    covariance_status : str
        ``computed``, ``off`` or the reason it failed.
    origin : (3,) float
        Local origin of the adjustment (world metres).
    reconstruction : pycolmap.Reconstruction
        The adjusted model in world coordinates.
    """

    image_ids: tuple[str, ...]
    eop: FloatArray
    eop_sigma: FloatArray
    in_adjustment: np.ndarray
    point_ids: tuple[str, ...]
    xyz: FloatArray
    xyz_sigma: FloatArray
    n_obs: np.ndarray
    camera: CameraConfig
    converged: bool
    termination: str
    iterations: int
    n_residuals: int
    n_prior_residuals: int
    sigma0: float
    redundancy: int
    rms_px: float
    ba_s: float
    linear_solver: str
    covariance_status: str
    origin: FloatArray
    reconstruction: pycolmap.Reconstruction
    n_control_points: int = 0
    n_control_residuals: int = 0


# --------------------------------------------------------------------------------------------
# Conversions
# --------------------------------------------------------------------------------------------


def _import_pycolmap() -> tuple[object, object]:
    """pycolmap and pyceres (pyceres makes the adjuster's ``problem`` reachable)."""
    import pyceres
    import pycolmap

    return pycolmap, pyceres


def colmap_camera(camera: CameraConfig, camera_id: int = CAMERA_ID) -> pycolmap.Camera:
    """COLMAP ``OPENCV`` camera of a camera config (``FULL_OPENCV`` when ``k3 != 0``).

    The principal point moves by +0.5 px (COLMAP's pixel convention).
    """
    import pycolmap

    cx, cy = camera.cx_px + COLMAP_PIXEL_OFFSET, camera.cy_px + COLMAP_PIXEL_OFFSET
    params = [camera.fx_px, camera.fy_px, cx, cy, camera.k1, camera.k2, camera.p1, camera.p2]
    model = "OPENCV"
    if camera.k3 != 0.0:
        model = "FULL_OPENCV"
        params += [camera.k3, 0.0, 0.0, 0.0]
    return pycolmap.Camera(model=model, width=camera.width_px, height=camera.height_px,
                           params=params, camera_id=camera_id)


def camera_config_from_colmap(cam: pycolmap.Camera, template: CameraConfig) -> CameraConfig:
    """The camera config of an (adjusted) COLMAP camera; inverse of :func:`colmap_camera`."""
    p = np.asarray(cam.params, dtype=np.float64)
    k3 = float(p[8]) if p.size == FULL_OPENCV_PARAMS else 0.0
    distorted = bool(np.any(p[4:8] != 0.0)) or k3 != 0.0 or p[0] != p[1]
    model = "OPENCV" if (template.model == "OPENCV" or distorted) else "PINHOLE"
    return CameraConfig(model=model, width_px=template.width_px, height_px=template.height_px,
                        fx_px=float(p[0]), fy_px=float(p[1]),
                        cx_px=float(p[2]) - COLMAP_PIXEL_OFFSET,
                        cy_px=float(p[3]) - COLMAP_PIXEL_OFFSET, k1=float(p[4]), k2=float(p[5]),
                        p1=float(p[6]), p2=float(p[7]), k3=k3)


def rigid_from_eop(eop: FloatArray) -> pycolmap.Rigid3d:
    """COLMAP ``cam_from_world`` of one EOP ``[X0, Y0, Z0, omega, phi, kappa]``."""
    import pycolmap

    R, t = cv_pose_from_eop(np.asarray(eop, dtype=np.float64)[None])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R[0]), t[0])


def eop_from_rigid(cam_from_world: pycolmap.Rigid3d) -> FloatArray:
    """EOP ``(6,)`` of a COLMAP ``cam_from_world``; inverse of :func:`rigid_from_eop`."""
    R = np.asarray(cam_from_world.rotation.matrix(), dtype=np.float64)
    return eop_from_cv_pose(R[None], np.asarray(cam_from_world.translation)[None])[0]


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class _Model:
    """A reconstruction and how its ids map to ours."""

    reconstruction: pycolmap.Reconstruction
    image_rows: np.ndarray  # rows of ReferenceInput.image_ids in the adjustment
    point_rows: np.ndarray  # rows of ReferenceInput.point_ids adjusted
    point3D_ids: np.ndarray  # COLMAP id of each adjusted point
    obs_used: np.ndarray  # (k,) bool: observation in the model


def build_reconstruction(data: ReferenceInput, origin: FloatArray) -> _Model:
    """The run as a :class:`pycolmap.Reconstruction` in local coordinates (world - origin).

    Images get ids ``1..n`` in acquisition order and their EOP ``eop0`` as pose; points seen
    in at least two images become 3D points (ids from 1) with their tracks.
    """
    import pycolmap

    n, m = len(data.image_ids), len(data.point_ids)
    counts = np.bincount(data.obs_point, minlength=m)
    used_point = counts >= 2
    obs_used = used_point[data.obs_point]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(colmap_camera(data.camera))
    has_obs = np.bincount(data.obs_image[obs_used], minlength=n) > 0
    image_rows = np.flatnonzero(has_obs)
    eop_local = data.eop0.copy()
    eop_local[:, :3] -= origin
    uv = data.obs_uv_px + COLMAP_PIXEL_OFFSET
    # point2D index of each used observation inside its image
    point2d_idx = np.full(data.obs_image.shape[0], -1)
    for i in image_rows:
        rows = np.flatnonzero((data.obs_image == i) & obs_used)
        point2d_idx[rows] = np.arange(rows.size)
        image = pycolmap.Image(name=data.image_ids[i], keypoints=uv[rows],
                               camera_id=CAMERA_ID, image_id=int(i) + 1)
        rec.add_image_with_trivial_frame(image, rigid_from_eop(eop_local[i]))
    point_rows = np.flatnonzero(used_point)
    point3D_ids = np.zeros(point_rows.size, dtype=np.int64)
    order = np.argsort(data.obs_point, kind="stable")
    starts = np.searchsorted(data.obs_point[order], point_rows)
    for j, (p, s) in enumerate(zip(point_rows, starts, strict=True)):
        track = pycolmap.Track()
        for o in order[s:s + counts[p]]:
            track.add_element(int(data.obs_image[o]) + 1, int(point2d_idx[o]))
        point3D_ids[j] = rec.add_point3D(data.xyz0[p] - origin, track)
    return _Model(reconstruction=rec, image_rows=image_rows, point_rows=point_rows,
                  point3D_ids=point3D_ids, obs_used=obs_used)


@contextmanager
def _quiet_glog() -> Iterator[None]:
    """Silence COLMAP's INFO log lines during the solve (warnings stay)."""
    import pycolmap

    logging = pycolmap.logging
    previous = logging.minloglevel
    logging.minloglevel = int(logging.WARNING)
    try:
        yield
    finally:
        logging.minloglevel = previous


def _ba_options(options: ReferenceOptions, sigma_px: float) -> pycolmap.BundleAdjustmentOptions:
    import pycolmap

    ba = pycolmap.BundleAdjustmentOptions()
    ba.print_summary = False
    ba.refine_focal_length = options.self_calibrate
    ba.refine_principal_point = options.self_calibrate
    ba.refine_extra_params = options.self_calibrate
    loss = RobustLoss.TRIVIAL if options.robust_loss is None else options.robust_loss
    ba.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss.value.upper())
    ba.ceres.loss_function_scale = options.loss_scale_sigmas * sigma_px
    solver = ba.ceres.solver_options
    solver.max_num_iterations = options.max_iterations
    solver.function_tolerance = options.function_tolerance
    solver.gradient_tolerance = options.gradient_tolerance
    solver.parameter_tolerance = options.parameter_tolerance
    ba.ceres.solver_options = solver
    return ba


def loss_weight(loss: RobustLoss | None, scale_px: float, r_px: FloatArray) -> FloatArray:
    """IRLS weight ``rho'(s)`` (in (0, 1]) of each image point under Ceres' ``loss`` at scale
    ``scale_px`` (pixels), from the norms ``r_px`` of its residuals, ``s = r^2``: Huber
    ``min(1, a / r)``, Cauchy ``1 / (1 + s / a^2)``, soft L1 ``1 / sqrt(1 + s / a^2)``
    (Ceres' ``loss_function.h``); 1 for least squares (``None`` or ``trivial``)."""
    r = np.asarray(r_px, dtype=np.float64)
    if loss is None or loss is RobustLoss.TRIVIAL:
        return np.ones_like(r)
    z = (r / scale_px) ** 2
    if loss is RobustLoss.HUBER:
        return np.minimum(1.0, 1.0 / np.sqrt(np.maximum(z, 1e-300)))
    if loss is RobustLoss.CAUCHY:
        return 1.0 / (1.0 + z)
    return 1.0 / np.sqrt(1.0 + z)


def loss_of_run(robust_scale: float | None) -> tuple[RobustLoss, float]:
    """The reference's loss for a run whose image points had the robust loss
    ``robust_scale`` (σ; ``None``: least squares).

    The run's loss is least squares within ``k`` σ and a Cauchy tail beyond
    (:mod:`seqat.robust`); Ceres has no such loss, and its Huber loss at ``k`` σ has the same
    core: on residuals within ``k`` σ the two adjust alike, and both bound the pull of a
    blunder (Huber's linear tail lets it pull a little more than the Cauchy tail).
    """
    if robust_scale is None:
        return RobustLoss.TRIVIAL, ReferenceOptions().loss_scale_sigmas
    return RobustLoss.HUBER, float(robust_scale)


def run_loss_scale(record: Mapping[str, object]) -> float | None:
    """The image points' robust scale of a run's final adjustment (σ; ``None``: least
    squares), from its ``run.json``: ``robustness.final_robust_scale`` (the configured
    ``robust_scale``, narrowed on a contaminated flight: docs/algorithm.md, *The loss of a
    contaminated flight*), or ``robust_scale`` for a run written before it."""
    rob = record.get("robustness")
    return final_robust_scale(rob) if isinstance(rob, Mapping) else None


def _prior_cost(kind: PriorKind, nav_local: FloatArray, cov: FloatArray | None,
                position_var: FloatArray) -> object:
    import pycolmap.cost_functions as cf

    if kind is PriorKind.POSE:
        return cf.AbsolutePosePriorCost(cov, rigid_from_eop(nav_local))
    return cf.AbsolutePosePositionPriorCost(np.diag(position_var), nav_local[:3])


def _point_prior_cost(prior_local: FloatArray, weight: FloatArray) -> object:
    """Ceres cost ``weight * (X - prior)`` on a 3D point (3 residuals, Jacobian diagonal)."""
    import pyceres

    class PointPriorCost(pyceres.CostFunction):  # type: ignore[misc]
        def __init__(self) -> None:
            super().__init__()
            self.set_num_residuals(3)
            self.set_parameter_block_sizes([3])

        def Evaluate(self, parameters: list[np.ndarray], residuals: np.ndarray,  # noqa: N802
                     jacobians: list[np.ndarray | None] | None) -> bool:
            residuals[:] = weight * (parameters[0] - prior_local)
            if jacobians is not None and jacobians[0] is not None:
                jacobians[0][:] = np.diag(weight).ravel()
            return True

    return PointPriorCost()


def _add_control(problem: object, rec: pycolmap.Reconstruction, data: ReferenceInput,
                 model: _Model, origin: FloatArray) -> tuple[list[tuple[int, int]], object]:
    """Add the GCP priors; returns (control row, model point row) pairs and the costs (kept
    alive while the problem lives)."""
    rows = {data.point_ids[p]: j for j, p in enumerate(model.point_rows)}
    pairs, costs = [], []
    for c, cid in enumerate(data.control_ids):
        j = rows.get(cid)
        if j is None:
            continue
        sig = data.control_sigma[c]
        weight = np.where(np.isfinite(sig), data.sigma_px / sig, 0.0)
        cost = _point_prior_cost(data.control_xyz[c] - origin, weight)
        costs.append(cost)
        problem.add_residual_block(  # type: ignore[attr-defined]
            cost, None, [rec.point3D(int(model.point3D_ids[j])).xyz])
        pairs.append((c, j))
    return pairs, costs


def adjust_reference(data: ReferenceInput,
                     options: ReferenceOptions = ReferenceOptions()) -> ReferenceResult:
    """Bundle-adjust the run's observations with COLMAP's Ceres adjuster and GPS/INS priors.

    Parameters
    ----------
    data : ReferenceInput
    options : ReferenceOptions

    Returns
    -------
    ReferenceResult

    Raises
    ------
    EstimationError
        No tie point, a residual count that does not match the problem built, or a failed
        solve.
    """
    pycolmap, pyceres = _import_pycolmap()
    missing = np.isnan(data.nav_eop)
    nav_eop = np.where(missing, data.eop0, data.nav_eop)
    nav_sigma = free_nav_sigma(np.where(missing, np.inf, data.nav_sigma))  # (n, 6)
    origin = np.round(nav_eop[0, :3])
    model = build_reconstruction(data, origin)
    rec = model.reconstruction
    if model.point_rows.size == 0:
        raise EstimationError("no tie point is seen in two images: nothing to adjust")
    config = pycolmap.BundleAdjustmentConfig()  # type: ignore[attr-defined]
    for i in model.image_rows:
        config.add_image(int(i) + 1)
    if not options.self_calibrate:
        config.set_constant_cam_intrinsics(CAMERA_ID)
    ba_options = _ba_options(options, data.sigma_px)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(  # type: ignore[attr-defined]
        ba_options, config, rec)
    problem = adjuster.problem
    n_obs_used = int(np.count_nonzero(model.obs_used))
    if problem.num_residuals() != OBS_RESIDUALS * n_obs_used:
        raise EstimationError(f"COLMAP's problem has {problem.num_residuals()} reprojection "
                              f"residuals, expected {OBS_RESIDUALS * n_obs_used} "
                              f"({n_obs_used} observations)")
    # GPS/INS priors: Sim's weights times sigma_px^2 (COLMAP's image residuals are unweighted).
    scale = 1.0 / data.sigma_px**2
    nav_local = nav_eop.copy()
    nav_local[:, :3] -= origin
    pose_cov = pose_prior_covariance(nav_eop, nav_sigma) * scale
    position_var = nav_sigma[:, :3] ** 2 * scale
    n_blocks = problem.num_parameter_blocks()
    for i in model.image_rows:
        frame = rec.frame(rec.image(int(i) + 1).frame_id)
        cost = _prior_cost(options.prior, nav_local[i], pose_cov[i], position_var[i])
        problem.add_residual_block(cost, None, [frame.rig_from_world.params])
    per_prior = (POSE_PRIOR_RESIDUALS if options.prior is PriorKind.POSE
                 else POSITION_PRIOR_RESIDUALS)
    n_prior = per_prior * int(model.image_rows.size)
    control_pairs, _costs = _add_control(problem, rec, data, model, origin)
    n_control = GP_SIZE * len(control_pairs)
    expected = OBS_RESIDUALS * n_obs_used + n_prior + n_control
    if problem.num_residuals() != expected:
        raise EstimationError(f"the problem has {problem.num_residuals()} residuals after adding "
                              f"the priors, expected {expected}")
    if problem.num_parameter_blocks() != n_blocks:  # a prior on a copy of a pose constrains nothing
        raise EstimationError(f"the priors added {problem.num_parameter_blocks() - n_blocks} "
                              "parameter blocks: they are not on the adjusted poses")
    if options.self_calibrate and rec.camera(CAMERA_ID).params.size == FULL_OPENCV_PARAMS:
        problem.set_manifold(rec.camera(CAMERA_ID).params, pyceres.SubsetManifold(
            FULL_OPENCV_PARAMS, list(FULL_OPENCV_RATIONAL_IDX)))
    t0 = time.perf_counter()
    with _quiet_glog():
        summary = adjuster.solve()
    ba_s = time.perf_counter() - t0
    ceres = summary.ceres_summary
    termination = summary.termination_type.name
    if not summary.is_solution_usable():
        raise EstimationError(f"COLMAP bundle adjustment failed: {termination} "
                              f"({ceres.message})")
    n_residuals = int(ceres.num_residuals)
    if n_residuals != expected:
        raise EstimationError(f"Ceres solved {n_residuals} residuals, expected {expected}")

    # Estimates back in our conventions (local coordinates first).
    n = len(data.image_ids)
    eop_local = nav_local.copy()  # images without ties keep their nav
    for i in model.image_rows:
        eop_local[i] = eop_from_rigid(rec.image(int(i) + 1).cam_from_world())
    xyz_local = np.array([rec.point3D(int(pid)).xyz for pid in model.point3D_ids])
    camera = camera_config_from_colmap(rec.camera(CAMERA_ID), data.camera)

    # sigma0 with Sim's definitions.
    uv_obs = data.obs_uv_px[model.obs_used] + COLMAP_PIXEL_OFFSET
    img_used = data.obs_image[model.obs_used]
    pt_local = np.full((len(data.point_ids), 3), np.nan)
    pt_local[model.point_rows] = xyz_local
    R_cv, t_cv = cv_pose_from_eop(eop_local)
    p_cam = np.einsum("kij,kj->ki", R_cv[img_used], pt_local[data.obs_point[model.obs_used]])
    p_cam += t_cv[img_used]
    uv_hat = np.asarray(rec.camera(CAMERA_ID).img_from_cam(p_cam, check_cheirality=False))
    v_img = uv_obs - uv_hat
    v_nav = nav_eop - (eop_local + np.concatenate([origin, np.zeros(3)]))
    v_nav[:, 3:] = wrap_angle(v_nav[:, 3:])
    in_adj = np.zeros(n, dtype=bool)
    in_adj[model.image_rows] = True
    prior_cols = slice(0, EOP_SIZE if options.prior is PriorKind.POSE else 3)
    # each image point at the final weight of the loss Ceres minimised (IRLS), as Sim's
    # sigma0 weighs its own: a blunder's residual must not scale every posterior sigma
    w_img = loss_weight(options.robust_loss, options.loss_scale_sigmas * data.sigma_px,
                        np.linalg.norm(v_img, axis=1))
    ssr = float(np.sum(w_img[:, None] * v_img**2) / data.sigma_px**2
                + np.sum((v_nav[in_adj] / nav_sigma[in_adj])[:, prior_cols] ** 2))
    for c, j in control_pairs:
        sig = data.control_sigma[c]
        free = ~np.isfinite(sig)
        v = np.where(free, 0.0, (xyz_local[j] + origin - data.control_xyz[c]) / sig)
        ssr += float(np.sum(v**2))
    n_control_obs = sum(int(np.count_nonzero(np.isfinite(data.control_sigma[c])))
                        for c, _ in control_pairs)
    redundancy = (OBS_RESIDUALS * n_obs_used - GP_SIZE * int(model.point_rows.size)
                  + n_control_obs)
    if options.prior is PriorKind.POSITION:
        redundancy -= 3 * int(model.image_rows.size)  # attitudes without pseudo-observations
    sigma0 = float(np.sqrt(ssr / redundancy)) if redundancy > 0 else float("nan")
    rms_px = float(np.sqrt(np.mean(v_img**2)))
    scale_post = sigma0 if np.isfinite(sigma0) else 1.0

    eop_sigma = np.full((n, EOP_SIZE), np.nan)
    eop_sigma[~in_adj] = nav_sigma[~in_adj]
    xyz_sigma = np.full((model.point_rows.size, GP_SIZE), np.nan)
    status = "off"
    if options.covariance:
        status = _covariances(pycolmap, rec, adjuster, model, eop_local, data.sigma_px,
                              scale_post, eop_sigma)

    # The model in world coordinates.
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), origin))  # type: ignore[attr-defined]
    eop = eop_local.copy()
    eop[:, :3] += origin
    n_obs = np.bincount(data.obs_point[model.obs_used],
                        minlength=len(data.point_ids))[model.point_rows]
    return ReferenceResult(
        image_ids=data.image_ids, eop=eop, eop_sigma=eop_sigma, in_adjustment=in_adj,
        point_ids=tuple(data.point_ids[p] for p in model.point_rows), xyz=xyz_local + origin,
        xyz_sigma=xyz_sigma, n_obs=n_obs, camera=camera,
        converged=termination == "CONVERGENCE", termination=termination,
        iterations=int(ceres.num_successful_steps + ceres.num_unsuccessful_steps),
        n_residuals=n_residuals, n_prior_residuals=n_prior, sigma0=sigma0,
        redundancy=redundancy, rms_px=rms_px, ba_s=ba_s,
        linear_solver=str(ceres.linear_solver_type_used.name), covariance_status=status,
        origin=origin, reconstruction=rec, n_control_points=len(control_pairs),
        n_control_residuals=n_control)


def _covariances(pycolmap: object, rec: pycolmap.Reconstruction, adjuster: object,
                 model: _Model, eop_local: FloatArray, sigma_px: float, sigma0: float,
                 eop_sigma: FloatArray) -> str:
    """Fill the a posteriori pose sigmas from ``pycolmap.estimate_ba_covariance``; status.

    COLMAP's covariances belong to the objective with unweighted image residuals, i.e. they
    are Sim's cofactors divided by ``sigma_px^2``. Point sigmas stay NaN: COLMAP's point
    covariance is conditioned on the poses (``get_point_cov``), not the marginal one Sim
    reports, and would understate them several times.
    """
    cov_options = pycolmap.BACovarianceOptions()  # type: ignore[attr-defined]
    cov_options.params = pycolmap.BACovarianceOptionsParams.POSES  # type: ignore[attr-defined]
    try:
        with _quiet_glog():
            cov = pycolmap.estimate_ba_covariance(cov_options, rec, adjuster)  # type: ignore[attr-defined]
    except RuntimeError as err:  # COLMAP's THROW_CHECKs
        return f"failed: {' '.join(str(err).split())[:200]}"
    if cov is None:
        return "failed: pycolmap.estimate_ba_covariance returned no result"
    factor = sigma_px**2 * sigma0**2
    missing = 0
    for i in model.image_rows:
        c = cov.get_cam_cov_from_world(int(i) + 1)
        if c is None or np.asarray(c).shape != (6, 6):
            missing += 1
            continue
        q = eop_covariance_from_tangent(eop_local[i], np.asarray(c) * factor)
        eop_sigma[i] = np.sqrt(np.clip(np.diagonal(q), 0.0, None))
    return "computed" if missing == 0 else f"computed, {missing} image(s) without covariance"
