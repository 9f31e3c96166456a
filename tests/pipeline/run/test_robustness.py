"""run.json ``robustness`` and its summary in the report (pipeline.run.robustness)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.run.robustness import robustness_record, robustness_rows, summarise
from pipeline.run.runner import Method, run_flight
from pipeline.run.store import read_points_csv, to_jsonable
from pipeline.simulate.folder import write_simulated_flight
from seqat.geometry import project
from seqat.sequential import SequentialOptions
from seqat.simulate import SimulatedFlight

from ..sample_flight import SIM_CRS


def test_points_left_out_reach_run_json_and_the_report() -> None:
    """The estimator's disagreeing, undetermined and untrusted tie points are named in
    run.json and counted in the report's *Blunders and GNSS faults* table, with the
    contamination that left the two-ray points out."""
    est = SimpleNamespace(disagreeing=["t1", "t2", "t3"], undetermined=["t9"])
    record = robustness_record(est, SequentialOptions(), off_surface=["t4", "t5"])
    assert record.disagreeing_points == ("t1", "t2", "t3")
    assert record.undetermined_points == ("t9",)
    assert record.off_surface_points == ("t4", "t5")
    summary = summarise({"robustness": to_jsonable(record), "images": []})
    assert summary is not None
    assert (summary.points_disagreeing, summary.points_undetermined,
            summary.points_off_surface) == (3, 1, 2)
    rows = dict(robustness_rows(summary))
    assert rows["tie points left out: rays disagree / undetermined / off the surface"] == (
        "3 / 1 / 2")
    assert rows["contamination (rays of 3+ ray tie points clearly off) / two-ray points "
                "left out"] == "not judged"
    # a contaminated flight: the fraction and the two-ray points left out
    assert rows["robust loss's core, configured / final adjustment"] == "3 σ / 3 σ"
    est = SimpleNamespace(contamination=0.21234, untrusted=["p1", "p2"],
                          options=SequentialOptions(robust_scale=2.0))  # narrowed core
    record = robustness_record(est, SequentialOptions())
    assert record.contamination == 0.2123 and record.untrusted_points == ("p1", "p2")
    assert (record.robust_scale, record.final_robust_scale) == (3.0, 2.0)
    summary = summarise({"robustness": to_jsonable(record), "images": []})
    assert summary is not None
    rows = dict(robustness_rows(summary))
    assert rows[
        "contamination (rays of 3+ ray tie points clearly off) / two-ray points left out"
    ] == "21.2 % / 2"
    assert rows["robust loss's core, configured / final adjustment"] == "3 σ / 2 σ"
    least = robustness_record(SimpleNamespace(), SequentialOptions(robust_scale=None))
    summary = summarise({"robustness": to_jsonable(least), "images": []})
    assert summary is not None and dict(robustness_rows(summary))[
        "robust loss's core, configured / final adjustment"] == "least squares / least squares"
    # not judged (NaN: no loss, no point of three rays): null in run.json
    nan = robustness_record(SimpleNamespace(contamination=float("nan")), SequentialOptions())
    assert nan.contamination is None and json.dumps(to_jsonable(nan))
    # a run.json written before the fields: none
    old = to_jsonable(robustness_record(SimpleNamespace(), SequentialOptions()))
    del old["disagreeing_points"], old["contamination"], old["untrusted_points"]
    del old["final_robust_scale"]
    summary = summarise({"robustness": old, "images": []})
    assert summary is not None and summary.points_disagreeing == 0
    assert summary.contamination is None and summary.points_untrusted == 0
    assert summary.final_robust_scale == summary.robust_scale == 3.0  # the configured one


def test_images_diverged_live_are_named_after_an_adopted_final_check() -> None:
    """The final check's Sim published (an adopted check): run.json names the images the
    Sim leaves diverged in ``diverged_images`` and, apart, those that diverged during the
    flight and that the check placed (``diverged_live``); with the run's own solution
    published, its diverged images alone, and nothing live."""
    flown = SimpleNamespace(diverged=["img_0030", "img_0031"], second_starts=["img_0005"])
    sim = SimpleNamespace(diverged=["img_0031"])
    record = robustness_record(sim, SequentialOptions(), flown=flown)
    assert record.diverged_images == ("img_0031",)
    assert record.diverged_live == ("img_0030",)
    assert record.second_starts == ("img_0005",)
    own = robustness_record(flown, SequentialOptions(), flown=flown)
    assert own.diverged_images == ("img_0030", "img_0031") and own.diverged_live == ()
    assert to_jsonable(record)["diverged_live"] == ["img_0030"]


def _wrong_depth(f: SimulatedFlight, down_m: float) -> tuple[SimulatedFlight, str]:
    """A point of the strip's middle image cut to its first and last rays, the last a wrong
    match on the point ``down_m`` further down the first ray: along the first ray's
    epipolar line, so both rays meet exactly there (no ray test can see it)."""
    counts = np.bincount(f.obs_point)
    mid = len(f.image_ids) // 2
    p = int(next(q for q in np.unique(f.obs_point[f.obs_image == mid]) if counts[q] >= 3))
    rows = np.flatnonzero(f.obs_point == p)
    X = f.truth_xyz[p]
    ray = X - f.truth_eop[f.obs_image[rows[0]], :3]
    uv = f.obs_uv.copy()
    uv[rows[-1]] = project(f.truth_eop[f.obs_image[rows[-1]]][None],
                           (X + down_m * ray / np.linalg.norm(ray))[None], f.camera)[0]
    keep = np.ones(len(uv), dtype=bool)
    keep[rows[1:-1]] = False
    return dataclasses.replace(f, obs_image=f.obs_image[keep], obs_point=f.obs_point[keep],
                               obs_uv=uv[keep]), f.point_ids[p]


@pytest.mark.parametrize("method", [Method.SEQ_R, Method.SIM])
def test_a_wrong_match_along_the_epipolar_line_is_not_published(
        short_strip: SimulatedFlight, tmp_path: Path, method: Method) -> None:
    """Two rays, the second a wrong match 100 m down the first ray: the rays agree and the
    point sits 100 m under ground whose points are 6 m (σ) rough. The run does not
    publish it (points.csv) and names it in run.json; 10 m down it is within that
    roughness and kept, and the clean strip loses no point."""

    def run(f: SimulatedFlight, name: str) -> tuple[set[str], list[str]]:
        out = tmp_path / name / "out"
        run_flight(write_simulated_flight(f, SIM_CRS, tmp_path / name / "flight"), out,
                   method=method, progress=False)
        rob = json.loads((out / "run.json").read_text(encoding="utf-8"))["robustness"]
        return set(read_points_csv(out / "points.csv").point_ids), rob["off_surface_points"]

    wrong, pid = _wrong_depth(short_strip, 100.0)
    published, named = run(wrong, "wrong")
    assert named == [pid] and pid not in published
    assert published == set(wrong.point_ids[j] for j in np.unique(wrong.obs_point)) - {pid}
    near, pid = _wrong_depth(short_strip, 10.0)
    published, named = run(near, "near")
    assert named == [] and pid in published
    published, named = run(short_strip, "clean")
    assert named == [] and published == set(short_strip.point_ids)
