"""The latency budget's dials (:mod:`pipeline.run.budget`): known answers per image."""

from __future__ import annotations

import pytest

from pipeline.cli.run import parse_budget
from pipeline.run.budget import (
    BACKLOG_PERIODS,
    DEFAULT_RELAX_AFTER_IMAGES,
    MIN_FEATURES,
    BudgetEvent,
    LatencyBudget,
)
from pipeline.run.runner import KEEP_UP, Method, make_budget
from seqat.errors import ConfigError
from seqat.sequential import SequentialOptions

SEQ = "sequential"


def _keep_up(period_s: float = 0.5, features: int | None = 4000,
             base_window_cap: int | None = None) -> LatencyBudget:
    """A keep-up budget that has seen a few arrivals ``period_s`` apart."""
    budget = LatencyBudget(None, 0.1, base_window_cap=base_window_cap)
    budget.track_features(features)
    for k in range(4):
        budget.arrived(100.0 + k * period_s)
    return budget


def test_a_fixed_budget_without_tracker_tightens_the_threshold_only() -> None:
    budget = LatencyBudget(500.0, 0.1)
    budget.track_features(None)
    assert budget.after_image("a", SEQ, 400.0) is None
    event = budget.after_image("b", SEQ, 600.0, tracking_ms=550.0)
    assert event is not None and (event.old_threshold, event.new_threshold) == (0.1, 0.2)
    assert event.new_features is None and event.reason == "over budget"
    assert budget.after_image("c", "initial", 5000.0) is None  # Sim: no dial
    assert budget.images_over == 2


def test_keep_up_follows_the_arrival_interval() -> None:
    budget = _keep_up(0.5)
    assert budget.period_ms == pytest.approx(500.0)
    assert budget.after_image("a", SEQ, 450.0, tracking_ms=300.0, latency_ms=460.0) is None
    # tracking alone over its share (0.6 x 500): fewer features; the update's share fits
    event = budget.after_image("b", SEQ, 520.0, tracking_ms=400.0, latency_ms=530.0)
    assert event is not None and (event.old_features, event.new_features) == (4000, 3000)
    assert event.new_threshold == 0.1 and event.budget_ms == pytest.approx(500.0)
    # the update over its share: the threshold too
    event = budget.after_image("c", SEQ, 800.0, tracking_ms=400.0, latency_ms=900.0)
    assert event is not None and (event.new_features, event.new_threshold) == (2250, 0.2)


def test_keep_up_treats_a_backlog_as_over_budget() -> None:
    budget = _keep_up(0.5)
    latency = BACKLOG_PERIODS * 500.0 + 1.0
    event = budget.after_image("a", SEQ, 300.0, tracking_ms=200.0, latency_ms=latency)
    assert event is not None and event.reason == "backlog"
    assert (event.new_threshold, event.new_features) == (0.2, 4000)


def test_keep_up_does_nothing_for_a_batch_of_inputs() -> None:
    budget = _keep_up(0.01)  # a folder copied at once: 10 ms apart
    assert budget.period_ms is None
    assert budget.after_image("a", SEQ, 5000.0, tracking_ms=4000.0, latency_ms=60e3) is None
    assert budget.images_over == 0 and not budget.events


def test_features_never_fall_below_the_floor_and_relax_after_calm_images() -> None:
    budget = _keep_up(0.5, features=1100)
    event = budget.after_image("a", SEQ, 600.0, tracking_ms=550.0, latency_ms=600.0)
    assert event is not None and event.new_features == MIN_FEATURES
    assert budget.after_image("b", SEQ, 600.0, tracking_ms=550.0, latency_ms=600.0) is not None
    assert budget.features == MIN_FEATURES and budget.threshold == 0.2
    changes = []
    for k in range(3 * DEFAULT_RELAX_AFTER_IMAGES):
        e = budget.after_image(f"c{k}", SEQ, 100.0, tracking_ms=80.0, latency_ms=110.0)
        if e is not None:
            changes.append((e.new_threshold, e.new_features))
    # the threshold relaxes first (by sqrt 2, down to the configured 0.1), then the features
    assert [c[0] for c in changes[:2]] == pytest.approx([0.2 / 2**0.5, 0.1])
    assert changes[-1][1] == 1100 and budget.features == 1100


def test_make_budget_and_the_watch_option() -> None:
    opts = SequentialOptions()
    assert make_budget(KEEP_UP, Method.SIM, opts) is None  # no dial to turn: no budget
    keep = make_budget(KEEP_UP, Method.SEQ_R, opts)
    assert keep is not None and keep.keep_up and keep.report().mode == "keep-up"
    assert make_budget(None, Method.SEQ_R, opts) is None
    with pytest.raises(ConfigError, match="applies to --method seq-r"):
        make_budget(300.0, Method.SIM, opts)
    assert parse_budget("keep-up") == KEEP_UP and parse_budget("off") is None
    assert parse_budget("250") == 250.0
    for bad in ("0", "-3", "soon", "inf", "nan"):
        with pytest.raises(ConfigError, match="--budget-ms: expected keep-up, off or a number"):
            parse_budget(bad)


def test_rows_found_in_bursts_give_the_rate_they_were_written_at() -> None:
    budget = LatencyBudget(None, 0.1)
    for burst in range(6):  # 5 rows every 2.5 s: one every 500 ms, found 5 at a time
        for _ in range(5):
            budget.arrived(10.0 + 2.5 * burst)
    assert budget.period_ms == pytest.approx(500.0)
    event = budget.after_image("a", SEQ, 300.0, tracking_ms=100.0, latency_ms=5000.0)
    assert event is not None and event.reason == "backlog"


def test_a_draining_backlog_changes_nothing() -> None:
    budget = _keep_up(0.5)
    assert budget.after_image("a", SEQ, 300.0, tracking_ms=200.0, latency_ms=4000.0)
    # the processing is under the interval: the latency falls image by image
    for k, latency in enumerate((3800.0, 3600.0, 3400.0)):
        assert budget.after_image(f"b{k}", SEQ, 300.0, tracking_ms=200.0,
                                  latency_ms=latency) is None
    event = budget.after_image("c", SEQ, 300.0, tracking_ms=200.0, latency_ms=3500.0)
    assert event is not None and event.reason == "backlog"  # growing again


def _over(budget: LatencyBudget, n: int, window: int) -> list[BudgetEvent]:
    """``n`` images whose update alone is over the 500 ms interval: each changes a dial."""
    events = [budget.after_image(f"a{k}", SEQ, 900.0, tracking_ms=100.0, latency_ms=900.0,
                                 window_images=window) for k in range(n)]
    assert all(e is not None for e in events)
    return events  # type: ignore[return-value]


def _calm(budget: LatencyBudget, n: int, window: int) -> list[tuple[float, int | None]]:
    """``n`` calm images: the (threshold, window cap) of each change they made."""
    events = [budget.after_image(f"b{k}", SEQ, 100.0, tracking_ms=80.0, latency_ms=110.0,
                                 window_images=window) for k in range(n)]
    return [(e.new_threshold, e.new_window_cap) for e in events if e is not None]


def test_the_window_cap_comes_after_the_threshold_and_goes_first() -> None:
    budget = _keep_up(0.5, features=None)
    steps = [(e.new_threshold, e.new_window_cap) for e in _over(budget, 6, window=40)]
    assert steps[:3] == [(0.2, None), (0.4, None), (0.8, None)]
    assert [c for _, c in steps[3:]] == [30, 22, 16]  # 0.75 x min(cap, window)
    assert budget.report().final_window_cap == 16
    relaxed = _calm(budget, 2 * DEFAULT_RELAX_AFTER_IMAGES, window=16)
    assert relaxed == [(0.8, 21), (0.8, 28)]  # the cap relaxes first, the threshold waits


def test_a_configured_window_cap_is_where_the_cap_relaxes_back_to() -> None:
    """With a window cap configured (Seq-R's default): tightening starts from it, and relaxing
    returns to it, never past it to no cap."""
    budget = _keep_up(0.5, features=None, base_window_cap=24)
    assert budget.window_cap == 24 and budget.report().final_window_cap == 24
    caps = [(e.old_window_cap, e.new_window_cap) for e in _over(budget, 5, window=40)]
    assert caps[3:] == [(24, 18), (18, 14)]  # 0.75 x min(cap, window)
    relaxed = _calm(budget, 4 * DEFAULT_RELAX_AFTER_IMAGES, window=14)
    assert relaxed[:2] == [(0.8, 19), (0.8, 24)]  # 25 would pass the configured 24
    assert all(c == 24 for _, c in relaxed[2:]) and relaxed[-1][0] < 0.8
    opts = SequentialOptions()
    budget = make_budget(300.0, Method.SEQ_R, opts)
    assert opts.max_window_images is not None
    assert budget is not None and budget.window_cap == opts.max_window_images
