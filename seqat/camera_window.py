"""Self-calibration in the window of :class:`seqat.sequential.SequentialAT`: the camera now,
its estimate with sigmas and correlations, and the hold after the last image
(docs/algorithm.md, *Self-calibration*)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqat.calibration import correlation, to_hold, undetermined
from seqat.information import add_block
from seqat.precision import sigma_scale
from seqat.relinearise import FINAL_RELINEARISE_PX
from seqat.types import CameraEstimate, FloatArray, PinholeCamera

#: Self-calibration: a parameter held at its prior after the last image gets this many times
#: its information (its sigma shrinks a hundredfold: the final re-linearisation moves it by
#: ~1 % of its sigma at most, and the reduced system stays far from the rank tolerance).
HOLD_WEIGHT = 1e4


@dataclass(frozen=True)
class CameraLock:
    """Camera parameters conditioned on their prior (:meth:`CameraMixin._lock_camera`)."""

    mask: np.ndarray  # which of the free parameters (their window indices may move)
    D: FloatArray | None  # the lock added to the window's information (None without L)
    prior: FloatArray  # their prior values
    pull: FloatArray  # the condition's multiplier, Q_hh^-1 (prior - x_h) before the lock


class CameraMixin:
    """The self-calibrated camera of :class:`seqat.sequential.SequentialAT`."""

    def _hold_undetermined_camera(self) -> bool:
        """After the last image: interior parameters the flight did not determine, or not
        significantly different from their prior (:func:`seqat.calibration.to_hold`, as Sim
        decides), are held at their prior.

        The window is conditioned on them: its mean moves by ``Q[:, h] Q_hh^-1 (prior - x_h)``
        (the exact conditional of the linearised problem; departed parameters follow through
        their smoothing gains, the camera being in every record's window), and an information
        :data:`HOLD_WEIGHT` times theirs locks them there, and the window is re-linearised;
        then the next round. True when any was held."""
        key, calibration = self._cam_key, self.options.calibration
        if key is None or calibration is None or not calibration.hold_undetermined:
            return False
        w = self._w
        idx = w.index(key)
        prior_sigma = calibration.prior_sigma(self.camera)[self._cam.index]
        prior = self.camera.intrinsics[self._cam.index]
        held = np.zeros(idx.size, dtype=bool)
        while not held.all():  # a round at a time, as Sim holds them
            cols = w.q_columns(idx)
            free = ~held
            bad = np.zeros(idx.size, dtype=bool)
            bad[free] = to_hold(calibration, cols[idx][np.ix_(free, free)], prior_sigma[free],
                                w.x[idx][free], prior[free],
                                sigma_scale(self.sigma0, self._redundancy))
            if not bad.any():
                break
            self._lock_camera(bad, cols)
            held |= bad
            if self.options.relinearise_px is not None:  # as Sim adjusts again after a round
                self._relinearise_if_needed(FINAL_RELINEARISE_PX, force=True)
        if not held.any():
            return False
        names = calibration.names
        self._camera_held = tuple(n for n, b in zip(names, held, strict=True) if b)
        return True

    def _lock_camera(self, bad: np.ndarray, cols: FloatArray | None = None) -> CameraLock:
        """Condition the window on the camera parameters ``bad`` (mask over the free ones)
        at their prior: its mean moves by ``Q[:, h] Q_hh^-1 (prior - x_h)`` (``cols``:
        ``Q[:, camera]`` when known), and an information :data:`HOLD_WEIGHT` times theirs
        locks them there (:class:`CameraLock`)."""
        assert self._cam_key is not None and self.options.calibration is not None
        w = self._w
        idx = w.index(self._cam_key)
        if cols is None:
            cols = w.q_columns(idx)
        prior = self.camera.intrinsics[self._cam.index][bad]
        h = idx[bad]
        Qh = cols[:, bad]
        Qhh = Qh[h]
        shift = np.linalg.solve(Qhh, prior - w.x[h])
        self._ssr += float((prior - w.x[h]) @ shift)  # the cost of the condition
        w.x = w.x + Qh @ shift
        w.x[h] = prior
        D = None
        if w.L is not None:
            D = np.diag(HOLD_WEIGHT * w.L.diagonal()[h])
            w.L = add_block(w.L, h, D)
        if self._inverse:
            prior_sigma = self.options.calibration.prior_sigma(self.camera)[self._cam.index]
            w.Q = w.Q - Qh @ np.linalg.solve(Qhh, Qh.T)
            w.Q[np.ix_(h, h)] = np.diag(prior_sigma[bad] ** 2 / HOLD_WEIGHT)
        w.changed()
        return CameraLock(mask=bad, D=D, prior=prior, pull=shift)

    def _release_camera(self, lock: CameraLock) -> None:
        """Take the lock of :meth:`_lock_camera` off (information engine): the window
        moves to the minimum of its model without it, ``x += Q[:, h] (D (x_h - prior) -
        pull)`` with ``Q`` of the unlocked information. The window holds its estimate for
        the minimum of whatever information it has, so the conditioning dropped the
        kept information's pull on ``h`` (the condition's multiplier, ``pull``) and the lock
        holds the rows' since (``D (x_h - prior)``): both are given back. Locked and
        released at once, the window is where it was."""
        w = self._w
        assert lock.D is not None and self._cam_key is not None
        h = w.index(self._cam_key)[lock.mask]
        d = w.x[h] - lock.prior
        g = lock.D @ d - lock.pull
        # the unlocked model's value here: the lock's term out, the multiplier's back in
        self._ssr += float(2.0 * lock.pull @ d - d @ lock.D @ d)
        w.L = add_block(w.L, h, -lock.D)
        w.changed()
        step = w.q_apply(h, g)
        self._ssr = max(self._ssr - float(g @ step[h]), 0.0)  # down to its minimum
        w.x = w.x + step
        w.changed()

    def camera_now(self) -> PinholeCamera:
        """The camera at the current estimate (the prior :attr:`camera` unless
        self-calibrating)."""
        if self._initial is not None:
            return self._initial.camera_now
        return self._camera_now()

    def _camera_now(self) -> PinholeCamera:
        key = self._cam_key
        if key is None or key not in self._w.offset:
            return self.camera
        return self._cam.at(self._w.x[self._w.index(key)])

    def camera_estimate(self) -> CameraEstimate | None:
        """The self-calibrated camera with the sigmas and correlations of its free
        parameters (None without self-calibration)."""
        if self._initial is not None:
            return self._initial.camera_estimate()
        key = self._cam_key
        if key is None:
            return None
        w = self._w
        assert self.options.calibration is not None
        names = self.options.calibration.names
        held = self._camera_held
        keep = np.array([n not in held for n in names], dtype=bool)
        idx = w.index(key)[keep]
        Q = w.q_block(idx)
        prior = self.options.calibration.prior_sigma(self.camera)[self._cam.index][keep]
        free = tuple(n for n in names if n not in held)
        weak = undetermined(Q, prior)
        return CameraEstimate(
            camera=self._camera_now(), prior=self.camera, free=free,
            sigma=np.sqrt(np.diagonal(Q)) * sigma_scale(self.sigma0, self._redundancy),
            correlation=correlation(Q), held=held,
            undetermined=tuple(n for n, b in zip(free, weak, strict=True) if b))

