"""Per-image latency of a run by stage, from ``run.json`` and ``ortho.json`` (report, benchmarks).

Stages, per image (milliseconds; the ``*_ms`` fields of docs/formats.md):

* tracking (image flights): ``read`` (the tracker's reduced gray decode), ``detect``,
  ``match`` and ``tracking`` (detection + matching + track bookkeeping, ``total_ms``);
* ``AT update``: the estimator's update (``update_ms``); ``refinement (after the AT
  update)``: what ran once the update's estimate was out (``refine_ms``: the drift check and
  re-linearisation of the window, a second start); ``second start (after the AT update)``:
  the second starts among it (``second_start_ms``); each listed when there are any, not in
  ``end to end``: the image's estimate was out before;
* ortho, live (``seqat run --ortho``): waiting for the ortho worker (``queue_ms``), the
  colour decode, the orthorectification (``compute_ms``), waiting for the previous COG
  write, the mosaic update, and ``AT update -> mosaic``: from the end of the image's AT
  update to its mosaic update (``latency_ms``, the sum of those parts);
* ``end to end``: read + tracking + AT update (+ AT update -> mosaic with a live ortho),
  per image: from the start of reading the image to its place in the mosaic. Rendering
  and acquisition are not included; the resection of the initial attitude (a few ms) is.

For images orthorectified again at the end of a live run the parts are those of the live
ortho (``ortho.json`` keeps them; the end's work is ``reortho_ms``, listed apart). A post-run
ortho (``seqat ortho``) has ortho times but is not part of the per-image latency.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.run.store import TimingStats, read_json_object

#: ``ortho.json`` of a run folder (pipeline.ortho.stage.ORTHO_JSON; not imported: no cycle).
ORTHO_JSON = "ortho.json"


@dataclass(frozen=True, kw_only=True)
class StageLatency:
    """One stage's per-image times."""

    stage: str
    images: int
    median_ms: float
    p95_ms: float
    max_ms: float


@dataclass(frozen=True, kw_only=True)
class LatencyTable:
    """Per-image latency by stage (module docstring).

    ``ortho``: ``live``, ``after the run`` (a ``seqat ortho`` on the run folder: its times
    are listed but not in ``end to end``) or ``none``.
    """

    ortho: str
    stages: tuple[StageLatency, ...]


def read_ortho_json(run_dir: Path) -> Mapping[str, object] | None:
    """``OUT/ortho.json`` parsed, or None when the run has no ortho."""
    path = run_dir / ORTHO_JSON
    return read_json_object(path) if path.is_file() else None


def _stage(name: str, values: Sequence[float]) -> StageLatency:
    v = np.asarray(values, dtype=np.float64)
    t = TimingStats.from_samples(v[np.isfinite(v)])
    return StageLatency(stage=name, images=int(np.isfinite(v).sum()), median_ms=t.median_ms,
                        p95_ms=t.p95_ms, max_ms=t.max_ms)


def _field(items: Sequence[Mapping[str, object]], key: str) -> list[float]:
    return [math.nan if item.get(key) is None else float(item[key])  # type: ignore[arg-type]
            for item in items]


def latency_table(record: Mapping[str, object],
                  ortho: Mapping[str, object] | None) -> LatencyTable:
    """The stages of a run (``run.json`` as parsed) and its ``ortho.json`` (or None)."""
    images = record.get("images", [])
    assert isinstance(images, list)
    ids = [str(im["image_id"]) for im in images]
    tracking = [im.get("tracking") or {} for im in images]
    stages: list[StageLatency] = []
    end_to_end = np.asarray(_field(images, "update_ms"))
    if any(tracking):
        parts = {"read": "read_ms", "detect": "detect_ms", "match": "match_ms",
                 "tracking (detect + match + tracks)": "total_ms"}
        for name, key in parts.items():
            stages.append(_stage(name, _field(tracking, key)))
        end_to_end = end_to_end + np.nan_to_num(_field(tracking, "read_ms")) + np.asarray(
            _field(tracking, "total_ms"))
    stages.append(_stage("AT update", _field(images, "update_ms")))
    refine = _field(images, "refine_ms")
    if np.isfinite(refine).any():
        stages.append(_stage("refinement (after the AT update)", refine))
    trials = _field(images, "second_start_ms")
    if np.isfinite(trials).any():
        stages.append(_stage("second start (after the AT update)", trials))
    kind = "none"
    if ortho is not None:
        live = ortho.get("live") is not None
        kind = "live" if live else "after the run"
        orthos = ortho.get("images", [])
        assert isinstance(orthos, list)
        by_id = {str(o["image"]): o for o in orthos}
        per_image = [by_id.get(i, {}) for i in ids]
        parts = {"ortho: wait for the worker": "queue_ms", "ortho: read image": "read_ms",
                 "ortho: orthorectify": "compute_ms", "ortho: wait for the COG write":
                 "write_ms", "ortho: mosaic update": "mosaic_ms",
                 "ortho: AT update -> mosaic": "latency_ms"}
        if not live:
            parts = {k: v for k, v in parts.items() if v not in ("queue_ms", "latency_ms")}
        for name, key in parts.items():
            stages.append(_stage(name, _field(per_image, key)))
        if live:
            end_to_end = end_to_end + np.asarray(_field(per_image, "latency_ms"))
            again = _field(per_image, "reortho_ms")
            if np.isfinite(again).any():
                stages.append(_stage("ortho again at the end (not live)", again))
    stages.append(_stage("end to end", end_to_end.tolist()))
    return LatencyTable(ortho=kind, stages=tuple(stages))

