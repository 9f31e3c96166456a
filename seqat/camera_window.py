"""Self-calibration in the window of :class:`seqat.sequential.SequentialAT`: the camera now,
its estimate with sigmas and correlations, and the hold after the last image
(docs/algorithm.md, *Self-calibration*)."""

from __future__ import annotations

import numpy as np

from seqat.calibration import correlation, to_hold, undetermined
from seqat.information import add_block
from seqat.precision import sigma_scale
from seqat.relinearise import FINAL_RELINEARISE_PX
from seqat.types import CameraEstimate, PinholeCamera

#: Self-calibration: a parameter held at its prior after the last image gets this many times
#: its information (its sigma shrinks a hundredfold: the final re-linearisation moves it by
#: ~1 % of its sigma at most, and the reduced system stays far from the rank tolerance).
HOLD_WEIGHT = 1e4


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
            h = idx[bad]
            Qh = cols[:, bad]
            Qhh = Qh[h]
            shift = np.linalg.solve(Qhh, prior[bad] - w.x[h])
            self._ssr += float((prior[bad] - w.x[h]) @ shift)  # the cost of the condition
            w.x = w.x + Qh @ shift
            w.x[h] = prior[bad]
            if w.L is not None:
                w.L = add_block(w.L, h, np.diag(HOLD_WEIGHT * w.L.diagonal()[h]))
            if self._inverse:
                w.Q = w.Q - Qh @ np.linalg.solve(Qhh, Qh.T)
                w.Q[np.ix_(h, h)] = np.diag(prior_sigma[bad] ** 2 / HOLD_WEIGHT)
            w.changed()
            held |= bad
            if self.options.relinearise_px is not None:  # as Sim adjusts again after a round
                self._relinearise_if_needed(FINAL_RELINEARISE_PX, force=True)
        if not held.any():
            return False
        names = calibration.names
        self._camera_held = tuple(n for n, b in zip(names, held, strict=True) if b)
        return True

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

