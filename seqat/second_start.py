"""A second start during the flight: after an update that moved earlier images far beyond
their sigma, the window is adjusted again from least-squares weights with the camera
parameters it does not determine held at their prior, and that solution replaces the
window's when it fits better (docs/algorithm.md, *A second start during the flight*).

A sequential estimator starts every solve where the last one stopped; when a late image
ties a poorly determined part of the flight to the rest, the solve that follows can stop in
a wrong minimum of the robust cost, kept by the robust weights it reached there and, with
self-calibration, by an undetermined focal length trading with the heights. Measured on a
subset of the real flight (docs/benchmarks.md, *A second start during the flight*): all
three — the undetermined parameters held, the weights started again and the window
re-linearised to finish()'s tolerance — were needed to leave it.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np

from seqat.calibration import undetermined
from seqat.errors import EstimationError
from seqat.geometry import wrap_angle
from seqat.relinearise import FINAL_RELINEARISE_PX
from seqat.types import EOP_SIZE, FloatArray

#: An update "jumped" when it moved an earlier window image by more than this many of that
#: image's sigma before the update (each EOP component; a priori units scaled by
#: ``max(sigma0, 1)``). A linear update moves an estimate by at most its sigma's worth of
#: new information (Var(change) = sigma_before^2 - sigma_after^2): beyond three, the new
#: rays contradict what the window held. Seneca's 70 images: at most 1.5; the link of the
#: subset's take-off pair: 3.2 (docs/benchmarks.md).
JUMP_SIGMAS = 3.0
#: After a jump, a second start is tried after this many updates (the jump's own included):
#: one is not always enough (on the subset, those after the link's update and the next stayed
#: in the wrong minimum; the third left it).
SECOND_START_UPDATES = 8


@dataclass(frozen=True)
class SecondStart:
    """A second start tried after the update of ``image_id``: kept or not, its time (ms)."""

    image_id: str
    kept: bool
    ms: float


class SecondStartMixin:
    """The second start of :class:`seqat.sequential.SequentialAT`."""

    def _remember_window_eops(self) -> None:
        """After an update's refinement (:meth:`refine`): each window image's EOP and its
        sigma, what the next update's jump is measured against."""
        if not self._second_start_possible():
            return
        w = self._w
        diag = w.q_diagonal()
        keys = [k for k in w.keys if k[0] == "e"]
        if not keys:
            self._eop_before = None
            return
        idx = w.indices(keys).reshape(-1, EOP_SIZE)
        scale = max(float(self.sigma0), 1.0) if np.isfinite(self.sigma0) else 1.0
        sd = np.sqrt(np.maximum(diag[idx], 0.0)) * scale
        self._eop_before = ([k[1] for k in keys], w.x[idx].copy(), sd)

    def _jumped(self) -> bool:
        """The update moved an image of the window before it by more than
        :data:`JUMP_SIGMAS` of its sigma then (angles wrapped)."""
        if self._eop_before is None:
            return False
        images, x0, sd = self._eop_before
        w = self._w
        keep = [n for n, i in enumerate(images) if ("e", i) in w.offset]
        if not keep:
            return False
        idx = w.indices([("e", images[n]) for n in keep]).reshape(-1, EOP_SIZE)
        d = w.x[idx] - x0[keep]
        d[:, 3:] = wrap_angle(d[:, 3:])
        s = sd[keep]
        return bool(np.any((s > 0.0) & (np.abs(d) > JUMP_SIGMAS * s)))

    def _arm_second_start(self, image_id: str) -> None:
        """After an update's re-linearisation: when the update jumped, a second start is due
        after it and after the next :data:`SECOND_START_UPDATES` - 1 updates
        (:meth:`refine` tries it)."""
        self._second_start_due = None
        if not self._second_start_possible():
            return
        if self._jumped():
            self._second_start_left = SECOND_START_UPDATES
        if self._second_start_left <= 0:
            return
        self._second_start_left -= 1
        self._second_start_due = image_id

    def _second_start(self) -> SecondStart | None:
        """:meth:`refine`: the second start the last update made due, if the window leaves camera
        parameters undetermined: they are locked at their prior and the window is adjusted
        again from least-squares weights to finish()'s tolerance, then released and adjusted
        again. Kept when σ0 is lower than the window's before (named in
        :attr:`second_starts`); otherwise the estimator is restored whole. None: none tried.
        Information engine with re-linearisation only.

        It runs after the update, so the image's estimate is out before it (a real-time
        caller publishes it first): it costs Gauss-Newton on the whole window to
        convergence, 0.1-1 s on the real flight's subsets, and stopped earlier it does not
        leave the wrong minimum (docs/algorithm.md, *A second start during the flight*).

        With the camera determined there is nothing to hold, and a trial from least-squares
        weights alone was measured to gain nothing on the real flight's subsets at up to
        3.6 s per update (docs/benchmarks.md, *A second start during the flight*)."""
        image_id, self._second_start_due = self._second_start_due, None
        if image_id is None:
            return None
        t0 = time.perf_counter()
        hold = self._undetermined_camera()
        if hold is None:
            return None
        before = self.sigma0
        saved = self._save_state()
        self.second_starts_tried += 1
        try:
            lock = self._lock_camera(*hold)
            self._relinearise(FINAL_RELINEARISE_PX, force=True, reset_weights=True)
            self._release_camera(lock)
            self._relinearise(FINAL_RELINEARISE_PX, force=True)
            kept = bool(np.isfinite(self.sigma0) and self.sigma0 < before
                        and np.all(np.isfinite(self._w.x)))
        except (EstimationError, np.linalg.LinAlgError):
            kept = False  # a trial that meets a singular window is not a solution
        if kept:
            self.second_starts.append(image_id)
            self._remember_window_eops()  # the next jump is from here
        else:
            self._restore_state(saved)
        return SecondStart(image_id=image_id, kept=kept, ms=(time.perf_counter() - t0) * 1e3)

    def _second_start_possible(self) -> bool:
        """On, the information engine, re-linearisation, and a self-calibrated camera
        (a fixed one leaves nothing to hold: the jump is not even watched)."""
        return (self.options.second_start and not self._inverse and self._w.L is not None
                and self.options.relinearise_px is not None and self._cam_key is not None)

    def _save_state(self) -> dict:
        """A deep copy of the estimator's state (the caller's sink and the recorded rows
        are references, not state; the records' kept gains are a cache, not copied)."""
        keep = (self._sink, self.recorded, self._w.on_singular, self._gains)
        self._sink, self.recorded, self._w.on_singular, self._gains = None, None, None, {}
        try:
            return copy.deepcopy(self.__dict__)
        finally:
            self._sink, self.recorded, self._w.on_singular, self._gains = keep

    def _restore_state(self, saved: dict) -> None:
        sink, recorded, tried = self._sink, self.recorded, self.second_starts_tried
        gains = self._gains
        self.__dict__.clear()
        self.__dict__.update(saved)
        self._sink, self.recorded, self.second_starts_tried = sink, recorded, tried
        self._w.on_singular = self._drop_undetermined
        # a record's departure gain does not change while it lives (splits keep it; the split
        # gain kept beside it is checked against the record's splits); the records the trial
        # added are gone with it, and their numbers will be reused
        n = len(self._departures)
        self._gains = {r: g for r, g in gains.items() if r < n}

    def _undetermined_camera(self) -> tuple[np.ndarray, FloatArray] | None:
        """The camera parameters the window does not determine
        (:func:`seqat.calibration.undetermined`, finish()'s test) as a mask over the free
        ones, with ``Q[:, camera]`` (:meth:`_lock_camera`'s arguments); None: none."""
        key, calibration = self._cam_key, self.options.calibration
        if key is None or calibration is None:
            return None
        w = self._w
        idx = w.index(key)
        cols = w.q_columns(idx)
        bad = undetermined(cols[idx], calibration.prior_sigma(self.camera)[self._cam.index])
        return (bad, cols) if bad.any() else None
