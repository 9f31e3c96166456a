"""Sequential aerial triangulation: Seq-F and Seq-R (seed 000 §2.2-2.3).

The first ``initial_images`` images are adjusted simultaneously (Sim, §2.1). From then on each
new image updates the estimates of the *window* with :mod:`seqat.update` (Eq. 13-14): only
``[I + P2bar A21 N11^-1 A21^T]`` and ``(M22 + L22)`` are inverted. The second moments are
carried by one of two engines (``SequentialOptions.engine``, docs/algorithm.md, *Engines*):
``information`` (default) adds the rows' information to the window's information matrix and
recovers the cofactor blocks it needs from a Cholesky factorisation with the GPs eliminated
(:mod:`seqat.information`); ``inverse`` is the paper's update of ``N^-1`` (Eq. 10-12).

This module holds the initial stage and the update step (the options:
:mod:`seqat.sequential_options`); the per-image report (:mod:`seqat.reports`), the window
cut, departures and re-opening (:mod:`seqat.departures`), the window re-linearisation
(:mod:`seqat.relinearise`) and the births of tie points (:mod:`seqat.births`) are mixed in.

* Seq-F (``correlation_threshold=None``): the window holds every parameter.
* Seq-R: before each update the window is cut by :mod:`seqat.window` (correlation of each
  window image's EOPs with the last image's, first-over-threshold rule), and GPs observed in
  fewer than two remaining images (counting the new one) leave with them.

Leaving parameters are *marginalised*: the window keeps the joint cofactor of what stays,
which in covariance form is exactly the marginal of the full solution (dropping rows and
columns of ``N^-1`` is marginalisation; dropping rows of ``N`` would be conditioning, i.e.
fixing). The information of the leaving parameters' observations thus stays in the window, and
the real-time estimates equal Seq-F's; only the leaving parameters themselves stop being updated
and keep their last estimate and sigma. With ``smoothing`` (default) each departure stores the
Rauch-Tung-Striebel gain of the leaving parameters on the staying ones, and :meth:`solution`
smooths the departed values with everything that came later. See docs/algorithm.md.

Re-opening (``reopen_max_age``): a departed GP observed again, or a departed image holding a
pending ray of a point being born, re-enters the window with its exact distribution given the
current window, derived from the departure records (no observation skipped; blocks need it
for cross-strip ties).

New observation classes (seed 000 Eq. 7-8): y21 = new image x existing GP; y12 = existing
window image x newly born GP (its earlier, pending observations); y22 = new image x new GP;
z2 = GPS/INS EOP of the new image. A tie point is born once it has ``min_rays`` observations
in window images with a usable intersection angle; its initial coordinates come from a
least-squares multi-ray intersection at the current EOPs.

Nonlinearity: the new rows are linearised at the current estimates and, optionally, re-
linearised around the updated estimate of the *new* rows' parameters (an iterated update,
``max_update_iterations``; 1 reproduces the paper). Old rows are re-linearised with the whole
window when they drift (``relinearise_px``, :mod:`seqat.relinearise`).
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np
from threadpoolctl import ThreadpoolController

from seqat import snooping
from seqat.births import BirthMixin
from seqat.calibration import FreeCamera
from seqat.camera_window import CameraMixin
from seqat.catalogue import control_by_id, free_nav_sigma
from seqat.departures import Departure, DepartureMixin
from seqat.errors import EstimationError
from seqat.geometry import wrap_angle
from seqat.information import window_matrix
from seqat.iteration import IterationMixin
from seqat.late import LateMixin
from seqat.precision import sigma_scale
from seqat.relinearise import RelinearisationMixin
from seqat.reports import RecordedRows, ReportMixin
from seqat.rows import Factors, RowBuilder, add_information, snoop_update
from seqat.second_start import SecondStart, SecondStartMixin
from seqat.sequential_options import SequentialOptions
from seqat.simultaneous import Covariance, SimultaneousAT
from seqat.types import (
    EOP_SIZE,
    GP_SIZE,
    ControlPoint,
    EopEstimate,
    FloatArray,
    Frame,
    ImageUpdate,
    PinholeCamera,
    PointEstimate,
    Solution,
)
from seqat.undetermined import UndeterminedMixin
from seqat.update import update_cofactor
from seqat.window import CAMERA, Key, Window, key_size

#: BLAS threads used by an update: the matrices are small (a few hundred), where OpenBLAS's
#: thread start-up costs milliseconds (measured: 6 ms with 2 threads vs 0.3 ms with 1).
UPDATE_BLAS_THREADS = 1
_BLAS = ThreadpoolController()


#: Data snooping: at most this many reject-and-resolve rounds per image.
MAX_SNOOPING_ROUNDS = 40

class SequentialAT(DepartureMixin, RelinearisationMixin, BirthMixin, IterationMixin,
                   ReportMixin, CameraMixin, LateMixin, UndeterminedMixin, SecondStartMixin):
    """Seq-F / Seq-R sequential aerial triangulation of a stream of frames.

    Parameters
    ----------
    camera : PinholeCamera
    options : SequentialOptions
    record : bool
        Keep every image's linearised rows (:attr:`recorded`) to verify against batch.
    sink : callable, optional
        With ``options.smoothing_lag``: receives each parameter once it is final (world
        frame), which is then forgotten (:meth:`solution` returns the others only). Without a
        sink final parameters stay in a compact store.
    control : sequence of ControlPoint
        Ground control: points whose coordinates are observed. A control point is born at
        its first ray, at its surveyed coordinates, with their observation as rows of that
        update (docs/algorithm.md, *Ground control*).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        options: SequentialOptions = SequentialOptions(),
        *,
        record: bool = False,
        sink: Callable[[EopEstimate | PointEstimate], None] | None = None,
        control: Sequence[ControlPoint] = (),
    ) -> None:
        self.camera = camera
        self.options = options
        self.control = control_by_id(control)
        # The initial block hands every free interior parameter to the window (none held:
        # later images may determine what the first few do not; the prior keeps it regular).
        calibration = (None if options.calibration is None else
                       dataclasses.replace(options.calibration, hold_undetermined=False))
        sim_opts = dataclasses.replace(options.sim_options(), calibration=calibration,
                                       untrust_pairs=False)
        if options.snooping_critical is not None:  # the initial block's points as births
            sim_opts = dataclasses.replace(sim_opts, min_ray_angle_deg=options.min_ray_angle_deg)
        # With data snooping the initial block is adjusted once, when complete: refits of its
        # first few images have too little redundancy to tell blunders from good rays, and a
        # wrong early solution would seed the later ones.
        self._inverse = options.engine == "inverse"
        self._records = options.smoothing  # departure records (RTS smoothing, re-opening)
        self._initial: SimultaneousAT | None = SimultaneousAT(
            camera, sim_opts, refit_every_frame=options.snooping_critical is None,
            control=control, calibrate_on_export=True)
        self._origin: FloatArray | None = None
        # The camera as the rows see it: with self-calibration its free interior parameters
        # are the window block ``_cam_key`` (set by the initial stage).
        self._cam = FreeCamera(camera, np.zeros(0, dtype=np.int64))
        self._cam_key: Key | None = None
        self._camera_held: tuple[str, ...] = ()  # held at their prior by finish()
        self._w = Window()
        self._window_images: deque[int] = deque()
        self._image_ids: list[str] = []
        self._image_index: dict[str, int] = {}
        self._point_ids: list[str] = []
        self._point_index: dict[str, int] = {}
        self._img_points: dict[int, list[int]] = {}
        self._gp_count: dict[int, int] = {}
        self._gp_nobs: dict[int, int] = {}
        self._gp_order: list[int] = []
        self._pending: dict[int, list[tuple[int, FloatArray, float]]] = {}
        self._frozen_eop: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._frozen_gp: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._departures: list[Departure | None] = []  # None: finalised (smoothing_lag)
        # records' gains (departure gain, split gain, splits applied), least recent first
        self._gains: dict[int, tuple[FloatArray, FloatArray, tuple]] = {}
        self._first_record = 0  # records before this one are finalised
        self._last_finalised = 0
        # Final parameters (smoothing_lag): local value and sigma (and GP observations).
        self._final_eop: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._final_gp: dict[int, tuple[FloatArray, FloatArray, int]] = {}
        self._sunk: set[int] = set()  # GPs handed to the sink (not re-opened, not re-born)
        self._sink = sink
        self._n_points = 0
        # Re-opening (docs/algorithm.md): where and when each departed key left, its cofactor
        # block then, and the departed images whose pending rays are kept (oldest first).
        self._departed: dict[Key, tuple[int, int, int]] = {}  # key -> (image, record, offset)
        self._frozen_cof: dict[Key, FloatArray] = {}
        self._departed_rays: deque[tuple[int, list[int]]] = deque()
        self.reopened = 0  # departed parameters re-opened so far
        self._orphans: set[int] = set()  # window GPs no window image sees (ray rejected)
        #: Images whose rows sent the update beyond every prior (DIVERGED_SIGMAS): nav only.
        self.diverged: list[str] = []
        #: Points the data do not determine (singular information), taken out, in order
        self._undetermined: dict[int, None] = {}  # (point indices: see ``undetermined``)
        self.rescued: list[str] = []  # GPs re-intersected robustly (relinearise)
        self.disagreeing: list[str] = []  # GPs whose rays disagree, not published (finish)
        self._disagreeing: set[int] = set()
        self._ambiguous: set[int] = set()  # GPs taken out at finish(): rays fit two places
        self._untrusted: set[int] = set()  # ... two-ray GPs of a contaminated window
        self._restart_points: dict[int, FloatArray] = {}  # the next re-linearisation's start
        #: seqat.robust.contamination of the finished window (NaN: not judged)
        self.contamination = float("nan")
        self._rescues: list[tuple[int, Key]] = []  # (records made before it, GP rescued)
        self._final_reopened: set[Key] = set()  # departed keys re-opened by finish()
        self.final_reopen_skipped = self.finish_born = 0  # finish(): not re-opened; born
        self._dropped_value: dict[Key, FloatArray] = {}
        self._w.on_singular = self._drop_undetermined
        #: Observations removed by data snooping: (image id, point id, w-test value).
        self.rejections: list[tuple[str, str, float]] = []
        #: GPS/INS groups down-weighted by data snooping (by the loss: nav_robust)
        self.nav_downweighted: list[tuple[str, str]] = []  # (image id, position/attitude)
        self._forced: set[int] = set()  # pending points already held back once (never twice)
        self._ssr, self._redundancy = 0.0, 0
        self._nav_rows: dict[int, FloatArray] = {}  # GPS/INS rows in L: relinearise.py
        self._nav_retired: dict[int, FloatArray] = {}  # ... their group weights once finalised
        self._factors = Factors()
        self.relinearisations = self.relinearisations_skipped = 0  # so far; given up: singular
        self._astray_tried: dict[int, int] = {}  # astray GP -> its window rays when last tried
        self._drift_px = self._drift_m = self._drift_deg = float("nan")
        self.recorded: list[RecordedRows] | None = [] if record else None
        # (keys, x, Q) the window started from: kept with the inverse engine or ``record``
        self.initial_state: tuple[list[Key], FloatArray, FloatArray] | None = None
        # A second start during the flight (seqat/second_start.py): the window's EOPs and
        # sigmas after the last update, updates left to try one, images after whose update
        # one was kept, and how many were tried.
        self._eop_before: tuple[list[int], FloatArray, FloatArray] | None = None
        self._second_start_left = 0
        self._second_start_due: str | None = None  # the image after whose update one is due
        # what the last update left for refine(): its image's id and index
        self._refine_due: tuple[str, int] | None = None
        self.second_starts: list[str] = []
        self.second_starts_tried = 0

    # ------------------------------------------------------------------ public API
    @property
    def sigma0(self) -> float:
        """A posteriori standard error of unit weight."""
        r = self._redundancy
        return float(np.sqrt(self._ssr / r)) if r > 0 else float("nan")

    def add_frame(self, frame: Frame, *, refine: bool = True) -> ImageUpdate:
        """Add the next image and update the triangulation. ``refine``: then run the
        refinement the update made due (:meth:`refine`, named in the update returned); a
        real-time caller passes False and calls :meth:`refine` once the image's estimate is
        out."""
        with _BLAS.limit(limits=UPDATE_BLAS_THREADS, user_api="blas"):
            if self._initial is not None:
                return self._add_initial(frame)
            t0 = time.perf_counter()
            self._refine(second_start=False)  # the last update's, if its caller did not
            update = dataclasses.replace(self._add_sequential(frame),
                                         update_ms=(time.perf_counter() - t0) * 1e3)
            return self._refined(update) if refine else update

    def refined(self, update: ImageUpdate) -> ImageUpdate:
        """``update`` with what :meth:`refine`, run now, did after it: the drift check and
        re-linearisation, its time (``refine_ms``) and a second start's outcome (unchanged
        if nothing was due)."""
        with _BLAS.limit(limits=UPDATE_BLAS_THREADS, user_api="blas"):
            return self._refined(update)

    def refine(self) -> SecondStart | None:
        """Work the last update made due that can wait until its image's estimate is out
        (docs/algorithm.md, *After the estimate is out*): the drift check and the window's
        re-linearisation, the smoothing lag's and the dormant factors' housekeeping, and a
        second start (seqat/second_start.py), whose outcome is returned; None: no second
        start. Left undone, it runs first in the next :meth:`add_frame` (but for the
        second start, which is then not tried), so the estimates do not depend on it."""
        with _BLAS.limit(limits=UPDATE_BLAS_THREADS, user_api="blas"):
            return self._refine(second_start=True)

    def _refine(self, *, second_start: bool) -> SecondStart | None:
        due, self._refine_due = self._refine_due, None
        if due is not None:
            image_id, i = due
            opts = self.options
            self._drift_px = self._drift_m = self._drift_deg = float("nan")
            if opts.relinearise_px is not None:
                check = opts.drift_check_every is not None and i % opts.drift_check_every == 0
                self._relinearise_if_needed(force=check)
                self._arm_second_start(image_id)
            if opts.smoothing_lag is not None:
                self._finalise_old(i)
            self._prune_dormant(i)
            self._remember_window_eops()  # what the next update's jump is measured against
        outcome = self._second_start() if second_start else None
        # the variances the next update's window rule reads first, from the factorisation a
        # re-linearisation or second start left: formed now, with the estimate out
        self._w.warm_diagonal()
        return outcome

    def _refined(self, update: ImageUpdate) -> ImageUpdate:
        """:meth:`refined` (its caller limits the BLAS threads)."""
        if self._refine_due is None or self._refine_due[0] != update.image_id:
            return update
        t0 = time.perf_counter()
        outcome = self._refine(second_start=True)
        update = dataclasses.replace(update, drift_px=self._drift_px, drift_m=self._drift_m,
                                     drift_deg=self._drift_deg,
                                     refine_ms=(time.perf_counter() - t0) * 1e3)
        if outcome is None:
            return update
        return dataclasses.replace(update, second_start="kept" if outcome.kept else "not kept",
                                   second_start_ms=outcome.ms)

    def finish(self) -> None:
        """After the last image: re-adjust the window by Gauss-Newton to convergence (steps
        below 1e-7 m / rad; during the flight re-linearisations stop at 0.01 px), so the
        final window values are the minimum of the collinearity equations, not of rows
        linearised on the way (Seq-F then equals Sim). One re-linearisation of the window,
        once per flight. No-op without ``relinearise_px``; :meth:`solution` itself never
        changes the state. A flight that ended in the initial block frees its camera (held
        while the block's images arrived: its solution then self-calibrates)."""
        if self._initial is not None:  # the flight ended in the initial block
            self._initial.free_camera()
        if self._initial is None:
            with _BLAS.limit(limits=UPDATE_BLAS_THREADS, user_api="blas"):
                self._refine(second_start=False)  # the last update's, if not yet done
                if self.options.relinearise_px is not None:
                    if self.options.smoothing and self.options.final_reopen:
                        self._reopen_departed()
                    self.finish_born = self._birth_at_finish()
                    self._final_relinearise()
                    self._drop_untrusted_pairs()
                    self._drop_ambiguous()
                self._hold_undetermined_camera()
                self._find_disagreeing()
                self._settle_ssr()

    def solution(self, *, smoothed: bool | None = None) -> Solution:
        """Estimates of every image and point so far (window and departed), with sigmas.

        Parameters
        ----------
        smoothed : bool, optional
            Seq-R only: apply the RTS backward pass to the parameters that left the window, so
            they also benefit from the data that came after they left (the result then equals
            Seq-F's). ``False`` gives the frozen, real-time values of the paper. Default:
            ``options.smoothing``. The sigmas of departed parameters stay those at departure
            (an upper bound of the smoothed ones).
        """
        if self._initial is not None:
            return self._initial.solution()
        if smoothed is None:
            smoothed = self.options.smoothing
        if smoothed and not self.options.smoothing:
            raise ValueError("smoothed=True needs SequentialOptions(smoothing=True)")
        scale = sigma_scale(self.sigma0, self._redundancy)
        w, origin = self._w, self._origin
        assert origin is not None
        sd = np.sqrt(w.q_diagonal()) * scale
        final = self._smoothed_departed() if smoothed else {}
        eops = []
        # finish() re-opened departed keys: their real-time value is the frozen one
        realtime = set() if smoothed else self._final_reopened
        for i, iid in enumerate(self._image_ids):
            if ("e", i) in w.offset and ("e", i) not in realtime:
                idx = w.index(("e", i))
                val, sig = w.x[idx].copy(), sd[idx]
            elif i in self._frozen_eop:
                val, sig = self._frozen_eop[i]
                val = final.get(("e", i), val).copy()
            elif i in self._final_eop:
                val, sig = self._final_eop[i]
                val = val.copy()
            else:
                continue  # handed to the sink
            val[:3] += origin
            val[3:] = wrap_angle(val[3:])
            eops.append(EopEstimate(image_id=iid, eop=val, sigma=sig))
        pts = []
        for p in self._gp_order:
            if p in self._disagreeing:
                continue  # its rays disagree (finish(): seqat.robust.withheld_points)
            if ("p", p) in w.offset and ("p", p) not in realtime:
                idx = w.index(("p", p))
                xyz, sig, nobs = w.x[idx] + origin, sd[idx], self._gp_nobs[p]
            elif p in self._frozen_gp:
                xyz, sig = self._frozen_gp[p]
                xyz, nobs = final.get(("p", p), xyz) + origin, self._gp_nobs[p]
            else:
                xyz, sig, nobs = self._final_gp[p]
                xyz = xyz + origin
            pts.append(
                PointEstimate(point_id=self._point_ids[p], xyz_m=xyz, sigma_m=sig, n_obs=nobs)
            )
        return Solution(
            eops=tuple(eops), points=tuple(pts), sigma0=self.sigma0, redundancy=self._redundancy,
            camera=self.camera_estimate(),
        )

    def window_solution(self) -> Solution:
        """Current estimates of the window's images and GPs with sigmas: O(window), any time;
        not the GPs whose rays disagree at the last drift check (the live map's points, the
        tracker's resection; docs/algorithm.md, *Points whose rays disagree*).

        During the initial stage the window is every image so far (the Sim solution).
        """
        if self._initial is not None:
            return self._initial.solution()
        w, origin = self._w, self._origin
        assert origin is not None
        sd = np.sqrt(w.q_diagonal()) * sigma_scale(self.sigma0, self._redundancy)
        eops, pts = [], []
        for k in w.keys:
            idx = w.index(k)
            if k[0] == "e":
                val = w.x[idx].copy()
                val[:3] += origin
                val[3:] = wrap_angle(val[3:])
                eops.append(EopEstimate(image_id=self._image_ids[k[1]], eop=val, sigma=sd[idx]))
            elif k[0] == "p" and k[1] not in self._disagreeing:
                pts.append(
                    PointEstimate(
                        point_id=self._point_ids[k[1]],
                        xyz_m=w.x[idx] + origin,
                        sigma_m=sd[idx],
                        n_obs=self._gp_nobs[k[1]],
                    )
                )
        return Solution(
            eops=tuple(eops), points=tuple(pts), sigma0=self.sigma0, redundancy=self._redundancy,
            camera=self.camera_estimate(), withheld=tuple(self._point_ids[p] for p in
                                                          sorted(self._disagreeing)),
        )

    # ------------------------------------------------------------------ initial stage (Sim)
    def _add_initial(self, frame: Frame) -> ImageUpdate:
        sim = self._initial
        assert sim is not None
        t0 = time.perf_counter()
        upd = sim.add_frame(frame)
        i = len(self._image_ids)
        self._image_ids.append(frame.image_id)
        self._image_index[frame.image_id] = i
        if i + 1 >= self.options.initial_images:
            self._start_sequential(sim)
        ms = (time.perf_counter() - t0) * 1e3
        return dataclasses.replace(upd, stage="initial-sim", update_ms=ms)

    def _start_sequential(self, sim: SimultaneousAT) -> None:
        """Take the initial Sim solution as the window: its normal matrix (information
        engine), its full inverse normal matrix (inverse engine; and to record the rows)."""
        # the information engine factorises the normal matrix point by point (its first
        # update does anyway); the dense inverse of 1000+ parameters, and a Cholesky of it
        # to see it positive definite, cost the hand-over ~100 ms (Seneca)
        full = self._inverse or self.recorded is not None
        st = sim.export_state(Covariance.FULL if full else Covariance.NORMAL)
        res = st.result
        singular = (f"the initial simultaneous block ({len(st.image_ids)} images) is singular or "
                    f"ill-conditioned: its cofactor matrix is not positive definite (its datum "
                    f"is fixed by the GPS/INS constraints alone: are the nav sigmas plausible?)")
        if full:
            assert res.full_cofactor is not None
            try:
                np.linalg.cholesky(res.full_cofactor)
            except np.linalg.LinAlgError as err:
                raise EstimationError(singular) from err
        self._origin = st.origin
        n = len(st.image_ids)
        keys: list[Key] = [("e", i) for i in range(n)]
        cam_values = np.zeros(0)
        if st.calibration is not None and st.calibration.free:
            # the free interior parameters: a block between the EOPs and the GPs (the layout
            # of Sim's normal matrix), in every image row from now on
            self._cam = FreeCamera(self.camera, st.calibration.index)
            self._cam_key = (CAMERA, self._cam.size)
            keys.append(self._cam_key)
            assert res.camera is not None
            cam_values = res.camera.intrinsics[self._cam.index]
        for pid in st.point_ids:
            self._point_index[pid] = len(self._point_ids)
            self._point_ids.append(pid)
        keys += [("p", int(j)) for j in st.selected]
        w = self._w
        w.inverse = self._inverse
        w.relayout(keys)
        w.x = np.concatenate([res.eop.ravel(), cam_values, res.gp.ravel()])
        ssr = res.weighted_ssr
        if res.model_step is not None and res.full_normal is not None:
            # a block stopped short of convergence: its rows are linearised at its estimate,
            # the window starts at their model's minimum, as every later step assumes (its
            # information times its estimate is its information vector); from the estimate
            # itself the first re-linearisation's kept information was wrong and the window
            # ran away (sigma0 2e7, or a focal length < 0)
            w.x = w.x + res.model_step
            ssr -= float(res.model_step @ (res.full_normal @ res.model_step))
        if self._inverse:
            w.Q = res.full_cofactor
        if self.options.smoothing or not self._inverse:
            # the initial block's normal matrix itself (not the inverse of its cofactor:
            # inverting that would cost digits and blur the GPs' block-diagonal structure)
            assert res.full_normal is not None  # FULL and NORMAL export it; the window owns it
            w.L = window_matrix(res.full_normal)  # exactly symmetric (normals.full_normal)
        self._window_images.extend(range(n))
        selected = set(int(j) for j in st.selected)
        self._gp_order = [int(j) for j in st.selected]
        self._n_points = len(self._gp_order)
        for i in range(n):
            self._img_points[i] = []
        for i, j, uv, s in zip(st.obs_image, st.obs_point, st.obs_uv, st.obs_sigma_px, strict=True):
            i, j = int(i), int(j)
            self._img_points[i].append(j)
            if j in selected:
                self._gp_count[j] = self._gp_count.get(j, 0) + 1
                self._gp_nobs[j] = self._gp_nobs.get(j, 0) + 1
            else:
                self._pending.setdefault(j, []).append(
                    (i, np.asarray(uv, dtype=np.float64), float(s))
                )
        self._ssr, self._redundancy = max(ssr, 0.0), res.redundancy
        if self.options.relinearise_px is not None:
            sel_of = {int(j): k for k, j in enumerate(st.selected)}
            use = [k for k, j in enumerate(st.obs_point) if int(j) in sel_of]
            img = np.asarray(st.obs_image, dtype=np.int64)[use]
            pt = np.asarray(st.obs_point, dtype=np.int64)[use]
            gp_row = np.array([sel_of[int(j)] for j in pt], dtype=np.int64)
            e_lin = np.concatenate([res.eop[img], np.broadcast_to(cam_values, (img.size,
                                                                           cam_values.size))],
                                   axis=1)
            self._factors.add(img, pt, np.asarray(st.obs_uv)[use],
                              np.asarray(st.obs_sigma_px)[use], e_lin, res.gp[gp_row],
                              self._cam, self.options.robust_scale)
        if res.full_cofactor is not None:
            self.initial_state = (keys, self._w.x.copy(), res.full_cofactor.copy())
        if res.undetermined is not None and res.undetermined.any():  # rows of weight 0 in L
            und = [int(j) for j, bad in zip(st.selected, res.undetermined, strict=True) if bad]
            self._factors.forget(set(und))
            self._drop_undetermined([("p", j) for j in und])
        if not full:
            try:  # positive definite: GPs it does not determine leave (Window.on_singular)
                w.factor()
            except EstimationError as err:
                raise EstimationError(singular) from err
        self.rejections.extend(sim.rejections)
        self.nav_downweighted.extend(sim.nav_downweighted)
        self.diverged.extend(sim.diverged)
        self._keep_nav_rows(np.arange(n), st.nav, res.nav_weight)
        self._initial = None

    # ------------------------------------------------------------------ sequential stage
    def _add_sequential(self, frame: Frame) -> ImageUpdate:
        opts, w = self.options, self._w
        assert self._origin is not None
        i = len(self._image_ids)
        # late observations of earlier images first: pending rays, or rows of window GPs
        late_rows, late_pending, late_skipped = self._insert_late(frame, i)
        self._image_ids.append(frame.image_id)
        self._image_index[frame.image_id] = i
        pts: list[int] = []
        for pid in frame.point_ids:
            p = self._point_index.get(pid)
            if p is None:
                p = self._point_index[pid] = len(self._point_ids)
                self._point_ids.append(pid)
            pts.append(p)
        dropped = self._select_window(set(pts) | {p for _, p, _, _ in late_rows})
        self._forget_old_rays(i)

        nav = frame.nav_eop.copy()
        nav[:3] -= self._origin
        # linearisation point of the new EOP: the nav, or the caller's (resection) value
        init = nav
        if frame.initial_eop is not None:
            init = frame.initial_eop.copy()
            init[:3] -= self._origin
        # A GNSS dropout without a resected start value: the new image's rays do not help to
        # place new points (they would be cast from the last fix).
        init_known = frame.initial_eop is not None or bool(np.all(np.isfinite(frame.nav_sigma[:3])))
        # --- classify the new observations (seed 000 Eq. 7-8)
        seen: list[tuple[int, FloatArray]] = []  # y21: window GPs and re-openable departed ones
        candidates: list[int] = []
        skipped = 0
        for p, uv in zip(pts, frame.uv_px, strict=True):
            if ("p", p) in w.offset or (p in self._frozen_gp
                                        and self._reopenable(("p", p), i)):
                seen.append((p, uv))
            elif p in self._frozen_gp or p in self._final_gp or p in self._sunk:
                skipped += 1  # left the window too long ago (reopen_max_age, smoothing_lag)
            else:
                lst = self._pending.setdefault(p, [])
                lst.append((i, uv, frame.sigma_px))
                if len(lst) >= self._min_rays(p):
                    candidates.append(p)
        in_frame = set(candidates)
        # points a late ray alone brings to enough rays (their new ray was left out)
        for p in dict.fromkeys(late_pending):
            if p not in in_frame and len(self._pending.get(p, ())) >= self._min_rays(p):
                candidates.append(p)
                in_frame.add(p)
        candidates += [p for p in self._forced if p not in in_frame and p in self._pending]

        nav_sigma = free_nav_sigma(frame.nav_sigma)
        rejected: list[tuple[int, int, float]] = []  # (image, point, w) removed by snooping
        rejected_new: set[int] = set()  # points whose ray in the new image was removed
        diverged = False
        downweighted: list[str] = []
        reopened: list[Key] = []
        held: set[int] = set()  # points whose birth made the update singular (wait)
        late_out: set[tuple[int, int]] = set()  # late rows rejected by data snooping
        rounds = 0
        while True:
            w.settle()  # an undetermined GP leaves now, before the rows are laid out
            y21 = [(p, uv) for p, uv in seen if p not in rejected_new
                   and (("p", p) in w.offset or self._reopenable(("p", p), i))]
            reopen: list[Key] = [("p", p) for p, _ in y21 if ("p", p) not in w.offset]
            ready = [p for p in candidates if p in self._pending and p not in held
                     and len(self._pending[p]) >= self._min_rays(p)]
            born, born_xyz = self._birth(ready, i, init, use_new=init_known)
            reopen += [("e", j) for p in born for (j, _, _) in self._pending[p]
                       if j != i and ("e", j) not in w.offset]
            y11 = [r for r in late_rows if (r[0], r[1]) not in late_out
                   and self._key_usable(("e", r[0]), i) and self._key_usable(("p", r[1]), i)]
            reopen += [k for j, p, _, _ in y11 for k in (("e", j), ("p", p))
                       if k not in w.offset]
            reopen = list(dict.fromkeys(reopen))
            if reopen:
                self._reopen(reopen)
                reopened += reopen
                w.settle()
                y21 = [(p, uv) for p, uv in y21 if ("p", p) in w.offset]
                y11 = [r for r in y11 if ("e", r[0]) in w.offset and ("p", r[1]) in w.offset]
            y21_pts = [p for p, _ in y21]
            y21_uv = [uv for _, uv in y21]

            # --- layout of the new parameters: [EOP of image i, born GPs]
            n2 = EOP_SIZE + GP_SIZE * len(born)
            x2_0 = np.concatenate([init, born_xyz.ravel()])
            y12 = [(j, b, uv, s) for b, p in enumerate(born)
                   for (j, uv, s) in self._pending[p] if j != i]
            y22 = [(b, uv, s) for b, p in enumerate(born)
                   for (j, uv, s) in self._pending[p] if j == i]
            # the camera block first (every image row has it), then the GPs and images
            touched_keys: list[Key] = [self._cam_key] if self._cam_key is not None else []
            touched_keys += [("p", p) for p in y21_pts]
            touched_keys += list(dict.fromkeys(("e", j) for (j, _, _, _) in y12))
            # late rays of estimated points: rows of two existing parameters (A22 = 0)
            touched_keys = list(dict.fromkeys(
                touched_keys + [k for j, p, _, _ in y11 for k in (("e", j), ("p", p))]))
            touched = w.indices(touched_keys)
            # the block Q[touched, touched] alone; d1 by one solve after (docs/algorithm.md,
            # *Engines*)
            Qtt = w.q_block(touched)
            col_of = {}
            c = 0
            for k in touched_keys:
                col_of[k] = c
                c += key_size(k)

            # One entry per image row: (EOP column, GP column, uv, sigma, in y2, (image,
            # point)) in z = [x1t, x2].
            t = touched.size
            obs: list[tuple[int, int, FloatArray, float, bool, tuple[int, int]]] = [
                (t, col_of[("p", p)], uv, frame.sigma_px, True, (i, p))
                for p, uv in zip(y21_pts, y21_uv, strict=True)
            ]
            obs += [
                (col_of[("e", j)], t + EOP_SIZE + GP_SIZE * b, uv, s, True, (j, born[b]))
                for (j, b, uv, s) in y12
            ]
            obs += [(col_of[("e", j)], col_of[("p", p)], uv, s, True, (j, p))
                    for (j, p, uv, s) in y11]
            # y22 rows touch an existing parameter too when the camera is estimated
            obs += [(t, t + EOP_SIZE + GP_SIZE * b, uv, s, self._cam_key is not None,
                     (i, born[b])) for (b, uv, s) in y22]
            builder = RowBuilder(self._cam, t, n2, obs, nav, nav_sigma, opts.robust_scale,
                                 opts.nav_robust_scale, control=self._control_rows(born, t))
            x1t = w.x[touched]
            builder.nav_loss_at(x1t, x2_0, i, born)  # a GPS/INS far from a resection start
            # the inverse update and data snooping read the update's observation-space terms
            terms = self._inverse or opts.snooping_critical is not None
            it = self._iterate_update(builder, Qtt, touched, terms, x1t, x2_0, born, born_xyz,
                                      y12, y22, col_of, i)
            rows, d1t, d2, iterations, degenerate = (it.rows, it.d1t, it.d2, it.iterations,
                                                     it.degenerate)
            if degenerate:
                held.update(born[b] for b in degenerate)
                continue
            if it.wild and diverged:
                raise EstimationError(f"image {frame.image_id!r}: the update left the models' "
                                      "domain even without the image's rays")
            if not diverged and (it.wild or self._diverged(
                    nav, nav_sigma, x2_0, d2, Qtt, d1t, builder.rays_hold(i, born))):
                # The image's rows sent the solution far beyond every prior sigma (gross
                # errors in most of its points), even from the held window's resection
                # (seqat.iteration): the image is carried by its GPS/INS alone and its rays
                # are left out, named in ``diverged``.
                diverged = True
                self.diverged.append(frame.image_id)
                rejected_new.update(pts)
                for p in pts:
                    self._drop_pending_ray(p, i)
                candidates = [p for p in candidates if p in self._pending]
                continue
            sol = it.sol
            assert sol is not None
            if opts.snooping_critical is None or rounds >= MAX_SNOOPING_ROUNDS:
                break
            rounds += 1
            verdict = snoop_update(Qtt, touched, rows, sol, builder, d1t, d2,
                                   opts.snooping_critical)
            if not verdict.observations and not set(verdict.nav_groups) - set(downweighted):
                break
            for q, wq in zip(verdict.observations, verdict.w, strict=True):
                j, p = (int(v) for v in builder.ids[q])
                rejected.append((j, p, wq))
                if j == i:
                    rejected_new.add(p)
                elif ("p", p) in w.offset and p not in born:
                    late_out.add((j, p))  # a late row of an estimated point
                if p in self._pending:  # a ray of a point being born: it stays out
                    self._drop_pending_ray(p, j)
                    if j != i and p in self._img_points.get(j, ()):
                        self._img_points[j].remove(p)
            for group in verdict.nav_groups:
                if group in downweighted:
                    continue  # once per image and group
                sl = slice(0, 3) if group == "position" else slice(3, 6)
                nav_sigma[sl] *= snooping.NAV_DOWNWEIGHT
                downweighted.append(group)
        self._forced.difference_update(born)
        if self.recorded is not None:
            self._record(touched_keys, touched, born, i, rows, x1t, x2_0)
        d1 = w.q_apply(touched, sol.kappa1)
        w.x = np.concatenate([w.x + d1, x2_0 + sol.delta2])
        if self._inverse:
            w.Q = update_cofactor(w.Q, touched, rows, sol)
        if w.L is not None:
            w.L = add_information(w.L, touched, rows)
        w.relayout(w.keys + [("e", i)] + [("p", p) for p in born])
        self._ssr += sol.ssr_increment
        self._redundancy += int(np.count_nonzero(rows.w2) + np.count_nonzero(rows.w3)) - n2
        if opts.relinearise_px is not None:
            builder.store_factors(self._factors)

        # --- bookkeeping (all O(new observations))
        self._window_images.append(i)
        self._img_points[i] = [p for p in pts if p not in rejected_new]
        for key in reopened:
            if key[0] == "p" and key[1] in rejected_new:
                self._orphans.add(key[1])  # re-opened for a ray that was then rejected
        self.rejections.extend(
            (self._image_ids[j], self._point_ids[p], wq) for j, p, wq in rejected)
        self.nav_downweighted.extend((frame.image_id, g) for g in downweighted)
        self._keep_nav_rows([i], (nav, nav_sigma), builder.nav_group_weights())
        for p in y21_pts:
            self._gp_count[p] += 1
            self._gp_nobs[p] += 1
        for j, p, _, _ in y11:
            self._gp_count[p] += 1
            self._gp_nobs[p] += 1
            self._img_points[j].append(p)
        for p in born:
            obs = self._pending.pop(p)
            self._undetermined.pop(p, None)  # taken out earlier, determined now
            self._gp_count[p] = self._gp_nobs[p] = len(obs)
            self._gp_order.append(p)
            self._n_points += 1
            for j, _, _ in obs:
                if ("e", j) in reopened and p not in self._img_points[j]:
                    self._img_points[j].append(p)
        # the published sigmas (the image's EOP, the window's GPs) are part of the update;
        # the window's re-linearisation follows once the estimate is out (:meth:`refine`)
        late_used = len(late_pending) + len(y11)
        update = self._report(
            frame, i, 0.0, rows, n2, len(born),
            len(pts) - skipped - len(rejected_new) + late_used, skipped + late_skipped,
            iterations, dropped
        )
        self._refine_due = (frame.image_id, i)
        return dataclasses.replace(
            update,
            reopened=len(reopened),
            rejected=tuple((self._image_ids[j], self._point_ids[p], round(wq, 2))
                           for j, p, wq in rejected),
            nav_downweighted=tuple(downweighted),
            late_used=late_used,
        )
