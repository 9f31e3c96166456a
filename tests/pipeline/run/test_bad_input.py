"""Issue 13: what a run says about bad input is one line per message, however long."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.cli import app

RUN_ARGS = ["--method", "seq-f", "--initial-images", "6", "--no-progress"]


def test_long_skip_lines_are_not_wrapped(small_sim_dir: Path, tmp_path: Path) -> None:
    flight = Path(shutil.copytree(small_sim_dir, tmp_path / "flight"))
    long_id = "img_0012_taken_by_the_second_camera_of_a_flight_with_very_long_image_names"
    for name in ("nav.csv", "observations.csv"):
        (flight / name).write_text((flight / name).read_text().replace("img_0012", long_id))
    nav = (flight / "nav.csv").read_text().splitlines(keepends=True)
    row = [line for line in nav if line.startswith(long_id)][0].split(",")
    row[2] = ""  # no position: a GNSS dropout
    nav = [",".join(row) if line.startswith(long_id) else line for line in nav]
    (flight / "nav.csv").write_text("".join(nav))
    yaml = (flight / "flight.yaml").read_text().replace("nav:\n", "nav:\n  dropout: skip\n")
    (flight / "flight.yaml").write_text(yaml)
    result = CliRunner().invoke(app, ["run", str(flight), "--out", str(tmp_path / "out"),
                                      *RUN_ARGS])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.stderr.splitlines() if long_id in line]
    assert len(lines) == 1
    assert lines[0].startswith("seqat: skipped: ") and lines[0].endswith("nav.dropout: skip)")
    assert len(lines[0]) > 100


def test_observations_outside_the_image_are_a_warning_in_run_json(
        small_sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    flight = Path(shutil.copytree(small_sim_dir, tmp_path / "flight"))
    lines = (flight / "observations.csv").read_text().splitlines(keepends=True)
    image, point, _, y = lines[5].strip().split(",")
    lines[4] = lines[4].split(",")[0] + "," + lines[4].split(",")[1] + ",-1.93," + y + "\n"
    lines[5] = f"{image},{point},-400.0,{y}\n"
    (flight / "observations.csv").write_text("".join(lines))
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", str(flight), "--out", str(out), *RUN_ARGS])
    assert result.exit_code == 0, result.output
    doc = json.loads((out / "run.json").read_text())
    expected = (f"{flight / 'observations.csv'}: 1 of {len(lines) - 1} observation(s) lie more "
                f"than 5 sigma_image_px outside the image and were left out (first: "
                f"{flight / 'observations.csv'}:6: pixel (-400.0, {float(y)!r}) of point "
                f"'{point}' lies outside the 2456 x 2058 px image)")
    assert doc["warnings"] == [expected]
    assert f"seqat: warning: {expected}\n" in result.stderr
    assert doc["totals"]["observations"] == len(lines) - 2
    # a benchmark's further runs of the flight record the warning without printing it again
    from pipeline.run.runner import run_flight

    run_flight(flight, tmp_path / "again", progress=False, echo_warnings=False)
    assert json.loads((tmp_path / "again" / "run.json").read_text())["warnings"] == [expected]
    assert "seqat:" not in capsys.readouterr().err


def test_corrupt_image_data_skips_the_image(tmp_path: Path) -> None:
    from pipeline.flight.folder import read_flight
    from pipeline.flight.inputs import SkippedImage
    from pipeline.run.sources import ImageSource

    src = Path("sample_data/seneca_mini/images")
    (tmp_path / "images").mkdir()
    paths = [Path(shutil.copy(p, tmp_path / "images" / p.name))
             for p in sorted(src.glob("*.jpg"))[:3]]
    data = bytearray(paths[1].read_bytes())
    sos = data.rfind(b"\xff\xda")  # the main image's scan (an EXIF thumbnail has one too)
    data[sos + 200: sos + 260] = b"\xff\xd8" * 30  # entropy-coded data damaged, headers intact
    paths[1].write_bytes(bytes(data))
    flight = read_flight(tmp_path)
    assert paths[1].stem in flight.nav.image_ids  # the file looks like a complete JPEG
    source = ImageSource(flight, flight.config.tracking)
    row = flight.nav.image_ids.index(paths[1].stem)
    nav_eop, nav_sigma = flight.frame_nav(row)
    result = source.prepare(paths[1].stem, flight.image_paths[row], nav_eop,
                            float(flight.nav.times_s[row]), nav_sigma=nav_sigma)
    assert isinstance(result, SkippedImage)
    assert result.reason.startswith(f"{paths[1].name}: corrupt JPEG data (marker 0xffd8 inside")


def test_sample_images_pass_the_scan_check() -> None:
    from pipeline.tracking.decode import jpeg_scan_problem

    paths = sorted(Path("sample_data").glob("*/images/*.jpg"))
    assert paths
    assert [p for p in paths if jpeg_scan_problem(p.read_bytes()) is not None] == []


def test_images_and_flights_without_tie_points_are_warned_about(small_sim_dir: Path,
                                                                tmp_path: Path) -> None:
    flight = Path(shutil.copytree(small_sim_dir, tmp_path / "flight"))
    obs = (flight / "observations.csv").read_text().splitlines(keepends=True)
    (flight / "observations.csv").write_text(
        "".join(line for line in obs if not line.startswith("img_0010,")))
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", str(flight), "--out", str(out), *RUN_ARGS])
    assert result.exit_code == 0, result.output
    expected = ("img_0010: no tie points (none of its observations is a ground point of the "
                "solution); its EOP rests on its GPS/INS nav")
    assert f"seqat: warning: {expected}\n" in result.stderr
    assert json.loads((out / "run.json").read_text())["warnings"] == [expected]

    (flight / "observations.csv").write_text(obs[0])  # not one tie point
    result = CliRunner().invoke(app, ["run", str(flight), "--out", str(out), *RUN_ARGS])
    assert result.exit_code == 0, result.output
    assert "seqat: warning: the flight has no tie points: no ground point was estimated " \
        "from its 24 images" in result.stderr


def test_calibration_in_the_estimator_options_is_refused(small_sim_dir: Path,
                                                        tmp_path: Path) -> None:
    """The self-calibration belongs to the flight (flight.yaml, --self-calibration): an
    estimator options file that sets it would be overridden silently; it is refused."""
    opts = tmp_path / "opts.yaml"
    opts.write_text("sequential:\n  calibration:\n    free: [f_px]\n")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", str(small_sim_dir), "--out", str(out),
                                      "--options", str(opts), "--no-progress"])
    assert result.exit_code == 2
    assert "calibration: the self-calibration is set in flight.yaml" in result.output
    assert not out.exists()
