"""The COLMAP reference: conventions, the prior model, agreement with Sim, the stage and CLI."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.common.columns import REFERENCE_DIR
from pipeline.flight.schema import CameraConfig
from pipeline.reference.colmap_ba import (
    COLMAP_PIXEL_OFFSET,
    OBS_RESIDUALS,
    POSE_PRIOR_RESIDUALS,
    PriorKind,
    ReferenceInput,
    ReferenceOptions,
    RobustLoss,
    adjust_reference,
    camera_config_from_colmap,
    colmap_camera,
    eop_from_rigid,
    loss_of_run,
    loss_weight,
    rigid_from_eop,
    run_loss_scale,
)
from pipeline.reference.stage import (
    COLMAP_MODEL_DIR,
    REFERENCE_JSON,
    check_prior_geometry,
    run_reference,
)
from pipeline.run.runner import Method, run_flight
from pipeline.run.store import read_eop_csv, read_points_csv
from seqat.cvframe import cv_pose_from_eop, pose_prior_covariance
from seqat.errors import EstimationError
from seqat.geometry import project, rotation_matrix
from seqat.robust import ROBUST_SCALE
from seqat.simulate import SimulatedFlight
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.types import PinholeCamera

#: Round trips of poses and projections (float64 arithmetic only). World (UTM) coordinates
#: of 4e6 m carry ~5e-10 m per ulp, so the metre bound is a few ulp there; projections are
#: compared in local coordinates (as the adjustment runs).
ROUND_TRIP_M = 5e-9
ROUND_TRIP_RAD = 1e-12
PROJECTION_PX = 1e-9
#: COLMAP's pixel convention: the centre of the top-left pixel is (0.5, 0.5); ours (OpenCV) 0, 0.
COLMAP_MINUS_OPENCV_PX = 0.5
#: A UTM-like world origin and the local one.
WORLD_ORIGIN = np.array([5e5, 4e6, 300.0])
LOCAL_ORIGIN = np.zeros(3)
#: COLMAP and Sim are the same estimator: the issue's bound, and what we measure (~0.5 mm).
AGREEMENT_POS_M = 0.01
AGREEMENT_ATT_DEG = 0.001
AGREEMENT_GP_M = 0.01
#: A robust Sim and COLMAP with Huber at the same scale: same core, different tails.
ROBUST_AGREEMENT_POS_M = 0.05
ROBUST_AGREEMENT_ATT_DEG = 0.01
#: A posteriori sigmas of COLMAP (converted) and of Sim, relative.
SIGMA_REL = 0.01


def random_eops(rng: np.random.Generator, n: int, origin: np.ndarray = LOCAL_ORIGIN) -> (
        np.ndarray):
    pos = rng.uniform(-1e3, 1e3, (n, 3)) + origin
    ang = np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n),
                           rng.uniform(-np.pi, np.pi, n)])
    return np.column_stack([pos, ang])


def test_pose_round_trip_through_pycolmap() -> None:
    rng = np.random.default_rng(1)
    for eop in np.concatenate([random_eops(rng, 10), random_eops(rng, 10, WORLD_ORIGIN)]):
        back = eop_from_rigid(rigid_from_eop(eop))
        np.testing.assert_allclose(back[:3], eop[:3], rtol=0, atol=ROUND_TRIP_M)
        np.testing.assert_allclose(back[3:], eop[3:], rtol=0, atol=ROUND_TRIP_RAD)


def test_nadir_camera_in_colmap_looks_down_with_image_top_north() -> None:
    """omega = phi = kappa = 0: COLMAP's z (forward) is world down, its y (down) south."""
    R_cv, t = cv_pose_from_eop(np.array([[10.0, 20.0, 100.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(R_cv[0], np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(t[0], [-10.0, 20.0, 100.0])


def test_colmap_principal_point_convention() -> None:
    """COLMAP's default principal point is the image centre W/2, H/2; ours is (W-1)/2."""
    default = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.OPENCV, 3000.0,
                                                    2000, 1500)
    ours = CameraConfig(model="PINHOLE", width_px=2000, height_px=1500, fx_px=3000.0,
                        fy_px=3000.0, cx_px=(2000 - 1) / 2, cy_px=(1500 - 1) / 2)
    np.testing.assert_allclose(colmap_camera(ours).params, default.params, rtol=0, atol=0)
    assert COLMAP_PIXEL_OFFSET == COLMAP_MINUS_OPENCV_PX


def test_projection_agrees_with_pycolmap_including_half_pixel() -> None:
    rng = np.random.default_rng(2)
    cam = PinholeCamera(f_px=3000.0, cx_px=999.5, cy_px=749.5, width_px=2000, height_px=1500)
    cfg = CameraConfig(model="PINHOLE", width_px=2000, height_px=1500, fx_px=3000.0,
                       fy_px=3000.0, cx_px=999.5, cy_px=749.5)
    colmap_cam = colmap_camera(cfg)
    assert colmap_cam.model_name == "OPENCV"
    for eop in random_eops(rng, 10):
        R = rotation_matrix(*eop[3:])
        X = eop[:3] + R @ np.array([rng.uniform(-50, 50), rng.uniform(-50, 50), -200.0])
        ours = project(eop[None], X[None], cam)[0]
        theirs = colmap_cam.img_from_cam(rigid_from_eop(eop) * X)
        np.testing.assert_allclose(theirs - COLMAP_MINUS_OPENCV_PX, ours, rtol=0,
                                   atol=PROJECTION_PX)


def test_distorted_projection_agrees_with_opencv() -> None:
    """COLMAP's OPENCV / FULL_OPENCV models = cv2.projectPoints, shifted by half a pixel."""
    rng = np.random.default_rng(3)
    for k3 in (0.0, 0.02):
        cfg = CameraConfig(model="OPENCV", width_px=2000, height_px=1500, fx_px=3000.0,
                           fy_px=3010.0, cx_px=990.0, cy_px=760.0, k1=-0.1, k2=0.05,
                           p1=1e-3, p2=-5e-4, k3=k3)
        colmap_cam = colmap_camera(cfg)
        assert colmap_cam.model_name == ("OPENCV" if k3 == 0 else "FULL_OPENCV")
        K = np.array([[cfg.fx_px, 0, cfg.cx_px], [0, cfg.fy_px, cfg.cy_px], [0, 0, 1.0]])
        for eop in random_eops(rng, 5):
            R_cv, t = cv_pose_from_eop(eop[None])
            R = rotation_matrix(*eop[3:])
            X = eop[:3] + R @ np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), -200.0])
            cv_uv, _ = cv2.projectPoints(X[None], cv2.Rodrigues(R_cv[0])[0], t[0], K,
                                         cfg.distortion)
            theirs = colmap_cam.img_from_cam(rigid_from_eop(eop) * X)
            np.testing.assert_allclose(theirs - COLMAP_MINUS_OPENCV_PX, cv_uv.reshape(2),
                                       rtol=0, atol=PROJECTION_PX)
        assert camera_config_from_colmap(colmap_cam, cfg) == cfg


def _colmap_prior_residual(eop: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """COLMAP's AbsolutePosePriorCost residual (unwhitened), written out in numpy."""
    R, t = cv_pose_from_eop(np.stack([eop, prior]))
    rho = cv2.Rodrigues(R[0] @ R[1].T)[0].reshape(3)
    tau = R[0] @ (prior[:3] - eop[:3])
    return np.concatenate([rho, tau])


def test_pose_prior_covariance_whitens_to_sims_prior_term() -> None:
    """r^T Sigma_r^-1 r equals Sim's sum((eop - nav)^2 / sigma^2) for small differences."""
    rng = np.random.default_rng(4)
    sigma = np.array([0.3, 0.3, 0.5, np.radians(0.1), np.radians(0.1), np.radians(0.2)])
    for prior in random_eops(rng, 10):
        cov = pose_prior_covariance(prior[None], sigma)[0]
        delta = rng.normal(0.0, 1.0, 6) * sigma
        r = _colmap_prior_residual(prior + delta, prior)
        colmap_term = r @ np.linalg.solve(cov, r)
        sim_term = np.sum((delta / sigma) ** 2)
        assert colmap_term == pytest.approx(sim_term, rel=1e-2)


def _sim_and_input(flight: SimulatedFlight, robust_scale: float | None = None,
                   blunder: tuple[int, int, float] | None = None,
                   ) -> tuple[object, ReferenceInput]:
    """Sim's solution and the same observations as a ReferenceInput (nav as initial EOPs);
    ``blunder`` (image, observation, pixels) moves one image point's u."""
    frames = list(flight.frames())
    if blunder is not None:
        i, k, px = blunder
        uv = frames[i].uv_px.copy()
        uv[k, 0] += px
        frames[i] = dataclasses.replace(frames[i], uv_px=uv)
    sim = SimultaneousAT(flight.camera, SimOptions(robust_scale=robust_scale),
                         refit_every_frame=False)
    for frame in frames:
        sim.add_frame(frame)
    solution = sim.solution()
    est = {p.point_id: p.xyz_m for p in solution.points}
    point_ids = tuple(est)
    index = {p: j for j, p in enumerate(point_ids)}
    obs_i, obs_p, uv = [], [], []
    for i, frame in enumerate(frames):
        for pid, u in zip(frame.point_ids, frame.uv_px, strict=True):
            if pid in index:
                obs_i.append(i)
                obs_p.append(index[pid])
                uv.append(u)
    cam = flight.camera
    cfg = CameraConfig(model="PINHOLE", width_px=cam.width_px, height_px=cam.height_px,
                       fx_px=cam.f_px, fy_px=cam.f_px, cx_px=cam.cx_px, cy_px=cam.cy_px)
    # Points start 0.5 m off Sim's solution: COLMAP must find the minimum by itself.
    start = np.array([est[p] for p in point_ids]) + np.random.default_rng(5).normal(
        0.0, 0.5, (len(point_ids), 3))
    data = ReferenceInput(camera=cfg, image_ids=flight.image_ids, nav_eop=flight.nav_eop,
                          nav_sigma=flight.nav_sigma, sigma_px=flight.sigma_px,
                          point_ids=point_ids, obs_image=np.asarray(obs_i),
                          obs_point=np.asarray(obs_p), obs_uv_px=np.asarray(uv),
                          eop0=flight.nav_eop.copy(), xyz0=start)
    return solution, data


def test_colmap_bundle_adjustment_equals_sim(small_sim: SimulatedFlight) -> None:
    solution, data = _sim_and_input(small_sim)  # least squares, both
    result = adjust_reference(data, ReferenceOptions(robust_loss=RobustLoss.TRIVIAL))
    assert result.converged
    sim_eop = np.array([e.eop for e in solution.eops])
    d = result.eop - sim_eop
    assert np.max(np.abs(d[:, :3])) <= AGREEMENT_POS_M
    assert np.max(np.degrees(np.abs(d[:, 3:]))) <= AGREEMENT_ATT_DEG
    sim_xyz = {p.point_id: p.xyz_m for p in solution.points}
    d_gp = result.xyz - np.array([sim_xyz[p] for p in result.point_ids])
    assert np.max(np.abs(d_gp)) <= AGREEMENT_GP_M
    assert result.sigma0 == pytest.approx(solution.sigma0, rel=1e-6)
    assert result.redundancy == solution.redundancy
    # The residual count: 2 per observation + 6 per image prior, checked inside too.
    k, n = data.obs_image.size, len(data.image_ids)
    assert result.n_prior_residuals == POSE_PRIOR_RESIDUALS * n
    assert result.n_residuals == OBS_RESIDUALS * k + POSE_PRIOR_RESIDUALS * n
    # Posterior sigmas (COLMAP's tangent covariance, converted) equal Sim's.
    assert result.covariance_status == "computed"
    sim_sigma = np.array([e.sigma for e in solution.eops])
    np.testing.assert_allclose(result.eop_sigma, sim_sigma, rtol=SIGMA_REL)


def test_the_reference_takes_the_loss_of_the_runs_final_adjustment() -> None:
    """run.json's final_robust_scale (a contaminated flight's narrower core) is the run's
    loss; a run.json written before it gives its robust_scale; null: least squares."""
    assert run_loss_scale({"robustness": {"robust_scale": 3.0,
                                          "final_robust_scale": 2.0}}) == 2.0
    assert run_loss_scale({"robustness": {"robust_scale": 3}}) == 3.0
    assert run_loss_scale({"robustness": {"robust_scale": None,
                                          "final_robust_scale": None}}) is None
    assert run_loss_scale({}) is None


def test_robust_reference_follows_robust_sim_through_a_blunder(
        small_sim: SimulatedFlight) -> None:
    """Sim's default loss (least squares within 3 sigma, Cauchy beyond) and COLMAP's Huber
    loss at 3 sigma (what ``seqat reference`` uses for a robust run) share the core and both
    bound a blunder's pull: with a 200 px blunder in one image point they agree within
    ROBUST_AGREEMENT (measured 3.1 cm / 0.006 deg: Huber's linear tail still pulls), and both
    stay within 5 cm of the clean solution where least squares moves 1.8 m."""
    blunder = (5, 3, 200.0)
    clean, _ = _sim_and_input(small_sim, robust_scale=None)
    clean_eop = np.array([e.eop for e in clean.eops])
    solution, data = _sim_and_input(small_sim, robust_scale=ROBUST_SCALE, blunder=blunder)
    loss, k = loss_of_run(ROBUST_SCALE)
    assert loss is RobustLoss.HUBER and k == ROBUST_SCALE
    assert loss_of_run(None)[0] is RobustLoss.TRIVIAL
    result = adjust_reference(data, ReferenceOptions(robust_loss=loss, loss_scale_sigmas=k))
    assert result.converged
    sim_eop = np.array([e.eop for e in solution.eops])
    d = result.eop - sim_eop
    assert np.max(np.abs(d[:, :3])) <= ROBUST_AGREEMENT_POS_M
    assert np.max(np.degrees(np.abs(d[:, 3:]))) <= ROBUST_AGREEMENT_ATT_DEG
    # sigma0 weighs each image point as Huber's final IRLS weight min(1, a / r) does: the
    # blunder adds a r / sigma_px^2 = k r / sigma_px to the clean ssr, not its r^2 / sigma_px^2
    # (which made it 5.4 here)
    r_blunder = blunder[2] / data.sigma_px
    expected = np.sqrt(clean.sigma0**2 + k * r_blunder / result.redundancy)
    assert result.sigma0 == pytest.approx(expected, rel=0.01)
    ls = adjust_reference(data, ReferenceOptions(robust_loss=RobustLoss.TRIVIAL))
    ls_off = np.max(np.abs(ls.eop[:, :3] - clean_eop[:, :3]))
    for robust in (sim_eop, result.eop):
        off = np.max(np.abs(robust[:, :3] - clean_eop[:, :3]))
        assert off <= ROBUST_AGREEMENT_POS_M and 20 * off < ls_off


@pytest.mark.parametrize("loss", list(RobustLoss))
def test_loss_weight_is_the_derivative_of_ceres_loss(loss: RobustLoss) -> None:
    """:func:`loss_weight` is rho'(s) of Ceres' own loss function (pyceres), s = r^2."""
    import pyceres

    a = 3.0
    ceres = {RobustLoss.TRIVIAL: pyceres.TrivialLoss(), RobustLoss.HUBER: pyceres.HuberLoss(a),
             RobustLoss.CAUCHY: pyceres.CauchyLoss(a),
             RobustLoss.SOFT_L1: pyceres.SoftLOneLoss(a)}[loss]
    r = np.array([0.0, 0.5, 2.9, 3.0, 3.1, 10.0, 200.0])
    expected = [ceres.evaluate(float(x) ** 2)[1] for x in r]
    # pyceres returns rho' to ~1e-8 relative (measured 2e-8 at r = 3.1)
    np.testing.assert_allclose(loss_weight(loss, a, r), expected, rtol=1e-6)


def test_position_prior_on_a_strip_is_refused(small_sim: SimulatedFlight) -> None:
    _, data = _sim_and_input(small_sim)
    with pytest.raises(EstimationError, match="on a line"):
        check_prior_geometry(data, PriorKind.POSITION)
    check_prior_geometry(data, PriorKind.POSE)  # no error


@pytest.fixture(scope="module")
def sim_run(small_sim_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "run"
    run_flight(small_sim_dir, out, method=Method.SIM, final_only=True, progress=False)
    return out


def test_reference_stage_writes_readable_model_and_our_formats(sim_run: Path) -> None:
    summary = run_reference(sim_run)
    folder = sim_run / REFERENCE_DIR
    record = json.loads((folder / REFERENCE_JSON).read_text())
    assert record["converged"] and record["covariance"] == "computed"
    assert record["n_residuals"] == summary.record.n_residuals
    for source in ("bin", "txt"):
        assert (folder / COLMAP_MODEL_DIR / f"images.{source}").is_file()
    rec = pycolmap.Reconstruction(str(folder / COLMAP_MODEL_DIR))
    eops = read_eop_csv(folder / "eop.csv")
    points = read_points_csv(folder / "points.csv")
    assert rec.num_images() == len(eops) and rec.num_points3D() == len(points)
    # The COLMAP model is in world coordinates, and agrees with eop.csv.
    image = rec.find_image_with_name(eops.image_ids[3])
    np.testing.assert_allclose(eop_from_rigid(image.cam_from_world())[:3], eops.eop[3, :3],
                               rtol=0, atol=1e-6)
    # Same observations as the run's Sim: the reference reproduces it.
    run_eop = read_eop_csv(sim_run / "eop.csv")
    assert np.max(np.abs(eops.eop[:, :3] - run_eop.eop[:, :3])) <= AGREEMENT_POS_M


def test_an_image_nothing_placed_is_left_out_of_the_reference(sim_run: Path,
                                                               tmp_path: Path) -> None:
    """A GNSS dropout the run skipped (no position in nav.csv, none in eop.csv, no
    observation): the reference leaves the image out as the run did; its eop.csv holds no
    NaN (it wrote NaN positions, which every reader of eop.csv refuses)."""
    run = tmp_path / "run"
    shutil.copytree(sim_run, run, ignore=shutil.ignore_patterns(REFERENCE_DIR))
    gone = read_eop_csv(run / "eop.csv").image_ids[4]
    for name in ("nav.csv", "eop.csv", "observations.csv"):
        lines = (run / name).read_text().splitlines(keepends=True)
        if name == "nav.csv":
            lines = [",".join([f[0], f[1], "nan", "nan", "nan", *f[5:]])
                     if f[0] == gone else ln for ln, f in ((ln, ln.split(",")) for ln in lines)]
        else:
            lines = [ln for ln in lines if not ln.startswith(gone + ",")]
        (run / name).write_text("".join(lines))
    run_reference(run)
    eops = read_eop_csv(run / REFERENCE_DIR / "eop.csv")
    run_eop = read_eop_csv(run / "eop.csv")
    assert eops.image_ids == run_eop.image_ids and gone not in eops.image_ids
    assert np.all(np.isfinite(eops.eop)) and np.all(np.isfinite(eops.sigma))


def test_cli_reference_bad_input_is_exit_2_one_line(tmp_path: Path, sim_run: Path) -> None:
    result = CliRunner().invoke(app, ["reference", str(tmp_path / "absent")])
    assert result.exit_code == 2
    assert result.stderr.startswith("seqat: error: ") and result.stderr.count("\n") == 1
    assert "no such run folder" in result.stderr
    result = CliRunner().invoke(app, ["reference", str(sim_run), "--prior", "gps"])
    assert result.exit_code == 2
    assert result.stderr == ("seqat: error: --prior: expected one of pose, position, "
                             "got 'gps'\n")
