"""Latency budget: the per-image work follows the speed requirement.

The paper selects the correlation threshold "for the speed requirement" (seed 000 §2.3): a
higher threshold cuts the window shorter, and an update costs less. :class:`LatencyBudget`
does it on line, after each image of the sequential stage, with three dials:

* the **Seq-R threshold** (the update's cost): over the budget, the next images use
  ``threshold × TIGHTEN_FACTOR`` (up to ``max_threshold``);
* the **tracker's feature count** (image flights: detection and matching cost): when the
  image's reading and tracking alone took more than :data:`TRACKING_SHARE` of the budget,
  the next images detect ``features × FEATURE_FACTOR`` (down to :data:`MIN_FEATURES`). A
  window cut shorter cannot make tracking cheaper (docs/benchmarks.md, *Watch mode at the
  real frame rate*);
* the **window cap** (Seq-R ``max_window_images``): when the update is over its share with
  the threshold already at ``max_threshold``, the window keeps at most
  ``window × WINDOW_FACTOR`` images (down to :data:`MIN_WINDOW_CAP`). On blocks the image of
  the previous strip under the new one correlates over any threshold, and the window spans
  the strip between them (30-70 images on the 196-image block at ρ ≥ 0.8).

After ``relax_after_images`` consecutive calm images they relax, one per step and in the
reverse order, towards their configured values (the cap by ``1 / WINDOW_FACTOR``, back to
the configured one, :data:`seqat.departures.DEFAULT_MAX_WINDOW_IMAGES` by default, when it
reaches it or :data:`MAX_WINDOW_CAP`; the threshold by ``RELAX_FACTOR``; the features by
``1 / FEATURE_FACTOR``).

The budget is either **fixed** (``--budget-ms N``: processing, reading and tracking + the
update + the refinement after it, ``ImageUpdate.processing_ms``, over N) or **keep-up**
(``seqat watch``'s default): the budget is the interval at which the inputs arrive, over the
last :data:`PERIOD_IMAGES` images' times of input complete (the span over the count of
inputs after its start, not a median of intervals: rows one poll finds share their file's
time). An image is also over it when its end-to-end latency exceeds :data:`BACKLOG_PERIODS`
intervals and is not smaller than the last image's (images queue and the queue does not
drain, whatever the reason). Inputs arriving faster than every :data:`MIN_PERIOD_MS` are a
batch (a folder copied at once): there is no rate to keep up with, and nothing changes; once
a rate was seen, such a burst leaves it in place.

Each change is an event (image, old and new threshold, features and cap, the measured
milliseconds), journaled (a resumed run replays it) and kept in ``run.json``
``latency_budget``; the report shows them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from seqat.errors import ConfigError

#: Threshold multiplier when an image went over the budget.
TIGHTEN_FACTOR = 2.0
#: Threshold divisor when relaxing (slower than tightening: two relaxations undo one doubling).
RELAX_FACTOR = 2.0**0.5
#: Default cap of the tightened threshold (a window of the last image or two beyond it).
DEFAULT_MAX_THRESHOLD = 0.8
#: Relax only after this many consecutive images under ``DEFAULT_RELAX_FRACTION`` of the budget.
DEFAULT_RELAX_AFTER_IMAGES = 10
DEFAULT_RELAX_FRACTION = 0.5
#: Only updates of this stage depend on the threshold (the initial Sim stage does not).
SEQUENTIAL_STAGE = "sequential"
#: Reading and tracking over this fraction of the budget lower the tracker's features.
TRACKING_SHARE = 0.6
#: Feature count multiplier when tracking was over its share (its inverse relaxes).
FEATURE_FACTOR = 0.75
#: Never fewer features than this (verification needs matches: 1000 SIFT features still
#: give ~1800 verified matches over 5 pairs of the rendered Autzen images).
MIN_FEATURES = 1000
#: Window cap multiplier (of the last update's window) when tightening; its inverse relaxes.
WINDOW_FACTOR = 0.75
#: Never a cap below this many images (two strips' neighbours and the new image).
MIN_WINDOW_CAP = 4
#: A cap relaxed above this many images is lifted.
MAX_WINDOW_CAP = 50
#: Keep-up budget: the arrival interval is the mean over the last this many arrivals.
PERIOD_IMAGES = 20
#: Keep-up budget: arrivals closer than this (ms) are a batch, not a rate to keep up with.
MIN_PERIOD_MS = 100.0
#: Keep-up budget: a latency of more than this many intervals is a backlog (over budget).
BACKLOG_PERIODS = 3.0
#: Keep-up budget: calm = processing under this fraction of the interval and no backlog
#: (tracking alone may take most of the interval: half of it would never be calm).
KEEP_UP_RELAX_FRACTION = 0.8


@dataclass(frozen=True, kw_only=True)
class BudgetEvent:
    """One change of the dials (``run.json`` ``latency_budget.events[]``).

    Attributes
    ----------
    image : str
        The image whose processing caused the change; the next image uses the new values.
    old_threshold, new_threshold : float
    measured_ms : float
        Processing time of ``image``: reading and tracking plus the update.
    reason : str
        ``over budget``, ``backlog`` (keep-up: the latency, not the processing, was over) or
        ``under F x budget for N images``.
    old_features, new_features : int or None
        The tracker's feature count before and after (None: no tracker, or journals written
        before the feature dial).
    budget_ms : float or None
        The budget the image was measured against (keep-up: the arrival interval).
    old_window_cap, new_window_cap : int or None
        Seq-R ``max_window_images`` before and after (None: no cap).
    """

    image: str
    old_threshold: float
    new_threshold: float
    measured_ms: float
    reason: str
    old_features: int | None = None
    new_features: int | None = None
    budget_ms: float | None = None
    old_window_cap: int | None = None
    new_window_cap: int | None = None


@dataclass(frozen=True, kw_only=True)
class BudgetReport:
    """``run.json`` ``latency_budget``."""

    mode: str  # "fixed" or "keep-up"
    budget_ms: float | None  # fixed: the budget; keep-up: the last arrival interval (or None)
    base_threshold: float
    max_threshold: float
    final_threshold: float
    base_features: int | None
    final_features: int | None
    final_window_cap: int | None
    images_over_budget: int
    events: tuple[BudgetEvent, ...]


class LatencyBudget:
    """Adapts the Seq-R threshold and the tracker's features to a per-image budget.

    Parameters
    ----------
    budget_ms : float or None
        Processing time allowed per image (reading and tracking + update), milliseconds;
        None: keep up with the arrivals (module docstring).
    base_threshold : float
        The configured threshold: never relaxed below it.
    max_threshold : float
        Never tightened above it.
    relax_after_images : int
    relax_fraction : float
        Fixed budget: an image under this fraction of it is calm.
    """

    def __init__(self, budget_ms: float | None, base_threshold: float, *,
                 max_threshold: float = DEFAULT_MAX_THRESHOLD,
                 relax_after_images: int = DEFAULT_RELAX_AFTER_IMAGES,
                 relax_fraction: float = DEFAULT_RELAX_FRACTION,
                 base_window_cap: int | None = None) -> None:
        if budget_ms is not None and not budget_ms > 0:
            raise ConfigError(f"--budget-ms: expected a positive number, got {budget_ms!r}")
        self.keep_up = budget_ms is None
        self.budget_ms = None if budget_ms is None else float(budget_ms)
        self.base_threshold = base_threshold
        self.max_threshold = max(max_threshold, base_threshold)
        self.relax_after_images = relax_after_images
        self.relax_fraction = KEEP_UP_RELAX_FRACTION if self.keep_up else relax_fraction
        self.threshold = base_threshold
        #: The tracker's configured and current feature counts (:meth:`track_features`).
        self.base_features: int | None = None
        self.features: int | None = None
        #: Seq-R ``max_window_images`` configured (None: none) and now.
        self.base_window_cap = base_window_cap
        self.window_cap: int | None = base_window_cap
        self.events: list[BudgetEvent] = []
        self.images_over = 0
        self._calm = 0  # consecutive calm images
        self._arrivals: deque[float] = deque(maxlen=PERIOD_IMAGES)
        self._period: float | None = None  # the last arrival interval seen (ms)
        self._last_latency: float | None = None

    def track_features(self, features: int | None) -> None:
        """The tracker's configured feature count (None: no tracker): the second dial."""
        self.base_features = self.features = features

    @property
    def period_ms(self) -> float | None:
        """Keep-up: the arrival interval (None before three arrivals, or for a batch)."""
        return self._period

    def arrived(self, ready_s: float | None) -> None:
        """Keep-up: the time (seconds) the next image's input was complete."""
        if ready_s is None:
            return
        self._arrivals.append(max(ready_s, self._arrivals[-1]) if self._arrivals else ready_s)
        # the inputs after the oldest time came in (t_first, t_last]: rows found together
        # share one time, so count them, not the intervals between them
        t_first = self._arrivals[0]
        later = sum(1 for t in self._arrivals if t > t_first)
        if later >= 2:
            period = (self._arrivals[-1] - t_first) / later * 1e3
            if period >= MIN_PERIOD_MS:
                self._period = period
            # else a burst: the watch fell behind and found several inputs at once (or a
            # batch, when no rate was ever seen): the last rate stands

    @property
    def limit_ms(self) -> float | None:
        """The budget now: fixed, or keep-up's arrival interval (None: none yet)."""
        return self.period_ms if self.keep_up else self.budget_ms

    def after_image(self, image: str, stage: str, measured_ms: float,
                    tracking_ms: float = 0.0, latency_ms: float | None = None,
                    window_images: int | None = None) -> BudgetEvent | None:
        """Account one image; returns the change for the next image, if any.

        ``measured_ms``: reading and tracking + update; ``tracking_ms``: reading and
        tracking alone; ``latency_ms``: input complete -> estimate (keep-up's backlog);
        ``window_images``: the update's window (the cap's reference)."""
        budget = self.limit_ms
        over, reason = self._verdict(stage, measured_ms, latency_ms, budget)
        if stage != SEQUENTIAL_STAGE or budget is None:
            return None
        old, old_f, old_c = self.threshold, self.features, self.window_cap
        new, new_f, new_c = old, old_f, old_c
        if over:
            tracking_over = (old_f is not None and old_f > MIN_FEATURES
                             and tracking_ms > TRACKING_SHARE * budget)
            if tracking_over:
                new_f = max(MIN_FEATURES, round(old_f * FEATURE_FACTOR))  # type: ignore[operator]
            if not tracking_over or measured_ms - tracking_ms > (1 - TRACKING_SHARE) * budget:
                new = min(self.max_threshold, old * TIGHTEN_FACTOR)
                if new == old and window_images is not None:  # the threshold is at its cap
                    ref = window_images if old_c is None else min(old_c, window_images)
                    new_c = max(MIN_WINDOW_CAP, round(ref * WINDOW_FACTOR))
        elif self._calm >= self.relax_after_images:
            reason = f"under {self.relax_fraction:g} x budget for {self._calm} images"
            base = self.base_window_cap
            if old_c != base:  # towards the configured cap (a cap relaxed past it is that)
                new_c = round(old_c / WINDOW_FACTOR)  # type: ignore[operator]
                if new_c > MAX_WINDOW_CAP or (base is not None and new_c >= base):
                    new_c = base
            elif old > self.base_threshold:
                new = max(self.base_threshold, old / RELAX_FACTOR)
            elif old_f is not None and self.base_features is not None \
                    and old_f < self.base_features:
                new_f = min(self.base_features, round(old_f / FEATURE_FACTOR))
        if new == old and new_f == old_f and new_c == old_c:
            return None
        event = BudgetEvent(image=image, old_threshold=old, new_threshold=new,
                            measured_ms=measured_ms, reason=reason, old_features=old_f,
                            new_features=new_f, budget_ms=budget, old_window_cap=old_c,
                            new_window_cap=new_c)
        self.apply(event)
        return event

    def _verdict(self, stage: str, measured_ms: float, latency_ms: float | None,
                 budget: float | None) -> tuple[bool, str]:
        """Over budget (and why); counts the image and the calm streak."""
        if budget is None:
            return False, ""
        over, reason = measured_ms > budget, "over budget"
        # a backlog that drains (each image's latency smaller than the last: the processing
        # is under the interval) needs no tighter dial; one that does not, does
        backlog = (self.keep_up and latency_ms is not None
                   and latency_ms > BACKLOG_PERIODS * budget
                   and (self._last_latency is None or latency_ms >= self._last_latency))
        self._last_latency = latency_ms
        if backlog and not over:
            over, reason = True, "backlog"
        self.images_over += int(over)
        if stage == SEQUENTIAL_STAGE:
            calm = (not over and measured_ms < self.relax_fraction * budget
                    and (latency_ms is None or not self.keep_up or latency_ms <= budget
                         + measured_ms))
            self._calm = self._calm + 1 if calm else 0
        return over, reason

    def account(self, stage: str, measured_ms: float) -> bool:
        """Count one replayed image (its change, if any, comes from the journal)."""
        over, _ = self._verdict(stage, measured_ms, None, self.limit_ms)
        return over

    def apply(self, event: BudgetEvent) -> None:
        """Take an event (also a journaled one): the dials take its new values."""
        self.threshold = event.new_threshold
        if event.new_features is not None:
            self.features = event.new_features
        self.window_cap = event.new_window_cap
        self.events.append(event)
        self._calm = 0

    def report(self) -> BudgetReport:
        return BudgetReport(mode="keep-up" if self.keep_up else "fixed",
                            budget_ms=self.limit_ms, base_threshold=self.base_threshold,
                            max_threshold=self.max_threshold, final_threshold=self.threshold,
                            base_features=self.base_features, final_features=self.features,
                            final_window_cap=self.window_cap,
                            images_over_budget=self.images_over, events=tuple(self.events))
