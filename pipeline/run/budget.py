"""Latency budget (``--budget-ms``): the Seq-R window threshold follows the speed requirement.

The paper selects the correlation threshold "for the speed requirement" (seed 000 §2.3): a
higher threshold cuts the window shorter, and an update costs less. :class:`LatencyBudget`
does it on line: after each image of the sequential stage it compares the image's
processing time (reading and tracking + the update) with the budget. Over budget, the next
images use ``threshold × TIGHTEN_FACTOR`` (up to ``max_threshold``); after
``relax_after_images`` consecutive images under ``relax_fraction`` of the budget it relaxes
by ``RELAX_FACTOR`` towards the configured threshold. Each change is an event (image, old
and new threshold, the measured milliseconds) kept in ``run.json`` ``latency_budget`` and
shown by the report.
"""

from __future__ import annotations

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


@dataclass(frozen=True, kw_only=True)
class BudgetEvent:
    """One threshold change (``run.json`` ``latency_budget.events[]``).

    Attributes
    ----------
    image : str
        The image whose processing time caused the change; the next image uses ``new``.
    old_threshold, new_threshold : float
    measured_ms : float
        Processing time of ``image``: reading and tracking plus the update.
    reason : str
        ``over budget`` or ``under budget for N images``.
    """

    image: str
    old_threshold: float
    new_threshold: float
    measured_ms: float
    reason: str


@dataclass(frozen=True, kw_only=True)
class BudgetReport:
    """``run.json`` ``latency_budget``."""

    budget_ms: float
    base_threshold: float
    max_threshold: float
    final_threshold: float
    images_over_budget: int
    events: tuple[BudgetEvent, ...]


class LatencyBudget:
    """Adapts the Seq-R correlation threshold to a per-image processing budget.

    Parameters
    ----------
    budget_ms : float
        Processing time allowed per image (tracking + update), milliseconds.
    base_threshold : float
        The configured threshold: never relaxed below it.
    max_threshold : float
        Never tightened above it.
    relax_after_images : int
    relax_fraction : float
    """

    def __init__(self, budget_ms: float, base_threshold: float, *,
                 max_threshold: float = DEFAULT_MAX_THRESHOLD,
                 relax_after_images: int = DEFAULT_RELAX_AFTER_IMAGES,
                 relax_fraction: float = DEFAULT_RELAX_FRACTION) -> None:
        if not budget_ms > 0:
            raise ConfigError(f"--budget-ms: expected a positive number, got {budget_ms!r}")
        self.budget_ms = float(budget_ms)
        self.base_threshold = base_threshold
        self.max_threshold = max(max_threshold, base_threshold)
        self.relax_after_images = relax_after_images
        self.relax_fraction = relax_fraction
        self.threshold = base_threshold
        self.events: list[BudgetEvent] = []
        self.images_over = 0
        self._calm = 0  # consecutive images under relax_fraction of the budget

    def after_image(self, image: str, stage: str, measured_ms: float) -> BudgetEvent | None:
        """Account one image; returns the threshold change for the next image, if any."""
        over = self.account(stage, measured_ms)
        if stage != SEQUENTIAL_STAGE:
            return None
        old = self.threshold
        if over:
            new, reason = min(self.max_threshold, old * TIGHTEN_FACTOR), "over budget"
        elif self._calm >= self.relax_after_images and old > self.base_threshold:
            new = max(self.base_threshold, old / RELAX_FACTOR)
            reason = f"under {self.relax_fraction:g} x budget for {self._calm} images"
        else:
            return None
        if new == old:
            return None
        event = BudgetEvent(image=image, old_threshold=old, new_threshold=new,
                            measured_ms=measured_ms, reason=reason)
        self.apply(event)
        return event

    def account(self, stage: str, measured_ms: float) -> bool:
        """Count one image (also a replayed one); True when it went over the budget."""
        over = measured_ms > self.budget_ms
        self.images_over += int(over)
        if stage == SEQUENTIAL_STAGE:
            calm = not over and measured_ms < self.relax_fraction * self.budget_ms
            self._calm = self._calm + 1 if calm else 0
        return over

    def apply(self, event: BudgetEvent) -> None:
        """Take an event (also a journaled one): the threshold becomes ``new_threshold``."""
        self.threshold = event.new_threshold
        self.events.append(event)
        self._calm = 0

    def report(self) -> BudgetReport:
        return BudgetReport(budget_ms=self.budget_ms, base_threshold=self.base_threshold,
                            max_threshold=self.max_threshold, final_threshold=self.threshold,
                            images_over_budget=self.images_over, events=tuple(self.events))
