"""GNSS dropouts: nav rows without a fix, the 6-DoF resection that bridges them, end to end."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.flight.dropout import MIN_POINTS, predict_missing, resect_pose
from pipeline.flight.folder import read_flight, read_truth
from pipeline.reference.stage import run_reference
from pipeline.report.stage import make_report
from pipeline.run.runner import run_flight
from pipeline.run.store import read_eop_csv, read_run
from seqat.cvframe import cv_pose_from_eop
from seqat.simulate import SimulatedFlight

from ..conftest import REPO_ROOT

STRIP = REPO_ROOT / "sample_data" / "strip_demo"
RENDERED = REPO_ROOT / "sample_data" / "autzen_rendered"
#: A resection on exact ground points with 1 px noise (paper camera, 200 m, ~15 points):
#: within this. Its 28° field over flat ground trades position for tilt (3.5 m per degree).
RESECTION_TOL_M = 2.0
RESECTION_TOL_DEG = 0.5


def test_resection_recovers_the_pose_despite_a_blunder(short_strip: SimulatedFlight) -> None:
    f = short_strip
    for i in (15, 30, 45):
        m = f.obs_image == i
        xyz, uv = f.truth_xyz[f.obs_point[m]], f.obs_uv[m].copy()
        uv[0] += 60.0  # a wrong match
        res = resect_pose(xyz, uv, f.camera, sigma_px=f.sigma_px)
        assert res.eop is not None and not res.inliers[0] and res.inliers[1:].all()
        d = res.eop - f.truth_eop[i]
        assert np.linalg.norm(d[:3]) < RESECTION_TOL_M
        assert np.degrees(np.abs(d[3:])).max() < RESECTION_TOL_DEG
        assert res.rms_px < 3.0 * f.sigma_px


@pytest.mark.parametrize("distortion", [{}, {"k1": -0.25, "k2": 0.06, "p2": -0.002}])
def test_resection_uses_the_opencv_pose_convention(short_strip: SimulatedFlight,
                                                   distortion: dict[str, float]) -> None:
    """Noise-free pixels: the pose is exact (a sign slip in the OpenCV frame would not be),
    through a distorted camera too (its coefficients in OpenCV's order)."""
    f = short_strip
    i = 20
    m = f.obs_image == i
    from seqat.geometry import project

    camera = dataclasses.replace(f.camera, **distortion)
    xyz = f.truth_xyz[f.obs_point[m]]
    uv = project(np.broadcast_to(f.truth_eop[i], (xyz.shape[0], 6)), xyz, camera)
    res = resect_pose(xyz, uv, camera)
    assert res.eop is not None
    R_est, t_est = cv_pose_from_eop(res.eop[None])
    R_true, t_true = cv_pose_from_eop(f.truth_eop[i][None])
    np.testing.assert_allclose(R_est, R_true, atol=1e-7)
    np.testing.assert_allclose(res.eop[:3], f.truth_eop[i, :3], rtol=0, atol=1e-4)


def test_too_few_points_give_a_reason(short_strip: SimulatedFlight) -> None:
    f = short_strip
    m = np.flatnonzero(f.obs_image == 20)[: MIN_POINTS - 1]
    res = resect_pose(f.truth_xyz[f.obs_point[m]], f.obs_uv[m], f.camera)
    assert res.eop is None and f"at least {MIN_POINTS}" in res.reason


def test_missing_nav_is_predicted_from_earlier_rows_only() -> None:
    eop = np.array([[0.0, 0, 100, 0.1, 0, 0], [10.0, 0, 100, 0.2, 0, 0],
                    [np.nan] * 3 + [0.3, 0, 0], [np.nan] * 6, [40.0, 0, 100, 0.5, 0, 0]])
    t = np.array([0.0, 1.0, 2.0, 4.0, 5.0])
    out = predict_missing(eop, t)
    np.testing.assert_allclose(out[2], [20.0, 0, 100, 0.3, 0, 0])  # 10 m/s on, own attitude
    np.testing.assert_allclose(out[3], [40.0, 0, 100, 0.3, 0, 0])  # row 4 is not used
    np.testing.assert_allclose(out[[0, 1, 4]], eop[[0, 1, 4]])


def _strip_with_dropout(folder: Path, images: range, extra_nav: str = "") -> None:
    shutil.copytree(STRIP, folder)
    lines = (folder / "nav.csv").read_text().splitlines()
    for k in images:
        f = lines[k + 1].split(",")
        lines[k + 1] = ",".join(f[:2] + ([""] * 3 + f[5:] if k % 2 else [""] * 6))
    (folder / "nav.csv").write_text("\n".join(lines) + "\n")
    if extra_nav:
        text = (folder / "flight.yaml").read_text()
        (folder / "flight.yaml").write_text(text.replace("nav:\n", "nav:\n" + extra_nav))


def test_empty_nav_fields_are_a_dropout_or_skipped(tmp_path: Path) -> None:
    _strip_with_dropout(tmp_path / "bridge", range(30, 34))
    flight = read_flight(tmp_path / "bridge")
    assert len(flight.nav) == 60 and np.isnan(flight.nav.eop[30:34, :3]).all()
    assert np.isfinite(flight.nav.eop[31, 3:]).all()  # odd rows keep their attitude
    frames = list(flight.frames())
    assert np.isinf(frames[30].nav_sigma).all() and np.isinf(frames[31].nav_sigma[:3]).all()
    assert np.isfinite(frames[31].nav_sigma[3:]).all()
    step = flight.nav.eop[29, :3] - flight.nav.eop[28, :3]
    np.testing.assert_allclose(frames[32].nav_eop[:3], flight.nav.eop[29, :3] + 3 * step)
    _strip_with_dropout(tmp_path / "skip", range(30, 34), "  dropout: skip\n")
    skip = read_flight(tmp_path / "skip")
    assert len(skip.nav) == 56 and [s.image for s in skip.skipped] == [
        f"img_{k + 1:04d}" for k in range(30, 34)]
    assert "GNSS dropout" in skip.skipped[0].reason
    assert len(list(skip.frames())) == 56  # their observations are left out too


def test_dropout_of_an_observations_flight_is_bridged_end_to_end(tmp_path: Path) -> None:
    flight = tmp_path / "flight"
    _strip_with_dropout(flight, range(30, 40))
    out = tmp_path / "out"
    run_flight(flight, out, progress=False)
    run = read_run(out)
    rob = run.record["robustness"]
    assert rob["dropout_bridged"] == [f"img_{k + 1:04d}" for k in range(30, 40)]
    assert rob["dropout_skipped"] == [] and rob["snooping_critical"] is None
    assert rob["final_reopen_skipped"] == 0  # a 60-image strip: every departed key re-opened
    truth = read_truth(flight)
    assert truth is not None
    err = np.linalg.norm(run.eop.eop[:, :3] - truth.eop.eop[:, :3], axis=1)
    around = np.sqrt(np.mean(np.r_[err[20:30], err[40:50]] ** 2))
    assert err[30:40].max() < 4.0 * around  # 5 s without GNSS on a 60-image strip
    assert np.isnan(run.nav.eop[30:40, :3]).all()  # the run's nav.csv keeps the dropout
    summary = make_report(out)  # a report of a dropout run: the direct method skips them
    assert summary.report.robustness is not None
    assert summary.report.robustness.dropout_bridged == 10
    ref = run_reference(out).record  # COLMAP: a free prior on the missing components, as Sim
    assert ref.n_images_adjusted == 60 and abs(ref.sigma0 - run.record["totals"]["sigma0"]) < 0.01
    ref_eop = read_eop_csv(out / "reference" / "eop.csv")
    d = np.linalg.norm(ref_eop.eop[30:40, :3] - run.eop.eop[30:40, :3], axis=1)
    assert d.max() < 0.05  # metres: Sim's minimum, which the sequential run reached


def test_images_without_a_fix_are_bridged_in_an_image_flight(tmp_path: Path) -> None:
    """The rendered sample with img_0008 without a nav row and img_0009 without a position:
    both are resected on the initial stage's ground points and adjusted."""
    flight = tmp_path / "flight"
    shutil.copytree(RENDERED, flight)
    lines = (flight / "nav.csv").read_text().splitlines()
    out_lines = []
    for line in lines:
        f = line.split(",")
        if f[0] == "img_0008":
            continue
        if f[0] == "img_0009":
            f = f[:2] + [""] * 3 + f[5:]
        out_lines.append(",".join(f))
    (flight / "nav.csv").write_text("\n".join(out_lines) + "\n")
    read = read_flight(flight)
    assert read.nav.image_ids[7] == "img_0008" and read.is_dropout(7) and read.is_dropout(8)
    assert read.nav.times_s[6] < read.nav.times_s[7] < read.nav.times_s[8]
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", str(flight), "--out", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    doc = json.loads((out / "run.json").read_text())
    assert doc["robustness"]["dropout_bridged"] == ["img_0008", "img_0009"]
    truth = read_truth(RENDERED)
    assert truth is not None
    eop = read_eop_csv(out / "eop.csv")
    err = np.linalg.norm(eop.eop[:, :3] - truth.eop.eop[:, :3], axis=1)
    assert err[7:9].max() < 0.5  # metres, at 120 m height (neighbours: ~0.05-0.1 m)


@pytest.mark.parametrize("edit", ["nan", "1e999"])
def test_a_non_finite_nav_field_is_a_dropout_or_an_error(tmp_path: Path, edit: str) -> None:
    shutil.copytree(STRIP, tmp_path / "f")
    lines = (tmp_path / "f" / "nav.csv").read_text().splitlines()
    f = lines[20].split(",")
    lines[20] = ",".join(f[:2] + [edit] + f[3:])
    (tmp_path / "f" / "nav.csv").write_text("\n".join(lines) + "\n")
    result = CliRunner().invoke(app, ["run", str(tmp_path / "f"), "--out",
                                      str(tmp_path / "o"), "--no-progress"])
    if edit == "nan":
        assert result.exit_code == 0, result.output
    else:  # not a dropout: a bad value (exit 2, nothing written)
        assert result.exit_code == 2 and "x_m" in result.stderr
        assert not (tmp_path / "o").exists()
