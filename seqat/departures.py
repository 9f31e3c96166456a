"""Seq-R: the window cut, the departure of parameters and their re-opening.

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there). Leaving
parameters are marginalised out of the window's information with a Rauch-Tung-Striebel
record (smoothing); a departed GP observed again, or a departed image holding a pending ray
of a point being born, re-enters with its exact conditional given the window
(docs/algorithm.md, *Seq-R: the window*, *Re-opening departed parameters*).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
import scipy.sparse

from seqat.assembly import factor_information
from seqat.conditional import Conditional, Departure
from seqat.dense import add_square, square_take
from seqat.geometry import wrap_angle
from seqat.information import (
    InformationFactor,
    RankDeficiency,
    WindowMatrix,
    add_block,
    dense_block,
    nonzero_columns,
    padded,
    submatrix,
    window_matrix,
)
from seqat.precision import sigma_scale
from seqat.rows import gradient_from_factors
from seqat.types import EOP_SIZE, EopEstimate, FloatArray, PointEstimate
from seqat.update import spd_inverse
from seqat.window import (
    Key,
    blocks_of,
    correlations_from_block,
    first_over_threshold,
    key_offsets,
    key_size,
    keys_of,
)

#: Default window cap (images). A block on a weak GPS/INS (1.5 m, 2 deg; 3 and 6 strips of 34
#: images, 70 % side overlap) stays correlated over 0.8 from end to end: the window held
#: every image and the update grew with the flight (204 images: 13,900 parameters, p99
#: 0.90 s). Capped at 70 images the finished estimates are the same to 0.1 mm and p99 is
#: 0.34 s; under ~50 the strip before the new one leaves and re-opens image by image (p99
#: 0.39 s at 56). The paper strip (25), Seneca (70) and the rendered blocks (<= 70) are not
#: cut by it (docs/benchmarks.md, *A block on a weak GPS/INS*).
DEFAULT_MAX_WINDOW_IMAGES = 70
#: The departure records' gains kept for re-openings (:meth:`DepartureMixin._record_gain`)
#: take at most this many bytes (a record's gain is |F| x |blanket|: ~0.2-3 MB on a block).
GAIN_CACHE_BYTES = 64 * 2**20
#: finish() re-opens the departed keys through their records only when they are at most this
#: many parameters: they join the reduced system densely (their conditional prior couples
#: them), so the final re-linearisation costs O(size^3) per step (Seneca: 1281 parameters,
#: ~50 steps, 5-12 s); beyond it the RTS values stand (SequentialAT.final_reopen_skipped) ...
FINAL_REOPEN_MAX_PARAMS = 2000
#: ... unless every departed key comes back (none finalised or handed to a sink, all within
#: the re-opening age) on a flight of at most this many images: then the window's information
#: is rebuilt from the flight's rows, GPs eliminated one by one again, whatever the number of
#: parameters (:meth:`DepartureMixin._reopen_all`; the reduced system is the EOPs, dense).
FINAL_REBUILD_MAX_IMAGES = 500
#: Dormant factors (of departed keys) are pruned every this many images.
PRUNE_EVERY = 50
#: A GP stays in the Seq-R window only while this many window images (new one included) see it.
MIN_WINDOW_RAYS = 2
#: GPs that a marginal prior ties to each other (departures, re-openings) are kept in the
#: reduced system, which then costs O(r^3) per factorisation. Over this many of them, the
#: coupled GPs that no longer observe (no ray in the newest :data:`ACTIVE_IMAGES` window
#: images nor in the new one) leave the window, exactly marginalised (a later ray re-opens
#: them): a block's cross-strip re-openings tied 750 GPs into one dense clique (reduced
#: system 2600 parameters, updates of 1-3 s; docs/algorithm.md, *Seq-R: the window*).
MAX_COUPLED_GPS = 100
#: ... a GP observed in one of this many newest window images still observes.
ACTIVE_IMAGES = 2
#: A departure's conditional cofactor of up to this many parameters is formed dense (an image
#: and its points: a few hundred); a larger one stays factorised (seqat.conditional), whose
#: pieces cost a solve each instead of an index.
DENSE_CONDITIONAL_UP_TO = 600



def leaving_conditional(L_ff: WindowMatrix, L_fs: FloatArray, leave_keys: list[Key],
                        coupled: set[Key]) -> tuple[Conditional, FloatArray]:
    """``L_FF^-1`` (kept factorised: :class:`seqat.conditional.Conditional`) and the RTS
    gain's support columns ``-L_FF^-1 L_FS`` of the parameters leaving the window, by the
    window's own elimination: the leaving GPs not coupled to other GPs are eliminated per
    3 x 3 block (Schur), so a departure of many images and their points costs
    O(|F| r^2 + |F| 3 n_p r) (r: the leaving EOPs and coupled GPs) instead of the O(|F|^3)
    of a dense inverse and the O(|F|^2 |S|) of the gain's product. A leaving block the
    elimination refuses (a point with next to no information) takes the dense inverse,
    which names it if it is not positive definite. ``L_FF`` sparse (a large window's) stays
    sparse: forty images and their points leaving at once were ~4000 x 4000, and making that
    block dense cost 0.8 s of a 1 s update (Seneca with gaps)."""
    gp = np.array([a for k, a in zip(leave_keys, key_offsets(leave_keys), strict=True)
                   if k[0] == "p" and k not in coupled], dtype=np.int64)
    if gp.size:
        try:
            f = InformationFactor(L_ff, gp)  # only read
        except RankDeficiency:
            pass
        else:
            cond = Conditional(f.dense() if f.n <= DENSE_CONDITIONAL_UP_TO else f)
            return cond, cond.gain(L_fs)
    if scipy.sparse.issparse(L_ff):
        L_ff = L_ff.toarray()
    cond = Conditional(spd_inverse(L_ff, "information of the leaving parameters"))
    return cond, cond.gain(L_fs)


class DepartureMixin:
    """Window cut, departures, re-opening and smoothing of :class:`SequentialAT`."""

    def _prune_dormant(self, i: int) -> None:
        """Every :data:`PRUNE_EVERY` images: the dormant factors of keys that can no longer
        re-open (left more than the re-opening age ago, finalised) are dropped: memory stays
        bounded by the re-opening age (and the smoothing lag)."""
        if i % PRUNE_EVERY:
            return
        imgs, pts = self._dormant_keys()
        if imgs is None or pts is None:
            imgs = pts = np.zeros(0, dtype=np.int64)
        self._factors.prune_dormant(self._w, imgs, pts)

    def _dormant_keys(self) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
        """Departed images and GPs that may still re-enter the window with their exact
        conditional (departure records kept, within the re-opening age): their factors are
        kept for re-linearisation after a re-opening (O(departed keys): called every
        :data:`PRUNE_EVERY` images and by finish())."""
        if not self._records or not self._departed:
            return None, None
        now = len(self._image_ids) - 1
        age = self._reopen_age
        imgs = [k[1] for k, (t, _, _) in self._departed.items() if k[0] == "e" and now - t <= age]
        pts = [k[1] for k, (t, _, _) in self._departed.items() if k[0] == "p" and now - t <= age]
        return np.asarray(imgs, dtype=np.int64), np.asarray(pts, dtype=np.int64)

    def _reopen_departed(self) -> None:
        """finish(): every departed key that may still re-enter (:meth:`_dormant_keys`)
        re-enters the window with its exact conditional, so that the final re-linearisation
        takes its rows too: the nonlinear counterpart of the RTS pass, once per flight
        (docs/algorithm.md, *What the window costs in accuracy*). Their real-time values stay
        in :attr:`_frozen_eop` / :attr:`_frozen_gp` for ``solution(smoothed=False)``."""
        imgs, pts = self._dormant_keys()
        if imgs is None or pts is None or self._reopen_age == 0:
            return
        keys: list[Key] = [("e", int(j)) for j in sorted(imgs)] + [("p", int(p))
                                                                   for p in sorted(pts)]
        keys = [k for k in keys if k in self._departed]
        size = sum(key_size(k) for k in keys)
        if (keys and not self._inverse and len(keys) == len(self._departed)
                and not self._final_eop
                and not self._final_gp and not self._sunk
                and len(self._image_ids) <= FINAL_REBUILD_MAX_IMAGES):
            self._final_reopened.update(keys)
            self._reopen_all(keys)
            return
        if not keys or size > FINAL_REOPEN_MAX_PARAMS:
            self.final_reopen_skipped = size if keys else 0
            return
        self._final_reopened.update(keys)
        self._reopen(keys)
        self._w.settle()

    def _reopen_all(self, keys: list[Key]) -> None:
        """finish() when every departed key re-enters: the window's information is rebuilt
        from the flight's rows (image points at their linearisation, GPS/INS, the camera's
        prior, ground control), the same information the departures' conditional priors
        restore but with its sparsity: GPs couple only through the images that see them and
        are eliminated one by one again, where the conditional priors, composed and inverted
        densely, tie every re-opened GP to the others (Seneca without 11 of its images: 3840
        parameters in the reduced system, the re-opening skipped and Seq-R 0.5 m / 0.3 deg
        from Sim; rebuilt: 3-4 mm / 0.004 deg). The keys start at their RTS-smoothed values;
        one solve takes the window to the minimum of the rebuilt model, which the final
        re-linearisation then continues from (docs/algorithm.md, *What the window costs in
        accuracy*)."""
        w = self._w
        smoothed = self._smoothed_departed()
        for key in keys:
            self._departed.pop(key)
        self._rejoin(keys, np.concatenate([smoothed[k] for k in keys]))
        n = w.x.size
        # the linear rows: GPS/INS of every image, the camera's prior, ground control
        diag, g = np.zeros(n), np.zeros(n)
        for key in w.keys:
            idx = w.index(key)
            if key[0] == "e" and key[1] in self._nav_rows:
                row = self._nav_rows[key[1]]
                r = row[:EOP_SIZE] - w.x[idx]
                r[3:] = wrap_angle(r[3:])
                wt = row[12:] / row[EOP_SIZE:12] ** 2
            elif key[0] == "p" and self.control and self._point_ids[key[1]] in self.control:
                cp = self.control[self._point_ids[key[1]]]
                r, wt = cp.xyz_m - self._origin - w.x[idx], cp.weight
            elif key == self._cam_key and self.options.calibration is not None:
                sigma = self.options.calibration.prior_sigma(self.camera)[self._cam.index]
                r = self.camera.intrinsics[self._cam.index] - w.x[idx]
                wt = 1.0 / sigma**2
            else:
                continue
            wt = np.where(np.isfinite(wt), wt, 0.0)
            diag[idx] += wt
            g[idx] += wt * r
        L = scipy.sparse.diags_array(diag).tocsr()
        ssr = float(g @ (g / np.where(diag > 0, diag, 1.0)))  # sum of w r^2 of those rows
        f = self._factors.in_window(w)
        if f is not None:
            e_idx, p_idx = f.columns(w)
            cols = np.concatenate([e_idx, p_idx], axis=1)
            r = f.r_lin - (np.einsum("kri,ki->kr", f.Je, w.x[e_idx] - f.e_lin)
                           + np.einsum("kri,ki->kr", f.Jp, w.x[p_idx] - f.p_lin))
            L = L + factor_information(f.Je, f.Jp, f.w, f.img, cols, n)
            g += gradient_from_factors(f.Je, f.Jp, r, f.w, cols, n)
            ssr += float(np.sum(f.w[:, None] * r**2))
        w.L = window_matrix(L)
        w.coupled = set()
        w.changed()
        g_key = {k: g[w.index(k)] for k in w.keys}
        w.settle()  # GPs the rows do not determine leave (on_singular)
        b = np.zeros(w.x.size)
        for k in w.keys:
            b[w.index(k)] = g_key[k]
        dx = w.q_apply(np.arange(b.size), b)
        w.x = w.x + dx
        self._ssr = max(ssr - float(b @ dx), 0.0)

    def _smoothed_departed(self) -> dict[Key, FloatArray]:
        """RTS backward pass over the departures, newest first: O(sum |F| |W|).

        A GP rescued after a record was made (:meth:`_rescue_points`: re-intersected from
        its good rays, a jump of up to 100 m after wandering astray) has not changed by a
        linear update of the record's estimate: the record sees no change of it. Passed
        through the gain, the jump moved the images that had left (a simulated block at 20 %
        blunders: one image 4.3 m off instead of 0.7 m; taking out the jump alone, not the
        wandering before it, left images 30-95 m off)."""
        w = self._w
        value: dict[Key, FloatArray] = dict(self._dropped_value)
        value.update({k: w.x[w.index(k)] for k in w.keys})
        last_rescue: dict[Key, int] = {}  # records made before a GP's last rescue
        for n_records, key in self._rescues:
            last_rescue[key] = max(last_rescue.get(key, 0), n_records)
        for r in range(len(self._departures) - 1, self._first_record - 1, -1):
            dep = self._departures[r]
            if dep is None:
                continue
            if not dep.staying:  # F was tied to nothing that stayed (no ties): its own value
                x_w = np.zeros(0)
            elif any(last_rescue.get(k, 0) > r for k in dep.staying):
                x_w = np.concatenate([value[k] if last_rescue.get(k, 0) <= r else
                                      dep.x_staying[o : o + key_size(k)]
                                      for k, o in zip(dep.staying, key_offsets(dep.staying),
                                                      strict=True)])
            else:
                x_w = np.concatenate([value[k] for k in dep.staying])
            x_f = dep.x_leaving + dep.rts_gain() @ (x_w - dep.x_staying)
            off = 0
            for k in dep.leaving:
                size = key_size(k)
                # a key that re-entered the window left again later (or is in it): the
                # newer departure, processed first, already holds its final value
                value.setdefault(k, x_f[off : off + size])
                off += size
        return value

    def set_correlation_threshold(self, threshold: float) -> None:
        """Seq-R: the window threshold of the next updates (the latency budget tightens it,
        seed 000: "select the threshold for the speed requirement"). Seq-F stays Seq-F."""
        if self.options.correlation_threshold is None:
            raise ValueError("Seq-F (correlation_threshold None) has no window to cut")
        self.options = dataclasses.replace(self.options, correlation_threshold=threshold)

    def set_max_window_images(self, cap: int | None) -> None:
        """Seq-R: the window's largest number of images from the next update on (None: no
        cap; the latency budget's second dial). Checked as the option is (ConfigError)."""
        self.options = dataclasses.replace(self.options, max_window_images=cap)

    def _select_window(self, frame_points: set[int]) -> int:
        """Seq-R: cut the window before the update; returns the number of images dropped."""
        thr = self.options.correlation_threshold
        if thr is None or len(self._window_images) < 2:
            return 0
        w = self._w
        w.settle()  # an undetermined GP leaves now, before the offsets are read
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
        # Self-calibration: the camera, shared by every image and never leaving, correlates
        # all EOPs with each other; the rule reads the correlations given the camera (what
        # the tie structure couples), else the window would never be cut.
        given_camera = None
        if self._cam_key is not None:
            cam = w.index(self._cam_key)
            q_cam = w.q_columns(cam)
            gain = np.linalg.solve(q_cam[cam], q_cam.T).T  # Q[:, c] Q_cc^-1
            given_camera = (gain, q_cam)
            given = diag - np.einsum("nc,nc->n", gain, q_cam)
            given[cam] = diag[cam]  # the camera's own (0 given itself) are not read
            diag = given
        rho = np.zeros(len(offs))
        eidx = (offs[:, None] + np.arange(EOP_SIZE)).ravel()  # the window's EOP parameters
        sd_e = np.sqrt(diag[eidx])
        for r in range(len(offs) - 1, -1, -1):
            ref = eidx[EOP_SIZE * r : EOP_SIZE * (r + 1)]
            block = w.q_entries(eidx, ref)  # Q[EOPs, reference]: no column of a GP
            if given_camera is not None:
                gain, q_cam = given_camera
                block = block - gain[eidx] @ q_cam[ref].T
            rho_r = correlations_from_block(block, sd_e, r)
            rho = np.maximum(rho, rho_r)
            rho_r[r] = 0.0
            if np.any(rho_r >= thr):
                break
        start = first_over_threshold(rho, thr)
        cap = self.options.max_window_images
        if cap is not None:  # the new image joins: cap - 1 stay
            start = max(start, len(offs) + 1 - cap)
        start = self._hold_pending_rays(start, frame_points)
        quiet = self._quiet_coupled(frame_points)
        if start == 0 and not quiet:
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
                quiet.add(p)
        for p in quiet:
            leaving.add(("p", p))
            idx = w.index(("p", p))
            self._frozen_gp[p] = (w.x[idx].copy(), sd[idx])
            del self._gp_count[p]
        self._depart(leaving, now)
        return start

    def _quiet_coupled(self, frame_points: set[int]) -> set[int]:
        """Over :data:`MAX_COUPLED_GPS` coupled GPs: those that no longer observe (they leave
        with this cut); else none. The rule of the paper keeps a GP while two window images
        see it, but a coupled one costs the reduced system three rows and columns, dense.
        Without departure records (no smoothing) or re-opening, a GP that left is not
        brought back exactly: none leaves early then."""
        w = self._w
        # only where a later ray re-opens them exactly (departure records kept)
        if len(w.coupled) <= MAX_COUPLED_GPS or not self._records or self._reopen_age == 0:
            return set()
        active = set(frame_points).union(
            *(self._img_points.get(j, ()) for j in list(self._window_images)[-ACTIVE_IMAGES:]))
        return {k[1] for k in w.coupled
                if k[0] == "p" and k[1] not in active and k[1] in self._gp_count}

    def _depart(self, leaving: set[Key], now: int) -> None:
        """Marginalise ``leaving`` out of the window, keeping its RTS record (smoothing)."""
        w = self._w
        keep_keys = [k for k in w.keys if k not in leaving]
        leave_keys = [k for k in w.keys if k in leaving]
        leave = w.indices(leave_keys)
        stays = np.ones(w.x.size, dtype=bool)
        stays[leave] = False
        keep = np.flatnonzero(stays)  # = w.indices(keep_keys): the layout keeps the order
        off = 0
        # each key's own marginal block (the RTS record holds the joint conditional)
        for k, frozen in zip(leave_keys, w.q_key_blocks(leave_keys), strict=True):
            self._frozen_cof[k] = frozen
            self._departed[k] = (now, len(self._departures), off)
            off += frozen.shape[0]
        if w.L is not None:
            # E[x_F | x_W] = x_F - L_FF^-1 L_FW (x_W - x_W0): the RTS gain from the information
            # matrix; marginalising F out of L is its Schur complement, which changes only
            # the block of F's neighbours (the support of L_FW: F's Markov blanket).
            if scipy.sparse.issparse(w.L):
                support = nonzero_columns(submatrix(w.L, leave, keep))
                L_fs = dense_block(w.L, leave, keep[support])
                L_ff = submatrix(w.L, leave, leave)
            else:  # one gather of the leaving rows (dense window)
                rows_f = w.L.take(leave, axis=0)
                L_fw = rows_f[:, keep]
                support = np.flatnonzero(np.any(L_fw != 0.0, axis=0))
                L_fs, L_ff = L_fw[:, support], rows_f[:, leave]
            cond, gain_s = leaving_conditional(L_ff, L_fs, leave_keys, w.coupled)
            fill = L_fs.T @ gain_s
            fill = 0.5 * (fill + fill.T)
            if scipy.sparse.issparse(w.L):
                L = window_matrix(add_block(submatrix(w.L, keep, keep), support, fill))
            else:
                L = square_take(w.L, keep)
                add_square(L, support, fill)
                L = window_matrix(L)
            # GPs the marginal prior now ties to other GPs are no longer eliminable alone;
            # the record's W is that blanket too: the gain is zero on every other key (a
            # block's departure of 40 images: 723 of 1935 kept columns, a dense gain on all
            # of them cost 0.1 s and 56 MB)
            blanket, cols = blocks_of(keep_keys, support)
            w.couple(blanket)
            w.L = L
        if w.L is not None and self._records:  # J is formed from L_FS on request
            self._departures.append(
                Departure(leaving=tuple(leave_keys), staying=tuple(blanket),
                          x_leaving=w.x[leave], x_staying=w.x[keep[cols]], conditional=cond,
                          at=now, coupling=scipy.sparse.csr_array(L_fs),
                          coupling_cols=np.searchsorted(cols, support),
                          gain_width=int(cols.size)))
        w.coupled -= leaving
        w.marginalise(keep_keys, keep, w.L)

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

    def _reopenable(self, key: Key, i: int) -> bool:
        left = self._departed.get(key)
        age = self._reopen_age
        return left is not None and age > 0 and i - left[0] <= age  # 0: never

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
        self._retire_nav_rows(k[1] for k in old if k[0] == "e")
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
            self._gains.pop(r, None)
            r += 1
        self._first_record = r
        # rescues that only records now finalised were made before (flat memory)
        self._rescues = [(n, k) for n, k in self._rescues if n > r]
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

    def _kept_rays(self, j: int) -> list[int]:
        """Points of which departed image ``j`` still holds a pending ray (kept in
        :attr:`_departed_rays`): a re-opened image takes them back, so that they leave with
        it again (and are forgotten in time) instead of staying pending untracked."""
        out: list[int] = []
        for jj, points in self._departed_rays:
            if jj == j:
                out += [p for p in points if p in self._pending and p not in out
                        and any(r[0] == j for r in self._pending[p])]
        return out

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
        sizes = [key_size(k) for k in keys]
        m = sum(sizes)
        if w.L is None or not self._records:
            # no departure records (smoothing off): frozen value and cofactor, uncorrelated
            J = np.zeros((m, n))
            mean = np.concatenate([self._frozen_value(k) for k in keys])
            C = scipy.linalg.block_diag(*(self._frozen_cof[k] for k in keys))
            for key in keys:
                self._departed.pop(key, None)
        else:
            mean, J, C = self._conditional_prior(keys, sizes)
            self._split_records(keys)
        C = 0.5 * (C + C.T)
        if self._inverse:
            QJt = w.Q @ J.T
            Q = np.empty((n + m, n + m))
            Q[:n, :n] = w.Q
            Q[:n, n:] = QJt
            Q[n:, :n] = QJt.T
            Q[n:, n:] = J @ QJt + C
            w.Q = Q
        base = w.current_solver()  # answers for the window before: Q' from it and the prior
        support = np.flatnonzero(np.any(J != 0.0, axis=0))  # the window keys J refers to
        if w.L is not None:
            # the prior ties the re-opened keys to the window keys its chain refers to
            w.couple(keys_of(w.keys, support) + keys)
            Ci = spd_inverse(C, "conditional cofactor of the re-opened parameters")
            # [[L + J^T Ci J, -J^T Ci], [-Ci J, Ci]] on the support of J and the new keys
            cols = np.concatenate([support, n + np.arange(m)])
            Js = np.hstack([-J[:, support], np.eye(m)])  # x_new - J x_W, on cols
            M = Js.T @ Ci @ Js
            w.L = window_matrix(add_block(padded(w.L, n + m), cols, 0.5 * (M + M.T)))
        self._rejoin(keys, mean)
        w.augment(base, J, C, support)

    def _rejoin(self, keys: list[Key], values: FloatArray) -> None:
        """Re-opened ``keys`` (left :attr:`_departed`) join the window's bookkeeping and
        layout at ``values``, after ``L`` (or ``Q``) took them."""
        w = self._w
        for key in keys:
            if key[0] == "e":
                j = key[1]
                # its kept pending rays are window rays again (born now or later)
                self._img_points[j] = self._kept_rays(j)
                pos = sum(1 for jj in self._window_images if jj < j)
                self._window_images.insert(pos, j)
            else:
                self._gp_count[key[1]] = 0
        w.x = np.concatenate([w.x, values])
        w.relayout(w.keys + keys)
        self._factors.wake(w)  # their rows, kept dormant, are window rows again
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
        # the form's coefficients by rows, one per parameter referred to (a transposed
        # layout: the chain gathers and adds whole columns of the form, here rows)
        buf = np.zeros((8 * m + 64, m))
        ncol = 0

        def column(key: Key) -> int:
            nonlocal buf, ncol
            c = col_of.get(key)
            if c is None:
                size = key_size(key)
                if ncol + size > buf.shape[0]:
                    buf = np.concatenate([buf, np.zeros_like(buf)], axis=0)
                c = col_of[key] = ncol
                ncol += size
            return c

        pending: dict[int, list[Key]] = {}
        row = 0
        for key, size in zip(keys, sizes, strict=True):
            c = column(key)
            buf[c : c + size, row : row + size] = np.eye(size)
            pending.setdefault(self._departed[key][1], []).append(key)
            row += size
        const = np.zeros(m)
        C = np.zeros((m, m))
        while pending:
            rec = min(pending)
            members = pending.pop(rec)
            dep = self._departures[rec]
            src = np.concatenate([self._departed[k][2] + np.arange(key_size(k))
                                  for k in members])
            cols = np.concatenate([col_of[k] + np.arange(key_size(k))
                                   for k in members])
            JK = buf[cols].T  # (m, |src|): a gather, a copy
            buf[cols] = 0.0
            G = self._record_gain(rec, dep)[src]
            const += JK @ (dep.x_leaving[src] - G @ dep.x_staying)
            C += dep.conditional.quadratic(src, JK)
            JG = G.T @ JK.T  # (JK G)^T, by rows
            # the staying keys' rows of buf (new ones appended): a key with one already
            # is queued, in the window or dropped; a departed new one is queued now
            for sk in [sk for sk in dep.staying if sk not in col_of]:
                column(sk)
                if sk not in w.offset and sk not in self._dropped_value:
                    later = self._departed[sk][1]
                    assert later > rec, "a departure record refers to an older one"
                    pending.setdefault(later, []).append(sk)
            sizes = dep.staying_sizes
            starts = np.fromiter((col_of[sk] for sk in dep.staying), np.int64, sizes.size)
            # key by key, the gain's columns are consecutive, as are their rows of buf
            ucols = np.arange(JG.shape[0]) + np.repeat(starts - (np.cumsum(sizes) - sizes),
                                                       sizes)
            buf[ucols] += JG
        n = w.x.size
        J = np.zeros((m, n))
        for key, c in col_of.items():
            if key in w.offset:
                idx = w.index(key)
                J[:, idx] = buf[c : c + idx.size].T
            elif key in self._dropped_value:  # taken out as undetermined: a constant
                val = self._dropped_value[key]
                const += val @ buf[c : c + val.size]
        mean = const + J @ w.x
        return mean, J, C

    def _record_gain(self, rec: int, dep: Departure) -> FloatArray:
        """Record ``rec``'s RTS gain as it stands (:meth:`Departure.rts_gain`: its departure
        gain with every split since applied), kept for the next re-openings while the kept
        ones stay under :data:`GAIN_CACHE_BYTES` (the least recently used leave first).

        Successive re-openings on a block walk the same chain of records (the previous
        strip's), each forming the same departure gain by a solve with one column per
        parameter of its blanket: ~12 records per re-opening, 1011 solves and 1.26 s of a
        204-image flight's updates, 106 solves with the gains kept (docs/benchmarks.md,
        *Compiled point kernels*). Each split is applied once, to every row, when a
        re-opening first reads the record after it, not again through every split at each
        reading (a record split nine times took 5 ms per reading on a block's returning
        strip). The departure gain is kept beside it: a second start's trial can leave
        splits that the estimator's state no longer has (the splits applied are compared by
        identity)."""
        gains = self._gains
        kept = gains.pop(rec, None)
        if kept is None:
            G0 = dep.departure_gain()
            G0.setflags(write=False)  # shared by the re-openings to come: read only
            kept = (G0, G0, ())
        G0, G, done = kept
        if len(done) > len(dep.splits) or any(a is not b for a, b
                                              in zip(done, dep.splits, strict=False)):
            G, done = G0, ()
        if len(done) < len(dep.splits):
            G = dep.split(G, len(done))
            G.setflags(write=False)
            done = dep.splits
        gains[rec] = (G0, G, done)  # the most recent last

        def nbytes(kept: tuple[FloatArray, FloatArray, tuple]) -> int:
            return kept[0].nbytes + (kept[1].nbytes if kept[1] is not kept[0] else 0)

        total = sum(nbytes(k) for k in gains.values())
        while total > GAIN_CACHE_BYTES and len(gains) > 1:
            total -= nbytes(gains.pop(next(iter(gains))))
        return G

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
            sizes = {k: key_size(k) for k in dep.leaving}
            starts = dict(zip(dep.leaving, key_offsets(dep.leaving), strict=True))
            chosen = set(reopened)
            rest = [k for k in dep.leaving if k not in chosen]
            r_idx = np.concatenate([starts[k] + np.arange(sizes[k]) for k in reopened])
            m_idx = (np.concatenate([starts[k] + np.arange(sizes[k]) for k in rest])
                     if rest else np.zeros(0, dtype=np.int64))
            C = dep.conditional
            C_rm = C.entries(r_idx, m_idx)
            K = np.linalg.solve(C.block(r_idx), C_rm).T
            self._departures[rec] = dataclasses.replace(
                dep,
                leaving=tuple(rest),
                staying=dep.staying + tuple(reopened),
                x_leaving=dep.x_leaving[m_idx],
                x_staying=np.concatenate([dep.x_staying, dep.x_leaving[r_idx]]),
                conditional=C.restricted(m_idx, K, C_rm),
                splits=dep.splits + ((m_idx, K, r_idx),),
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
