"""Simultaneous aerial triangulation (Sim) with GPS/INS stochastic constraints.

Seed 000 §2.1 (Choi & Lee 2012, Eq. 1-6): image observations plus the GPS/INS EOPs as
stochastic constraints; ground points (GP) eliminated per 3x3 block (Schur complement), the
reduced EOP normal matrix ``N_r = N_ee + N_z - N_ep N_pp^-1 N_ep^T`` (sparse, banded along a
strip) factorised with a sparse LU; GPs back-substituted; Gauss-Newton to convergence;
a posteriori sigma0 and cofactor blocks of EOPs and GPs.

Coordinates here are *local* (the caller subtracts an origin for conditioning).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum

import numpy as np

from seqat import robust as rloss
from seqat.calibration import FreeCamera, SelfCalibration, correlation, to_hold
from seqat.catalogue import Catalogue, control_by_id
from seqat.errors import EstimationError
from seqat.geometry import depth, intersect_rays, project
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
from seqat.precision import deviations, rms_point_sigma, sigma_scale
from seqat.robust import ROBUST_SCALE, cauchy_weight
from seqat.sim_points import PointChecksMixin
from seqat.sim_restart import RestartMixin
from seqat.sim_snooping import SnoopingMixin
from seqat.tail_points import TAIL_NEWTON_FROM, newton_on_tail_points
from seqat.types import (
    EOP_SIZE,
    GP_SIZE,
    CameraEstimate,
    ControlPoint,
    EopEstimate,
    FloatArray,
    Frame,
    ImageUpdate,
    PinholeCamera,
    PointEstimate,
    Solution,
)

#: Levenberg-Marquardt: first damping, its growth factor on a rejected step, the largest.
FIRST_DAMPING = 1e-4
DAMPING_FACTOR = 10.0
MAX_DAMPING = 1e8
#: Times the block is adjusted again with the points the adjusted EOPs let in (_solve).
MAX_READMISSIONS = 2
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


#: Data snooping: at most this many reject-and-adjust rounds per solve.
MAX_SNOOPING_ROUNDS = 30


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


def adjust_block(
    camera: PinholeCamera,
    data: BlockData,
    eop0: FloatArray,
    gp0: FloatArray,
    options: SimOptions = SimOptions(),
    covariance: Covariance = Covariance.BLOCKS,
    calib: CameraBlock | None = None,
    nav_on: bool = False,
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
        # Gauss-Newton while it lowers the cost, shortened by a line search when the full
        # step overshoots, Levenberg-Marquardt damping when no shortened step helps (bad
        # initial values of real flights). Near the minimum the full Gauss-Newton step is
        # taken, so the solution is Gauss-Newton's wherever Gauss-Newton converges.
        while True:
            nrm, rhs, _ = linearise(cam, data, eop, gp, damping, robust, calib, nav_robust)
            delta_r = nrm.lu.solve(rhs)
            if not np.all(np.isfinite(delta_r)):
                raise EstimationError(
                    f"non-finite correction in iteration {iterations} "
                    f"(reduced system of order {nrm.size})"
                )
            delta_p = back_substitute(nrm, delta_r).reshape(m, GP_SIZE)
            de = delta_r[: EOP_SIZE * n].reshape(n, EOP_SIZE)
            dc = delta_r[EOP_SIZE * n :]
            new_cost, step = math.inf, 1.0
            for step in LINE_SEARCH_STEPS:
                if not free_cam.admissible(cam_x + step * dc):  # a focal length <= 0: no camera
                    new_cost = math.inf
                    continue
                new_cost = weighted_ssr(camera_at(cam_x + step * dc), data, eop + step * de,
                                        gp + step * delta_p, robust, calib, nav_robust)
                if _accepted(new_cost, cost):
                    break
            if _accepted(new_cost, cost) or damping >= MAX_DAMPING:
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
        if damping == 0.0 and step == 1.0 and cost - new_cost <= TAIL_NEWTON_FROM * cost:
            gp, moved = newton_on_tail_points(cam, data, eop, gp, robust, nrm.undetermined)
        if turned or moved:
            new_cost = weighted_ssr(cam, data, eop, gp, robust, calib, nav_robust)
        settled = cost - new_cost <= SETTLED_TOLERANCE * cost
        cost = new_cost
        was_damped = damping > 0.0 or step < 1.0
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
    if was_damped or not converged or turned:
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


#: :meth:`SimultaneousAT.export_state` solves again, from where the last solve stopped, up
#: to this many times while it has not converged.
EXPORT_MORE_SOLVES = 4


@dataclass(frozen=True, kw_only=True, eq=False)
class SimState:
    """Everything a simultaneous solution knows, for handing over to the sequential stage.

    Point indices refer to ``point_ids`` (every point seen, adjusted or not); ``selected``
    lists the adjusted ones in the order of ``result.gp``.
    """

    origin: FloatArray  # (3,) world metres subtracted from every coordinate
    image_ids: tuple[str, ...]
    point_ids: tuple[str, ...]
    selected: np.ndarray
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_uv: FloatArray
    obs_sigma_px: FloatArray
    result: SimResult
    #: The self-calibration of ``result`` (its free parameters sit between the EOPs and the
    #: GPs of the full matrices); None: the camera was fixed.
    calibration: SelfCalibration | None = None
    nav: tuple[FloatArray, FloatArray] | None = None  # GPS/INS (n, 6; local), its sigmas


class SimultaneousAT(SnoopingMixin, RestartMixin, PointChecksMixin):
    """The Sim baseline as a streaming estimator: refit the whole block after each frame.

    Parameters
    ----------
    camera : PinholeCamera
    options : SimOptions
    refit_every_frame : bool
        ``False`` only buffers frames; :meth:`solution` then solves once (``--final-only``).
    control : sequence of ControlPoint
        Ground control: points whose coordinates are observed (adjusted from one ray on).
    calibrate_on_export : bool
        Self-calibrating, the refits while the images arrive hold the camera at its prior;
        :meth:`export_state` frees it, starting from the held solution (the initial block
        of :class:`seqat.sequential.SequentialAT`: in a block of a few images the free
        interior parameters absorb a poor GPS/INS start; docs/algorithm.md, *A poor start*).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        options: SimOptions = SimOptions(),
        *,
        refit_every_frame: bool = True,
        control: Sequence[ControlPoint] = (),
        calibrate_on_export: bool = False,
    ) -> None:
        self.camera = camera
        self.options = options  # its robust_scale: the one in force (_solve)
        self._scale = options.robust_scale  # ... and the one configured
        self.refit_every_frame = refit_every_frame
        self._camera_held = calibrate_on_export  # until export_state
        self.control = control_by_id(control)
        #: The camera at the last solution (the prior ``camera`` until self-calibrated).
        self.camera_now = camera
        self._held: tuple[str, ...] = ()  # free parameters the last solution held at the prior
        self._cat = Catalogue()
        self._origin: FloatArray | None = None
        self._result: SimResult | None = None
        self._point_sel: np.ndarray = np.zeros(0, dtype=np.int64)
        self._eop_est: FloatArray = np.zeros((0, EOP_SIZE))
        self._gp_est: FloatArray = np.zeros((0, GP_SIZE))
        self._dirty = False
        self._rejected: set[int] = set()  # catalogue indices of observations rejected
        self._ambiguous: set[int] = set()  # catalogue points held out: uninformative_points
        self._untrusted: set[int] = set()  # ... two-ray points of a contaminated block
        #: Fraction of the rays of points of three rays or more clearly beyond the robust
        #: loss's core at the last solution (seqat.robust.contamination; NaN: not judged).
        self.contamination = float("nan")
        #: Observations removed by data snooping: (image id, point id, w-test value).
        self.rejections: list[tuple[str, str, float]] = []
        #: GPS/INS groups down-weighted by data snooping: (image id, "position"/"attitude").
        self.nav_downweighted: list[tuple[str, str]] = []
        #: Tie points left out of the solution: their rays disagree (seqat.robust).
        self.disagreeing: list[str] = []
        #: Images whose start made the block fail as they were added (refit_every_frame), or
        #: most of whose rays rejected the solution from their start and from a resection:
        #: carried by their GPS/INS, their rays left out (seqat.sim_restart).
        self.diverged: list[str] = []
        self._diverged: set[int] = set()
        self._nav_on = False  # this solve found GPS/INS outliers (_adjust_and_keep)
        self._readmit_tried: dict[int, int] = {}  # diverged image -> its points tried on

    @property
    def nav_robust(self) -> list[tuple[str, str, float]]:
        """GPS/INS groups the robust loss down-weighted in the last solution: (image id,
        group, weight factor) below :data:`seqat.robust.NAV_REPORT_WEIGHT`."""
        w = self._result.nav_weight if self._result is not None else None
        return [] if w is None else rloss.nav_report(self._cat.image_ids, w)

    def add_frame(self, frame: Frame) -> ImageUpdate:
        """Add one image; refit everything when ``refit_every_frame``."""
        t0 = time.perf_counter()
        cat = self._cat
        if self._origin is None:
            self._origin = np.round(frame.nav_eop[:3])
        nav = frame.nav_eop.copy()
        nav[:3] -= self._origin
        i = cat.add_frame(frame, nav, self._start_nav_sigma(frame, nav))
        init = nav
        if frame.initial_eop is not None:
            init = frame.initial_eop.copy()
            init[:3] -= self._origin
        self._eop_est = np.vstack([self._eop_est, init[None]])
        self._dirty = True
        iterations = 0
        if self.refit_every_frame:
            cov = Covariance.BLOCKS if self.options.covariance_every_frame else Covariance.NONE
            iterations = self._refit(i, cov)
        return self._update_record(frame, i, (time.perf_counter() - t0) * 1e3, iterations)

    def _observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, FloatArray, FloatArray]:
        """Catalogue index, image, point, pixels and sigma of every observation not rejected."""
        cat = self._cat
        oi, op = cat.rays()
        idx = np.arange(oi.size)
        if self._rejected:
            idx = np.setdiff1d(idx, np.fromiter(self._rejected, dtype=np.int64))
        if self._diverged:
            idx = idx[~np.isin(oi[idx], np.fromiter(self._diverged, dtype=np.int64))]
        oi, op = oi[idx], op[idx]
        uv = np.asarray(cat.obs_uv, dtype=np.float64).reshape(-1, 2)[idx]
        sg = np.asarray(cat.obs_sigma, dtype=np.float64)[idx]
        return idx, oi, op, uv, sg

    def _block(self) -> tuple[BlockData, np.ndarray, FloatArray, FloatArray, np.ndarray]:
        """Block of all points with at least ``min_rays`` observations and initial values;
        last, the catalogue index of each of its observations."""
        cat = self._cat
        cat_idx, oi, op, uv, sg = self._observations()
        n_pts = len(cat.point_ids)
        counts = np.bincount(op, minlength=n_pts)
        # ground control: adjusted from one ray on, started at its surveyed coordinates
        ctrl = np.asarray([j for j, pid in enumerate(cat.point_ids) if pid in self.control],
                          dtype=np.int64)
        ctrl_xyz = np.asarray([self.control[cat.point_ids[j]].xyz_m - self._origin
                               for j in ctrl]).reshape(-1, GP_SIZE)
        min_rays = np.full(n_pts, self.options.min_rays)
        min_rays[ctrl] = 1
        # Initial GP values: previous estimate where known, else intersection at current EOPs.
        known = np.full(n_pts, False)
        gp_init = np.full((n_pts, 3), np.nan)
        if self._point_sel.size:
            gp_init[self._point_sel] = self._gp_est
            known[self._point_sel] = np.all(np.isfinite(self._gp_est), axis=1)
        need = (~known) & (counts >= min_rays)
        if np.any(need):
            mask = need[op]
            X, spread = intersect_rays(self._eop_est[oi[mask]], uv[mask], op[mask], n_pts,
                                       self.camera_now)
            if self.options.min_ray_angle_deg > 0:
                X[spread < np.radians(self.options.min_ray_angle_deg)] = np.nan
            gp_init[need] = X[need]
        start = need[ctrl]
        gp_init[ctrl[start]] = ctrl_xyz[start]
        usable = (counts >= min_rays) & np.all(np.isfinite(gp_init), axis=1)
        held = self._ambiguous | self._untrusted
        usable[np.fromiter(held, dtype=np.int64, count=len(held))] = False
        # A new point must lie in front of every camera that sees it (a mismatch intersected
        # behind the cameras would make the normal equations indefinite).
        check = usable[op] & need[op]
        if np.any(check):
            front = np.ones(n_pts, dtype=bool)
            d = depth(self._eop_est[oi[check]], gp_init[op[check]])
            np.logical_and.at(front, op[check], d > 0)
            usable &= front
        sel = np.flatnonzero(usable)
        remap = np.full(n_pts, -1)
        remap[sel] = np.arange(sel.size)
        keep = remap[op] >= 0
        data = BlockData(
            nav_eop=np.asarray(cat.nav_eop),
            nav_sigma=np.asarray(cat.nav_sigma),
            obs_image=oi[keep],
            obs_point=remap[op[keep]],
            obs_uv=uv[keep],
            obs_sigma_px=sg[keep],
            n_points=int(sel.size),
            control_point=remap[ctrl[usable[ctrl]]],
            control_xyz=ctrl_xyz[usable[ctrl]],
            control_weight=np.asarray([self.control[cat.point_ids[j]].weight
                                       for j in ctrl[usable[ctrl]]]).reshape(-1, GP_SIZE),
        )
        return data, sel, self._eop_est, gp_init[sel], cat_idx[keep]

    def free_camera(self) -> None:
        """``calibrate_on_export``: free the camera now (the flight ended before the
        export); the next solution self-calibrates."""
        if self._camera_held:
            self._camera_held, self._dirty = False, True

    def export_state(self, covariance: Covariance = Covariance.FULL) -> SimState:
        """Adjust the frames so far and return the solution with its observations."""
        if self._origin is None:
            raise EstimationError("no frames were added")
        self.free_camera()
        self._solve(covariance)
        self._start_rejected_again(covariance)
        res = self._result
        assert res is not None
        # The sequential stage takes this solution for the minimum of its model (its
        # information times its estimate is its information vector): from a solve stopped
        # short, the first re-linearisation's kept information was wrong, and Seneca's
        # window ran away (sigma0 2.5e13, no tie point left). The camera, freed only now,
        # may need more iterations than the refits that had it free all along (Seneca: 35).
        res = self._solve_on(covariance, res, EXPORT_MORE_SOLVES)[0]
        cat = self._cat
        _, oi, op, uv, sg = self._observations()
        return SimState(
            origin=self._origin,
            image_ids=tuple(cat.image_ids),
            point_ids=tuple(cat.point_ids),
            selected=self._point_sel.copy(),
            obs_image=oi,
            obs_point=op,
            obs_uv=uv,
            obs_sigma_px=sg,
            result=res,
            calibration=self._calibration if res.camera_cofactor is not None else None,
            nav=(np.asarray(cat.nav_eop), np.asarray(cat.nav_sigma)))

    def _solve(self, covariance: Covariance) -> SimResult:
        critical = self.options.snooping_critical
        self._nav_on = False  # its first adjustment: GPS/INS least squares first
        for rounds in range(MAX_SNOOPING_ROUNDS + 1):
            data, sel, eop0, gp0, cat_idx = self._block()
            res = self._adjust_and_keep(data, sel, eop0, gp0, covariance)
            if (critical is None or rounds == MAX_SNOOPING_ROUNDS
                    or not self._snoop(res, data, sel, cat_idx, critical)):
                break
        # Points left out at the start (intersected behind a camera or not at all from the
        # GPS/INS attitude, 5-20 deg off on a light UAV) are intersected again at the adjusted
        # EOPs and, where they now lie in front of every camera, the block is adjusted again
        # with them (as COLMAP re-triangulates after a bundle adjustment): Sim then uses
        # every tie point the sequential estimators use (Seneca: 17 of 1789 were left out).
        for _ in range(MAX_READMISSIONS):
            more, more_sel, eop0, gp0, _ = self._block()
            if more_sel.size <= sel.size:
                break
            data, sel = more, more_sel
            res = self._adjust_and_keep(data, sel, eop0, gp0, covariance)
        # Two-ray tie points of a block whose other points show many wrong matches
        # (seqat.robust.untrusted_two_ray_points): adjusted again without them and with the
        # loss's core narrowed (seqat.robust.scale_in_force), the points intersected anew at
        # the EOPs (the robust minimum they held is not left by re-weighting), before the
        # points below are judged on that estimate
        untrusted = self._untrusted_pairs(res, data, sel)
        scale = rloss.scale_in_force(self._scale, self.contamination)  # a narrower core?
        if untrusted != self._untrusted or scale != self.options.robust_scale:
            self._untrusted = untrusted
            self.options = dataclasses.replace(self.options, robust_scale=scale)
            self._gp_est = np.full_like(self._gp_est, np.nan)
            data, sel, eop0, gp0, _ = self._block()
            res = self._adjust_and_keep(data, sel, eop0, gp0, covariance)
        # Tie points whose rays disagree or fit two places as well
        # (seqat.robust.uninformative_points): which ray or pair the loss keeps depends on the
        # start, and with it a weakly tied image's pose (Seneca without every fifth image: 0.1
        # deg on the last one). They carry no information on the images: the block is
        # adjusted again without them, as Seq-R's finish() takes their rows out
        # (docs/algorithm.md, *Points whose rays disagree*, *... fit two places*).
        self._ambiguous = set()
        for _ in range(rloss.MAX_AMBIGUOUS_ROUNDS):
            found = self._ambiguous_points(res, data, sel)
            if not found:
                break
            self._ambiguous |= found
            data, sel, eop0, gp0, _ = self._block()
            res = self._adjust_and_keep(data, sel, eop0, gp0, covariance)
        self._n_obs = np.bincount(data.obs_point, minlength=data.n_points)
        self._dirty = False
        return res

    def _adjust_and_keep(self, data: BlockData, sel: np.ndarray, eop0: FloatArray,
                      gp0: FloatArray, covariance: Covariance) -> SimResult:
        """:meth:`_adjust` the block of points ``sel`` (the full cofactor with data snooping)
        and keep its solution as the current estimates."""
        critical = self.options.snooping_critical
        res = self._adjust(data, eop0, gp0,
                           Covariance.FULL if critical is not None else covariance)
        # the next solve of this _solve starts here: GPS/INS outliers found stay judged (a
        # least-squares phase again pulled a 5 m jump back in, creeping past max_iterations)
        self._nav_on = self._nav_on or bool(np.any(res.nav_weight < 1.0))  # type: ignore[operator]
        self._result, self._point_sel = res, sel
        self._eop_est, self._gp_est = res.eop.copy(), res.gp.copy()
        return res

    def calibration_block(self, calibration: SelfCalibration) -> CameraBlock:
        """The prior of ``calibration``'s free parameters: the values of :attr:`camera`."""
        idx = calibration.index
        return CameraBlock(index=idx, prior=self.camera.intrinsics[idx],
                           sigma=calibration.prior_sigma(self.camera)[idx])

    def _adjust(self, data: BlockData, eop0: FloatArray, gp0: FloatArray,
                covariance: Covariance) -> SimResult:
        """:func:`adjust_block`, self-calibrating with :attr:`SimOptions.calibration`:
        parameters the block does not determine, or not significantly different from their
        prior (:func:`seqat.calibration.to_hold`), are held at their prior and the block
        adjusted again without them."""
        calibration = None if self._camera_held else self.options.calibration
        held: tuple[str, ...] = ()
        while True:
            calib = None
            start = self.camera
            if calibration is not None and calibration.free:
                calib = self.calibration_block(calibration)
                # start from the last estimate of the free parameters, the prior of the others
                start = FreeCamera(self.camera, calib.index).at(
                    self.camera_now.intrinsics[calib.index])
            res = adjust_block(start, data, eop0, gp0, self.options, covariance, calib,
                               self._nav_on)
            if calib is None or calibration is None or not calibration.hold_undetermined:
                break
            assert res.camera_cofactor is not None and res.camera is not None
            bad = to_hold(calibration, res.camera_cofactor, calib.sigma,
                          res.camera.intrinsics[calib.index], calib.prior,
                          sigma_scale(res.sigma0, res.redundancy))
            if not bad.any():
                break
            names = tuple(n for n, b in zip(calibration.names, bad, strict=True) if b)
            held += names
            calibration = calibration.holding(names)
        self._held = held
        assert res.camera is not None
        self.camera_now = res.camera
        return res

    @property
    def _calibration(self) -> SelfCalibration | None:
        """The parameters the last solution estimated: the options' free ones but the held
        (none while ``calibrate_on_export`` holds the camera)."""
        cal = None if self._camera_held else self.options.calibration
        return cal.holding(self._held) if cal is not None and self._held else cal

    def camera_estimate(self) -> CameraEstimate | None:
        """The self-calibrated camera of the last solution (None without self-calibration)."""
        res = self._result
        cal = self._calibration
        if self.options.calibration is None or res is None or cal is None:
            return None
        scale = sigma_scale(res.sigma0, res.redundancy)
        Q = res.camera_cofactor if res.camera_cofactor is not None else np.zeros((0, 0))
        return CameraEstimate(camera=self.camera_now, prior=self.camera, free=cal.names,
                              sigma=np.sqrt(np.diagonal(Q)) * scale,
                              correlation=correlation(Q), held=self._held)

    def _update_record(self, frame: Frame, i: int, ms: float, iterations: int) -> ImageUpdate:
        res = self._result if not self._dirty else None
        n = i + 1
        eop = self._eop_est[i].copy()
        eop[:3] += self._origin  # type: ignore[operator]
        sigma = np.full(EOP_SIZE, np.nan)
        sigma0, red, rms_gp = float("nan"), 0, (float("nan"),) * 3
        if res is not None:
            scale = sigma_scale(res.sigma0, res.redundancy)
            sigma0, red = res.sigma0, res.redundancy
            if res.eop_cofactor is not None:
                # a variance <= 0 is a block the data do not determine to rounding (a second
                # image 60 deg off: reduced system of condition 1e14): no sigma yet, as
                # before the first solution, not the root of a negative number
                var = np.diagonal(res.eop_cofactor[i])
                sigma = deviations(var) * scale
            if res.gp_cofactor is not None:
                rms_gp = rms_point_sigma(np.diagonal(res.gp_cofactor, axis1=1, axis2=2) * scale**2)
        n_pts = int(self._point_sel.size)
        return ImageUpdate(
            image_id=frame.image_id,
            index=i,
            stage="sim",
            update_ms=ms,
            window_images=n,
            window_first_image=self._cat.image_ids[0],
            window_params=6 * n + 3 * n_pts,
            window_eop_params=6 * n,
            window_gp_params=3 * n_pts,
            inverse_sizes=(0, 0),
            sim_reduced_size=6 * n if res is not None else 0,
            sigma0=sigma0,
            redundancy=red,
            rms_gp_sigma_m=rms_gp,  # type: ignore[arg-type]
            n_points_total=n_pts,
            new_points=0,
            observations_used=len(frame.point_ids) + frame.n_late,
            late_used=frame.n_late,
            observations_skipped=0,
            iterations=iterations,
            eop=EopEstimate(image_id=frame.image_id, eop=eop, sigma=sigma),
        )

    def solution(self) -> Solution:
        """Final estimates of every image and point with standard deviations; not the tie
        points whose rays disagree (:meth:`_disagreeing_points`)."""
        if not self._cat.image_ids:
            raise EstimationError("no frames were added")
        if self._dirty or self._result is None or self._result.eop_cofactor is None:
            self._solve(Covariance.BLOCKS)
        if not self.refit_every_frame:  # (a refit tests each image as it comes: _refit)
            self._start_rejected_again(Covariance.BLOCKS)
        res = self._result
        assert res is not None and res.eop_cofactor is not None and res.gp_cofactor is not None
        scale = sigma_scale(res.sigma0, res.redundancy)
        origin = self._origin
        eops = []
        for i, iid in enumerate(self._cat.image_ids):
            e = res.eop[i].copy()
            e[:3] += origin  # type: ignore[operator]
            eops.append(EopEstimate(image_id=iid, eop=e,
                                    sigma=deviations(np.diagonal(res.eop_cofactor[i])) * scale))
        pts = []
        und = res.undetermined
        off = self._disagreeing_points(res)
        for j, gi in enumerate(self._point_sel):
            if ((und is not None and und[j]) or j in off
                    or not np.all(np.diagonal(res.gp_cofactor[j]) > 0)):
                continue  # the data do not determine it (docs/algorithm.md)
            pts.append(
                PointEstimate(
                    point_id=self._cat.point_ids[gi],
                    xyz_m=res.gp[j] + origin,
                    sigma_m=np.sqrt(np.diagonal(res.gp_cofactor[j])) * scale,
                    n_obs=int(self._n_obs[j]),
                )
            )
        return Solution(
            eops=tuple(eops), points=tuple(pts), sigma0=res.sigma0, redundancy=res.redundancy,
            camera=self.camera_estimate(), withheld=tuple(self.disagreeing),
        )
