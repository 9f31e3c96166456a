"""GTSAM fixed-lag benchmark (optional gtsam): pose conversion, prior mapping, a tiny run."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from pipeline.bench.gtsam import (  # noqa: E402
    attitude_jacobian,
    calibration,
    check_conversion,
    eop_to_pose3,
    pose3_to_eop,
    prior_noise,
    run_gtsam,
    run_gtsam_bench,
)
from seqat.errors import ConfigError  # noqa: E402
from seqat.geometry import project, rotation_matrix  # noqa: E402
from seqat.simulate import StripSimConfig, simulate_strip  # noqa: E402

TINY_CONFIG = """\
kind: observations
crs: "EPSG:32652"
simulation:
  n_images: 15
  n_points: 60
"""


def test_pose_conversion_projects_like_seqat() -> None:
    """A noise-free strip: GTSAM's camera reproduces the observed pixels and seqat's project."""
    cfg = StripSimConfig(n_images=12, n_points=40, sigma_px=1e-12, sigma_position_m=1e-9,
                         sigma_attitude_deg=1e-9)
    flight = simulate_strip(cfg, seed=3)
    c = check_conversion(flight)
    assert c["max_px_vs_seqat_project"] < 1e-6
    assert c["max_px_vs_observed"] < 1e-6
    assert c["max_roundtrip_m"] < 1e-9
    assert c["max_roundtrip_rad"] < 1e-12


def test_pose_conversion_oblique_and_round_trip() -> None:
    """Away from nadir too: one point through PinholeCameraCal3_S2 and seqat.geometry.project."""
    cam = StripSimConfig().camera
    eop = np.array([500010.0, 4090020.0, 320.0, 0.2, -0.3, 2.5])
    origin = np.array([500000.0, 4090000.0, 0.0])
    R = rotation_matrix(*eop[3:])
    X = eop[:3] - 150.0 * R[:, 2] + 20.0 * R[:, 0] - 10.0 * R[:, 1]  # in front (-z)
    pose = eop_to_pose3(eop, origin)
    uv = gtsam.PinholeCameraCal3_S2(pose, calibration(cam)).project(X - origin)
    np.testing.assert_allclose(uv, project(eop[None], X[None], cam)[0], atol=1e-9)
    np.testing.assert_allclose(pose3_to_eop(pose, origin), eop, atol=1e-9)


def test_attitude_jacobian_and_prior_sigmas() -> None:
    """d[omega, phi, kappa] -> GTSAM body tangent, and the prior's whitened error of a perturbed
    pose equals the perturbation over its sigma (first order)."""
    eop = np.array([10.0, 20.0, 300.0, 0.05, -0.4, 1.2])
    h = 1e-6
    R0 = eop_to_pose3(eop, np.zeros(3)).rotation()
    num = np.column_stack([
        gtsam.Rot3.Logmap(R0.between(eop_to_pose3(eop + h * np.eye(6)[3 + c],
                                                  np.zeros(3)).rotation())) / h
        for c in range(3)
    ])
    np.testing.assert_allclose(num, attitude_jacobian(*eop[3:]), atol=1e-6)
    sigma = np.array([0.3, 0.3, 0.5, 1e-3, 2e-3, 3e-3])
    noise, _ = prior_noise(eop, sigma)
    factor = gtsam.PriorFactorPose3(1, eop_to_pose3(eop, np.zeros(3)), noise)
    for c in range(6):
        d = 1e-3 * sigma[c]
        values = gtsam.Values()
        values.insert(1, eop_to_pose3(eop + d * np.eye(6)[c], np.zeros(3)))
        # error() = 0.5 |whitened|^2: the perturbation is 1e-3 sigma
        assert np.sqrt(2 * factor.error(values)) == pytest.approx(1e-3, rel=1e-3)


def test_tiny_strip_bench(tmp_path: Path) -> None:
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY_CONFIG, encoding="utf-8")
    report = run_gtsam_bench(config, seeds=(1,), lag_images=(5,), out_dir=tmp_path / "out")
    (seed,) = report["results"]
    rows = {m["label"]: m for m in seed["methods"]}
    g = rows["GTSAM iFLS lag 5"]
    assert g["failure"] is None
    nav_sigma = StripSimConfig().sigma_position_m
    assert g["accuracy"]["n_images"] == 15
    assert g["accuracy"]["pos_rmse_m"] < 3 * nav_sigma
    assert g["accuracy"]["gp_rmse_m"] < 3 * nav_sigma
    assert g["extra"]["threads_max"] == g["extra"]["threads_before"]  # gtsam starts no threads
    assert rows["Seq-R ρ≥0.1"]["accuracy"]["pos_rmse_m"] < 3 * nav_sigma
    data = json.loads((tmp_path / "out" / "bench_gtsam.json").read_text(encoding="utf-8"))
    summary = {s["label"]: s for s in data["summary"]}
    assert set(summary) == {"Seq-R ρ≥0.1", "Seq-R ρ≥0.1 RTS-smoothed (same run)",
                            "GTSAM iFLS lag 5"}
    assert summary["GTSAM iFLS lag 5"]["ratio_to_gtsam_median"]["GTSAM iFLS lag 5"] == 1.0
    assert summary["Seq-R ρ≥0.1"]["update"]["n"] == 5  # after the 10 initial images
    md = (tmp_path / "out" / "bench_gtsam.md").read_text(encoding="utf-8")
    assert "GTSAM iFLS lag 5" in md and "Seq-R" in md


def test_sigma_runs_time_the_marginals_seq_r_publishes(tmp_path: Path) -> None:
    """``--sigma pose``: one more run per lag that reads the new pose's marginal covariance
    after each update; its ratio reference is update + σ per image, its estimates those of
    the plain run (reading marginals changes no estimate)."""
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY_CONFIG, encoding="utf-8")
    report = run_gtsam_bench(config, seeds=(1,), lag_images=(5,), out_dir=tmp_path / "out",
                             sigmas=("pose", "pose"))
    (seed,) = report["results"]
    rows = {m["label"]: m for m in seed["methods"]}
    assert set(rows) == {"Seq-R ρ≥0.1", "Seq-R ρ≥0.1 RTS-smoothed (same run)",
                         "GTSAM iFLS lag 5", "GTSAM iFLS lag 5 + σ new pose"}  # once each
    plain, with_sigma = rows["GTSAM iFLS lag 5"], rows["GTSAM iFLS lag 5 + σ new pose"]
    assert plain["sigma"] is None and with_sigma["extra"]["sigma"] == "pose"
    assert with_sigma["sigma"]["n"] == 5 and with_sigma["sigma"]["median_ms"] > 0
    assert with_sigma["update_plus_sigma"]["median_ms"] > with_sigma["update"]["median_ms"]
    assert with_sigma["accuracy"] == plain["accuracy"]
    summary = {s["label"]: s for s in report["summary"]}
    own = summary["GTSAM iFLS lag 5 + σ new pose"]
    assert own["ratio_to_gtsam_median"]["GTSAM iFLS lag 5 + σ new pose"] == 1.0
    seq = summary["Seq-R ρ≥0.1"]
    assert seq["ratio_to_gtsam_median"]["GTSAM iFLS lag 5 + σ new pose"] == pytest.approx(
        seq["update"]["median_ms"] / own["update_plus_sigma"]["median_ms"])
    md = (tmp_path / "out" / "bench_gtsam.md").read_text(encoding="utf-8")
    assert "| GTSAM iFLS lag 5 + σ new pose |" in md


def test_a_marginal_error_ends_the_run_like_an_update_error(
        monkeypatch: pytest.MonkeyPatch) -> None:
    class Failing(gtsam.IncrementalFixedLagSmoother):
        def marginalCovariance(self, key):  # type: ignore[no-untyped-def]
            if gtsam.Symbol(key).index() == 2:
                raise RuntimeError("Indeterminant linear system detected (test)")
            return super().marginalCovariance(key)

    monkeypatch.setattr(gtsam, "IncrementalFixedLagSmoother", Failing)
    flight = simulate_strip(dataclasses.replace(StripSimConfig(), n_images=8, n_points=30), 2)
    run = run_gtsam(flight, lag=3, sigma="pose")
    assert run.failure is not None and run.failure["image"] == 2
    assert len(run.extra["sigma_ms"]) == len(run.update_ms) == 3  # type: ignore[arg-type]
    assert np.isnan(run.extra["sigma_ms"][-1])  # type: ignore[index]


def test_unknown_sigma_kind_is_a_config_error() -> None:
    flight = simulate_strip(dataclasses.replace(StripSimConfig(), n_images=4, n_points=20), 1)
    with pytest.raises(ConfigError, match="--sigma: expected one of"):
        run_gtsam(flight, lag=2, sigma="landmarks")


def test_gtsam_error_is_reported_not_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    """An exception from smoother.update (e.g. IndeterminantLinearSystemException at a
    marginalisation) ends the run with a failure record and the images done so far."""

    class Failing(gtsam.IncrementalFixedLagSmoother):
        calls = 0

        def update(self, *args, **kwargs):  # type: ignore[no-untyped-def]
            Failing.calls += 1
            if Failing.calls == 4:
                raise RuntimeError("Indeterminant linear system detected (test)")
            return super().update(*args, **kwargs)

    monkeypatch.setattr(gtsam, "IncrementalFixedLagSmoother", Failing)
    flight = simulate_strip(dataclasses.replace(StripSimConfig(), n_images=8, n_points=30), 2)
    run = run_gtsam(flight, lag=3)
    assert run.failure is not None and run.failure["image"] == 3
    assert "Indeterminant" in run.failure["message"]
    assert run.eop.shape == (3, 6)
