"""The independent SfM check (``seqat reference OUT --sfm``): the similarity, the stage on real
images (sample_data/seneca_mini), its files, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.common.columns import REFERENCE_DIR, SFM_DIR
from pipeline.common.csvio import read_csv
from pipeline.reference.sfm import SfmOptions
from pipeline.reference.sfm_stage import (
    DIRECT,
    REFERENCE,
    SFM_IMAGE_COLUMNS,
    SFM_IMAGES_CSV,
    SFM_JSON,
    SFM_MODEL_DIR,
    SFM_PLOT,
    SfmSummary,
    run_sfm_check,
)
from pipeline.reference.similarity import fit_similarity, pose_agreement
from seqat.cvframe import cv_pose_from_eop
from seqat.errors import EstimationError

from ..sample_runs import MINI, copy_run_files

#: The check on the 18 Seneca sample images (~25 s CPU) with every default: SIFT's first octave
#: 0 and the mapper's thresholds lowered for the weakly textured fields of images 466-470
#: (with COLMAP's mapper defaults, min_pose_inliers=30 and no two-view tracks, 11 of 18
#: register).
FAST = SfmOptions()
#: Measured with FAST (2026-12-01, pycolmap 4.2.1): 17 of 18 registered, 0.25 px; Seq-R agrees
#: with the SfM to 2.7 m / 4.3 deg rms (max 4.8 m, 7.9 deg), mostly in height (Z 2.4 m rms).
#: Both are weak here: the run's camera is EXIF's without distortion, and an 18-image nadir
#: strip hardly separates the SfM's focal length from the height (f 745 px with these options,
#: 679 px with 11 images registered, EXIF 694): 7 % of f is 4 m of the 62 m height. The bounds
#: leave ~1.5x margin over that; the nav itself (direct) is 17 deg rms off in attitude, so the
#: attitude bound discriminates.
MIN_REGISTERED = 15
SEQ_R_POS_RMS_M = 4.0
SEQ_R_ATT_RMS_DEG = 6.0
#: Known-answer test of the similarity: noise of the centres (m) and what is recovered.
NOISE_M = 0.02
SCALE_REL = 1e-4
ROTATION_DEG = 0.01
TRANSLATION_M = 0.1


# --------------------------------------------------------------------------------------------
# The similarity (no images)
# --------------------------------------------------------------------------------------------


def _block(rng: np.random.Generator, n: int) -> np.ndarray:
    """EOPs of a block over a UTM-like origin: 400 m x 300 m at 100 m, near nadir."""
    pos = np.column_stack([rng.uniform(0, 400, n), rng.uniform(0, 300, n),
                           rng.normal(100, 3, n)]) + [5e5, 4.5e6, 200.0]
    ang = np.column_stack([rng.normal(0, 0.05, n), rng.normal(0, 0.05, n),
                           rng.uniform(-np.pi, np.pi, n)])
    return np.column_stack([pos, ang])


def _sfm_frame(eop: np.ndarray, scale: float, R: np.ndarray, t: np.ndarray) -> (
        tuple[np.ndarray, np.ndarray]):
    """Centres and cam_from_world rotations of ``eop`` in a frame ``x_sfm = s R x + t``."""
    R_cw, _ = cv_pose_from_eop(eop)
    centres = scale * eop[:, :3] @ R.T + t
    return centres, np.einsum("nij,kj->nik", R_cw, R)


def test_similarity_recovers_a_known_sim3_with_noise_and_outliers() -> None:
    rng = np.random.default_rng(7)
    eop = _block(rng, 40)
    R_true = Rotation.from_euler("zyx", [40, -20, 130], degrees=True).as_matrix()
    s_true, t_true = 0.0137, np.array([3.0, -7.0, 11.0])
    centres, R_cw = _sfm_frame(eop, s_true, R_true, t_true)
    centres = centres + rng.normal(0, NOISE_M * s_true, centres.shape)
    outliers = [3, 17, 29]
    centres[outliers] += [5.0 * s_true, -8.0 * s_true, 6.0 * s_true]  # metres in the world
    a = pose_agreement(centres, R_cw, eop)
    # method_from_sfm is the inverse of the known transform
    sim = a.similarity
    assert sim.scale == pytest.approx(1.0 / s_true, rel=SCALE_REL)
    angle = np.degrees(Rotation.from_matrix(sim.rotation @ R_true).magnitude())
    assert angle < ROTATION_DEG
    back = sim.apply(s_true * eop[:, :3] @ R_true.T + t_true)
    np.testing.assert_allclose(back, eop[:, :3], rtol=0, atol=TRANSLATION_M)
    assert not a.inlier[outliers].any() and a.inlier.sum() == len(eop) - len(outliers)
    inl = a.inlier
    # residuals: the noise on inliers, the displacement on outliers; attitudes exact
    assert np.sqrt(np.mean(a.d_position_m[inl] ** 2)) < 3 * NOISE_M * np.sqrt(3)
    np.testing.assert_allclose(a.d_position_m[outliers], np.linalg.norm([5.0, -8.0, 6.0]),
                               atol=0.1)
    assert np.degrees(a.d_rotation_rad).max() < ROTATION_DEG
    assert np.degrees(np.abs(a.d_angles_rad)).max() < ROTATION_DEG


def test_similarity_sees_an_attitude_error_after_alignment() -> None:
    """A 1 deg roll of one image shows as 1 deg in it and nowhere else."""
    rng = np.random.default_rng(8)
    eop = _block(rng, 20)
    centres, R_cw = _sfm_frame(eop, 2.0, np.eye(3), np.zeros(3))
    tilted = eop.copy()
    tilted[5, 3] += np.radians(1.0)
    a = pose_agreement(centres, R_cw, tilted)
    deg = np.degrees(a.d_rotation_rad)
    assert deg[5] == pytest.approx(1.0, abs=1e-6)
    assert np.delete(deg, 5).max() < 1e-6
    assert np.degrees(a.d_angles_rad[5, 0]) == pytest.approx(-1.0, abs=1e-6)


def test_similarity_needs_five_points() -> None:
    with pytest.raises(EstimationError, match="needs >= 5"):
        fit_similarity(np.zeros((4, 3)), np.zeros((4, 3)))


# --------------------------------------------------------------------------------------------
# The stage on real images
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mini_run(mini_chain: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The session's Seq-R run of the sample as a plain ``seqat run`` folder (a copy: the
    check writes into it)."""
    return copy_run_files(mini_chain, tmp_path_factory.mktemp("sfm_mini") / "run")


@pytest.fixture(scope="module")
def mini_sfm(mini_run: Path) -> SfmSummary:
    return run_sfm_check(mini_run, FAST, progress=False)


def test_sfm_registers_the_sample_and_agrees_with_seq_r(mini_sfm: SfmSummary) -> None:
    s = mini_sfm
    assert s.n_images == 18 and s.n_registered >= MIN_REGISTERED
    stats = dict(s.methods)
    assert set(stats) == {"seq-r", DIRECT}
    seq_r = stats["seq-r"]
    assert seq_r.n_images == s.n_registered
    assert seq_r.position_rms_m < SEQ_R_POS_RMS_M
    assert seq_r.attitude_rms_deg < SEQ_R_ATT_RMS_DEG
    # the bounds discriminate: the nav alone does not meet them
    assert stats[DIRECT].attitude_rms_deg > SEQ_R_ATT_RMS_DEG
    # self-calibrated: distortion found, focal length within 15 % of EXIF's
    assert s.camera.model == "OPENCV" and s.camera.k1 != 0.0
    assert s.camera.fx_px == pytest.approx(s.run_camera.fx_px, rel=0.15)
    assert 0.1 < s.mean_reprojection_px < 1.0 and s.mean_track_length > 2.0


def test_sfm_files_are_complete_and_consistent(mini_sfm: SfmSummary) -> None:
    folder = mini_sfm.sfm_dir
    assert folder == mini_sfm.out_dir / REFERENCE_DIR / SFM_DIR
    names = {p.name for p in folder.iterdir()}
    assert names == {SFM_JSON, SFM_IMAGES_CSV, SFM_PLOT, SFM_MODEL_DIR}  # no scratch left
    doc = json.loads((folder / SFM_JSON).read_text(encoding="utf-8"))
    assert doc["version"] == 1 and doc["n_registered"] == mini_sfm.n_registered
    assert len(doc["unregistered"]) == doc["n_images"] - doc["n_registered"]
    assert "not accuracy" in doc["note"]
    rows = list(read_csv(folder / SFM_IMAGES_CSV, SFM_IMAGE_COLUMNS))
    for m in doc["methods"]:
        mine = [r for r in rows if r.values["method"] == m["label"]]
        assert len(mine) == m["n_images"]
        d = np.array([r.number("d_m") for r in mine])
        assert np.sqrt(np.mean(d ** 2)) == pytest.approx(m["position_rms_m"], rel=1e-12)
        assert sum(r.values["inlier"] == "1" for r in mine) == m["n_inliers"]
    assert (folder / SFM_PLOT).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert {p.name for p in (folder / SFM_MODEL_DIR).iterdir()} >= {"cameras.bin", "images.bin"}


def test_realign_keeps_the_model_and_adds_a_method(mini_sfm: SfmSummary,
                                                    mini_run: Path, tmp_path: Path) -> None:
    """--realign: the same model aligned again, here also to a second run (a copy)."""
    other = _copy_run(mini_run, tmp_path)
    again = run_sfm_check(mini_sfm.out_dir, SfmOptions(max_num_features=1), compare=[other],
                          realign=True, progress=False)
    assert again.n_registered == mini_sfm.n_registered
    assert again.camera == mini_sfm.camera
    labels = [label for label, _ in again.methods]
    assert labels == ["seq-r", "seq-r (run)", DIRECT]
    first, copy = dict(again.methods)["seq-r"], dict(again.methods)["seq-r (run)"]
    assert first == dict(mini_sfm.methods)["seq-r"] == copy
    doc = json.loads((again.sfm_dir / SFM_JSON).read_text(encoding="utf-8"))
    assert doc["options"]["max_num_features"] == FAST.max_num_features  # the model's options


def test_bundle_adjustment_keeps_the_check_and_realign_adds_it(mini_sfm: SfmSummary,
                                                               tmp_path: Path) -> None:
    """`seqat reference OUT` rewrites OUT/reference/ whole but keeps sfm/; --realign then
    compares the SfM with the bundle adjustment (`colmap`) too."""
    from pipeline.reference.stage import run_reference

    out = tmp_path / "run"
    shutil.copytree(mini_sfm.out_dir, out)
    run_reference(out)
    assert (out / REFERENCE_DIR / SFM_DIR / SFM_JSON).is_file()
    again = run_sfm_check(out, realign=True, progress=False)
    assert [label for label, _ in again.methods] == ["seq-r", REFERENCE, DIRECT]
    assert dict(again.methods)[REFERENCE].attitude_rms_deg < SEQ_R_ATT_RMS_DEG


def test_report_shows_the_agreement(mini_sfm: SfmSummary) -> None:
    from pipeline.report.stage import make_report

    make_report(mini_sfm.out_dir)
    html = (mini_sfm.out_dir / "report.html").read_text(encoding="utf-8")
    assert "Agreement with an independent SfM" in html and "not an accuracy" in html
    doc = json.loads((mini_sfm.out_dir / "report.json").read_text(encoding="utf-8"))
    assert doc["sfm_agreement"]["n_registered"] == mini_sfm.n_registered


# --------------------------------------------------------------------------------------------
# Bad input: one line, exit 2, nothing written
# --------------------------------------------------------------------------------------------


def _copy_run(mini_run: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(mini_run, out, ignore=shutil.ignore_patterns(REFERENCE_DIR, "report.*"))
    return out


def _set_images_dir(out: Path, value: str | None) -> None:
    doc = json.loads((out / "run.json").read_text(encoding="utf-8"))
    doc["images_dir"] = value
    (out / "run.json").write_text(json.dumps(doc), encoding="utf-8")


def _fails(out: Path, *args: str) -> str:
    result = CliRunner().invoke(app, ["reference", str(out), "--sfm", *args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("seqat: error: ")
    assert "Traceback" not in result.output
    assert not (out / REFERENCE_DIR).exists()
    return lines[0]


def test_bad_input_without_images(mini_run: Path, tmp_path: Path) -> None:
    out = _copy_run(mini_run, tmp_path)
    _set_images_dir(out, None)
    assert "the run has no images" in _fails(out)
    _set_images_dir(out, str(tmp_path / "gone"))
    assert "no such image folder" in _fails(out)


def test_bad_input_missing_images(mini_run: Path, tmp_path: Path) -> None:
    out = _copy_run(mini_run, tmp_path)
    images = tmp_path / "images"
    shutil.copytree(MINI / "images", images)
    for name in ("IMG_0463.jpg", "IMG_0470.jpg"):
        (images / name).unlink()
    _set_images_dir(out, str(images))
    line = _fails(out)
    assert "2 of the run's 18 images are missing: IMG_0463, IMG_0470" in line


def test_too_few_images_registered_is_an_error(mini_run: Path, tmp_path: Path) -> None:
    """Six tiny copies of the images (200 px, 300 features) do not make a model of 6."""
    out = _copy_run(mini_run, tmp_path)
    line = _fails(out, "--max-image-size", "200", "--max-features", "300")
    assert "registered" in line or "no model" in line


def test_bad_option() -> None:
    result = CliRunner().invoke(app, ["reference", "x", "--sfm", "--matching", "vocab"])
    assert result.exit_code == 2 and "--matching: expected one of" in result.stderr
