"""Re-linearising the Seq-F / Seq-R window (seed 003 §3.2; docs/algorithm.md).

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import scipy.sparse

from seqat.assembly import WindowAssembly, factor_information, factor_matvec
from seqat.geometry import depth, intersect_rays, wrap_angle
from seqat.information import InformationFactor, RankDeficiency, window_matrix
from seqat.robust import (
    NAV_GROUPS,
    NAV_REPORT_WEIGHT,
    cauchy_weight,
    nav_components,
    nav_groups_of,
    nav_report,
    nav_weight,
    robust_cost,
    robust_weight,
)
from seqat.rows import FactorSet, gradient_from_factors
from seqat.types import EOP_SIZE, FloatArray
from seqat.window import Key

#: Times a re-linearisation is tried again after taking out singular GPs.
MAX_SINGULAR_RETRIES = 10
#: A singular re-linearisation whose weakest direction lies on more GPs than this is not
#: about those points: the window as a whole lost its conditioning there, and the
#: re-linearisation is skipped instead of dropping them. On a 204-image weak-GPS block
#: capped at 40 images, one such step named 349 coupled points (1308 x 1308 reduced system,
#: scaled eigenvalues from -1.8e-7): all were dropped and 1725 later rays skipped.
MAX_UNDETERMINED_AT_ONCE = 10
#: Robust loss: at most this many re-weightings per re-linearisation, and the change of a
#: weight factor below which they stop.
ROBUST_ROUNDS = 3
ROBUST_WEIGHT_TOLERANCE = 0.05
#: ... and in finish()'s re-linearisation, until the weights settle as Sim's IRLS does (the
#: final window minimises the same robust objective as Sim: Seq-F == Sim). IRLS converges
#: linearly, one factorisation per round. With the weights read where the estimate is
#: (2026-12-04), finished Seq-R − Sim and finish()'s time at 1e-3 / 1e-4 / 1e-6: the clean
#: strip with four blunders 2.4e-5 / 3.5e-6 / 6e-8 m; Seneca 0.1 mm at each, 3.1 / 3.9 /
#: 5.9 s; the 100-image rendered block 4.0 / 9.2 s (old loop: 1.6e-4 m, 1.4 s, 2.3 s).
FINAL_ROBUST_ROUNDS = 100
FINAL_ROBUST_WEIGHT_TOLERANCE = 1e-3
#: A re-linearisation step that raises the window's cost is halved at most this many times.
MAX_STEP_HALVINGS = 8
#: A window re-linearisation stops when no parameter moves more than this (m or rad), or,
#: during the flight, when its last step would move no image point by more than
#: ``SequentialOptions.iteration_tolerance_px`` (the update's own rule: Gauss-Newton on the
#: window converges linearly, and the last 10-30 steps to 1e-7 moved nothing a pixel could
#: see; measured on Seneca: 9-35 steps per re-linearisation, 3-7 to 0.01 px). finish()
#: re-linearises to this tolerance.
RELINEARISE_TOLERANCE = 1e-7
#: A window GP is re-intersected robustly when more than half of at least this many of its
#: rays disagree with it beyond the robust scale (docs/algorithm.md, *Robust loss*).
ASTRAY_MIN_RAYS = 4
#: ... from every pair of at most this many of its rays (435 pairs), when at least this
#: many rays agree with the pair's intersection (the pair itself always does: a third ray
#: confirms it).
RESCUE_MAX_RAYS = 30
RESCUE_MIN_CONSENSUS = 3
#: finish() re-linearises the window when its rows are this far off (pixels).
FINAL_RELINEARISE_PX = 1e-3
#: During the flight a re-linearisation takes at most this many Gauss-Newton steps (each
#: one assembles and factorises the window: ~30 ms CPU for Seneca's 8100-parameter window,
#: plus ~40 ms once to find its pattern: seqat.assembly, 2026-12-03), then leaves the
#: estimate at the last step's model minimum; if the rows still drift, the next update's
#: check goes on. Real time needs bounded work per image: 9 steps made a 1.2 s update on
#: Seneca (2026-12-02). finish() is not bounded (SequentialOptions.relinearise_iterations).
FLIGHT_RELINEARISE_STEPS = 3
#: ... and when an astray point alone asks for it (a rescue moved it, or its rays changed;
#: the rows not drifting): one factorisation, the window left at the model's minimum with
#: the point's new start. The rows are linear there to the update's tolerance; whatever
#: drift remains goes to the next update's check. A 204-image block on a weak GPS/INS
#: re-linearised after 49 of 194 images for astray points (drift <= 0.06 px), each the
#: cost of ~4.5 updates; with one step CPU p95 / p99 fell from 308-323 / 352-359 to
#: 241-261 / 279-287 ms, the finished estimates the same to 0.5 mm and 0.0002 deg
#: (docs/benchmarks.md, *A block on a weak GPS/INS*).
ASTRAY_RELINEARISE_STEPS = 1
#: finish(): the GPS/INS groups' robust weights are re-computed at the window's estimate
#: (each time one factorisation of the window) until no weight factor changes by more than
#: this, then the window is re-linearised again at them; at most this many times each.
FINAL_NAV_WEIGHT_TOLERANCE = 1e-6
FINAL_NAV_ROUNDS = 50


class RelinearisationMixin:
    """Window re-linearisation of :class:`SequentialAT`."""

    def _keep_nav_rows(self, images: Sequence[int] | np.ndarray,
                       nav: tuple[FloatArray, FloatArray] | None, weights: FloatArray) -> None:
        """Record the GPS/INS rows ``L`` holds for ``images``: observation and sigmas
        (``nav``: (k, 6) each, local) and the robust weight factor of their groups
        (``weights``, (k, g))."""
        assert nav is not None
        obs, sigma = (np.asarray(a, dtype=np.float64).reshape(-1, EOP_SIZE) for a in nav)
        wc = nav_components(weights)
        for q, i in enumerate(images):
            self._nav_rows[int(i)] = np.concatenate([obs[q], sigma[q], wc[q]])

    def _retire_nav_rows(self, images: Iterable[int]) -> None:
        """``images`` can no longer re-enter the window (``smoothing_lag``: finalised), so
        ``finish()`` will not re-weight their GPS/INS rows and only :attr:`nav_robust` reads
        them: a down-weighted image keeps its group weights, the others nothing (memory
        flat along the flight)."""
        for i in images:
            row = self._nav_rows.pop(int(i), None)
            groups = None if row is None else nav_groups_of(row[12:])[0]
            if groups is not None and np.any(groups < NAV_REPORT_WEIGHT):
                self._nav_retired[int(i)] = groups

    @property
    def nav_robust(self) -> list[tuple[str, str, float]]:
        """GPS/INS groups the robust loss down-weights: (image id, group, weight factor)
        below :data:`seqat.robust.NAV_REPORT_WEIGHT`, as ``L`` holds them now (after
        finish(): the final weights; finalised images: as they left)."""
        groups = {i: nav_groups_of(row[12:])[0] for i, row in self._nav_rows.items()}
        groups.update(self._nav_retired)
        ids = sorted(groups)
        weights = np.array([groups[i] for i in ids]).reshape(-1, len(NAV_GROUPS))
        return nav_report([self._image_ids[i] for i in ids], weights)

    def _reweight_nav(self) -> bool:
        """finish(): the robust weights of the window images' GPS/INS groups at the window's
        estimate. The rows are linear (``A = I`` on the image's EOP): a weight change ``d``
        adds ``diag(d / σ²)`` to ``L`` and the estimate moves to the minimum of the changed
        model, ``x + (L + D)^-1 D r`` (``r = nav - x``), with σ0's sum of squares. Returns
        whether a weight changed by more than :data:`FINAL_NAV_WEIGHT_TOLERANCE`."""
        k, w = self.options.nav_robust_scale, self._w
        keys = [key for key in w.keys if key[0] == "e" and key[1] in self._nav_rows]
        if k is None or not keys:
            return False
        rows, idx, r = self._nav_residuals(keys)
        sigma, old = rows[:, 6:12], rows[:, 12:]
        new = nav_weight(r, sigma, k)
        if not np.max(np.abs(new - old)) > FINAL_NAV_WEIGHT_TOLERANCE:
            return False
        d = (new - old) / sigma**2
        diag = scipy.sparse.csr_array((d.ravel(), (idx.ravel(), idx.ravel())),
                                      shape=(w.x.size, w.x.size))
        L = w.L if w.L is not None else window_matrix(np.linalg.inv(w.Q))
        H = window_matrix(L + (diag.toarray() if not scipy.sparse.issparse(L) else diag))
        if w.L is not None:
            w.L = H
        if self._inverse:
            Q = np.linalg.inv(H.toarray() if scipy.sparse.issparse(H) else H)
            w.Q = 0.5 * (Q + Q.T)
        w.changed()
        g = (d * r).ravel()
        dx = w.q_apply(idx.ravel(), g)
        self._ssr = max(self._ssr + float(np.sum(d * r**2)) - float(g @ dx[idx.ravel()]), 0.0)
        w.x = w.x + dx
        for key, row in zip(keys, new, strict=True):
            self._nav_rows[key[1]][12:] = row
        return True

    def _final_relinearise(self) -> None:
        """finish()'s re-linearisation; with the GPS/INS robust loss, alternated with
        :meth:`_reweight_nav` until the weights settle (Sim's IRLS reaches the same
        minimum: Seq-F == Sim). Clean GPS/INS (every group in the core): no extra work."""
        self._relinearise_if_needed(FINAL_RELINEARISE_PX, force=True)
        for _ in range(FINAL_NAV_ROUNDS):
            changed = False
            for _ in range(FINAL_NAV_ROUNDS):
                if not self._reweight_nav():
                    break
                changed = True
            if not changed:
                break
            self._relinearise_if_needed(FINAL_RELINEARISE_PX, force=True)

    def _window_factors(self) -> FactorSet | None:
        """The window's image-point factors (:meth:`Factors.in_window`); those of departed
        keys set aside while they may re-open (departure records kept)."""
        return self._factors.in_window(self._w,
                                       keep_leaving=self._records and self._reopen_age > 0)

    def _nav_residuals(self, keys: list[Key]) -> tuple[FloatArray, np.ndarray, FloatArray]:
        """The GPS/INS rows ``L`` holds for the image ``keys`` (m, 18: observation, σ, weight
        factors), their window indices (m, 6) and residuals ``nav - x`` (angles wrapped)."""
        w = self._w
        rows = np.stack([self._nav_rows[key[1]] for key in keys]).reshape(-1, 3 * EOP_SIZE)
        idx = w.indices(keys).reshape(-1, EOP_SIZE)
        r = rows[:, :EOP_SIZE] - w.x[idx]
        r[:, 3:] = wrap_angle(r[:, 3:])
        return rows, idx, r

    def _settle_ssr(self) -> None:
        """finish(): σ0's sum of squares recomputed at the final estimate when the window
        holds every image and point (Seq-F; Seq-R once the final re-opening brought every
        departed key back): the image rows at their final weights, the GPS/INS rows, the
        camera's free parameters against their prior, the control points — Sim's sum. Kept
        during the flight, the sum is exact for linear rows only: re-linearisations move it
        by their linearised residuals (Seneca's every third image: 205.19 against 206.21,
        σ0 0.3 % under Sim's with the same EOPs)."""
        w = self._w
        n = len(self._image_ids)
        if (w.L is None or self._inverse or any(("e", i) not in w.offset for i in range(n))
                or any(("p", p) not in w.offset for p in self._gp_order)
                or any(i not in self._nav_rows for i in range(n))):
            return
        f = self._window_factors()
        ssr = 0.0
        if f is not None:
            e_idx, p_idx = f.columns(w)
            ssr += float(np.sum(f.w[:, None] * f.residuals(w.x[e_idx], w.x[p_idx],
                                                            self._cam) ** 2))
        if n:
            rows, _, d = self._nav_residuals([("e", i) for i in range(n)])
            ssr += float(np.sum(rows[:, 12:] * (d / rows[:, EOP_SIZE:12]) ** 2))
        calibration = self.options.calibration
        if self._cam_key is not None and calibration is not None:
            free = np.array([c not in self._camera_held for c in calibration.names])
            sigma = calibration.prior_sigma(self.camera)[self._cam.index][free]
            prior = self.camera.intrinsics[self._cam.index][free]
            ssr += float(np.sum(((w.x[w.index(self._cam_key)][free] - prior) / sigma) ** 2))
        for p in self._gp_order:
            ctrl = self._control_of(p)
            if ctrl is not None:
                ssr += float(np.sum(ctrl[1] * (w.x[w.index(("p", p))] - ctrl[0]) ** 2))
        self._ssr = ssr

    def _relinearise_if_needed(self, threshold_px: float | None = None,
                               force: bool = False) -> None:
        """:meth:`_relinearise`; GPs that become singular on the way are taken out
        (:meth:`_drop_undetermined`) and the re-linearisation is tried again without them.
        If it still meets a singular system, or one whose weakest direction lies on more
        than :data:`MAX_UNDETERMINED_AT_ONCE` GPs (not those points' fault), it is skipped
        (the window stays as the updates left it, counted in
        :attr:`relinearisations_skipped`): a re-linearisation refines, its failure must not
        end the flight, nor take hundreds of points with it."""
        for _ in range(MAX_SINGULAR_RETRIES):
            try:
                self._relinearise(threshold_px, force)
                return
            except RankDeficiency as err:
                keys = self._w.keys_at(err.gp_blocks)
                if not keys or len(keys) > MAX_UNDETERMINED_AT_ONCE:
                    break
                self._drop_undetermined(keys)
        self.relinearisations_skipped += 1

    def _astray_points(self, f: FactorSet, u2: FloatArray) -> np.ndarray:
        """Window GPs (point indices) whose estimate most of their own rays disagree with:
        at least :data:`ASTRAY_MIN_RAYS` rays and more than half of them beyond the robust
        scale. A point born on a blunder (two rays, one wrong: an exact but wrong
        intersection) is such a point once good rays arrive: the redescending loss keeps it
        where it is and down-weights them instead (a local minimum). ``u2``: each factor's
        squared normalised residual at the estimate."""
        k = self.options.robust_scale
        if k is None or f.pt.size == 0:
            return np.zeros(0, dtype=np.int64)
        out = u2 > k**2
        if not out.any():  # clean data: no ray beyond the scale, no point astray
            return np.zeros(0, dtype=np.int64)
        pts = np.unique(f.pt[out])  # only points with a ray out can be astray
        pos = np.minimum(np.searchsorted(pts, f.pt), pts.size - 1)
        mine = pts[pos] == f.pt
        n = np.bincount(pos[mine], minlength=pts.size)
        n_out = np.bincount(pos[mine & out], minlength=pts.size)
        return pts[(n >= ASTRAY_MIN_RAYS) & (2 * n_out > n)]

    def _restart_at(self, f: FactorSet, x: FloatArray, e_idx: np.ndarray, p_idx: np.ndarray,
                    wf: FloatArray) -> FloatArray:
        """Start the points of :attr:`_restart_points` (taken) at their values there (``x``
        is changed in place) and weight their rows at that start; returns the weights."""
        start, self._restart_points = self._restart_points, {}
        rows = np.flatnonzero(np.isin(f.pt, np.fromiter(start, dtype=np.int64)))
        pts, at = np.unique(f.pt[rows], return_index=True)  # each point's first row
        for p, row in zip(pts.tolist(), rows[at].tolist(), strict=True):
            x[p_idx[row]] = start[p]
        res = f.uv[rows] - self._cam.project(x[e_idx[rows]], x[p_idx[rows]])
        wf = wf.copy()
        wf[rows] = f.w0[rows] * robust_weight(np.sum(res**2, axis=1) * f.w0[rows],
                                              self.options.robust_scale)
        return wf

    def _rescue_points(self, f: FactorSet, astray: np.ndarray, x: FloatArray,
                       e_idx: np.ndarray, p_idx: np.ndarray, wf: FloatArray,
                       rescues: list[tuple[int, Key]]) -> FloatArray:
        """Re-intersect each astray point from its rays robustly and start the
        re-linearisation there if its robust cost is lower (``x`` is changed in place; each
        one appended to ``rescues``, for the smoothing pass once the re-linearisation is
        kept); returns the weights with those points' rows re-weighted at the new start.

        Robust intersection (as COLMAP re-triangulates, by consensus over ray pairs): every
        pair of rays intersected (of at most :data:`RESCUE_MAX_RAYS` rays spread over the
        point's rays), the candidate with most rays within the robust scale wins if at least
        :data:`RESCUE_MIN_CONSENSUS` agree, and is intersected again from those rays, twice.
        Pairs, not each ray left out in turn: a point with 11 rays, 5 of them blunders, has
        no good leave-one-out subset (the simulated strip at 20 % blunders left such a point
        26 m off). A consensus of 2 is none (a pair always fits itself): accepting it
        re-started points whose window rays were mostly blunders again and again against
        their departed rays (one point 13 times in 13 updates; the strip's κ error 1.8 times
        the oracle's)."""
        k = self.options.robust_scale
        assert k is not None
        cam = self._camera_now()
        wf = wf.copy()
        for p in astray:
            rows = np.flatnonzero(f.pt == p)
            e = x[e_idx[rows]]
            sigma = 1.0 / np.sqrt(f.w0[rows])
            start = x[p_idx[rows[0]]].copy()
            n = rows.size

            def u2(X: FloatArray, rows: np.ndarray = rows, e: FloatArray = e,
                   sigma: FloatArray = sigma) -> FloatArray:
                """Squared normalised residuals of the rays at each point of ``X`` (c, 3):
                (c, n); a point behind a camera or not finite gets inf."""
                X = np.atleast_2d(X)
                c = X.shape[0]
                ee, XX = np.tile(e, (c, 1)), np.repeat(X, rows.size, axis=0)
                with np.errstate(invalid="ignore", over="ignore"):
                    res = f.uv[np.tile(rows, c)] - self._cam.project(ee, XX)
                    out = (np.sum(res**2, axis=1) / np.tile(sigma, c) ** 2).reshape(c, -1)
                ok = np.all(np.isfinite(X), axis=1)[:, None] & (
                    depth(ee[:, :EOP_SIZE], XX).reshape(c, -1) > 0.0)
                return np.where(ok & np.isfinite(out), out, np.inf)

            use = np.unique(np.linspace(0, n - 1, min(n, RESCUE_MAX_RAYS)).round().astype(int))
            a, b = np.triu_indices(use.size, 1)
            pair = np.stack([use[a], use[b]], axis=1).ravel()
            cands, _ = intersect_rays(e[pair, :EOP_SIZE], f.uv[rows[pair]],
                                      np.repeat(np.arange(a.size), 2), a.size, cam)
            n_in = np.count_nonzero(u2(cands) <= k**2, axis=1)
            if n_in.max(initial=0) < RESCUE_MIN_CONSENSUS:
                continue
            cand = cands[int(np.argmax(n_in))]
            for _ in range(2):  # refine from the consensus, then from its own consensus
                keep = u2(cand)[0] <= k**2
                if np.count_nonzero(keep) < RESCUE_MIN_CONSENSUS:
                    break
                X, _ = intersect_rays(e[keep, :EOP_SIZE], f.uv[rows[keep]],
                                      np.zeros(int(keep.sum()), dtype=np.int64), 1, cam)
                if not np.all(np.isfinite(X[0])):
                    break
                cand = X[0]
            u2_cand = u2(cand)[0]
            if robust_cost(u2_cand, k) < robust_cost(u2(start)[0], k):
                rescues.append((len(self._departures), ("p", int(p))))
                x[p_idx[rows[0]]] = cand
                wf[rows] = f.w0[rows] * robust_weight(u2_cand, k)
        return wf

    def _relinearise(self, threshold_px: float | None = None, force: bool = False,
                     reset_weights: bool = False) -> None:
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
        ``reset_weights``: the robust weights start again from least squares (the old rows
        still come out at the weights they went in with; seqat/second_start.py).
        """
        w, opts = self._w, self.options
        assert opts.relinearise_px is not None
        f = self._window_factors()
        if f is None:
            return
        e_idx, p_idx = f.columns(w)
        x = w.x
        limit = opts.relinearise_px if threshold_px is None else threshold_px
        final = threshold_px is not None
        rounds, weight_tol = ((FINAL_ROBUST_ROUNDS, FINAL_ROBUST_WEIGHT_TOLERANCE) if final
                              else (ROBUST_ROUNDS, ROBUST_WEIGHT_TOLERANCE))
        xe, xp = x[e_idx], x[p_idx]
        true = f.residuals(xe, xp, self._cam)
        self._drift_px = f.linearisation_error(xe, xp, self._cam, true)
        u2 = np.sum(true**2, axis=1) * f.w0  # each ray's squared normalised residual
        astray = self._astray_points(f, u2)
        self._note_disagreeing(f, u2, xe)
        # astray points are re-intersected first. One that no consensus moves re-linearises
        # the window again only once its rays changed (a new ray may move it or its weights):
        # on the same rays it re-linearised a 3900-parameter block window after every image,
        # 0.1-0.6 s each (docs/algorithm.md, *Robust loss*: points born on a blunder)
        xk, wf = x.copy(), (f.w0.copy() if reset_weights else f.w)
        rescues: list[tuple[int, Key]] = []
        if astray.size:
            wf = self._rescue_points(f, astray, xk, e_idx, p_idx, wf, rescues)
        if self._restart_points:  # finish(): points intersected anew (_intersect_anew)
            wf = self._restart_at(f, xk, e_idx, p_idx, wf)
        rays = np.count_nonzero(f.pt[:, None] == astray[None, :], axis=0)
        tried = dict(zip(astray.tolist(), rays.tolist(), strict=True))
        if (self._drift_px <= limit and not force and not rescues
                and all(self._astray_tried.get(p) == n for p, n in tried.items())):
            return
        self.relinearisations += 1
        L = w.L if w.L is not None else window_matrix(np.linalg.inv(w.Q))
        cols = np.concatenate([e_idx, p_idx], axis=1)  # (k, 9) window columns per factor
        # The kept information H_p = L - (the own rows at their old linearisation): its
        # values on L's pattern, and each iterate's rows scattered onto them (seqat.assembly;
        # no sparse matrix built per step); where L's pattern does not allow it (a dense
        # small window) H_p is not formed (O(n) entries per step): products with it are L's
        # minus the old rows', its GP-eliminated blocks L's minus theirs (docs/algorithm.md,
        # *Re-linearising the window*). The inverse engine (small windows) forms it.
        J_old = (f.Je, f.Jp, f.w)
        x_lin = np.concatenate([f.e_lin, f.p_lin], axis=1)
        rhs_old = f.r_lin + np.einsum("kri,ki->kr", np.concatenate([f.Je, f.Jp], axis=2), x_lin)
        eta_p = L @ x - gradient_from_factors(f.Je, f.Jp, rhs_old, f.w, cols, x.size)
        H_p_dense = (L - factor_information(*J_old, f.img, cols, x.size)
                     if self._inverse else None)
        n = x.size
        gp, kept = w.elimination()
        assembly = None if self._inverse else WindowAssembly(L, f.img, cols, gp, J_old)
        H_p = H_p_dense if assembly is None or assembly.kept is None else assembly.kept

        def H_p_times(z: FloatArray) -> FloatArray:
            if H_p is not None:
                return H_p @ z
            return L @ z - factor_matvec(*J_old, cols, z)

        def prior(z: FloatArray, Hp_z: FloatArray) -> float:  # the kept information / 2
            return float(0.5 * z @ Hp_z - eta_p @ z)

        def solver_at(Je: FloatArray, Jp: FloatArray,
                      wf: FloatArray) -> Callable[[FloatArray], FloatArray]:
            if self._inverse:
                H = factor_information(Je, Jp, wf, f.img, cols, n) + H_p_dense
                H = H.toarray() if scipy.sparse.issparse(H) else H
                return lambda g: np.linalg.solve(H, g)
            assert assembly is not None
            factor = InformationFactor(None, gp, kept, parts=assembly.parts(Je, Jp, wf), n=n)
            last_factor[:] = [(Je, Jp, wf), factor]
            return factor.solve

        last_factor: list = []  # [(Je, Jp, wf) it was made at, InformationFactor]

        # Robust loss: the weights are re-computed only where Gauss-Newton has converged with
        # the previous ones (an outer IRLS loop, at most ROBUST_ROUNDS); re-weighting at every
        # iterate let a re-linearisation after a turn, far from the start, trade dozens of
        # good points for outliers (seen on Seneca: 1e-9 weights, a singular window).
        robust = opts.robust_scale
        sigma = 1.0 / np.sqrt(f.w0)
        ssr_old_factors = f.linearised_ssr(x[e_idx], x[p_idx])
        prior_old = prior(x, H_p_times(x))
        Hp_x = H_p_times(xk)
        Je, Jp, r = f.evaluate(xk[e_idx], xk[p_idx], self._cam)
        # The window's estimate ends at the minimum of its quadratic model (``L x = eta``:
        # everything after takes ``x`` for it): at a Gauss-Newton iterate when the steps have
        # converged, else at the model's minimum at the last linearisation (the last step,
        # solved but not taken: rows linearised at ``xk``, estimate ``xk + delta``).
        step = np.zeros_like(xk)

        # factorisations left (during the flight shared by the robust rounds)
        if final:
            budget = opts.relinearise_iterations * (rounds if robust is not None else 1) + 1
        elif self._drift_px > limit or force:
            budget = FLIGHT_RELINEARISE_STEPS
        else:  # an astray point alone, the rows not drifting
            budget = ASTRAY_RELINEARISE_STEPS

        cam_idx = w.index(self._cam_key) if self._cam_key is not None else None

        def admissible(z: FloatArray) -> bool:
            return cam_idx is None or self._cam.admissible(z[cam_idx])

        def gauss_newton(step_px: float) -> None:
            """Gauss-Newton steps at the weights ``wf`` until a step moves no parameter more
            than RELINEARISE_TOLERANCE, or no image point more than ``step_px``; after
            the step ``budget`` the last step is the model's (solved, not taken)."""
            nonlocal xk, Je, Jp, r, Hp_x, step, budget
            step = np.zeros_like(xk)
            cost = 0.5 * float(np.sum(wf[:, None] * r**2)) + prior(xk, Hp_x)
            for it in range(opts.relinearise_iterations):
                g = gradient_from_factors(Je, Jp, r, wf, cols, n) + eta_p - Hp_x
                delta = solver_at(Je, Jp, wf)(g)
                budget -= 1
                moved_px = np.max(np.abs(np.einsum("kri,ki->kr", Je, delta[e_idx])
                                         + np.einsum("kri,ki->kr", Jp, delta[p_idx])),
                                  initial=0.0)
                if (moved_px < step_px or budget <= 0
                        or it == opts.relinearise_iterations - 1):
                    step = delta
                    return
                # step halving: the window's cost never goes up (a turn's rows far from
                # linear would otherwise send it off)
                for _ in range(MAX_STEP_HALVINGS):
                    trial = xk + delta
                    if not admissible(trial):  # a focal length <= 0: no camera, no cost
                        delta = 0.5 * delta
                        continue
                    Hp_t = H_p_times(trial)
                    Je_t, Jp_t, r_t = f.evaluate(trial[e_idx], trial[p_idx], self._cam)
                    cost_t = 0.5 * float(np.sum(wf[:, None] * r_t**2)) + prior(trial, Hp_t)
                    if np.isfinite(cost_t) and cost_t <= cost + 1e-9 * abs(cost):
                        break
                    delta = 0.5 * delta
                else:
                    return  # no step lowers the cost: xk is the minimum to rounding
                xk, cost, Je, Jp, r, Hp_x = trial, cost_t, Je_t, Jp_t, r_t, Hp_t
                if np.max(np.abs(delta)) < RELINEARISE_TOLERANCE:
                    return

        # During the flight to the update's pixel tolerance; in finish() the robust weights
        # settle at that tolerance first, then one pass converges to RELINEARISE_TOLERANCE.
        for rnd in range(1 if robust is None else rounds):
            gauss_newton(opts.iteration_tolerance_px)
            # the weights change only before another solve: the window ends at the minimum
            # of the model it keeps (the weights of its last solve)
            if robust is None or budget <= 0 or rnd == rounds - 1:
                break
            if final and np.any(step):
                # the last step, solved but not taken at the pixel tolerance, is taken: the
                # weights are read where the estimate is. Read before it, the weights looked
                # settled after two or three rounds and IRLS stopped short of its fixed point
                # (the clean 60-image strip: 0.16 mm from Sim, whose robust cost is lower
                # there); converging every round instead cost Seneca's finish() 16.5 s.
                xk = xk + step
                Hp_x = H_p_times(xk)
                Je, Jp, r = f.evaluate(xk[e_idx], xk[p_idx], self._cam)
                step = np.zeros_like(xk)
            w_new = f.w0 * cauchy_weight(r, sigma, robust)
            if np.max(np.abs(w_new - wf) / f.w0) < weight_tol:
                break
            wf = w_new
            step = np.zeros_like(xk)  # new weights: the model is solved again
        if final:  # one tight pass at the settled weights
            budget = opts.relinearise_iterations
            xk = xk + step  # the loose pass's model minimum starts the tight one
            Hp_x = H_p_times(xk)
            Je, Jp, r = f.evaluate(xk[e_idx], xk[p_idx], self._cam)
            gauss_newton(0.0)
        # the window's information: L with the own rows' old blocks replaced by the new ones
        # (one sparse addition of their difference, exactly symmetric)
        H = (assembly.matrix(Je, Jp, wf) if assembly is not None else
             window_matrix(L + factor_information(Je, Jp, wf, f.img, cols, n, minus=J_old)))
        if not admissible(xk + step):  # the model's minimum is no camera: stay at xk
            step = np.zeros_like(xk)
        x_new = xk + step
        r_new = r - (np.einsum("kri,ki->kr", Je, step[e_idx])
                     + np.einsum("kri,ki->kr", Jp, step[p_idx]))  # rows as linearised
        prior_new = prior(x_new, H_p_times(x_new))
        ssr_new_factors = float(np.sum(wf[:, None] * r_new**2))
        self._ssr = max(self._ssr + ssr_new_factors - ssr_old_factors
                        + 2.0 * (prior_new - prior_old), 0.0)
        dx = x_new - x
        eop_keys = [k for k in w.keys if k[0] == "e"]
        ie = w.indices(eop_keys).reshape(-1, EOP_SIZE)
        self._drift_m = float(np.max(np.abs(dx[ie[:, :3]]), initial=0.0))
        self._drift_deg = float(np.degrees(np.max(np.abs(dx[ie[:, 3:]]), initial=0.0)))
        w.x = x_new
        self._rescues.extend(rescues)  # named once the re-linearisation is kept
        self.rescued.extend(self._point_ids[k[1]] for _, k in rescues)
        self._astray_tried = tried  # (a re-linearisation refused as singular tries again)
        w.L = H if w.L is not None else None
        if self._inverse:
            Q = np.linalg.inv(H.toarray() if scipy.sparse.issparse(H) else H)
            w.Q = 0.5 * (Q + Q.T)
        w.changed()
        if last_factor and all(a is b for a, b in zip(last_factor[0], (Je, Jp, wf),
                                                      strict=True)):
            w.adopt_factor(last_factor[1])  # the last step's factor is H's: not made twice
        f.relinearised_at(xk[e_idx], xk[p_idx], Je, Jp, r)
        f.w = wf
        self._factors.replace(f)
