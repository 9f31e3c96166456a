"""Issue 13: bad output folders never overwrite inputs or the user's files, and output errors
are bad input (exit 2, one line naming the user's path)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.common.outdir import RUN_MARKER

RUN_ARGS = ["--method", "seq-f", "--initial-images", "6", "--no-progress"]


@pytest.fixture
def flight(small_sim_dir: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(small_sim_dir, tmp_path / "flight"))


def _run(flight: Path, out: Path, *extra: str) -> object:
    return CliRunner().invoke(app, ["run", str(flight), "--out", str(out), *RUN_ARGS, *extra])


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


@pytest.mark.parametrize("where", ["flight", "inside", "truth"])
def test_out_in_or_at_the_inputs_is_refused(flight: Path, where: str) -> None:
    before = _snapshot(flight)
    out = {"flight": flight, "inside": flight / "runs" / "a", "truth": flight / "truth"}[where]
    result = _run(flight, out)
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(f"seqat: error: {out}: --out ")
    assert result.stderr.count("\n") == 1
    assert _snapshot(flight) == before
    assert not (flight / "runs").exists()


def test_out_containing_the_flight_is_refused(flight: Path, tmp_path: Path) -> None:
    result = _run(flight, tmp_path)
    assert result.exit_code == 2, result.output
    assert "contains the input" in result.stderr


def test_user_files_in_out_are_never_overwritten(flight: Path, tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "eop.csv").write_text("my own eop\n")
    result = _run(flight, out)
    assert result.exit_code == 2, result.output
    assert "is not a seqat run folder" in result.stderr
    assert (out / "eop.csv").read_text() == "my own eop\n"
    assert sorted(os.listdir(out)) == ["eop.csv"]


def test_run_folder_is_marked_and_may_be_rerun(flight: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _run(flight, out).exit_code == 0
    assert (out / RUN_MARKER).is_file()
    result = _run(flight, out)  # seqat's own folder: replaced
    assert result.exit_code == 0, result.output
    legacy = tmp_path / "legacy"  # a run folder written before the marker: run.json marks it
    shutil.copytree(out, legacy)
    (legacy / RUN_MARKER).unlink()
    assert _run(flight, legacy).exit_code == 0


def test_failed_run_creates_no_folder(flight: Path, tmp_path: Path) -> None:
    (flight / "nav.csv").write_text("image,time_s\n")
    out = tmp_path / "new" / "out"
    assert _run(flight, out).exit_code == 2
    assert not (tmp_path / "new").exists()


def test_option_file_inside_out_is_refused(flight: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / RUN_MARKER).write_text("")
    options = out / "options.yaml"
    options.write_text("sequential: {initial_images: 6}\n")
    result = _run(flight, out, "--options", str(options))
    assert result.exit_code == 2, result.output
    assert "contains the input" in result.stderr
    assert options.read_text() == "sequential: {initial_images: 6}\n"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_out_is_exit_2(flight: Path, tmp_path: Path) -> None:
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        result = _run(flight, parent / "out")
    finally:
        parent.chmod(0o755)
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(f"seqat: error: {parent / 'out'}: cannot write")
    assert "Permission denied" in result.stderr and ".tmp" not in result.stderr


def test_out_in_proc_is_exit_2(flight: Path) -> None:
    result = _run(flight, Path("/proc/seqat-out"))
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith("seqat: error: /proc/seqat-out: cannot write")


def test_dsm_out_existing_folder_is_exit_2(tmp_path: Path) -> None:
    las = Path("sample_data/autzen_rendered/lidar/surface.laz")
    if not las.is_file():
        pytest.skip("no sample LiDAR")
    out = tmp_path / "dsm"
    out.mkdir()
    result = CliRunner().invoke(app, ["dsm", str(las), "--out", str(out),
                                      "--las-crs", "EPSG:2994"])
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(f"seqat: error: {out}: ")
    assert ".tmp" not in result.stderr and result.stderr.count("\n") == 1


def test_dsm_out_over_its_input_is_refused(tmp_path: Path) -> None:
    las = Path("sample_data/autzen_rendered/lidar/surface.laz")
    if not las.is_file():
        pytest.skip("no sample LiDAR")
    copy = tmp_path / "surface.laz"
    shutil.copy(las, copy)
    result = CliRunner().invoke(app, ["dsm", str(copy), "--out", str(copy)])
    assert result.exit_code == 2, result.output
    assert copy.read_bytes() == las.read_bytes()


def test_failed_watch_keeps_the_journal_and_creates_nothing(flight: Path,
                                                            tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _run(flight, out).exit_code == 0
    journal = _snapshot(out / "journal")
    assert journal
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "flight.yaml").write_text((flight / "flight.yaml").read_text()
                                     .replace("observations: observations.csv",
                                              "images: images"))
    for target in (out, tmp_path / "new"):
        result = CliRunner().invoke(app, ["watch", str(bad), "--out", str(target),
                                          "--idle-timeout-s", "0.1"])
        assert result.exit_code == 2, result.output
        assert "no such image folder" in result.stderr
    assert _snapshot(out / "journal") == journal
    assert not (tmp_path / "new").exists()


def test_dsm_out_in_proc_is_exit_2() -> None:
    las = Path("sample_data/autzen_rendered/lidar/surface.laz")
    if not las.is_file():
        pytest.skip("no sample LiDAR")
    result = CliRunner().invoke(app, ["dsm", str(las), "--out", "/proc/seqat-dsm.tif"])
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith("seqat: error: /proc/seqat-dsm.tif: cannot write")
    assert ".tmp" not in result.stderr


def test_write_files_atomically_names_the_folder(tmp_path: Path) -> None:
    from pipeline.common.atomic import atomic_write_text, write_files_atomically
    from seqat.errors import InputDataError

    with pytest.raises(InputDataError, match=r"^/proc/seqat-x: cannot write: "):
        write_files_atomically(Path("/proc/seqat-x"), {"a.csv": "x\n"})
    with pytest.raises(InputDataError, match=r"is a folder"):
        atomic_write_text(tmp_path, "x")


def test_bench_out_inside_the_flight_is_refused(flight: Path) -> None:
    result = CliRunner().invoke(app, ["bench", str(flight), "--out", str(flight / "bench")])
    assert result.exit_code == 2, result.output
    assert "lies inside the input" in result.stderr
    assert not (flight / "bench").exists()
