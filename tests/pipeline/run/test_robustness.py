"""run.json ``robustness`` and its summary in the report (pipeline.run.robustness)."""

from __future__ import annotations

from types import SimpleNamespace

from pipeline.run.robustness import robustness_record, robustness_rows, summarise
from pipeline.run.store import to_jsonable
from seqat.sequential import SequentialOptions


def test_points_left_out_reach_run_json_and_the_report() -> None:
    """The estimator's disagreeing and undetermined tie points are named in run.json and
    counted in the report's *Blunders and GNSS faults* table."""
    est = SimpleNamespace(disagreeing=["t1", "t2", "t3"], undetermined=["t9"])
    record = robustness_record(est, SequentialOptions())
    assert record.disagreeing_points == ("t1", "t2", "t3")
    assert record.undetermined_points == ("t9",)
    summary = summarise({"robustness": to_jsonable(record), "images": []})
    assert summary is not None
    assert (summary.points_disagreeing, summary.points_undetermined) == (3, 1)
    rows = dict(robustness_rows(summary))
    assert rows["tie points left out: rays disagree / undetermined"] == "3 / 1"
    # a run.json written before the field: none
    old = to_jsonable(robustness_record(SimpleNamespace(), SequentialOptions()))
    del old["disagreeing_points"]
    summary = summarise({"robustness": old, "images": []})
    assert summary is not None and summary.points_disagreeing == 0
