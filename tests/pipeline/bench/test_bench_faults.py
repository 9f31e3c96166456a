"""The fault benchmark's harness: injection counts, scoring, and a tiny end-to-end run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.bench.faults.cases import FaultBenchOptions
from pipeline.bench.faults.flight import enu_offset_to_geodetic
from pipeline.bench.faults.injection import (
    detection,
    gap_stats,
    inject_blunders,
    pick_dropout,
    pick_jump,
)
from pipeline.bench.faults.suite import run_fault_bench
from seqat.errors import ConfigError

#: A 20 s strip with the paper's camera (the bench's tiny case: ~30 runs in a few seconds).
TINY_CONFIG = """\
kind: observations
crs: "EPSG:32652"
simulation:
  n_images: 40
  n_points: 40
"""
WIDTH_PX, HEIGHT_PX = 640, 480


def test_blunders_hit_an_exact_share_with_sizes_in_range_inside_the_image() -> None:
    rng = np.random.default_rng(3)
    uv = np.column_stack([rng.uniform(0, WIDTH_PX - 1, 1000), rng.uniform(0, HEIGHT_PX - 1, 1000)])
    b = inject_blunders(uv, WIDTH_PX, HEIGHT_PX, 0.2, np.random.default_rng(7))
    assert b.index.size == 200 and np.unique(b.index).size == 200
    length = np.linalg.norm(b.offset_px, axis=1)
    # clipped to the image only after 20 draws: never happens with 640 x 480 and 100 px
    assert np.all((length >= 10.0 - 1e-9) & (length <= 100.0 + 1e-9))
    np.testing.assert_allclose(b.uv_px[b.index] - uv[b.index], b.offset_px)
    rest = np.setdiff1d(np.arange(1000), b.index)
    np.testing.assert_array_equal(b.uv_px[rest], uv[rest])
    assert np.all((b.uv_px >= -0.5) & (b.uv_px <= [WIDTH_PX - 0.5, HEIGHT_PX - 0.5]))
    again = inject_blunders(uv, WIDTH_PX, HEIGHT_PX, 0.2, np.random.default_rng(7))
    np.testing.assert_array_equal(again.uv_px, b.uv_px)  # seeded
    assert inject_blunders(uv, WIDTH_PX, HEIGHT_PX, 0.0, rng).index.size == 0
    with pytest.raises(ConfigError, match="fraction"):
        inject_blunders(uv, WIDTH_PX, HEIGHT_PX, 1.5, rng)


def test_detection_counts_precision_and_recall() -> None:
    bad = {("a", "p1"), ("a", "p2"), ("b", "p3"), ("c", "p4")}
    rejected = {("a", "p1"), ("b", "p3"), ("b", "p9")}
    d = detection(bad, rejected)
    assert (d.injected, d.rejected, d.true_positives) == (4, 3, 2)
    assert d.precision == pytest.approx(2 / 3) and d.recall == pytest.approx(0.5)
    none = detection(bad, set())
    assert math.isnan(none.precision) and none.recall == 0.0
    assert math.isnan(detection(set(), rejected).recall)


def test_gap_stats_compares_the_gap_with_its_neighbours() -> None:
    err = np.array([1.0, 1.0, 1.0, 4.0, 2.0, 1.0, 1.0, np.nan])
    s = gap_stats(err, np.array([3, 4]), neighbours=2)
    assert s.images == 2 and s.gap_max == 4.0
    assert s.gap_rms == pytest.approx(math.sqrt(10.0))
    assert s.neighbour_rms == 1.0 and s.neighbour_max == 1.0  # 1, 2 and 5, 6
    assert s.ratio_max == 4.0 and s.ratio_rms == pytest.approx(math.sqrt(10.0))


def test_jump_and_dropout_picks() -> None:
    rng = np.random.default_rng(1)
    i, off = pick_jump(100, 11, rng, 5.0)
    assert 11 <= i < 95 and np.linalg.norm(off) == pytest.approx(5.0)
    t = np.arange(100) * 0.5
    gap = pick_dropout(t, 10, 30.0, rng)
    assert gap.size == 60 and np.all(np.diff(gap) == 1) and gap[0] >= 10
    short = pick_dropout(t[:40], 10, 30.0, rng)  # longer than the flight: from `first` on
    np.testing.assert_array_equal(short, np.arange(10, 40))


def test_enu_offset_to_geodetic_is_metres() -> None:
    dlat, dlon = enu_offset_to_geodetic(44.0, 3.0, 4.0)
    # 1 deg of latitude at 44 N: 111.1 km; of longitude: 80.2 km
    assert dlat * 111_141.0 == pytest.approx(4.0, rel=1e-3)
    assert dlon * 80_233.0 == pytest.approx(3.0, rel=1e-3)


@pytest.fixture(scope="module")
def tiny_faults(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:  # type: ignore[type-arg]
    root = tmp_path_factory.mktemp("faults")
    config = root / "tiny.yaml"
    config.write_text(TINY_CONFIG, encoding="utf-8")
    out = root / "out"
    run_fault_bench(out, seeds=(5,), cases=("strip",), strip_config=config,
                    options=FaultBenchOptions(dropout_s=4.0), progress=False)
    return json.loads((out / "faults.json").read_text(encoding="utf-8")), out


def test_tiny_fault_bench_injects_what_it_says_and_scores_it(
        tiny_faults: tuple[dict, Path]) -> None:  # type: ignore[type-arg]
    doc, out = tiny_faults
    (setup,) = doc["setups"]
    k = setup["n_observations"]
    assert setup["blunders"] == [round(0.05 * k), round(0.2 * k)]
    assert len(setup["dropout_images"]) == 8  # 4 s at 2 Hz
    assert np.linalg.norm(setup["jump_offset_m"]) == pytest.approx(5.0)
    runs = doc["runs"]
    faults = [(r["fault"], r["variant"]) for r in runs]
    assert ("blunders 5 %", "oracle") in faults and ("dropout 4 s", "Sim") in faults
    assert len(runs) == 2 + 3 * 2 + 2 + 3
    for r in runs:
        det = r["detection"]
        if r["error"]:  # 20 % blunders may break an adjustment: recorded, not scored
            assert r["fault"] == "blunders 20 %" and det is None
            continue
        if r["fault"].startswith("blunders") and r["variant"] != "oracle":
            n = setup["blunders"][0 if "5 %" in r["fault"] else 1]
            assert det["injected"] == n
            assert det["rejected"] == r["rejected"]
            assert det["true_positives"] <= min(det["rejected"], n)
            assert det["recall"] == pytest.approx(det["true_positives"] / n)
            if det["rejected"]:
                assert det["precision"] == pytest.approx(det["true_positives"]
                                                         / det["rejected"])
            if r["variant"] == "snooping off":
                assert det["rejected"] == 0 and det["recall"] == 0.0
        else:
            assert det is None
    on = next(r for r in runs if r["fault"] == "blunders 5 %" and r["variant"] == "snooping on")
    assert on["detection"]["recall"] > 0.8  # the estimator finds most of them
    jump = [r for r in runs if r["fault"].startswith("jump")]
    assert all(isinstance(r["jump_flagged"], bool) for r in jump)
    assert (out / "faults.md").read_text(encoding="utf-8").startswith("# Fault benchmark")


def test_fault_bench_rejects_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="--case"):
        run_fault_bench(tmp_path, cases=("nope",), progress=False)
    with pytest.raises(ConfigError, match="seed"):
        run_fault_bench(tmp_path, seeds=(), progress=False)
    with pytest.raises(ConfigError, match="truth"):
        run_fault_bench(tmp_path, cases=("rendered",), rendered_flight=tmp_path, progress=False)
    with pytest.raises(ConfigError, match="no such folder"):  # a relative default elsewhere
        run_fault_bench(tmp_path, cases=("rendered",), rendered_flight=tmp_path / "nope",
                        progress=False)


def test_cli_bench_faults_bad_case_exits_2(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    result = CliRunner().invoke(app, ["bench", "faults", "--out", str(tmp_path / "o"),
                                      "--case", "nope"])
    assert result.exit_code == 2
    assert result.stderr.strip().startswith("seqat: error: bench faults: --case")
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


def test_faults_json_renders_the_same_tables_again(tiny_faults: tuple[dict, Path]) -> None:  # type: ignore[type-arg]
    from pipeline.bench.faults.report import render_fault_markdown, report_from_json

    doc, out = tiny_faults
    again = render_fault_markdown(report_from_json(doc))
    assert again == (out / "faults.md").read_text(encoding="utf-8")
