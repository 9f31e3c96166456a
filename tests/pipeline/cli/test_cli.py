"""The command line: exit codes, one-line errors, tracebacks only on request."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.run import runner
from pipeline.run.store import read_eop_csv

REPO_ROOT = Path(__file__).resolve().parents[3]


def test_simulate_then_run(tmp_path: Path) -> None:
    config = tmp_path / "sim.yaml"
    config.write_text("kind: observations\ncrs: EPSG:32652\n"
                      "simulation: {n_images: 16, n_points: 25}\n")
    cli = CliRunner()
    result = cli.invoke(app, ["simulate", str(config), "--out", str(tmp_path / "f"),
                              "--seed", "2"])
    assert result.exit_code == 0, result.output
    assert "observations" in result.stdout
    result = cli.invoke(app, ["run", str(tmp_path / "f"), "--out", str(tmp_path / "r"),
                              "--method", "seq-f", "--initial-images", "6", "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "sigma0" in result.stdout and "GPS/INS input" in result.stdout
    assert len(read_eop_csv(tmp_path / "r" / "eop.csv")) == 16


def test_bad_method_is_exit_2(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["run", str(tmp_path), "--out", str(tmp_path / "o"),
                                      "--method", "fast"])
    assert result.exit_code == 2
    assert result.stderr == ("seqat: error: --method: expected one of seq-r, seq-f, sim, "
                             "got 'fast'\n")


def test_missing_config_is_exit_2(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["simulate", str(tmp_path / "none.yaml"), "--out",
                                      str(tmp_path / "f")])
    assert result.exit_code == 2
    assert result.stderr.startswith(f"seqat: error: {tmp_path / 'none.yaml'}: cannot read")
    assert not (tmp_path / "f").exists()


def test_usage_error_is_exit_2(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["run", str(tmp_path)])  # --out missing
    assert result.exit_code == 2


def boom(*args: object, **kwargs: object) -> None:
    raise RuntimeError("boom\nsecond line")


def test_internal_error_is_exit_1_without_traceback(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SEQAT_DEBUG", raising=False)
    monkeypatch.setattr(runner, "run_flight", boom)
    result = CliRunner().invoke(app, ["run", str(tmp_path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 1
    assert result.stderr.startswith("seqat: internal error: RuntimeError: boom second line")
    assert "Traceback" not in result.stderr and len(result.stderr.splitlines()) == 1


@pytest.mark.parametrize("how", ["flag", "env"])
def test_debug_shows_traceback(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str) -> None:
    monkeypatch.setattr(runner, "run_flight", boom)
    args = ["run", str(tmp_path), "--out", str(tmp_path / "o")]
    if how == "flag":
        monkeypatch.delenv("SEQAT_DEBUG", raising=False)
        args = ["--debug", *args]
    else:
        monkeypatch.setenv("SEQAT_DEBUG", "1")
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1
    assert "Traceback (most recent call last)" in result.stderr
    assert 'raise RuntimeError("boom' in result.stderr


def test_bench_passes_config_out_seeds_and_thresholds(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[object, ...]] = []
    fake = types.ModuleType("pipeline.bench.strip")

    def run_bench(config_path: Path, out_dir: Path, *, seeds: tuple[int, ...] = (1,),
                  thresholds: tuple[float, ...] = (0.1,)) -> types.SimpleNamespace:
        calls.append((config_path, out_dir, seeds, thresholds))
        check = types.SimpleNamespace(label="Seq-R", name="median update time", value=1.5,
                                      target=2.0, unit="ms", two_sided=False, passed=True)
        return types.SimpleNamespace(checks=(check,))

    fake.run_bench = run_bench  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "pipeline.bench.strip", fake)
    config = REPO_ROOT / "configs" / "paper_sim.yaml"
    result = CliRunner().invoke(app, ["bench", str(config), "--out", str(tmp_path / "b"),
                                      "--seed", "3", "--seed", "4", "--threshold", "0.05"])
    assert result.exit_code == 0, result.output
    assert calls == [(config, tmp_path / "b", (3, 4), (0.05,))]
    assert "median update time" in result.output and "PASS" in result.output
    assert "≤ 2 ms" in result.output


@pytest.mark.parametrize(("name", "args", "forwarded"), [
    ("rendered", ["RUN", "--config", "c.yaml", "--json", "s.json"],
     ["RUN", "--config", "c.yaml", "--json", "s.json"]),
    ("ortho", ["--images", "3", "--no-occlusion", "--out", "o"],
     ["--out", "o", "--images", "3", "--no-occlusion"]),
    ("gtsam", ["--seed", "1", "--lag", "5", "--seed", "2", "--config", "c.yaml", "--out", "o"],
     ["--out", "o", "--seed", "1", "--seed", "2", "--lag", "5", "--config", "c.yaml"]),
])
def test_bench_reaches_the_module_benchmarks(name: str, args: list[str], forwarded: list[str],
                                             tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                             ) -> None:
    calls: list[list[str]] = []
    fake = types.ModuleType(f"pipeline.bench.{name}")
    fake.main = lambda argv: calls.append(list(argv))  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, f"pipeline.bench.{name}", fake)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["bench", name, *args])
    assert result.exit_code == 0, result.output
    assert calls == [forwarded]


def test_bench_rejects_unknown_options() -> None:
    config = REPO_ROOT / "configs" / "paper_sim.yaml"
    result = CliRunner().invoke(app, ["bench", str(config), "--bogus"])
    assert result.exit_code == 2


def test_bench_gtsam_without_gtsam_is_exit_2(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """gtsam is optional: without it the benchmark stops at once with one line."""
    monkeypatch.setitem(sys.modules, "gtsam", None)  # import gtsam raises ImportError
    result = CliRunner().invoke(app, ["bench", "gtsam", "--seed", "1", "--lag", "5",
                                      "--out", str(tmp_path / "b")])
    assert result.exit_code == 2
    assert result.stderr == ("seqat: error: seqat bench gtsam needs the optional package gtsam "
                             "(pip install 'seqat[bench]')\n")
    assert not (tmp_path / "b").exists()
