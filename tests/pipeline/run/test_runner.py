"""The run stage: estimator choice and options, streaming, outputs, nothing written on failure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.flight.folder import read_flight, read_truth
from pipeline.run import runner
from pipeline.run.runner import (
    EstimatorConfig,
    Method,
    estimator_options,
    load_estimator_config,
    run_flight,
)
from pipeline.run.store import read_eop_csv, read_points_csv
from seqat.errors import ConfigError, EstimationError
from seqat.sequential import SequentialOptions
from seqat.simultaneous import SimOptions
from seqat.types import Frame, ImageUpdate, PinholeCamera, Solution

from ..sample_flight import FlightMaker


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2)))


@pytest.mark.parametrize("method", [Method.SIM, Method.SEQ_R])
def test_run_improves_on_nav_and_writes_consistent_outputs(small_sim_dir: Path, tmp_path: Path,
                                                           method: Method) -> None:
    out = tmp_path / "run"
    summary = run_flight(small_sim_dir, out, method=method, progress=False)
    truth = read_truth(small_sim_dir)
    nav = read_flight(small_sim_dir).nav
    assert truth is not None
    eops, points = read_eop_csv(out / "eop.csv"), read_points_csv(out / "points.csv")
    assert eops.image_ids == truth.eop.image_ids == nav.image_ids
    # The adjustment uses the image points: positions beat the GPS/INS input they started from.
    est_err = rms(eops.eop[:, :3] - truth.eop.eop[:, :3])
    nav_err = rms(nav.eop[:, :3] - truth.eop.eop[:, :3])
    assert est_err < nav_err
    assert np.all(np.isfinite(eops.sigma)) and np.all(eops.sigma > 0)
    assert summary.n_images == len(eops) and summary.n_points == len(points)
    assert summary.accuracy is not None
    assert rms(np.asarray(summary.accuracy.pos_rmse_m)) == pytest.approx(est_err, rel=1e-9)
    assert rms(np.asarray(summary.accuracy.nav_pos_rmse_m)) == pytest.approx(nav_err, rel=1e-9)
    doc = json.loads((out / "run.json").read_text())
    assert doc["method"] == method.value and len(doc["images"]) == summary.n_images
    assert [r["image_id"] for r in doc["images"]] == list(nav.image_ids)
    assert doc["totals"]["observations"] == summary.n_observations
    assert doc["totals"]["sigma0"] == pytest.approx(summary.sigma0)
    assert doc["totals"]["update_ms"]["total_ms"] == pytest.approx(
        sum(r["update_ms"] for r in doc["images"]))


def test_flags_override_the_options_file(tmp_path: Path) -> None:
    path = tmp_path / "est.yaml"
    path.write_text("sequential:\n  correlation_threshold: 0.3\n  initial_images: 6\n"
                    "  sim: {max_iterations: 7}\nsim: {max_iterations: 9}\n")
    config = load_estimator_config(path)
    seq_r = estimator_options(Method.SEQ_R, config, initial_images=4)
    assert isinstance(seq_r, SequentialOptions)
    assert (seq_r.correlation_threshold, seq_r.initial_images, seq_r.sim.max_iterations) == (
        0.3, 4, 7)
    lower = estimator_options(Method.SEQ_R, config, threshold=0.05)
    assert isinstance(lower, SequentialOptions) and lower.correlation_threshold == 0.05
    seq_f = estimator_options(Method.SEQ_F, config)
    assert isinstance(seq_f, SequentialOptions) and seq_f.correlation_threshold is None
    sim = estimator_options(Method.SIM, config, final_only=True)
    assert isinstance(sim, SimOptions) and sim.max_iterations == 9


@pytest.mark.parametrize(("method", "kwargs", "message"), [
    (Method.SEQ_F, {"threshold": 0.2}, "--threshold applies to --method seq-r"),
    (Method.SIM, {"threshold": 0.2}, "--threshold applies to the sequential methods"),
    (Method.SIM, {"initial_images": 5}, "--initial-images applies to the sequential methods"),
    (Method.SEQ_R, {"final_only": True}, "--final-only applies to --method sim"),
    (Method.SEQ_R, {"threshold": 1.5}, "correlation_threshold: expected a value in [0, 1]"),
])
def test_inapplicable_or_bad_flags_are_config_errors(method: Method, kwargs: dict[str, object],
                                                     message: str) -> None:
    with pytest.raises(ConfigError) as info:
        estimator_options(method, EstimatorConfig(), **kwargs)  # type: ignore[arg-type]
    assert message in str(info.value)


def test_options_file_unknown_key_names_file(tmp_path: Path) -> None:
    path = tmp_path / "est.yaml"
    path.write_text("sequential: {treshold: 0.2}\n")
    with pytest.raises(ConfigError, match=r"est\.yaml: sequential\.treshold: unknown key"):
        load_estimator_config(path)


class RecordingEstimator:
    """Fake estimator: records the frames it gets, fails in solution()."""

    def __init__(self) -> None:
        self.frames: list[Frame] = []

    def add_frame(self, frame: Frame) -> ImageUpdate:
        self.frames.append(frame)
        raise EstimationError("singular window: cond 1e17")

    def solution(self) -> Solution:
        raise AssertionError("not reached")


def test_estimation_failure_writes_nothing(make_flight: FlightMaker, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    fake = RecordingEstimator()

    def make(method: Method, camera: PinholeCamera, options: object, *,
             final_only: bool = False, control: object = ()) -> RecordingEstimator:
        return fake

    monkeypatch.setattr(runner, "make_estimator", make)
    out = tmp_path / "out"
    with pytest.raises(EstimationError, match="singular window"):
        run_flight(make_flight(), out, method=Method.SEQ_R, progress=False)
    assert [f.image_id for f in fake.frames] == ["img_1"]
    assert not out.exists()


def test_a_self_calibration_that_holds_every_parameter_is_the_fixed_camera(
        autzen_run: Path, tmp_path: Path) -> None:
    """The rendered sample (OPENCV camera, k1 -0.08): self-calibrated, its 12 images hold
    every interior parameter at the prior, and the solution is the fixed camera's
    (docs/architecture.md, *Distortion is in the model*). With the distortion removed from
    the fixed camera's image points their noise was stretched and σ0 read 0.503, not 0.484."""
    from ..sample_runs import AUTZEN

    out = tmp_path / "calibrated"
    run_flight(AUTZEN, out, progress=False, self_calibration=True)
    fixed, held = (json.loads((run / "run.json").read_text()) for run in (autzen_run, out))
    assert held["camera_estimate"]["free"] == []
    assert held["totals"]["redundancy"] == fixed["totals"]["redundancy"]
    assert held["totals"]["sigma0"] == pytest.approx(fixed["totals"]["sigma0"], rel=1e-4)
    a, b = read_eop_csv(autzen_run / "eop.csv"), read_eop_csv(out / "eop.csv")
    assert a.image_ids == b.image_ids
    np.testing.assert_allclose(b.eop[:, :3], a.eop[:, :3], rtol=0, atol=1e-4)  # 0.1 mm
    np.testing.assert_allclose(b.eop[:, 3:], a.eop[:, 3:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.sigma, a.sigma, rtol=1e-3)
