"""``seqat process``: run (+ live ortho) → reference → report in one command, and its bad
input (exit 2, one line, nothing written)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.cli import app

from ..sample_runs import AUTZEN, STRIP


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory, autzen_run: Path) -> tuple[Path, str]:
    """``seqat process`` of the rendered Autzen sample (lidar and check points), with the tie
    points the session's ``seqat run`` of it tracked (``--observations``: the suite tracks
    those images once)."""
    out = tmp_path_factory.mktemp("process") / "out"
    result = CliRunner().invoke(app, ["process", str(AUTZEN), "--out", str(out),
                                      "--observations", str(autzen_run / "observations.csv"),
                                      "--no-progress"])
    assert result.exit_code == 0, result.output
    return out, result.stdout


def test_process_runs_every_stage(processed: tuple[Path, str]) -> None:
    out, stdout = processed
    for name in ("eop.csv", "run.json", "dsm.tif", "mosaic.tif", "cameras.gpkg", "ortho.json",
                 "reference/reference.json", "report.json", "report.html", "report.pdf"):
        assert (out / name).is_file(), name
    assert "1/3: run + live ortho (surface: the flight's lidar)" in stdout
    assert "2/3: COLMAP reference" in stdout and "3/3: report" in stdout
    for name in ("mosaic.tif", "cameras.gpkg", "report.html", "report.pdf"):
        assert str(out / name) in stdout, name
    doc = json.loads((out / "report.json").read_text())
    assert doc["methods"] == ["direct", "seq-r", "colmap"]
    cp = doc["checkpoints"]
    assert cp["count"] == 36 and cp["rmse_v_m"] < 0.15
    assert abs(cp["mean_z_m"]) > cp["std_z_m"]  # the rendered sample's bias is in the verdict
    assert any("systematic offset" in line for line in doc["verdict"])
    assert any(w["stage"] == "ortho" for w in doc["warnings"])
    pdf = (out / "report.pdf").read_bytes()
    assert len(re.findall(rb"/Type\s*/Page\b(?!s)", pdf)) >= 4  # verdict, map, rasters, tables
    page = (out / "report.html").read_text()
    assert "<h1>autzen_rendered</h1>" in page
    assert "alt=\"mosaic and DSM\"" in page and "alt=\"check point residual map\"" in page


def _bad(args: list[str]) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["process", *args, "--no-progress"])
    return result.exit_code, result.stderr


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "out"
    code, err = _bad([str(STRIP), "--out", str(out), "--method", "fast"])
    assert code == 2 and err == ("seqat: error: --method: expected one of seq-r, seq-f, sim, "
                                 "got 'fast'\n")
    code, err = _bad([str(STRIP), "--out", str(out), "--no-ortho", "--dsm", "d.tif"])
    assert code == 2 and "--dsm and --ortho-options need the ortho" in err
    code, err = _bad([str(tmp_path / "absent"), "--out", str(out)])
    assert code == 2 and err.startswith("seqat: error: ") and err.count("\n") == 1
    assert not out.exists()


def test_broken_check_points_are_found_before_the_run(tmp_path: Path) -> None:
    flight = tmp_path / "flight"
    shutil.copytree(AUTZEN, flight)
    (flight / "checkpoint_obs.csv").unlink()
    code, err = _bad([str(flight), "--out", str(tmp_path / "out")])
    assert code == 2 and err.count("\n") == 1
    assert "checkpoint_obs.csv" in err
    assert not (tmp_path / "out").exists()
    (flight / "checkpoints.csv").write_text("point,x_m,y_m,z_m\ncp1,1.0,oops,3.0\n")
    (flight / "checkpoint_obs.csv").write_text("image,point,x_px,y_px\n")
    code, err = _bad([str(flight), "--out", str(tmp_path / "out")])
    assert code == 2 and err.count("\n") == 1 and "checkpoints.csv" in err and "y_m" in err
    assert not (tmp_path / "out").exists()
