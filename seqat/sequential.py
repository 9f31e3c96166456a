"""Sequential aerial triangulation: Seq-F and Seq-R (seed 000 §2.2-2.3).

The first ``initial_images`` images are adjusted simultaneously (Sim, §2.1). From then on each
new image updates the estimates and the inverse normal matrix of the *window* with
:mod:`seqat.update` (Eq. 10-14): only ``[I + P2bar A21 N11^-1 A21^T]`` and ``(M22 + L22)`` are
inverted, the big system is never refactorised.

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
``max_update_iterations``; 1 reproduces the paper). Old rows are never re-linearised.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from threadpoolctl import ThreadpoolController

from seqat import snooping
from seqat.errors import EstimationError
from seqat.geometry import depth, intersect_rays, project, wrap_angle
from seqat.information import InformationFactor, RankDeficiency
from seqat.rows import (
    Factors,
    RowBuilder,
    add_information,
    normal_from_factors,
    snoop_update,
)
from seqat.simultaneous import (
    Covariance,
    SimOptions,
    SimultaneousAT,
    free_nav_sigma,
    rms_point_sigma,
    sigma_scale,
)
from seqat.types import (
    EOP_SIZE,
    GP_SIZE,
    EopEstimate,
    FloatArray,
    Frame,
    ImageUpdate,
    PinholeCamera,
    PointEstimate,
    Solution,
)
from seqat.update import LinearRows, solve_update, spd_inverse, update_cofactor
from seqat.window import correlations_from_columns, first_over_threshold

#: BLAS threads used by an update: the matrices are small (a few hundred), where OpenBLAS's
#: thread start-up costs milliseconds (measured: 6 ms with 2 threads vs 0.3 ms with 1).
UPDATE_BLAS_THREADS = 1
_BLAS = ThreadpoolController()

#: A tie point whose rays would otherwise leave the window is born with at least this spread.
MIN_FORCED_RAY_ANGLE_DEG = 1.0

#: A GP stays in the Seq-R window only while this many window images (new one included) see it.
MIN_WINDOW_RAYS = 2

#: Data snooping at birth: a ray farther than this many critical sigmas from the others'
#: intersection is screened out (SequentialAT._screen_rays), in at most this many rounds.
SCREEN_SIGMAS = 2.0
MAX_SCREEN_ROUNDS = 5
#: Data snooping: at most this many reject-and-resolve rounds per image.
MAX_SNOOPING_ROUNDS = 40

#: Window engines (SequentialOptions.engine).
ENGINES = ("information", "inverse")

#: Parameter key: (kind, index) with kind "e" (EOP of image index) or "p" (GP index).
Key = tuple[str, int]


@dataclass(frozen=True, kw_only=True)
class SequentialOptions:
    """Options of the sequential estimator."""

    correlation_threshold: float | None = 0.1  # None: Seq-F (no window cut)
    initial_images: int = 10  # images adjusted simultaneously before the sequential stage
    min_rays: int = 2  # a tie point is born once seen in this many window images
    min_ray_angle_deg: float = 8.0  # ... and its rays spread at least this much (docs/algorithm.md)
    max_update_iterations: int = 10  # 1 = the paper's single linearisation
    iteration_tolerance_px: float = 0.01  # stop when the rows predict the new estimate this well
    smoothing: bool = True  # Seq-R: keep RTS gains so solution() can smooth departed parameters
    relinearise_px: float | None = 1.0  # re-linearise the window when its rows are this far off
    relinearise_iterations: int = 20  # at most this many Gauss-Newton steps per re-linearisation
    # Drift check (seed 003 §3.2): every this many images the window is re-adjusted from its
    # observations whatever its linearisation error, and the change is reported (drift_m,
    # drift_deg of ImageUpdate). None: only when the error exceeds relinearise_px.
    drift_check_every: int | None = None
    # Seq-R: a departed GP seen again, or a departed image holding a pending ray of a point
    # being born, re-enters the window if it left at most this many images ago (0: never).
    reopen_max_age: int = 1000
    # Seq-R: departed parameters older than this many images are final: smoothed once more,
    # then moved to a compact store or handed to the caller's sink, their records dropped.
    # Memory stays flat with flight length. None: keep everything (exact RTS smoothing).
    smoothing_lag: int | None = None
    # Baarda's data snooping of each update's rows (w-test, critical value; 3.29 is
    # alpha0 = 0.001 two-sided); None: off (the paper). docs/algorithm.md, "Blunders".
    snooping_critical: float | None = None
    # "information": the window's information matrix, Cholesky-factorised with its GPs
    # eliminated after every update (numerically stable, rank checked); "inverse": the
    # paper's update of the inverse normal matrix (Eq. 10-14). docs/algorithm.md, *Engines*.
    engine: str = "information"
    # Robust loss of the image points: least squares within this many sigma, a Cauchy tail
    # beyond (seqat/robust.py, 3 recommended; the initial Sim uses the same); None: least
    # squares (the paper's estimator). docs/algorithm.md, *Robust loss*.
    robust_scale: float | None = None
    sim: SimOptions = SimOptions()

    def __post_init__(self) -> None:
        from seqat.errors import ConfigError

        if self.robust_scale is not None and not self.robust_scale > 0:
            raise ConfigError(f"robust_scale: expected a positive number (sigmas) or null, "
                              f"got {self.robust_scale!r}")
        if self.engine not in ENGINES:
            raise ConfigError(f"engine: expected one of {', '.join(ENGINES)}, "
                              f"got {self.engine!r}")
        if self.correlation_threshold is not None and not 0 <= self.correlation_threshold <= 1:
            raise ConfigError(
                f"correlation_threshold: expected a value in [0, 1] or null, "
                f"got {self.correlation_threshold!r}"
            )
        if self.initial_images < 1:
            raise ConfigError(f"initial_images: expected >= 1, got {self.initial_images}")
        if self.min_rays < 2:
            raise ConfigError(f"min_rays: expected >= 2, got {self.min_rays}")
        if self.max_update_iterations < 1:
            raise ConfigError(
                f"max_update_iterations: expected >= 1, got {self.max_update_iterations}"
            )
        if self.relinearise_px is not None and not self.relinearise_px > 0:
            raise ConfigError(
                f"relinearise_px: expected a positive number or null, got {self.relinearise_px!r}"
            )
        if self.snooping_critical is not None and not self.snooping_critical > 0:
            raise ConfigError(f"snooping_critical: expected a positive number or null, "
                              f"got {self.snooping_critical!r}")
        if self.smoothing_lag is not None and self.smoothing_lag < 10:
            raise ConfigError(f"smoothing_lag: expected >= 10 images or null, "
                              f"got {self.smoothing_lag}")
        if self.reopen_max_age < 0:
            raise ConfigError(f"reopen_max_age: expected >= 0, got {self.reopen_max_age}")
        if self.drift_check_every is not None and (self.drift_check_every < 1
                                                   or self.relinearise_px is None):
            raise ConfigError("drift_check_every: expected >= 1 (and relinearise_px set), "
                              f"got {self.drift_check_every}")
        if self.relinearise_iterations < 1:
            raise ConfigError(
                f"relinearise_iterations: expected >= 1, got {self.relinearise_iterations}"
            )


@dataclass(frozen=True, kw_only=True, eq=False)
class RecordedRows:
    """One image's linearised rows in absolute form ``b = A xi + e`` (for verification).

    ``columns`` names each column ``(kind, index, component)``.
    """

    columns: tuple[tuple[str, int, int], ...]
    A: FloatArray
    b: FloatArray
    w: FloatArray


@dataclass(frozen=True, kw_only=True, eq=False)
class _Departure:
    """Parameters F leaving the Seq-R window and their Rauch-Tung-Striebel gain on the rest W.

    Later data reach F only through W (F is never observed again), so given the final
    (smoothed) estimate of W the final estimate of F is ``x_F + J (x_W_final - x_W)`` with
    ``J = Q_FW Q_WW^-1`` taken at departure (Rauch, Tung & Striebel 1965).
    """

    leaving: tuple[Key, ...]
    staying: tuple[Key, ...]
    x_leaving: FloatArray
    x_staying: FloatArray
    gain: FloatArray  # (|F|, |W|)
    conditional: FloatArray  # (|F|, |F|) Q_F|W = L_FF^-1
    at: int  # index of the image before which F left


@dataclass(eq=False)
class Window:
    """Parameters being updated: estimates, information or cofactor, and their block layout.

    Two engines (docs/algorithm.md, *Engines*):

    * ``"information"`` (default): the information matrix ``L`` is the one source of truth.
      Updates only add ``A^T P A`` to it; the cofactor blocks the update, the window rule and
      the sigmas need are recovered from its Cholesky factorisation with the GPs eliminated
      (:class:`seqat.information.InformationFactor`), refactorised after every change.
    * ``"inverse"``: the paper's inverse normal matrix ``Q``, carried by Eq. 10-14. ``L`` is
      then kept only for smoothing (the RTS gain of leaving parameters).

    ``coupled`` are the GPs that a marginal or re-opening prior couples to other GPs; the
    factorisation keeps them with the EOPs and eliminates every other GP by its 3x3 block.
    """

    x: FloatArray = field(default_factory=lambda: np.zeros(0))
    L: FloatArray | None = None
    keys: list[Key] = field(default_factory=list)
    offset: dict[Key, int] = field(default_factory=dict)
    inverse: bool = False
    coupled: set[Key] = field(default_factory=set)
    _Q: FloatArray | None = None
    _factor: InformationFactor | None = None
    _diag: FloatArray | None = None
    #: Called with the GP keys whose information is singular (the data do not determine
    #: them); it must take them out of the window. None: the RankDeficiency propagates.
    on_singular: Callable[[list[Key]], None] | None = None

    @property
    def Q(self) -> FloatArray:
        """The cofactor matrix (dense; the information engine forms it on request only)."""
        if self.inverse:
            assert self._Q is not None
            return self._Q
        if self._Q is None:
            self._Q = self.factor().dense()
        return self._Q

    @Q.setter
    def Q(self, value: FloatArray) -> None:
        if not self.inverse:
            raise AttributeError("the information engine derives Q from L")
        self._Q = value
        self._diag = None

    def changed(self) -> None:
        """``L`` (information engine) or ``Q`` changed: drop what was derived from it."""
        self._factor = None
        self._diag = None
        if not self.inverse:
            self._Q = None

    def factor(self) -> InformationFactor:
        """Factorisation of ``L`` (information engine), cached until :meth:`changed`."""
        assert self.L is not None
        while self._factor is None:
            gp = np.fromiter((self.offset[k] for k in self.keys
                              if k[0] == "p" and k not in self.coupled), dtype=np.int64)
            kept = np.fromiter((self.offset[k] for k in self.coupled), dtype=np.int64)
            try:
                self._factor = InformationFactor(self.L, gp, kept)
            except RankDeficiency as err:
                keys = self.keys_at(err.gp_blocks)
                if not keys or self.on_singular is None:
                    raise
                self.on_singular(keys)  # removes them: the loop factorises the rest
        return self._factor

    def keys_at(self, offsets: np.ndarray) -> list[Key]:
        """The keys whose blocks start at ``offsets``."""
        at = {off: k for k, off in self.offset.items()}
        return [at[int(o)] for o in offsets if int(o) in at]

    def drop(self, keys: list[Key]) -> None:
        """Take ``keys`` out without marginalising them (their rows and columns of ``L`` are
        deleted: the window is conditioned on their values, which the data do not determine
        and which therefore carry no information)."""
        gone = set(keys)
        keep_keys = [k for k in self.keys if k not in gone]
        keep = self.indices(keep_keys)
        if self.L is not None:
            self.L = self.L[np.ix_(keep, keep)]
        if self.inverse:
            self._Q = self.Q[np.ix_(keep, keep)]
        self.x = self.x[keep]
        self.coupled -= gone
        self.relayout(keep_keys)

    def q_columns(self, idx: np.ndarray) -> FloatArray:
        """``Q[:, idx]``."""
        if self.inverse:
            return self.Q[:, idx]
        return self.factor().columns(idx)

    def q_diagonal(self) -> FloatArray:
        """``diag(Q)``: every marginal variance (cofactor units)."""
        if self._diag is None:
            d = np.diagonal(self.Q).copy() if self.inverse else self.factor().diagonal()
            if d.size and not np.all(d > 0):
                bad = [self.keys[int(np.searchsorted(self._offsets(), q, side="right")) - 1]
                       for q in np.flatnonzero(~(d > 0))[:3]]
                raise EstimationError(f"the window's cofactor has non-positive variances "
                                      f"(parameters {bad})")
            self._diag = d
        return self._diag

    def q_block(self, idx: np.ndarray) -> FloatArray:
        """``Q[idx, idx]``."""
        if self.inverse:
            return self.Q[np.ix_(idx, idx)].copy()
        return self.factor().block(idx)

    def _offsets(self) -> np.ndarray:
        return np.fromiter((self.offset[k] for k in self.keys), dtype=np.int64)

    def relayout(self, keys: list[Key]) -> None:
        self.changed()
        self.keys = keys
        self.offset = {}
        off = 0
        for k in keys:
            self.offset[k] = off
            off += EOP_SIZE if k[0] == "e" else GP_SIZE

    def index(self, key: Key) -> np.ndarray:
        off = self.offset[key]
        return np.arange(off, off + (EOP_SIZE if key[0] == "e" else GP_SIZE))

    def indices(self, keys: list[Key]) -> np.ndarray:
        """Parameter indices of several blocks, concatenated in the order of ``keys``."""
        if not keys:
            return np.zeros(0, dtype=np.int64)
        offs = np.fromiter((self.offset[k] for k in keys), dtype=np.int64, count=len(keys))
        sizes = np.fromiter(
            (EOP_SIZE if k[0] == "e" else GP_SIZE for k in keys), dtype=np.int64, count=len(keys)
        )
        starts = np.cumsum(sizes) - sizes
        return np.repeat(offs - starts, sizes) + np.arange(int(sizes.sum()))


class SequentialAT:
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
    """

    def __init__(
        self,
        camera: PinholeCamera,
        options: SequentialOptions = SequentialOptions(),
        *,
        record: bool = False,
        sink: Callable[[EopEstimate | PointEstimate], None] | None = None,
    ) -> None:
        self.camera = camera
        self.options = options
        sim_opts = dataclasses.replace(options.sim, min_rays=options.min_rays,
                                       snooping_critical=options.snooping_critical,
                                       robust_scale=options.robust_scale)
        if options.snooping_critical is not None:  # the initial block's points as births
            sim_opts = dataclasses.replace(sim_opts, min_ray_angle_deg=options.min_ray_angle_deg)
        # With data snooping the initial block is adjusted once, when complete: refits of its
        # first few images have too little redundancy to tell blunders from good rays, and a
        # wrong early solution would seed the later ones.
        self._inverse = options.engine == "inverse"
        self._records = options.smoothing  # departure records (RTS smoothing, re-opening)
        self._initial: SimultaneousAT | None = SimultaneousAT(
            camera, sim_opts, refit_every_frame=options.snooping_critical is None)
        self._origin: FloatArray | None = None
        self._w = Window()
        self._window_images: deque[int] = deque()
        self._image_ids: list[str] = []
        self._point_ids: list[str] = []
        self._point_index: dict[str, int] = {}
        self._img_points: dict[int, list[int]] = {}
        self._gp_count: dict[int, int] = {}
        self._gp_nobs: dict[int, int] = {}
        self._gp_order: list[int] = []
        self._pending: dict[int, list[tuple[int, FloatArray, float]]] = {}
        self._frozen_eop: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._frozen_gp: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._departures: list[_Departure | None] = []  # None: finalised (smoothing_lag)
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
        #: Points the data do not determine (singular information), taken out: point ids.
        self.undetermined: list[str] = []
        self._dropped_value: dict[Key, FloatArray] = {}
        self._w.on_singular = self._drop_undetermined
        #: Observations removed by data snooping: (image id, point id, w-test value).
        self.rejections: list[tuple[str, str, float]] = []
        #: GPS/INS groups down-weighted by data snooping: (image id, "position"/"attitude").
        self.nav_downweighted: list[tuple[str, str]] = []
        self._forced: set[int] = set()  # pending points already held back once (never twice)
        self._ssr = 0.0
        self._redundancy = 0
        self._factors = Factors()
        self.relinearisations = 0  # window re-linearisations so far
        self._drift_px = self._drift_m = self._drift_deg = float("nan")
        self.recorded: list[RecordedRows] | None = [] if record else None
        self.initial_state: tuple[list[Key], FloatArray, FloatArray] | None = None

    # ------------------------------------------------------------------ public API
    @property
    def sigma0(self) -> float:
        """A posteriori standard error of unit weight."""
        return (
            float(np.sqrt(self._ssr / self._redundancy)) if self._redundancy > 0 else float("nan")
        )

    def set_correlation_threshold(self, threshold: float) -> None:
        """Seq-R: the window threshold of the next updates (the latency budget tightens it,
        seed 000: "select the threshold for the speed requirement"). Seq-F stays Seq-F."""
        if self.options.correlation_threshold is None:
            raise ValueError("Seq-F (correlation_threshold None) has no window to cut")
        self.options = dataclasses.replace(self.options, correlation_threshold=threshold)

    def add_frame(self, frame: Frame) -> ImageUpdate:
        """Add the next image and update the triangulation."""
        with _BLAS.limit(limits=UPDATE_BLAS_THREADS, user_api="blas"):
            if self._initial is not None:
                return self._add_initial(frame)
            return self._add_sequential(frame)

    def finish(self) -> None:
        """After the last image: re-linearise the window at its estimate (to
        :data:`FINAL_RELINEARISE_PX`), so the final window values are those of the
        collinearity equations, not of rows linearised on the way (Seq-F then equals Sim).
        No-op without ``relinearise_px``; :meth:`solution` itself never changes the state."""
        if self._initial is None and self.options.relinearise_px is not None:
            with _BLAS.limit(limits=UPDATE_BLAS_THREADS, user_api="blas"):
                self._relinearise_if_needed(FINAL_RELINEARISE_PX)

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
        for i, iid in enumerate(self._image_ids):
            if ("e", i) in w.offset:
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
            if ("p", p) in w.offset:
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
            eops=tuple(eops), points=tuple(pts), sigma0=self.sigma0, redundancy=self._redundancy
        )

    def window_solution(self) -> Solution:
        """Current estimates of the window's images and GPs with sigmas: O(window), any time.

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
            else:
                pts.append(
                    PointEstimate(
                        point_id=self._point_ids[k[1]],
                        xyz_m=w.x[idx] + origin,
                        sigma_m=sd[idx],
                        n_obs=self._gp_nobs[k[1]],
                    )
                )
        return Solution(
            eops=tuple(eops), points=tuple(pts), sigma0=self.sigma0, redundancy=self._redundancy
        )

    def _smoothed_departed(self) -> dict[Key, FloatArray]:
        """RTS backward pass over the departures, newest first: O(sum |F| |W|)."""
        w = self._w
        value: dict[Key, FloatArray] = dict(self._dropped_value)
        value.update({k: w.x[w.index(k)] for k in w.keys})
        for dep in reversed(self._departures[self._first_record:]):
            if dep is None:
                continue
            x_w = np.concatenate([value[k] for k in dep.staying])
            x_f = dep.x_leaving + dep.gain @ (x_w - dep.x_staying)
            off = 0
            for k in dep.leaving:
                size = EOP_SIZE if k[0] == "e" else GP_SIZE
                # a key that re-entered the window left again later (or is in it): the
                # newer departure, processed first, already holds its final value
                value.setdefault(k, x_f[off : off + size])
                off += size
        return value

    # ------------------------------------------------------------------ initial stage (Sim)
    def _add_initial(self, frame: Frame) -> ImageUpdate:
        sim = self._initial
        assert sim is not None
        t0 = time.perf_counter()
        upd = sim.add_frame(frame)
        i = len(self._image_ids)
        self._image_ids.append(frame.image_id)
        if i + 1 >= self.options.initial_images:
            self._start_sequential(sim)
        ms = (time.perf_counter() - t0) * 1e3
        return dataclasses.replace(upd, stage="initial-sim", update_ms=ms)

    def _start_sequential(self, sim: SimultaneousAT) -> None:
        """Take the initial Sim solution with its full inverse normal matrix as the window."""
        st = sim.export_state(Covariance.FULL)
        res = st.result
        assert res.full_cofactor is not None
        try:
            np.linalg.cholesky(res.full_cofactor)
        except np.linalg.LinAlgError as err:
            raise EstimationError(
                f"the initial simultaneous block ({len(st.image_ids)} images) is singular or "
                f"ill-conditioned: its cofactor matrix is not positive definite") from err
        self._origin = st.origin
        n = len(st.image_ids)
        keys: list[Key] = [("e", i) for i in range(n)]
        for pid in st.point_ids:
            self._point_index[pid] = len(self._point_ids)
            self._point_ids.append(pid)
        keys += [("p", int(j)) for j in st.selected]
        w = self._w
        w.inverse = self._inverse
        w.relayout(keys)
        w.x = np.concatenate([res.eop.ravel(), res.gp.ravel()])
        if self._inverse:
            w.Q = res.full_cofactor
        if self.options.smoothing or not self._inverse:
            # the initial block's normal matrix itself (not the inverse of its cofactor:
            # inverting that would cost digits and blur the GPs' block-diagonal structure)
            L = res.full_normal if res.full_normal is not None else np.linalg.inv(
                res.full_cofactor)
            w.L = 0.5 * (L + L.T)
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
        self._ssr, self._redundancy = res.weighted_ssr, res.redundancy
        if self.options.relinearise_px is not None:
            sel_of = {int(j): k for k, j in enumerate(st.selected)}
            use = [k for k, j in enumerate(st.obs_point) if int(j) in sel_of]
            img = np.asarray(st.obs_image, dtype=np.int64)[use]
            pt = np.asarray(st.obs_point, dtype=np.int64)[use]
            gp_row = np.array([sel_of[int(j)] for j in pt], dtype=np.int64)
            self._factors.add(img, pt, np.asarray(st.obs_uv)[use],
                              np.asarray(st.obs_sigma_px)[use], res.eop[img], res.gp[gp_row],
                              self.camera, self.options.robust_scale)
        self.initial_state = (keys, self._w.x.copy(), res.full_cofactor.copy())
        if res.undetermined is not None and res.undetermined.any():
            self._drop_undetermined([("p", int(j)) for j, bad
                                     in zip(st.selected, res.undetermined, strict=True) if bad])
        self.rejections.extend(sim.rejections)
        self.nav_downweighted.extend(sim.nav_downweighted)
        self._initial = None

    # ------------------------------------------------------------------ sequential stage
    def _select_window(self, frame_points: set[int]) -> int:
        """Seq-R: cut the window before the update; returns the number of images dropped."""
        thr = self.options.correlation_threshold
        if thr is None or len(self._window_images) < 2:
            return 0
        w = self._w
        offs = np.fromiter(
            (w.offset[("e", j)] for j in self._window_images),
            dtype=np.int64,
            count=len(self._window_images),
        )
        # The paper's reference is the last image. On real flights it may be tied to nothing
        # yet (its points wait for a wider ray spread): its correlations are all zero and the
        # rule would cut the whole window. Then the newest image that is tied (correlated
        # over the threshold with another window image) is the reference as well.
        diag = w.q_diagonal()
        rho = np.zeros(len(offs))
        for r in range(len(offs) - 1, -1, -1):
            o = int(offs[r])
            rho_r = correlations_from_columns(w.q_columns(o + np.arange(EOP_SIZE)), diag,
                                              offs, o)
            rho = np.maximum(rho, rho_r)
            rho_r[r] = 0.0
            if np.any(rho_r >= thr):
                break
        start = first_over_threshold(rho, thr)
        start = self._hold_pending_rays(start, frame_points)
        if start == 0:
            return 0
        scale = sigma_scale(self.sigma0, self._redundancy)
        sd = np.sqrt(w.q_diagonal()) * scale
        now = len(self._image_ids) - 1
        keep_rays = self._reopen_age > 0
        leaving: set[Key] = set()
        changed: set[int] = {p for p in self._orphans if p in self._gp_count}
        self._orphans.clear()
        for _ in range(start):
            j = self._window_images.popleft()
            leaving.add(("e", j))
            idx = w.index(("e", j))
            self._frozen_eop[j] = (w.x[idx].copy(), sd[idx])
            with_rays = []
            for p in self._img_points.pop(j):
                if p in self._gp_count:
                    self._gp_count[p] -= 1
                    changed.add(p)
                elif p in self._pending:
                    if keep_rays:
                        with_rays.append(p)  # kept: image j re-enters if p is born
                    else:
                        self._drop_pending_ray(p, j)
            if with_rays:
                self._departed_rays.append((j, with_rays))
        for p in changed:
            if self._gp_count[p] + (p in frame_points) < MIN_WINDOW_RAYS:
                leaving.add(("p", p))
                idx = w.index(("p", p))
                self._frozen_gp[p] = (w.x[idx].copy(), sd[idx])
                del self._gp_count[p]
        self._depart(leaving, now)
        return start

    def _depart(self, leaving: set[Key], now: int) -> None:
        """Marginalise ``leaving`` out of the window, keeping its RTS record (smoothing)."""
        w = self._w
        keep_keys = [k for k in w.keys if k not in leaving]
        leave_keys = [k for k in w.keys if k in leaving]
        keep, leave = w.indices(keep_keys), w.indices(leave_keys)
        off = 0
        frozen = w.q_block(leave) if leave.size else np.zeros((0, 0))
        for k in leave_keys:
            idx = w.index(k)
            self._frozen_cof[k] = frozen[off : off + idx.size, off : off + idx.size].copy()
            self._departed[k] = (now, len(self._departures), off)
            off += idx.size
        if w.L is not None:
            # E[x_F | x_W] = x_F - L_FF^-1 L_FW (x_W - x_W0): the RTS gain from the information
            # matrix; marginalising F out of L is its Schur complement.
            L_fw = w.L[np.ix_(leave, keep)]
            cond = spd_inverse(w.L[np.ix_(leave, leave)], "information of the leaving "
                                "parameters")
            gain = -cond @ L_fw
            fill = L_fw.T @ gain
            L = w.L[np.ix_(keep, keep)] + 0.5 * (fill + fill.T)
            # GPs the marginal prior now ties to other GPs are no longer eliminable alone
            support = np.flatnonzero(np.any(L_fw != 0.0, axis=0))
            gps = {keep_keys[int(np.searchsorted(self._starts(keep_keys), c, side="right")) - 1]
                   for c in support}
            gps = {k for k in gps if k[0] == "p"}
            if len(gps) > 1:
                w.coupled |= gps
            w.L = L
        if w.L is not None and self._records:
            self._departures.append(
                _Departure(
                    leaving=tuple(leave_keys),
                    staying=tuple(keep_keys),
                    x_leaving=w.x[leave],
                    x_staying=w.x[keep],
                    gain=gain,
                    conditional=0.5 * (cond + cond.T),
                    at=now,
                )
            )
        if self._inverse:
            w.Q = w.Q[np.ix_(keep, keep)]
        w.coupled -= leaving
        w.x = w.x[keep]
        w.relayout(keep_keys)

    def _factorise(self, H: FloatArray) -> InformationFactor:
        """Factorisation of an information matrix laid out as the window (GPs eliminated)."""
        w = self._w
        gp = np.fromiter((w.offset[k] for k in w.keys if k[0] == "p" and k not in w.coupled),
                         dtype=np.int64)
        kept = np.fromiter((w.offset[k] for k in w.coupled), dtype=np.int64)
        return InformationFactor(H, gp, kept)

    @staticmethod
    def _starts(keys: list[Key]) -> np.ndarray:
        """Offsets of ``keys`` laid out in that order."""
        sizes = np.fromiter((EOP_SIZE if k[0] == "e" else GP_SIZE for k in keys),
                            dtype=np.int64, count=len(keys))
        return np.cumsum(sizes) - sizes

    def _hold_pending_rays(self, start: int, frame_points: set[int]) -> int:
        """Never lose tie rays by waiting: shorten the cut before the first leaving image that
        holds pending rays of a point with ``min_rays`` rays, and have those points born now.

        Without this, a window shorter than the span a point needs to reach
        ``min_ray_angle_deg`` would drop every ray before birth: no new ties, lower
        correlations, a shorter window (observed: collapse to 2 images). Each point is held
        back at most once; its images leave at the next cut.
        """
        min_rays = self.options.min_rays
        for h in range(start):
            j = self._window_images[h]
            live = [
                p
                for p in self._img_points[j]
                if p in self._pending
                and p not in self._forced
                and len(self._pending[p]) + (p in frame_points) >= min_rays
            ]
            if live:
                for jj in list(self._window_images)[h:start]:
                    self._forced.update(
                        p
                        for p in self._img_points[jj]
                        if p in self._pending
                        and len(self._pending[p]) + (p in frame_points) >= min_rays
                    )
                return h
        return start

    def _add_sequential(self, frame: Frame) -> ImageUpdate:
        t0 = time.perf_counter()
        opts, cam, w = self.options, self.camera, self._w
        assert self._origin is not None
        i = len(self._image_ids)
        self._image_ids.append(frame.image_id)
        pts: list[int] = []
        for pid in frame.point_ids:
            p = self._point_index.get(pid)
            if p is None:
                p = self._point_index[pid] = len(self._point_ids)
                self._point_ids.append(pid)
            pts.append(p)
        dropped = self._select_window(set(pts))
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
                if len(lst) >= opts.min_rays:
                    candidates.append(p)
        in_frame = set(candidates)
        candidates += [p for p in self._forced if p not in in_frame and p in self._pending]

        nav_sigma = free_nav_sigma(frame.nav_sigma)
        rejected: list[tuple[int, int, float]] = []  # (image, point, w) removed by snooping
        rejected_new: set[int] = set()  # points whose ray in the new image was removed
        downweighted: list[str] = []
        reopened: list[Key] = []
        held: set[int] = set()  # points whose birth made the update singular (wait)
        rounds = 0
        while True:
            if not self._inverse:
                w.factor()  # an undetermined GP leaves now, before the rows are laid out
            y21 = [(p, uv) for p, uv in seen if p not in rejected_new
                   and (("p", p) in w.offset or self._reopenable(("p", p), i))]
            y21_pts = [p for p, _ in y21]
            y21_uv = [uv for _, uv in y21]
            reopen: list[Key] = [("p", p) for p in y21_pts if ("p", p) not in w.offset]
            ready = [p for p in candidates if p in self._pending and p not in held
                     and len(self._pending[p]) >= opts.min_rays]
            born, born_xyz = self._birth(ready, i, init, use_new=init_known)
            reopen += list(dict.fromkeys(
                ("e", j) for p in born for (j, _, _) in self._pending[p]
                if j != i and ("e", j) not in w.offset))
            if reopen:
                self._reopen(reopen)
                reopened += reopen
                if not self._inverse:
                    w.factor()
                    keep = [k for k, (p, _) in enumerate(y21) if ("p", p) in w.offset]
                    y21_pts = [y21_pts[k] for k in keep]
                    y21_uv = [y21_uv[k] for k in keep]

            # --- layout of the new parameters: [EOP of image i, born GPs]
            n2 = EOP_SIZE + GP_SIZE * len(born)
            x2_0 = np.concatenate([init, born_xyz.ravel()])
            y12 = [(j, b, uv, s) for b, p in enumerate(born)
                   for (j, uv, s) in self._pending[p] if j != i]
            y22 = [(b, uv, s) for b, p in enumerate(born)
                   for (j, uv, s) in self._pending[p] if j == i]
            touched_keys: list[Key] = [("p", p) for p in y21_pts]
            touched_keys += list(dict.fromkeys(("e", j) for (j, _, _, _) in y12))
            touched = w.indices(touched_keys)
            Qc = w.Q[:, touched] if self._inverse else w.q_columns(touched)  # Q[:, touched]
            col_of = {}
            c = 0
            for k in touched_keys:
                col_of[k] = c
                c += EOP_SIZE if k[0] == "e" else GP_SIZE

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
            obs += [(t, t + EOP_SIZE + GP_SIZE * b, uv, s, False, (i, born[b]))
                    for (b, uv, s) in y22]
            builder = RowBuilder(cam, t, n2, obs, nav, nav_sigma, opts.robust_scale)
            x1t = w.x[touched]
            d1t = np.zeros(touched.size)
            d2 = np.zeros(n2)
            iterations = 0
            degenerate: list[int] = []
            while True:
                iterations += 1
                # the first iterate is linearised at the start values (an INS 20 deg off):
                # least squares there, the robust loss from the second on, so that a bad start
                # does not make every ray an outlier
                builder.robust_scale = None if iterations == 1 else opts.robust_scale
                rows = builder.rows(x1t, x2_0, d1t, d2)
                try:
                    sol = solve_update(Qc, touched, rows, columns=True)
                except EstimationError:
                    # a point being born that its rays no longer fix (an iterate sent it far
                    # off): it waits for more rays; anything else is a real failure
                    degenerate = _degenerate_points(rows, len(born))
                    if not degenerate:
                        raise
                    break
                d1t, d2 = sol.delta1_touched, sol.delta2
                degenerate = self._unstable_births(born, born_xyz, y12, y22, x1t + d1t,
                                                   x2_0 + d2, col_of)
                if degenerate:
                    break
                # Converged when the rows, linearised where they were, still describe the
                # image points at the new estimate: re-linearising would move it by less.
                if iterations >= opts.max_update_iterations or (
                    builder.linearisation_error(x1t, x2_0, d1t, d2)
                    < opts.iteration_tolerance_px
                    and (opts.robust_scale is None or iterations > 1)
                ):
                    break
            if degenerate:
                held.update(born[b] for b in degenerate)
                continue
            if opts.snooping_critical is None or rounds >= MAX_SNOOPING_ROUNDS:
                break
            rounds += 1
            verdict = snoop_update(Qc[touched], touched, rows, sol, builder, d1t, d2,
                                   opts.snooping_critical)
            if not verdict.observations and not set(verdict.nav_groups) - set(downweighted):
                break
            for q, wq in zip(verdict.observations, verdict.w, strict=True):
                j, p = (int(v) for v in builder.ids[q])
                rejected.append((j, p, wq))
                if j == i:
                    rejected_new.add(p)
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
        w.x = np.concatenate([w.x + sol.delta1(), x2_0 + sol.delta2])
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
        for p in y21_pts:
            self._gp_count[p] += 1
            self._gp_nobs[p] += 1
        for p in born:
            obs = self._pending.pop(p)
            self._gp_count[p] = self._gp_nobs[p] = len(obs)
            self._gp_order.append(p)
            self._n_points += 1
            for j, _, _ in obs:
                if ("e", j) in reopened:
                    self._img_points[j].append(p)
        self._drift_m = self._drift_deg = float("nan")
        if opts.relinearise_px is not None:
            check = opts.drift_check_every is not None and i % opts.drift_check_every == 0
            self._relinearise_if_needed(force=check)
        if opts.smoothing_lag is not None:
            self._finalise_old(i)
        ms = (time.perf_counter() - t0) * 1e3
        update = self._report(
            frame, i, ms, rows, n2, len(born), len(pts) - skipped - len(rejected_new), skipped,
            iterations, dropped
        )
        return dataclasses.replace(
            update,
            reopened=len(reopened),
            drift_px=self._drift_px,
            drift_m=self._drift_m,
            drift_deg=self._drift_deg,
            rejected=tuple((self._image_ids[j], self._point_ids[p], round(wq, 2))
                           for j, p, wq in rejected),
            nav_downweighted=tuple(downweighted),
        )

    def _unstable_births(self, born: list[int], born_xyz: FloatArray,
                         y12: list[tuple[int, int, FloatArray, float]],
                         y22: list[tuple[int, FloatArray, float]], x1t: FloatArray,
                         x2: FloatArray, col_of: dict[Key, int]) -> list[int]:
        """Points being born (index in the update) that an iterate of the update sent where
        their rays no longer fix them: behind a camera, or more than
        :data:`BIRTH_DEPTH_FACTOR` times farther than at birth (seen on a real flight: 1e8 m
        after a turn, with a singular 3x3 block). They wait for more rays instead of being
        born into a singular, far-off solution."""
        if not born:
            return []
        E, I = [], []
        for j, b, _, _ in y12:
            c = col_of[("e", j)]
            E.append(x1t[c : c + EOP_SIZE])
            I.append(b)
        for b, _, _ in y22:
            E.append(x2[:EOP_SIZE])
            I.append(b)
        E_a, I_a = np.asarray(E).reshape(-1, EOP_SIZE), np.asarray(I, dtype=np.int64)
        X = x2[EOP_SIZE:].reshape(-1, GP_SIZE)
        with np.errstate(all="ignore"):
            d = depth(E_a, X[I_a])
            d0 = depth(E_a, born_xyz[I_a])
        bad_ray = ~((d > 0) & (d < BIRTH_DEPTH_FACTOR * np.maximum(d0, 0.0)))
        bad = np.zeros(len(born), dtype=bool)
        np.logical_or.at(bad, I_a, bad_ray)
        bad |= ~np.all(np.isfinite(X), axis=1)
        return [int(b) for b in np.flatnonzero(bad)]

    def _drop_undetermined(self, keys: list[Key]) -> None:
        """GPs whose information became singular (every ray down-weighted by the robust loss,
        or rays that no longer intersect): out of the window and of the solution, named in
        :attr:`undetermined`. A later observation of the point starts it anew."""
        w = self._w
        for k in keys:  # departure records may refer to them: they are constants now
            self._dropped_value[k] = w.x[w.index(k)].copy()
        w.drop(keys)
        gone = {k[1] for k in keys if k[0] == "p"}
        for p in gone:
            self._gp_count.pop(p, None)
            self._orphans.discard(p)
            self.undetermined.append(self._point_ids[p])
        self._gp_order = [p for p in self._gp_order if p not in gone]
        self._n_points -= len(gone)

    def _reopenable(self, key: Key, i: int) -> bool:
        left = self._departed.get(key)
        return left is not None and i - left[0] <= self._reopen_age

    @property
    def _reopen_age(self) -> int:
        lag = self.options.smoothing_lag
        age = self.options.reopen_max_age
        return age if lag is None else min(age, lag)

    def _finalise_old(self, i: int) -> None:
        """``smoothing_lag``: every ``lag / 2`` images, parameters that left more than ``lag``
        images ago take their smoothed value (the RTS pass over the records kept) and are
        stored compactly or handed to the sink; their departure records are dropped."""
        lag = self.options.smoothing_lag
        assert lag is not None
        if i - self._last_finalised < max(1, lag // 2):
            return
        self._last_finalised = i
        cutoff = i - lag
        old = [k for k, (t, _, _) in self._departed.items() if t < cutoff]
        if not old:
            return
        value = self._smoothed_departed() if self._records else {}
        origin = self._origin
        assert origin is not None
        for k in old:
            del self._departed[k]
            self._frozen_cof.pop(k, None)
            if k[0] == "e":
                frozen, sig = self._frozen_eop.pop(k[1])
                val = value.get(k, frozen).copy()
                if self._sink is None:
                    self._final_eop[k[1]] = (val, sig)
                else:
                    val[:3] += origin
                    val[3:] = wrap_angle(val[3:])
                    self._sink(EopEstimate(image_id=self._image_ids[k[1]], eop=val, sigma=sig))
            else:
                frozen, sig = self._frozen_gp.pop(k[1])
                val = value.get(k, frozen).copy()
                nobs = self._gp_nobs.pop(k[1])
                if self._sink is None:
                    self._final_gp[k[1]] = (val, sig, nobs)
                else:
                    self._sunk.add(k[1])
                    self._sink(PointEstimate(point_id=self._point_ids[k[1]], xyz_m=val + origin,
                                             sigma_m=sig, n_obs=nobs))
        r = self._first_record
        while r < len(self._departures):
            dep = self._departures[r]
            if dep is not None and dep.at >= cutoff:
                break
            self._departures[r] = None
            r += 1
        self._first_record = r
        if self._sink is not None:
            gone = {k[1] for k in old if k[0] == "p"}
            self._gp_order = [p for p in self._gp_order if p not in gone]

    def _forget_old_rays(self, i: int) -> None:
        """Drop the kept pending rays of images that left more than ``reopen_max_age`` ago."""
        limit = i - self._reopen_age
        rays = self._departed_rays
        while rays:
            j, points = rays[0]
            left = self._departed.get(("e", j))
            if left is not None and left[0] >= limit:
                break
            rays.popleft()
            if ("e", j) in self._w.offset:
                continue  # re-opened: its rays were used then
            for p in points:
                self._drop_pending_ray(p, j)

    def _drop_pending_ray(self, p: int, j: int) -> None:
        """Forget image ``j``'s pending ray of point ``p`` (and the point with its last ray)."""
        if p not in self._pending:
            return
        rest = [o for o in self._pending[p] if o[0] != j]
        if rest:
            self._pending[p] = rest
        else:
            del self._pending[p]
            self._forced.discard(p)

    def _reopen(self, keys: list[Key]) -> None:
        """Bring departed parameters back into the window (docs/algorithm.md, re-opening).

        With smoothing (departure records kept) each key enters with its exact distribution
        given the current window (:meth:`_conditional_prior`), jointly with the others, and
        the records it left with are rewritten to condition on it (:meth:`_split_records`).
        Without, it enters with its frozen value and cofactor, uncorrelated with the window.
        The prior adds as many pseudo-observations as parameters: redundancy and sum of
        squares do not change.
        """
        w = self._w
        n = w.x.size
        sizes = [EOP_SIZE if k[0] == "e" else GP_SIZE for k in keys]
        m = sum(sizes)
        if w.L is None:
            J = np.zeros((m, n))
            mean = np.concatenate([self._frozen_value(k) for k in keys])
            C = scipy.linalg.block_diag(*(self._frozen_cof[k] for k in keys))
        else:
            mean, J, C = self._conditional_prior(keys, sizes)
            self._split_records(keys)
        for key in keys:
            if key[0] == "e":
                j = key[1]
                self._img_points[j] = []
                pos = sum(1 for jj in self._window_images if jj < j)
                self._window_images.insert(pos, j)
            else:
                self._gp_count[key[1]] = 0
        C = 0.5 * (C + C.T)
        if self._inverse:
            QJt = w.Q @ J.T
            Q = np.empty((n + m, n + m))
            Q[:n, :n] = w.Q
            Q[:n, n:] = QJt
            Q[n:, :n] = QJt.T
            Q[n:, n:] = J @ QJt + C
            w.Q = Q
        if w.L is not None:
            # the prior ties the re-opened keys to the window keys its chain refers to
            support = [k for k in w.keys if k[0] == "p" and np.any(J[:, w.index(k)] != 0.0)]
            gps = set(support) | {k for k in keys if k[0] == "p"}
            if len(gps) > 1:
                w.coupled |= gps
            Ci = spd_inverse(C, "conditional cofactor of the re-opened parameters")
            CiJ = Ci @ J
            L = np.empty((n + m, n + m))
            L[:n, :n] = w.L + J.T @ CiJ
            L[:n, n:] = -CiJ.T
            L[n:, :n] = -CiJ
            L[n:, n:] = Ci
            w.L = L
        w.x = np.concatenate([w.x, mean])
        w.relayout(w.keys + keys)
        self.reopened += len(keys)

    def _conditional_prior(self, keys: list[Key],
                           sizes: list[int]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Departed ``keys`` given the current window: ``y = mean + J (x_W - x_W,now) + e``.

        Each departure record says ``x_F = x_F0 + G (x_W - x_W0) + e``, ``e ~ (0, L_FF^-1)``
        independent of everything after. Starting from the keys themselves, every departed key
        the form refers to is replaced by its record's relation, oldest record first (a record
        refers only to keys that left later or are still in the window), until the form refers
        to window keys only. The result is the exact conditional of the keys given the window
        as long as no departed key was touched in between; a key re-opened since is taken at
        its last departure.
        """
        w = self._w
        m = sum(sizes)
        col_of: dict[Key, int] = {}
        buf = np.zeros((m, 8 * m + 64))
        ncol = 0

        def column(key: Key) -> int:
            nonlocal buf, ncol
            c = col_of.get(key)
            if c is None:
                size = EOP_SIZE if key[0] == "e" else GP_SIZE
                if ncol + size > buf.shape[1]:
                    buf = np.concatenate([buf, np.zeros_like(buf)], axis=1)
                c = col_of[key] = ncol
                ncol += size
            return c

        pending: dict[int, list[Key]] = {}
        row = 0
        for key, size in zip(keys, sizes, strict=True):
            c = column(key)
            buf[row : row + size, c : c + size] = np.eye(size)
            pending.setdefault(self._departed[key][1], []).append(key)
            row += size
        const = np.zeros(m)
        C = np.zeros((m, m))
        queued = set(keys)
        while pending:
            rec = min(pending)
            members = pending.pop(rec)
            dep = self._departures[rec]
            src = np.concatenate([self._departed[k][2] + np.arange(EOP_SIZE if k[0] == "e"
                                                                   else GP_SIZE)
                                  for k in members])
            cols = np.concatenate([col_of[k] + np.arange(EOP_SIZE if k[0] == "e" else GP_SIZE)
                                   for k in members])
            JK = buf[:, cols].copy()
            buf[:, cols] = 0.0
            G = dep.gain[src]
            const += JK @ (dep.x_leaving[src] - G @ dep.x_staying)
            C += JK @ dep.conditional[np.ix_(src, src)] @ JK.T
            JG = JK @ G
            ucols = np.empty(JG.shape[1], dtype=np.int64)
            off = 0
            for sk in dep.staying:
                size = EOP_SIZE if sk[0] == "e" else GP_SIZE
                c = column(sk)
                ucols[off : off + size] = c + np.arange(size)
                off += size
                if sk not in w.offset and sk not in queued and sk not in self._dropped_value:
                    queued.add(sk)
                    later = self._departed[sk][1]
                    assert later > rec, "a departure record refers to an older one"
                    pending.setdefault(later, []).append(sk)
            buf[:, ucols] += JG
        n = w.x.size
        J = np.zeros((m, n))
        for key, c in col_of.items():
            if key in w.offset:
                idx = w.index(key)
                J[:, idx] = buf[:, c : c + idx.size]
            elif key in self._dropped_value:  # taken out as undetermined: a constant
                val = self._dropped_value[key]
                const += buf[:, c : c + val.size] @ val
        mean = const + J @ w.x
        return mean, J, C

    def _split_records(self, keys: list[Key]) -> None:
        """Re-opened keys become conditioning keys of the departure records they left with.

        Record ``x_F = x_F0 + G (x_W - x_W0) + e`` with F = R (re-opened) + M (not): given
        ``x_R`` as well, ``x_M = x_M0 + (G_M - K G_R)(x_W - x_W0) + K (x_R - x_R0) + e'`` with
        ``K = C_MR C_RR^-1`` and ``Cov(e') = C_MM - K C_RM``. The record then says how M
        follows everything R learns from now on (for later re-opening and for smoothing).
        """
        by_record: dict[int, list[Key]] = {}
        for key in keys:
            by_record.setdefault(self._departed.pop(key)[1], []).append(key)
        for rec, reopened in by_record.items():
            dep = self._departures[rec]
            sizes = {k: EOP_SIZE if k[0] == "e" else GP_SIZE for k in dep.leaving}
            starts = dict(zip(dep.leaving, np.cumsum([0] + list(sizes.values()))[:-1],
                              strict=True))
            chosen = set(reopened)
            rest = [k for k in dep.leaving if k not in chosen]
            r_idx = np.concatenate([starts[k] + np.arange(sizes[k]) for k in reopened])
            m_idx = (np.concatenate([starts[k] + np.arange(sizes[k]) for k in rest])
                     if rest else np.zeros(0, dtype=np.int64))
            C = dep.conditional
            K = np.linalg.solve(C[np.ix_(r_idx, r_idx)], C[np.ix_(r_idx, m_idx)]).T
            cond = C[np.ix_(m_idx, m_idx)] - K @ C[np.ix_(r_idx, m_idx)]
            self._departures[rec] = _Departure(
                leaving=tuple(rest),
                staying=dep.staying + tuple(reopened),
                x_leaving=dep.x_leaving[m_idx],
                x_staying=np.concatenate([dep.x_staying, dep.x_leaving[r_idx]]),
                gain=np.hstack([dep.gain[m_idx] - K @ dep.gain[r_idx], K]),
                conditional=0.5 * (cond + cond.T),
                at=dep.at,
            )
            off = 0
            for k in rest:
                self._departed[k] = (self._departed[k][0], rec, off)
                off += sizes[k]

    def _frozen_value(self, key: Key) -> FloatArray:
        """Last estimate of a departed key (local frame)."""
        if key in self._w.offset:
            return self._w.x[self._w.index(key)]
        return (self._frozen_eop if key[0] == "e" else self._frozen_gp)[key[1]][0]

    def _relinearise_if_needed(self, threshold_px: float | None = None,
                               force: bool = False) -> None:
        """:meth:`_relinearise`; GPs that become singular on the way are taken out
        (:meth:`_drop_undetermined`) and the re-linearisation is tried again without them."""
        for _ in range(MAX_SINGULAR_RETRIES):
            try:
                self._relinearise(threshold_px, force)
                return
            except RankDeficiency as err:
                keys = self._w.keys_at(err.gp_blocks)
                if not keys:
                    raise
                self._drop_undetermined(keys)
        self._relinearise(threshold_px, force)

    def _relinearise(self, threshold_px: float | None = None, force: bool = False) -> None:
        """Re-linearise the window when its rows no longer describe the image points.

        Old rows were linearised where the estimate stood when they arrived; when later data
        move the estimate (a light UAV's INS is degrees off), the linear model drifts from
        the collinearity equations (seed 003 §3.2). The check costs O(window observations):
        the largest difference between the projected image points and the rows' linear
        prediction at the current estimate. Above ``relinearise_px`` the window is
        re-adjusted by Gauss-Newton: its information is split into the rows of its own
        observations (taken out at their old linearisation) and the rest (the marginalised
        prior of the departed parameters and the linear GPS/INS rows, kept), and the own
        rows are linearised anew at each iterate. ``Q``, ``L`` and σ0 follow.
        """
        w, opts = self._w, self.options
        assert opts.relinearise_px is not None
        f = self._factors.in_window(w)
        if f is None:
            return
        e_idx, p_idx = f.columns(w)
        x = w.x
        limit = opts.relinearise_px if threshold_px is None else threshold_px
        self._drift_px = f.linearisation_error(x[e_idx], x[p_idx], self.camera)
        if self._drift_px <= limit and not force:
            return
        self.relinearisations += 1
        L = w.L if w.L is not None else np.linalg.inv(w.Q)
        cols = np.concatenate([e_idx, p_idx], axis=1)  # (k, 9) window columns per factor
        H_old, eta_old = f.information(cols, x.size)
        H_p = L - H_old
        del H_old
        eta_p = L @ x - eta_old

        def prior(z: FloatArray) -> float:  # the kept information's part of the cost / 2
            return float(0.5 * z @ H_p @ z - eta_p @ z)

        def solve(H: FloatArray, g: FloatArray) -> FloatArray:
            if self._inverse:
                return np.linalg.solve(H, g)
            return self._factorise(H).solve(g)

        xk = x.copy()
        ssr_old_factors = f.linearised_ssr(x[e_idx], x[p_idx])
        prior_old = prior(x)
        def evaluate(z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray,
                                              float]:
            # The rows keep the robust weights their update gave them: re-weighting the whole
            # window here (IRLS) let a re-linearisation after a turn, far from the start,
            # trade dozens of good points for outliers (seen on Seneca: 1e-9 weights, a
            # singular window).
            Je, Jp, r = f.evaluate(z[e_idx], z[p_idx], self.camera)
            return Je, Jp, r, f.w, 0.5 * float(np.sum(f.w[:, None] * r**2)) + prior(z)

        Je, Jp, r, wf, cost = evaluate(xk)
        for _ in range(opts.relinearise_iterations):
            H, g = normal_from_factors(Je, Jp, r, wf, cols, x.size)
            H += H_p
            g += eta_p - H_p @ xk
            delta = solve(H, g)
            del H
            # Gauss-Newton (IRLS) with step halving: the window's cost never goes up (a
            # turn's rows far from linear would otherwise send it off)
            for _ in range(MAX_STEP_HALVINGS):
                trial = xk + delta
                Je_t, Jp_t, r_t, wf_t, cost_t = evaluate(trial)
                if np.isfinite(cost_t) and cost_t <= cost + 1e-9 * abs(cost):
                    break
                delta = 0.5 * delta
            else:
                break  # no step lowers the cost: xk is the minimum to rounding
            xk, cost, Je, Jp, r, wf = trial, cost_t, Je_t, Jp_t, r_t, wf_t
            if np.max(np.abs(delta)) < RELINEARISE_TOLERANCE:
                break
        H, _ = normal_from_factors(Je, Jp, r, wf, cols, x.size)
        H += H_p
        H = 0.5 * (H + H.T)
        prior_new = prior(xk)
        ssr_new_factors = float(np.sum(wf[:, None] * r**2))
        self._ssr = max(self._ssr + ssr_new_factors - ssr_old_factors
                        + 2.0 * (prior_new - prior_old), 0.0)
        dx = xk - x
        eop_keys = [k for k in w.keys if k[0] == "e"]
        ie = w.indices(eop_keys).reshape(-1, EOP_SIZE)
        self._drift_m = float(np.max(np.abs(dx[ie[:, :3]]), initial=0.0))
        self._drift_deg = float(np.degrees(np.max(np.abs(dx[ie[:, 3:]]), initial=0.0)))
        w.x = xk
        w.L = H if w.L is not None else None
        if self._inverse:
            Q = np.linalg.inv(H)
            w.Q = 0.5 * (Q + Q.T)
        w.changed()
        f.relinearised_at(xk[e_idx], xk[p_idx], Je, Jp, r)
        f.w = wf
        self._factors.replace(f)

    def _birth(
        self, candidates: list[int], i: int, nav: FloatArray, *, use_new: bool = True
    ) -> tuple[list[int], FloatArray]:
        """Intersect candidate tie points; return those with a usable geometry and their XYZ.

        ``use_new=False`` leaves the new image's rays out of the intersection (its EOP start
        value is unknown: a GNSS dropout); the point then needs two other rays.
        """
        if not candidates:
            return [], np.zeros((0, GP_SIZE))
        if self.options.snooping_critical is not None:
            self._screen_rays(candidates, i)
            ok = [p for p in candidates if p in self._pending
                  and len(self._pending[p]) >= self.options.min_rays]
            if len(ok) < len(candidates):
                return self._birth(ok, i, nav, use_new=use_new)
        eops, uvs, idx = [], [], []
        for c, p in enumerate(candidates):
            for j, uv, _ in self._pending[p]:
                if j == i and not use_new:
                    continue
                eops.append(nav if j == i else self._eop_value(j))
                uvs.append(uv)
                idx.append(c)
        if not idx:
            return [], np.zeros((0, GP_SIZE))
        E, UV, I = np.asarray(eops), np.asarray(uvs), np.asarray(idx)
        X, spread = intersect_rays(E, UV, I, len(candidates), self.camera)
        min_angle = np.radians(
            [
                MIN_FORCED_RAY_ANGLE_DEG if p in self._forced else self.options.min_ray_angle_deg
                for p in candidates
            ]
        )
        ok = np.all(np.isfinite(X), axis=1) & (spread >= min_angle)
        front = np.ones(len(candidates), dtype=bool)
        if np.any(ok):
            d = depth(E, np.nan_to_num(X)[I])
            np.logical_and.at(front, I, d > 0)
        ok &= front
        sel = np.flatnonzero(ok)
        return [candidates[c] for c in sel], X[sel]

    def _eop_value(self, j: int) -> FloatArray:
        w = self._w
        return w.x[w.index(("e", j))] if ("e", j) in w.offset else self._frozen_eop[j][0]

    def _screen_rays(self, candidates: list[int], i: int) -> None:
        """Data snooping at birth: the rays of estimated images (not the new one, whose EOP is
        still the nav) must meet in one point. The worst ray of a point whose rays miss it by
        more than ``SCREEN_SIGMAS * critical * sigma`` pixels is rejected while at least two
        remain; a blunder in a point's first rays would otherwise be intersected into a wrong
        point the update cannot leave (a local minimum that fits all its rays)."""
        crit = self.options.snooping_critical
        assert crit is not None
        rays = [(c, j, uv) for c, p in enumerate(candidates) for (j, uv, _) in self._pending[p]]
        I = np.asarray([r[0] for r in rays], dtype=np.int64)
        UV = np.asarray([r[2] for r in rays], dtype=np.float64).reshape(-1, 2)
        # the new image's rays take any EOP: they are not used here
        E = np.asarray([self._eop_value(j) if j != i else np.zeros(EOP_SIZE)
                        for (_, j, _) in rays]).reshape(-1, EOP_SIZE)
        old = np.asarray([j != i for (_, j, _) in rays], dtype=bool)
        sig = np.asarray([s for p in candidates for (_, _, s) in self._pending[p]])
        limit = SCREEN_SIGMAS * crit * sig
        alive = old.copy()
        for _ in range(MAX_SCREEN_ROUNDS):
            n_old = np.bincount(I[alive], minlength=len(candidates))
            if not np.any(n_old >= 3):
                break
            X, _ = intersect_rays(E[alive], UV[alive], I[alive], len(candidates), self.camera)
            res = np.full(I.size, -np.inf)
            sel = alive & (n_old[I] >= 3) & np.all(np.isfinite(X[I]), axis=1)
            if not np.any(sel):
                break
            res[sel] = (np.linalg.norm(UV[sel] - project(E[sel], X[I[sel]], self.camera),
                                       axis=1) - limit[sel])
            order = np.lexsort((-res, I))
            first = order[np.r_[True, I[order][1:] != I[order][:-1]]]
            worst = first[res[first] > 0]
            if worst.size == 0:
                break
            alive[worst] = False
            for r in worst:
                p = candidates[int(I[r])]
                rays = self._pending[p]
                k = int(r - np.flatnonzero(I == I[r])[0])
                j, _, s = rays[k]
                self.rejections.append((self._image_ids[j], self._point_ids[p],
                                        float(res[r] / s / crit + SCREEN_SIGMAS)))
        if not np.all(alive | ~old):
            for c, p in enumerate(candidates):
                rays = self._pending[p]
                gone = ~alive[I == c] & old[I == c]
                if gone.any():
                    for (j, _, _), g in zip(rays, gone, strict=True):
                        if g and j in self._img_points and p in self._img_points[j]:
                            self._img_points[j].remove(p)
                    self._pending[p] = [o for o, g in zip(rays, gone, strict=True) if not g]

    def _record(
        self,
        touched_keys: list[Key],
        touched: np.ndarray,
        born: list[int],
        i: int,
        rows: LinearRows,
        x1t: FloatArray,
        x2_0: FloatArray,
    ) -> None:
        cols: list[tuple[str, int, int]] = []
        for k in touched_keys + [("e", i)] + [("p", p) for p in born]:
            cols += [(k[0], k[1], c) for c in range(EOP_SIZE if k[0] == "e" else GP_SIZE)]
        m2, m3 = rows.l2.size, rows.l3.size
        A = np.zeros((m2 + m3, len(cols)))
        A[:m2, : touched.size] = rows.A21
        A[:m2, touched.size :] = rows.A22
        A[m2:, touched.size :] = rows.A32
        b = np.concatenate([rows.l2, rows.l3]) + A @ np.concatenate([x1t, x2_0])
        assert self.recorded is not None
        self.recorded.append(
            RecordedRows(columns=tuple(cols), A=A, b=b, w=np.concatenate([rows.w2, rows.w3]))
        )

    def _report(
        self,
        frame: Frame,
        i: int,
        ms: float,
        rows: LinearRows,
        n2: int,
        n_born: int,
        used: int,
        skipped: int,
        iterations: int,
        dropped: int,
    ) -> ImageUpdate:
        w = self._w
        scale = sigma_scale(self.sigma0, self._redundancy)
        idx = w.index(("e", i))
        eop = w.x[idx].copy()
        eop[:3] += self._origin  # type: ignore[operator]
        eop[3:] = wrap_angle(eop[3:])
        gp_offs = np.fromiter((w.offset[k] for k in w.keys if k[0] == "p"), dtype=np.int64)
        var = w.q_diagonal()[gp_offs[:, None] + np.arange(GP_SIZE)] * scale**2
        rms = rms_point_sigma(var)
        n_img = len(self._window_images)
        return ImageUpdate(
            image_id=frame.image_id,
            index=i,
            stage="sequential",
            update_ms=ms,
            window_images=n_img,
            window_first_image=self._image_ids[self._window_images[0]],
            window_params=w.x.size,
            window_eop_params=EOP_SIZE * n_img,
            window_gp_params=w.x.size - EOP_SIZE * n_img,
            inverse_sizes=(rows.l2.size, n2),
            sim_reduced_size=0,
            sigma0=self.sigma0,
            redundancy=self._redundancy,
            rms_gp_sigma_m=rms,  # type: ignore[arg-type]
            n_points_total=self._n_points,
            new_points=n_born,
            observations_used=used,
            observations_skipped=skipped,
            iterations=iterations,
            eop=EopEstimate(
                image_id=frame.image_id, eop=eop, sigma=np.sqrt(w.q_diagonal()[idx]) * scale
            ),
            images_left_window=dropped,
        )


def _degenerate_points(rows: LinearRows, n_born: int) -> list[int]:
    """Points being born (index in the update) whose own 3x3 normal block is singular."""
    D = rows.A22.T @ (rows.w2[:, None] * rows.A22) + rows.A32.T @ (rows.w3[:, None] * rows.A32)
    out = []
    for b in range(n_born):
        sl = slice(EOP_SIZE + GP_SIZE * b, EOP_SIZE + GP_SIZE * (b + 1))
        ev = np.linalg.eigvalsh(D[sl, sl])
        if not ev[0] > 1e-9 * max(ev[-1], 1e-300):
            out.append(b)
    return out


#: A point being born whose update iterate lies this many times farther from a camera than
#: its birth intersection (or behind it) is held back (SequentialAT._unstable_births).
BIRTH_DEPTH_FACTOR = 100.0
#: Times a re-linearisation is tried again after taking out singular GPs.
MAX_SINGULAR_RETRIES = 3
#: A re-linearisation step that raises the window's cost is halved at most this many times.
MAX_STEP_HALVINGS = 8
#: A window re-linearisation stops when no parameter moves more than this (m or rad).
RELINEARISE_TOLERANCE = 1e-7
#: finish() re-linearises the window when its rows are this far off (pixels).
FINAL_RELINEARISE_PX = 1e-3
