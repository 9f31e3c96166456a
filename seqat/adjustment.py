"""One adjustment of a block: Sim's solver (seed 000 §2.1, Choi & Lee 2012, Eq. 1-6).

Image observations plus the GPS/INS EOPs as stochastic constraints; ground points (GP)
eliminated per 3x3 block (Schur complement, :mod:`seqat.normals`); Gauss-Newton, shortened
by a line search or damped (Levenberg-Marquardt) where it overshoots, Newton's method on the
robust losses once in the basin; a posteriori sigma0 and the cofactors asked for.
:class:`seqat.simultaneous.SimultaneousAT` runs it on the growing block; the sequential
estimators start from it.

Coordinates here are *local* (the caller subtracts an origin for conditioning).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from seqat import robust as rloss
from seqat.calibration import FreeCamera, SelfCalibration
from seqat.errors import EstimationError
from seqat.geometry import project
from seqat.normals import (
    BlockData,
    CameraBlock,
    Normals,
    back_substitute,
    camera_cofactor,
    eop_cofactor_blocks,
    eop_residual,
    full_cofactor,
    full_normal,
    gp_cofactors,
    linearise,
    on_nav_branch,
    weighted_ssr,
)
from seqat.robust import ROBUST_SCALE, cauchy_weight
from seqat.tail_points import TAIL_NEWTON_FROM, embedded_points, newton_on_tail_points
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray, PinholeCamera

#: Levenberg-Marquardt: first damping, its growth factor on a rejected step, the largest.
FIRST_DAMPING = 1e-4
DAMPING_FACTOR = 10.0
MAX_DAMPING = 1e8
MIN_DAMPING = 1e-8  # below this an accepted damped step turns back to Gauss-Newton
#: Step lengths tried along a Gauss-Newton (or damped) correction, longest first.
LINE_SEARCH_STEPS = (1.0, 0.5, 0.25, 0.125)
#: A step is accepted when it does not raise the weighted SSR by more than this (relative):
#: round-off at the minimum must not count as a rise.
COST_TOLERANCE = 1e-10
#: Convergence of the camera's free interior parameters: correction below this fraction of
#: each one's prior sigma.
CAMERA_TOLERANCE = 1e-6
#: The least-squares phase has settled, and the GPS/INS groups are judged for their loss,
#: when an undamped step lowers the cost by less than this fraction (Ceres' default
#: function_tolerance), though a point may still creep: under the rays' loss a two-ray
#: point converged linearly, the steps' tolerances were met after 50 iterations, beyond
#: ``max_iterations``, and a 5 m GNSS jump was never down-weighted (docs/algorithm.md).
SETTLED_TOLERANCE = 1e-6


class Covariance(Enum):
    """Which cofactors an adjustment returns."""

    NONE = "none"
    BLOCKS = "blocks"  # 6x6 per image, 3x3 per point
    FULL = "full"  # dense matrix over [EOPs..., GPs...] (small blocks only)
    NORMAL = "normal"  # the normal matrix alone (full_normal): the information engine


@dataclass(frozen=True, kw_only=True)
class SimOptions:
    """Options of the simultaneous adjustment."""

    max_iterations: int = 20
    position_tolerance_m: float = 1e-6  # convergence: max |correction| of EOP and GP positions
    angle_tolerance_rad: float = 1e-9  # convergence: max |correction| of angles
    min_rays: int = 2  # a tie point enters the adjustment once seen in this many images
    covariance_every_frame: bool = True  # per-frame refits also compute the cofactor blocks
    # Baarda's data snooping after each adjustment (w-test critical value; None: off). Needs
    # the full cofactor: meant for the initial stage and blocks of a few hundred images.
    snooping_critical: float | None = None
    # A new point enters once its rays spread this much (0: any intersection, the paper).
    # With blunders a small spread lets a bad ray place the point anywhere along the others.
    min_ray_angle_deg: float = 0.0
    # Leave every two-ray tie point out of the block when the points of three rays or more
    # show many wrong matches (seqat.robust.untrusted_two_ray_points; Seq-R's initial block:
    # off, its finish() judges them).
    untrust_pairs: bool = True
    # Robust loss of the image points: least squares within this many sigma, a Cauchy tail
    # beyond (seqat/robust.py; on by default); None: least squares (the paper's estimator).
    robust_scale: float | None = ROBUST_SCALE
    # Robust loss of the GPS/INS groups (position, attitude: 3 DoF each): least squares
    # within this many sigma per degree of freedom (u² <= 3 k²), a Cauchy tail beyond; on
    # once Gauss-Newton has converged with least-squares GPS/INS. None: least squares.
    nav_robust_scale: float | None = rloss.NAV_ROBUST_SCALE
    # Self-calibration: the camera's interior parameters it sets free are estimated too,
    # with the camera as their prior (seqat/calibration.py); None: the camera is fixed.
    calibration: SelfCalibration | None = None

    def __post_init__(self) -> None:
        rloss.check_scale("robust_scale", self.robust_scale)
        rloss.check_scale("nav_robust_scale", self.nav_robust_scale)


@dataclass(frozen=True, kw_only=True, eq=False)
class SimResult:
    """Typed result of :func:`adjust_block`.

    ``eop_cofactor`` (n, 6, 6) and ``gp_cofactor`` (m, 3, 3) are cofactors (multiply by
    ``sigma0**2`` for covariances); ``full_cofactor`` is the dense inverse normal matrix over
    ``[eop_0..eop_{n-1}, gp_0..gp_{m-1}]`` when requested.
    """

    eop: FloatArray
    gp: FloatArray
    converged: bool
    iterations: int
    sigma0: float
    redundancy: int
    weighted_ssr: float
    rms_px: float
    reduced_size: int
    eop_cofactor: FloatArray | None = None
    gp_cofactor: FloatArray | None = None
    full_cofactor: FloatArray | None = None
    full_normal: FloatArray | None = None  # the normal matrix (Covariance.FULL, NORMAL)
    undetermined: np.ndarray | None = None  # (m,) bool: points the data do not determine
    #: The camera at the solution (the input camera unless self-calibrating) and the
    #: cofactor of its free interior parameters, (c, c); ``full_*`` then hold them between
    #: the EOPs and the GPs.
    camera: PinholeCamera | None = None
    camera_cofactor: FloatArray | None = None
    #: (n, g) robust weight factor of each image's GPS/INS groups (seqat.robust.NAV_GROUPS).
    nav_weight: FloatArray | None = None
    #: Not converged: the step from the estimate to the minimum of the model linearised
    #: there, over ``[EOPs, camera, GPs]`` (``full_normal``'s layout); None when converged.
    model_step: FloatArray | None = None


def _accepted(new_cost: float, cost: float) -> bool:
    """A step's cost ``new_cost`` lowers ``cost`` (to :data:`COST_TOLERANCE`) and is finite:
    from a start outside the models' domain (a point behind a camera: ``cost`` inf) only a
    step back into it is taken, never one that leaves the camera's (a focal length <= 0,
    which a start of infinite cost let through: an iterate no camera can be made of)."""
    return math.isfinite(new_cost) and new_cost <= cost * (1.0 + COST_TOLERANCE)


def _in_tails(camera: PinholeCamera, data: BlockData, eop: FloatArray, gp: FloatArray,
              robust: float | None, nav_robust: float | None) -> bool:
    """A ray or a GPS/INS group lies beyond its loss's core at ``(eop, gp, camera)``."""
    if robust is not None and data.obs_image.size:
        res = data.obs_uv - project(eop[data.obs_image], gp[data.obs_point], camera)
        if np.any(rloss.ray_u2(res, data.obs_sigma_px) > robust**2):
            return True
    return bool(nav_robust is not None and rloss.nav_outside(
        eop_residual(data.nav_eop, eop), data.nav_sigma, nav_robust).any())


def adjust_block(
    camera: PinholeCamera,
    data: BlockData,
    eop0: FloatArray,
    gp0: FloatArray,
    options: SimOptions = SimOptions(),
    covariance: Covariance = Covariance.BLOCKS,
    calib: CameraBlock | None = None,
    nav_on: bool = False,
    accelerate: bool = True,
) -> SimResult:
    """Simultaneous adjustment by Gauss-Newton (seed 000 §2.1).

    Parameters
    ----------
    camera : PinholeCamera
    data : BlockData
        Observations in local coordinates.
    eop0 : (n, 6) float
        Initial EOPs (local).
    gp0 : (m, 3) float
        Initial GP coordinates (local), all finite.
    options : SimOptions
    covariance : Covariance
    calib : CameraBlock, optional
        Self-calibration: these interior parameters of ``camera`` (its values the initial
        ones) are estimated too, with their prior.
    nav_on : bool
        The GPS/INS loss from the first iteration: the start is a solution of the block
        that found GPS/INS outliers (the datum set), not a least-squares phase first.
    accelerate : bool
        A full step that raises the cost is tried again with its points made optimal for
        its images (:func:`seqat.tail_points.embedded_points`; once per iteration) before
        it is shortened, and
        in the basin the step is Newton's on the robust cost where IRLS creeps (the losses'
        own curvature beyond their cores). False: Gauss-Newton on IRLS weights with its line
        search to the end, as the refits of :class:`seqat.simultaneous.SimultaneousAT` while
        the images arrive want it: a block that does not converge with a new image is
        their sign of a wrong minimum, which they start that image again for
        (docs/algorithm.md, *Sim's iterations*).

    Returns
    -------
    SimResult

    Raises
    ------
    EstimationError
        Singular reduced system or GP block.
    """
    n, m = data.n_images, data.n_points
    if not np.all(np.isfinite(gp0)):
        raise EstimationError("initial ground point coordinates must be finite")
    eop = np.array(eop0, dtype=np.float64)
    on_nav_branch(eop, data.nav_eop)
    gp = np.array(gp0, dtype=np.float64)
    c = calib.size if calib is not None else 0
    free_cam = FreeCamera(camera, calib.index if calib is not None
                          else np.zeros(0, dtype=np.int64))
    camera_at = free_cam.at
    cam_x = camera.intrinsics[free_cam.index]
    cam = camera
    converged = turned = was_damped = False
    newton = newton_failed = False  # Newton's method on the robust cost (in the basin)
    nrm: Normals | None = None
    damping = 0.0
    robust = options.robust_scale
    # GPS/INS least squares until converged or settled (the datum), then robust if any is off
    # (robust.py); robust from the start when ``nav_on``
    nav_robust = options.nav_robust_scale if nav_on else None
    cost = weighted_ssr(cam, data, eop, gp, robust, calib, nav_robust)
    limit = options.max_iterations
    iterations = 0
    while iterations < limit:
        iterations += 1
        # Gauss-Newton while it lowers the cost: the full step with its points made optimal
        # for its images when it does not, shortened by a line search when that does not
        # either, Levenberg-Marquardt damping when no shortened step helps (bad initial
        # values of real flights). In the basin, Newton's method on the robust cost while
        # its steps lower it (IRLS's creeps), Gauss-Newton's again when one does not.
        # Near the minimum the full step is taken, so the solution is Gauss-Newton's (or
        # Newton's: the same stationary point) wherever Gauss-Newton converges.
        # one trial with embedded points per iteration, at its least damped step (a trial
        # at every damping: Seneca's hand-over 182 ms against 111, docs/benchmarks.md)
        trial = accelerate and m > 0
        while True:
            try:
                nrm, rhs, _ = linearise(cam, data, eop, gp, damping, robust, calib, nav_robust,
                                        newton=newton)
            except EstimationError:
                if not newton:
                    raise
                newton, newton_failed = False, True  # singular with the loss's own curvature
                continue
            delta_r = nrm.lu.solve(rhs)
            if newton and not np.all(np.isfinite(delta_r)):
                newton, newton_failed = False, True
                continue
            if not np.all(np.isfinite(delta_r)):
                raise EstimationError(
                    f"non-finite correction in iteration {iterations} "
                    f"(reduced system of order {nrm.size})"
                )
            delta_p = back_substitute(nrm, delta_r).reshape(m, GP_SIZE)
            de = delta_r[: EOP_SIZE * n].reshape(n, EOP_SIZE)
            dc = delta_r[EOP_SIZE * n :]
            new_cost, step, embedded = math.inf, 1.0, False
            for step in LINE_SEARCH_STEPS:
                if not free_cam.admissible(cam_x + step * dc):  # a focal length <= 0: no camera
                    new_cost = math.inf
                    continue
                new_cost = weighted_ssr(camera_at(cam_x + step * dc), data, eop + step * de,
                                        gp + step * delta_p, robust, calib, nav_robust)
                if _accepted(new_cost, cost):
                    break
                if step == 1.0 and trial:  # its points optimal for its images
                    trial = False
                    trial_cam = camera_at(cam_x + dc)
                    trial_gp, _ = embedded_points(trial_cam, data, eop + de, gp + delta_p,
                                                  robust, nrm.undetermined)
                    trial_cost = weighted_ssr(trial_cam, data, eop + de, trial_gp, robust,
                                              calib, nav_robust)
                    if _accepted(trial_cost, cost):
                        new_cost, embedded, delta_p = trial_cost, True, trial_gp - gp
                        break
            if _accepted(new_cost, cost):
                break
            if newton:  # no step along Newton's direction lowers the cost: IRLS's again
                newton, newton_failed = False, True
                continue
            if damping >= MAX_DAMPING:
                break
            damping = FIRST_DAMPING if damping == 0.0 else damping * DAMPING_FACTOR
        if not _accepted(new_cost, cost):
            raise EstimationError(f"adjustment diverges (cost {new_cost:.4g} > {cost:.4g} even "
                                  f"with damping {damping:g}, iteration {iterations})")
        de, delta_p, dc = step * de, step * delta_p, step * dc
        eop += de
        gp += delta_p
        cam_x = cam_x + dc
        cam = camera_at(cam_x)
        turned = on_nav_branch(eop, data.nav_eop)  # a step can reach the other branch
        moved = 0.0  # once in the basin: from a poor start it led the points astray
        # in the basin: a full Gauss-Newton step that lowered the cost by little
        basin = (damping == 0.0 and step == 1.0 and not embedded
                 and cost - new_cost <= TAIL_NEWTON_FROM * cost)
        if basin and not newton:
            gp, moved = newton_on_tail_points(cam, data, eop, gp, robust, nrm.undetermined)
        if turned or moved:
            new_cost = weighted_ssr(cam, data, eop, gp, robust, calib, nav_robust)
        settled = cost - new_cost <= SETTLED_TOLERANCE * cost
        # rays and GPS/INS groups in their loss's tail creep under IRLS (by a constant
        # fraction per step): in the basin, Newton's method on the robust cost instead
        if basin and accelerate and not newton and not newton_failed:
            newton = _in_tails(cam, data, eop, gp, robust, nav_robust)
        cost = new_cost
        was_damped = damping > 0.0 or step < 1.0 or embedded
        damping = damping / DAMPING_FACTOR if damping > MIN_DAMPING else 0.0
        max_pos = max(np.max(np.abs(de[:, :3]), initial=0.0),
                      np.max(np.abs(delta_p), initial=0.0), moved)
        max_ang = np.max(np.abs(de[:, 3:]), initial=0.0)
        # the camera: its correction small against its own prior sigma
        max_cam = np.max(np.abs(dc) / calib.sigma, initial=0.0) if c else 0.0  # type: ignore[union-attr]
        small = (max_pos < options.position_tolerance_m
                 and max_ang < options.angle_tolerance_rad and max_cam < CAMERA_TOLERANCE)
        if not was_damped and (small or (settled and nav_robust is None)):
            if nav_robust is None and not rloss.nav_within_core(
                    eop_residual(data.nav_eop, eop), data.nav_sigma, options.nav_robust_scale):
                nav_robust = options.nav_robust_scale
                cost = weighted_ssr(cam, data, eop, gp, robust, calib, nav_robust)
                limit = iterations + options.max_iterations
                continue
            if small:
                converged = True
                break
    if was_damped or not converged or turned or newton:
        # the system at the estimate returned, undamped and on its branch, not one step
        # before: the sequential stage subtracts the rays' rows linearised at the estimate
        # from it, and from a system linearised elsewhere that left an indefinite matrix
        # (an initial block stopped 20 iterations short, camera self-calibrated)
        nrm, rhs, _ = linearise(cam, data, eop, gp, 0.0, robust, calib, nav_robust)
    assert nrm is not None
    model_step = None
    if not converged:  # where the model at the estimate has its minimum (Gauss-Newton's step)
        delta_r = nrm.lu.solve(rhs)
        step = np.concatenate([delta_r, back_substitute(nrm, delta_r).ravel()])
        model_step = step if np.all(np.isfinite(step)) else None
    img, pt = data.obs_image, data.obs_point
    res_img = data.obs_uv - project(eop[img], gp[pt], cam)
    res_nav = eop_residual(data.nav_eop, eop)
    weight = cauchy_weight(res_img, data.obs_sigma_px, robust)
    und = nrm.undetermined
    weight = np.where(und[pt], 0.0, weight)
    w_nav = rloss.nav_weight(res_nav, data.nav_sigma, nav_robust)
    ssr = float(
        np.sum(weight[:, None] * res_img**2 / data.obs_sigma_px[:, None] ** 2)
        + np.sum(w_nav * res_nav**2 / data.nav_sigma**2)
    )
    ssr += data.control_ssr(gp)
    if calib is not None:
        ssr += float(np.sum((calib.residual(cam) / calib.sigma) ** 2))
    redundancy = (2 * int(np.count_nonzero(~und[pt])) - GP_SIZE * int(np.count_nonzero(~und))
                  + int(np.count_nonzero(data.control_weight)))
    sigma0 = float(np.sqrt(ssr / redundancy)) if redundancy > 0 else float("nan")
    rms_px = float(np.sqrt(np.mean(res_img**2))) if img.size else float("nan")
    eop_cof = gp_cof = full = normal = None
    cam_cof = camera_cofactor(nrm) if c else None
    if covariance in (Covariance.FULL, Covariance.NORMAL):
        normal = full_normal(nrm, n, m)
    if covariance is Covariance.FULL:
        full = full_cofactor(nrm, n, m)
        eop_cof = np.stack([full[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(n)])
        off = EOP_SIZE * n + c
        gp_cof = (np.stack([full[off + 3 * j : off + 3 * j + 3, off + 3 * j : off + 3 * j + 3]
                            for j in range(m)]) if m else np.zeros((0, 3, 3)))
    elif covariance is Covariance.BLOCKS:
        eop_cof = eop_cofactor_blocks(nrm, n)
        gp_cof = gp_cofactors(nrm, data) if m else np.zeros((0, 3, 3))
    return SimResult(
        eop=eop,
        gp=gp,
        converged=converged,
        iterations=iterations,
        sigma0=sigma0,
        redundancy=redundancy,
        weighted_ssr=ssr,
        rms_px=rms_px,
        reduced_size=nrm.size,
        eop_cofactor=eop_cof,
        gp_cofactor=gp_cof,
        full_cofactor=full,
        full_normal=normal,
        undetermined=und,
        camera=cam,
        camera_cofactor=cam_cof,
        nav_weight=rloss.nav_groups_of(w_nav),
        model_step=model_step,
    )
