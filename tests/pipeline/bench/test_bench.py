"""The benchmark stage on a tiny strip: JSON report, figures, markdown tables, checks."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from pipeline.bench.common import load_sim_config
from pipeline.bench.report import PNG_SIGNATURE, TARGET_GP_DIFF_STD_M, BenchReport
from pipeline.bench.strip import run_bench
from seqat.errors import ConfigError

#: A 20 s strip with the paper's camera: long enough for a sequential stage after the
#: 10 initial images, short enough for Sim to refit after every image in about a second.
TINY_CONFIG = """\
kind: observations
crs: "EPSG:32652"
simulation:
  n_images: 40
  n_points: 30
"""
METHODS = ("Direct (GPS/INS)", "Seq-R ρ≥0.1", "Seq-R ρ≥0.1 RTS-smoothed", "Seq-F",
           "Seq-R ρ≥0.1 without RTS gains", "Sim")
#: The methods that are timed (the smoothed Seq-R is the same run's final solution).
TIMED = ("Seq-R ρ≥0.1", "Seq-F", "Seq-R ρ≥0.1 without RTS gains", "Sim")
FIGURES = (
    "fig04_position_rmse.png",
    "fig05_attitude_rmse.png",
    "fig06_gp_rmse.png",
    "fig07_gp_diff_std.png",
    "fig08_time_per_image.png",
    "fig09_inverse_sizes.png",
    "fig10_time_zoom.png",
    "fig11_window_size.png",
    "sigma_per_image.png",
)


@pytest.fixture(scope="module")
def tiny_bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[BenchReport, Path]:
    root = tmp_path_factory.mktemp("bench")
    config = root / "tiny_sim.yaml"
    config.write_text(TINY_CONFIG, encoding="utf-8")
    out = root / "out"
    report = run_bench(
        config, out, seeds=(1,), thresholds=(0.1,), sim_every_frame=True, progress=False
    )
    return report, out


def test_json_has_finite_accuracy_and_at_beats_direct(tiny_bench: tuple[BenchReport, Path]) -> None:
    _, out = tiny_bench
    data = json.loads((out / "bench.json").read_text(encoding="utf-8"))
    (seed,) = data["results"]
    runs = {m["label"]: m for m in seed["methods"]}
    assert tuple(runs) == METHODS
    for label, run in runs.items():
        acc = run["accuracy"]
        values = acc["pos_rmse_m"] + acc["att_rmse_deg"] + acc["gp_rmse_m"]
        assert all(v is not None and math.isfinite(v) and v > 0 for v in values), label
        assert acc["n_images"] == 40
    direct_att = runs["Direct (GPS/INS)"]["accuracy"]["att_deg"]
    for label in METHODS[1:]:
        assert runs[label]["accuracy"]["att_deg"] < direct_att, label
        assert runs[label]["accuracy"]["pos_m"] < runs["Direct (GPS/INS)"]["accuracy"]["pos_m"]
    for label in TIMED:
        timing = runs[label]["timing"]
        assert 0 < timing["median_ms"] <= timing["p99_ms"] <= timing["max_ms"]
        assert len(runs[label]["series"]["update_ms"]) == 40
    # Keeping the RTS gains does not change the real-time (frozen) values.
    assert runs["Seq-R ρ≥0.1 without RTS gains"]["accuracy"] == runs["Seq-R ρ≥0.1"]["accuracy"]
    # Seq-R and Seq-F time only their sequential stage (after the 10 initial Sim images).
    assert runs["Seq-F"]["timing"]["n_timed"] == 30
    assert runs["Sim"]["timing"]["n_timed"] == 40


def test_figures_are_non_empty_pngs(tiny_bench: tuple[BenchReport, Path]) -> None:
    report, out = tiny_bench
    assert sorted(Path(f).name for f in report.figures) == sorted(FIGURES)
    for name in FIGURES:
        data = (out / "figures" / name).read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 1000, name


def test_markdown_tables_name_every_method_and_computed_checks(
    tiny_bench: tuple[BenchReport, Path],
) -> None:
    report, out = tiny_bench
    text = (out / "bench.md").read_text(encoding="utf-8")
    sections = text.split("\n## ")
    accuracy = next(s for s in sections if s.startswith("Accuracy"))
    timing = next(s for s in sections if s.startswith("Update time"))
    diffs = next(s for s in sections if s.startswith("Final differences"))
    for label in METHODS:
        assert f"| {label} |" in accuracy
    for label in TIMED:
        assert f"| {label} |" in timing
    for label in METHODS[1:4]:
        assert f"| {label} |" in diffs
    # PASS/FAIL follow the values (never written by hand).
    gp_check = next(
        c for c in report.checks if c.label == "Seq-R ρ≥0.1" and "GP difference" in c.name
    )
    assert gp_check.passed == (gp_check.value <= TARGET_GP_DIFF_STD_M)
    for c in report.checks:
        assert c.passed == ((abs(c.value) if c.two_sided else c.value) <= c.target), c
    targets = next(s for s in sections if s.startswith("Targets"))
    for c in report.checks:
        assert ("PASS" if c.passed else "FAIL") in targets
    assert report.machine.cpu_count > 0 and "machine:" in text


def test_every_kth_sim_refit_is_timed_alone(tmp_path: Path) -> None:
    config = tmp_path / "tiny_sim.yaml"
    config.write_text(TINY_CONFIG.replace("n_images: 40", "n_images: 24"), encoding="utf-8")
    report = run_bench(
        config,
        tmp_path / "out",
        seeds=(2,),
        sim_every_frame=False,
        progress=False,
        sim_refit_every=8,
    )
    sim = next(m for m in report.results[0].methods if m.method == "sim")
    assert sim.timing is not None and sim.timing.n_timed == 3  # images 8, 16, 24
    assert "every 8th image" in sim.timing.mode
    assert sim.accuracy.att_deg < report.results[0].methods[0].accuracy.att_deg


def test_config_unknown_key_names_file_and_key(tmp_path: Path) -> None:
    config = tmp_path / "bad_sim.yaml"
    config.write_text(TINY_CONFIG + "  n_imagez: 3\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad_sim\.yaml.*n_imagez"):
        load_sim_config(config)
    with pytest.raises(ConfigError):
        run_bench(config, tmp_path / "out", progress=False)
