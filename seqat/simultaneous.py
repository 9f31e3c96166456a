"""Simultaneous aerial triangulation (Sim) with GPS/INS stochastic constraints.

Seed 000 §2.1 (Choi & Lee 2012, Eq. 1-6): image observations plus the GPS/INS EOPs as
stochastic constraints; ground points (GP) eliminated per 3x3 block (Schur complement), the
reduced EOP normal matrix ``N_r = N_ee + N_z - N_ep N_pp^-1 N_ep^T`` (sparse, banded along a
strip) factorised with a sparse LU; GPs back-substituted; Gauss-Newton to convergence;
a posteriori sigma0 and cofactor blocks of EOPs and GPs. One adjustment of the block is
:func:`seqat.adjustment.adjust_block`; this module streams the images into it.

Coordinates here are *local* (the caller subtracts an origin for conditioning).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from seqat import robust as rloss
from seqat.adjustment import Covariance, SimOptions, SimResult, adjust_block
from seqat.calibration import FreeCamera, SelfCalibration, correlation, to_hold
from seqat.catalogue import Catalogue, control_by_id
from seqat.errors import EstimationError
from seqat.geometry import depth, intersect_rays
from seqat.normals import (
    BlockData,
    CameraBlock,
)
from seqat.precision import deviations, rms_point_sigma, sigma_scale
from seqat.sim_points import PointChecksMixin
from seqat.sim_restart import RestartMixin
from seqat.sim_snooping import SnoopingMixin
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

#: Times the block is adjusted again with the points the adjusted EOPs let in (_solve).
MAX_READMISSIONS = 2
#: Data snooping: at most this many reject-and-adjust rounds per solve.
MAX_SNOOPING_ROUNDS = 30


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
        self._refitting = False  # in _refit: adjust_block not accelerated
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
            self._refitting = True  # plain Gauss-Newton: _refit reads its creep (adjust_block)
            try:
                iterations = self._refit(i, cov)
            finally:
                self._refitting = False
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
                               self._nav_on, accelerate=not self._refitting)
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
