"""Re-linearising the Seq-F / Seq-R window (seed 003 §3.2; docs/algorithm.md).

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from seqat.information import (
    InformationFactor,
    RankDeficiency,
    add_factor_parts,
    gather_parts,
    split_indices,
)
from seqat.robust import cauchy_weight
from seqat.rows import factor_blocks, gradient_from_factors, scatter_blocks
from seqat.types import EOP_SIZE, FloatArray

#: Times a re-linearisation is tried again after taking out singular GPs.
MAX_SINGULAR_RETRIES = 10
#: Robust loss: at most this many re-weightings per re-linearisation, and the change of a
#: weight factor below which they stop.
ROBUST_ROUNDS = 3
ROBUST_WEIGHT_TOLERANCE = 0.05
#: A re-linearisation step that raises the window's cost is halved at most this many times.
MAX_STEP_HALVINGS = 8
#: A window re-linearisation stops when no parameter moves more than this (m or rad).
RELINEARISE_TOLERANCE = 1e-7
#: finish() re-linearises the window when its rows are this far off (pixels).
FINAL_RELINEARISE_PX = 1e-3


class RelinearisationMixin:
    """Window re-linearisation of :class:`SequentialAT`."""

    def _relinearise_if_needed(self, threshold_px: float | None = None,
                               force: bool = False) -> None:
        """:meth:`_relinearise`; GPs that become singular on the way are taken out
        (:meth:`_drop_undetermined`) and the re-linearisation is tried again without them.
        If it still meets a singular system it is skipped (the window stays as the updates
        left it, counted in :attr:`relinearisations_skipped`): a re-linearisation refines,
        its failure must not end the flight."""
        for _ in range(MAX_SINGULAR_RETRIES):
            try:
                self._relinearise(threshold_px, force)
                return
            except RankDeficiency as err:
                keys = self._w.keys_at(err.gp_blocks)
                if not keys:
                    break
                self._drop_undetermined(keys)
        self.relinearisations_skipped += 1

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
        self._drift_px = f.linearisation_error(x[e_idx], x[p_idx], self._cam)
        if self._drift_px <= limit and not force:
            return
        self.relinearisations += 1
        L = w.L if w.L is not None else np.linalg.inv(w.Q)
        cols = np.concatenate([e_idx, p_idx], axis=1)  # (k, 9) window columns per factor
        H_old, eta_old = f.information(cols, x.size)
        H_p = L - H_old
        del H_old
        eta_p = L @ x - eta_old

        def prior(z: FloatArray, Hp_z: FloatArray) -> float:  # the kept information / 2
            return float(0.5 * z @ Hp_z - eta_p @ z)

        n = x.size
        if not self._inverse:
            # the GP-eliminated blocks of H_p once; each step adds its rows' blocks to them
            # (no n x n matrix per step: docs/algorithm.md, *Re-linearising the window*)
            gp, kept = w.elimination()
            r_idx, p_blk = split_indices(n, gp)
            base = gather_parts(H_p, r_idx, p_blk)

        def solver_at(Je: FloatArray, Jp: FloatArray,
                      wf: FloatArray) -> Callable[[FloatArray], FloatArray]:
            if self._inverse:
                H = scatter_blocks(factor_blocks(Je, Jp, wf), cols, n) + H_p
                return lambda g: np.linalg.solve(H, g)
            parts = add_factor_parts(base, Je, Jp, wf, f.img, cols, r_idx, p_blk, n)
            return InformationFactor(None, gp, kept, parts=parts, n=n).solve

        # Robust loss: the weights are re-computed only where Gauss-Newton has converged with
        # the previous ones (an outer IRLS loop, at most ROBUST_ROUNDS); re-weighting at every
        # iterate let a re-linearisation after a turn, far from the start, trade dozens of
        # good points for outliers (seen on Seneca: 1e-9 weights, a singular window).
        wf = f.w
        robust = opts.robust_scale
        sigma = 1.0 / np.sqrt(f.w0)
        xk = x.copy()
        ssr_old_factors = f.linearised_ssr(x[e_idx], x[p_idx])
        Hp_x = H_p @ xk
        prior_old = prior(x, Hp_x)
        Je, Jp, r = f.evaluate(xk[e_idx], xk[p_idx], self._cam)
        for _ in range(1 if robust is None else ROBUST_ROUNDS):
            cost = 0.5 * float(np.sum(wf[:, None] * r**2)) + prior(xk, Hp_x)
            for _ in range(opts.relinearise_iterations):
                g = gradient_from_factors(Je, Jp, r, wf, cols, n) + eta_p - Hp_x
                delta = solver_at(Je, Jp, wf)(g)
                # Gauss-Newton with step halving: the window's cost never goes up (a turn's
                # rows far from linear would otherwise send it off)
                for _ in range(MAX_STEP_HALVINGS):
                    trial = xk + delta
                    Hp_t = H_p @ trial
                    Je_t, Jp_t, r_t = f.evaluate(trial[e_idx], trial[p_idx], self._cam)
                    cost_t = 0.5 * float(np.sum(wf[:, None] * r_t**2)) + prior(trial, Hp_t)
                    if np.isfinite(cost_t) and cost_t <= cost + 1e-9 * abs(cost):
                        break
                    delta = 0.5 * delta
                else:
                    break  # no step lowers the cost: xk is the minimum to rounding
                xk, cost, Je, Jp, r, Hp_x = trial, cost_t, Je_t, Jp_t, r_t, Hp_t
                if np.max(np.abs(delta)) < RELINEARISE_TOLERANCE:
                    break
            if robust is None:
                break
            w_new = f.w0 * cauchy_weight(r, sigma, robust)
            if np.max(np.abs(w_new - wf) / f.w0) < ROBUST_WEIGHT_TOLERANCE:
                break
            wf = w_new
        H = scatter_blocks(factor_blocks(Je, Jp, wf), cols, n) + H_p
        H = 0.5 * (H + H.T)
        prior_new = prior(xk, Hp_x)
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
