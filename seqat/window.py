"""Seq-R window selection by correlation (seed 000 §2.3, Fig. 2), and the window itself.

The correlation between two images is the largest absolute correlation coefficient in the
6x6 block of their EOPs taken from the cofactor matrix the sequential update already holds.
Images are scanned from the oldest; the first one whose correlation with the *last* image
reaches the threshold starts the window, and every later image stays in it ("first over
threshold"), whatever its own correlation.

:class:`Window` holds the window's estimates and its information (or, for the paper's engine,
cofactor) matrix with their block layout (docs/algorithm.md, *Engines*).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from seqat.errors import EstimationError
from seqat.factor_views import AugmentedFactor, MarginalFactor, SolverLike
from seqat.information import InformationFactor, RankDeficiency, WindowMatrix, submatrix
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray

#: Parameter key: (kind, index) with kind "e" (EOP of image index), "p" (GP index) or "c"
#: (the camera's free interior parameters, self-calibration; its index is their number).
Key = tuple[str, int]
#: The camera's key kind (one block per camera, never leaves the window).
CAMERA = "c"


#: Block size of the fixed-size key kinds; a camera key's index is its size.
_SIZES = {"e": EOP_SIZE, "p": GP_SIZE}


def key_size(key: Key) -> int:
    """Number of parameters of a key's block."""
    return _SIZES.get(key[0], key[1])


def key_offsets(keys: Sequence[Key]) -> list[int]:
    """Offset of each key's block in the keys' stacked values."""
    return [0, *np.cumsum([key_size(k) for k in keys])[:-1].tolist()]


def eop_correlations(Q: FloatArray, eop_offsets: np.ndarray, last_offset: int) -> FloatArray:
    """Max |rho| of each image's EOP block against the last image's EOP block.

    Parameters
    ----------
    Q : (n, n) float
        Cofactor of the window parameters.
    eop_offsets : (W,) int
        Offset in ``Q`` of the EOP block of each window image, oldest first.
    last_offset : int
        Offset of the last image's EOP block.

    Returns
    -------
    (W,) float
        In ``[0, 1]``; the last image's own value is 1.
    """
    last = last_offset + np.arange(EOP_SIZE)
    return correlations_from_columns(Q[:, last], np.diagonal(Q), eop_offsets, last_offset)


def correlations_from_columns(q_last: FloatArray, q_diag: FloatArray, eop_offsets: np.ndarray,
                              last_offset: int) -> FloatArray:
    """:func:`eop_correlations` from the last image's cofactor columns ``Q[:, last]`` (n, 6)
    and the diagonal of ``Q``: what a factorised engine recovers without forming ``Q``."""
    idx = (eop_offsets[:, None] + np.arange(EOP_SIZE)).ravel()
    ref = int(np.flatnonzero(eop_offsets == last_offset)[0])
    return correlations_from_block(q_last[idx], np.sqrt(q_diag[idx]), ref)


def correlations_from_block(q_eop: FloatArray, sd_eop: FloatArray, ref: int) -> FloatArray:
    """Max |rho| of each window image's EOP block against image ``ref``'s, from
    ``Q[EOPs, EOPs of ref]`` (6 W, 6) and the EOPs' standard deviations (6 W,), images in
    window order."""
    sd_ref = sd_eop[EOP_SIZE * ref : EOP_SIZE * (ref + 1)]
    rho = q_eop / (sd_eop[:, None] * sd_ref[None, :])
    return np.minimum(np.max(np.abs(rho).reshape(-1, EOP_SIZE * EOP_SIZE), axis=1), 1.0)


def first_over_threshold(correlations: FloatArray, threshold: float) -> int:
    """Index of the first image (oldest first) whose correlation reaches ``threshold``.

    The last image always qualifies (its correlation with itself is 1), so the result is in
    ``[0, W-1]``.
    """
    over = np.flatnonzero(correlations >= threshold)
    return int(over[0]) if over.size else len(correlations) - 1


def keys_of(keys: list[Key], indices: np.ndarray) -> list[Key]:
    """The keys holding the parameter ``indices``, each once, in layout order, for ``keys``
    laid out in that order."""
    return blocks_of(keys, indices)[0]


def blocks_of(keys: list[Key], indices: np.ndarray) -> tuple[list[Key], np.ndarray]:
    """:func:`keys_of` and every parameter of those keys (their indices, ascending)."""
    table = _SIZES
    sizes = np.fromiter((table.get(k[0], k[1]) for k in keys), dtype=np.int64,
                        count=len(keys))
    starts = np.cumsum(sizes) - sizes
    blocks = np.unique(np.searchsorted(starts, indices, side="right") - 1)
    first, size = starts[blocks], sizes[blocks]
    cols = np.repeat(first - (np.cumsum(size) - size), size) + np.arange(size.sum())
    return [keys[b] for b in blocks.tolist()], cols


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
    L: WindowMatrix | None = None  # dense when small, else sparse (information.window_matrix)
    keys: list[Key] = field(default_factory=list)
    offset: dict[Key, int] = field(default_factory=dict)
    inverse: bool = False
    coupled: set[Key] = field(default_factory=set)
    _Q: FloatArray | None = None
    _factor: InformationFactor | None = None
    #: Right after a departure or a re-opening: a view of the factorisation the window had
    #: before (:meth:`marginalise`, :meth:`augment`), answering for ``Q`` until ``L``
    #: changes again.
    _marginal: MarginalFactor | AugmentedFactor | None = None
    _diag: FloatArray | None = None
    _lookup: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
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
        self._marginal = None
        self._diag = None
        if not self.inverse:
            self._Q = None

    def factor(self) -> InformationFactor:
        """Factorisation of ``L`` (information engine), cached until :meth:`changed`."""
        assert self.L is not None
        while self._factor is None:
            gp, kept = self.elimination()
            try:
                self._factor = InformationFactor(self.L, gp, kept)
            except RankDeficiency as err:
                keys = self.keys_at(err.gp_blocks)
                if not keys or self.on_singular is None:
                    raise
                self.on_singular(keys)  # removes them: the loop factorises the rest
        return self._factor

    def adopt_factor(self, factor: InformationFactor) -> None:
        """Take ``factor`` as the factorisation of the current ``L`` (its caller made it
        from the same information and the window's :meth:`elimination`)."""
        assert factor.n == self.x.size
        self._factor = factor
        self._diag = None

    def settle(self) -> None:
        """Information engine: factorise now, so that GPs the data do not determine leave
        (:attr:`on_singular`) before offsets are read; no-op for the inverse engine and right
        after a departure or a re-opening (the marginal of a factorised, positive definite
        ``L`` is positive definite, as is ``L`` with a positive definite prior of new
        parameters: :meth:`marginalise`, :meth:`augment`)."""
        if not self.inverse and self.L is not None and self._marginal is None:
            self.factor()

    def _solver(self) -> SolverLike:
        """What answers for ``Q`` (information engine): :meth:`current_solver` (the
        factorisation of ``L``, or right after a departure or a re-opening a view of the
        one before), else a factorisation of ``L`` now."""
        return self.current_solver() or self.factor()

    def marginalise(self, keep_keys: list[Key], keep: np.ndarray, L: WindowMatrix | None) -> None:
        """The window after parameters left: ``keep_keys`` stay (window indices ``keep``),
        ``L`` is the Schur complement of the leaving ones (the caller forms it).

        Marginalising is deleting rows and columns of ``Q``: ``Q' = Q[keep, keep]``. Until
        ``L`` changes again (the next update adds its rows), the cofactor blocks the update
        needs come from the factorisation of the ``L`` before the departure
        (:class:`seqat.factor_views.MarginalFactor`): a departure costs no factorisation."""
        base = None if self.inverse else self.current_solver()
        if self.inverse:
            self._Q = self.Q[np.ix_(keep, keep)]
        self.L = L
        self.x = self.x[keep]
        self.relayout(keep_keys)
        if base is not None:
            self._marginal = MarginalFactor.of(base, keep)

    def augment(self, base: SolverLike | None, J: FloatArray, C: FloatArray,
                support: np.ndarray | None = None) -> None:
        """Departed parameters re-opened at the end of the layout with the prior
        ``x_R = mean + J x_W + e``, ``e ~ (0, C)``, after ``L`` took that prior and the layout
        the keys: until ``L`` changes again the cofactor blocks come from ``base``, what
        answered for the window before (:class:`seqat.factor_views.AugmentedFactor`): a
        re-opening costs no factorisation. No-op without one (the inverse engine, or no
        factorisation at hand: the next request factorises). ``support``: ``J``'s non-zero
        columns, when the caller has them."""
        if not self.inverse and base is not None:
            self._marginal = AugmentedFactor(base, J, C, support)

    def current_solver(self) -> SolverLike | None:
        """What answers for ``Q`` now without factorising (None: nothing at hand)."""
        return self._factor or self._marginal

    def couple(self, keys: list[Key]) -> None:
        """A prior now ties ``keys`` together: if two or more are GPs, those are no longer
        eliminable one by one."""
        gps = {k for k in keys if k[0] == "p"}
        if len(gps) > 1:
            self.coupled |= gps

    def elimination(self) -> tuple[np.ndarray, np.ndarray]:
        """Offsets of the GP blocks the factorisation eliminates, and of the coupled ones it
        keeps with the EOPs."""
        gp = np.fromiter((self.offset[k] for k in self.keys
                          if k[0] == "p" and k not in self.coupled), dtype=np.int64)
        return gp, np.fromiter((self.offset[k] for k in self.coupled), dtype=np.int64)

    def ids(self, kind: str) -> np.ndarray:
        """Indices of the window's images (``kind`` "e") or GPs ("p"), in window order."""
        return np.fromiter((k[1] for k in self.keys if k[0] == kind), dtype=np.int64)

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
            self.L = submatrix(self.L, keep, keep)
        if self.inverse:
            self._Q = self.Q[np.ix_(keep, keep)]
        self.x = self.x[keep]
        self.coupled -= gone
        self.relayout(keep_keys)

    def q_columns(self, idx: np.ndarray) -> FloatArray:
        """``Q[:, idx]``."""
        if self.inverse:
            return self.Q[:, idx]
        return self._solver().columns(idx)

    def q_diagonal(self) -> FloatArray:
        """``diag(Q)``: every marginal variance (cofactor units)."""
        if self._diag is None:
            d = np.diagonal(self.Q).copy() if self.inverse else self.factor().diagonal()
            if d.size and not np.all(d > 0):
                bad = keys_of(self.keys, np.flatnonzero(~(d > 0))[:3])
                raise EstimationError(f"the window's cofactor has non-positive variances "
                                      f"(parameters {bad})")
            self._diag = d
        return self._diag

    def warm_diagonal(self) -> None:
        """Form :meth:`q_diagonal` now if the factorisation of ``L`` is at hand (never
        factorise here: a factorisation can take GPs out, which is the next update's)."""
        if not self.inverse and self._factor is not None:
            self.q_diagonal()

    def q_apply(self, idx: np.ndarray, v: FloatArray) -> FloatArray:
        """``Q[:, idx] @ v``, (n,): one solve, not ``len(idx)`` columns."""
        if self.inverse:
            return self.Q[:, idx] @ v
        b = np.zeros(self.x.size)
        np.add.at(b, idx, v)
        return self._solver().solve(b)

    def q_block(self, idx: np.ndarray) -> FloatArray:
        """``Q[idx, idx]``."""
        if self.inverse:
            return self.Q[np.ix_(idx, idx)].copy()
        return self._solver().block(idx)

    def q_key_blocks(self, keys: list[Key]) -> list[FloatArray]:
        """``Q[k, k]`` of each key, without the blocks between them."""
        if not keys:
            return []
        idx = self.indices(keys)
        if self.inverse:
            out, off = [], 0
            for k in keys:
                m = key_size(k)
                sub = idx[off:off + m]
                out.append(self.Q[np.ix_(sub, sub)].copy())
                off += m
            return out
        sizes = np.array([key_size(k) for k in keys], dtype=np.int64)
        return self._solver().diagonal_blocks(idx, sizes)

    def q_entries(self, rows: np.ndarray, cols: np.ndarray) -> FloatArray:
        """``Q[rows, cols]`` (outer): EOP rows and columns come from the reduced system
        alone (``Q_RR = S^-1``), no back-substitution of the eliminated GPs
        (:meth:`seqat.information.InformationFactor.entries`)."""
        if self.inverse:
            return self.Q[np.ix_(rows, cols)]
        return self._solver().entries(rows, cols)

    def relayout(self, keys: list[Key]) -> None:
        self.changed()
        self.keys = keys
        self.offset = offset = {}
        off = 0
        for k in keys:
            offset[k] = off
            kind = k[0]
            off += EOP_SIZE if kind == "e" else GP_SIZE if kind == "p" else k[1]
        self._lookup = {}

    def offsets_of(self, kind: str, ids: np.ndarray) -> np.ndarray:
        """Window offset of the block of each image (``kind`` "e") or GP ("p") index in
        ``ids``; -1 for those not in the window (vectorised: O(len(ids) log window))."""
        if not self._lookup:  # both kinds in one pass over the layout
            flat: dict[str, list[int]] = {"e": [], "p": []}
            for k, off in self.offset.items():
                pairs = flat.get(k[0])
                if pairs is not None:
                    pairs += (k[1], off)
            for name, pairs in flat.items():
                a = np.array(pairs, dtype=np.int64).reshape(-1, 2)
                a = a[a[:, 0].argsort(kind="stable")]
                self._lookup[name] = (a[:, 0], a[:, 1])
        sorted_ids, offs = self._lookup[kind]
        ids = np.asarray(ids, dtype=np.int64)
        if sorted_ids.size == 0:
            return np.full(ids.shape, -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(sorted_ids, ids), sorted_ids.size - 1)
        return np.where(sorted_ids[pos] == ids, offs[pos], -1)

    def index(self, key: Key) -> np.ndarray:
        off = self.offset[key]
        return np.arange(off, off + (key_size(key)))

    def indices(self, keys: list[Key]) -> np.ndarray:
        """Parameter indices of several blocks, concatenated in the order of ``keys``."""
        if not keys:
            return np.zeros(0, dtype=np.int64)
        offs = np.fromiter(map(self.offset.__getitem__, keys), dtype=np.int64, count=len(keys))
        table = _SIZES
        sizes = np.fromiter((table.get(k[0], k[1]) for k in keys), dtype=np.int64,
                            count=len(keys))
        starts = np.cumsum(sizes) - sizes
        return np.repeat(offs - starts, sizes) + np.arange(int(sizes.sum()))
