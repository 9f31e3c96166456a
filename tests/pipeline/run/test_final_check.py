"""The final check of a run: the flight adjusted once more from its GPS/INS, published when the
sequential solution stopped in a wrong minimum (pipeline.run.final_check)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.run.final_check import (
    MOVED_SIGMA,
    FinalChecker,
    check_warnings,
    fit_gain,
    moved_images,
)
from pipeline.run.robustness import check_summary
from pipeline.run.runner import Method, RunSummary, run_flight
from pipeline.run.store import read_eop_csv
from seqat.errors import EstimationError
from seqat.simultaneous import SimultaneousAT
from seqat.types import EopEstimate, Frame, PinholeCamera, Solution

from ..conftest import REPO_ROOT

#: Tie points of the real flight (CC0), IMG_0451-IMG_0470, self-calibrating: the run's
#: sequential solve stops in a wrong minimum when IMG_0465 ties the take-off images to the rest.
TAKEOFF = REPO_ROOT / "sample_data" / "seneca_takeoff_ties"
TAKEOFF_IMAGES = ("IMG_0451", "IMG_0452", "IMG_0453", "IMG_0454")


def _solution(eops: list[tuple[str, list[float], list[float]]], sigma0: float = 1.0,
              redundancy: int = 100) -> Solution:
    return Solution(eops=tuple(EopEstimate(image_id=i, eop=np.array(e), sigma=np.array(s))
                               for i, e, s in eops),
                    points=(), sigma0=sigma0, redundancy=redundancy)


def test_moved_images_and_gain_known_answers() -> None:
    sig = [0.1, 0.1, 0.2, 0.01, 0.01, 0.02]
    cold = _solution([("a", [0, 0, 0, 0, 0, np.pi - 0.01], sig),
                      ("b", [0, 0, 0, 0, 0, 0], sig),
                      ("c", [0, 0, 0, 0, 0, 0], [np.nan] * 6)])
    # a: kappa across +-pi, 0.02 rad apart = 1 sigma; b: z 0.8 m = 4 sigma; c: no sigma
    run = _solution([("a", [0.2, 0, 0, 0, 0, -np.pi + 0.01], sig),
                     ("b", [0, 0, 0.8, 0, 0, 0], sig),
                     ("c", [50, 0, 0, 0, 0, 0], sig)])
    moved, worst = moved_images(run, cold)
    assert moved == ("b",)
    assert worst == pytest.approx(4.0)
    assert MOVED_SIGMA < 4.0
    assert fit_gain(_solution([], 1.1, 1000), _solution([], 1.0, 900)) == pytest.approx(210.0)
    assert fit_gain(_solution([], 1.0, 1000), _solution([], np.nan, 900)) == -np.inf


def test_check_summary_in_words() -> None:
    assert check_summary(None) == "not run"
    assert check_summary({"failed": "cold: no convergence"}).startswith("no solution")
    assert check_summary({"max_moved_sigma": 0.02, "moved_images": []}) == (
        "agrees (largest difference 0.0 σ)")
    moved = {"max_moved_sigma": 16.0, "moved_images": ["x", "y"], "sigma0_warm": 0.75,
             "sigma0_cold": 0.73}
    assert check_summary({**moved, "adopted": True}).startswith("wrong minimum: 2 image(s) up "
                                                                "to 16 σ apart")
    assert "kept" in check_summary({**moved, "adopted": False})


def test_a_sim_adjusting_once_is_not_checked_again() -> None:
    cam = PinholeCamera(f_px=1000.0, cx_px=500.0, cy_px=400.0, width_px=1000, height_px=800)
    assert FinalChecker.of(SimultaneousAT(cam, refit_every_frame=False)) is None
    assert FinalChecker.of(SimultaneousAT(cam)) is not None
    assert FinalChecker.of(object()) is None


@pytest.fixture(scope="module")
def takeoff_batch(tmp_path_factory: pytest.TempPathFactory) -> RunSummary:
    """Sim adjusting the take-off flight once, from its GPS/INS."""
    return run_flight(TAKEOFF, tmp_path_factory.mktemp("batch"), method=Method.SIM,
                      final_only=True, progress=False)


@pytest.mark.parametrize("method", [Method.SEQ_R])
def test_a_run_in_a_wrong_minimum_publishes_the_flight_adjusted_from_its_gps_ins(
        tmp_path: Path, method: Method, takeoff_batch: RunSummary) -> None:
    # Real tie points: without the check, the take-off images end metres and degrees from
    # where the whole flight adjusted at once puts them, many published sigmas away.
    (tmp_path / "off.yaml").write_text("final_check: false\n")
    unchecked = run_flight(TAKEOFF, tmp_path / "off", method=method, progress=False,
                           options_path=tmp_path / "off.yaml")
    checked = run_flight(TAKEOFF, tmp_path / "on", method=method, progress=False)
    batch = takeoff_batch
    off, on, ref = (read_eop_csv(s.out_dir / "eop.csv") for s in (unchecked, checked, batch))
    first = [off.image_ids.index(i) for i in TAKEOFF_IMAGES]
    apart = np.linalg.norm(off.eop[first, :3] - ref.eop[first, :3], axis=1)
    assert apart.max() > 5.0  # the wrong minimum
    assert np.all(apart / off.sigma[first, :3].max(axis=1) > MOVED_SIGMA)
    # checked: the batch adjustment's solution, its fit better than the run's
    np.testing.assert_allclose(on.eop, ref.eop, atol=1e-6)
    np.testing.assert_allclose(on.sigma, ref.sigma, rtol=1e-6)
    assert checked.sigma0 == pytest.approx(batch.sigma0)
    assert checked.sigma0 < unchecked.sigma0
    doc = json.loads((checked.out_dir / "run.json").read_text())
    check = doc["robustness"]["final_check"]
    assert check["adopted"] is True and check["gain"] > 25
    assert set(TAKEOFF_IMAGES) <= set(check["moved_images"])
    assert check["sigma0_cold"] == pytest.approx(checked.sigma0)
    assert any(w.startswith("final check: the sequential solution was in a wrong minimum")
               for w in doc["warnings"])
    assert json.loads((unchecked.out_dir / "run.json").read_text())["robustness"][
        "final_check"] is None


def test_the_final_check_leaves_a_clean_run_alone(tmp_path: Path) -> None:
    strip = REPO_ROOT / "sample_data" / "strip_demo"
    (tmp_path / "off.yaml").write_text("final_check: false\n")
    on = run_flight(strip, tmp_path / "on", progress=False)
    off = run_flight(strip, tmp_path / "off", progress=False, options_path=tmp_path / "off.yaml")
    for name in ("eop.csv", "points.csv"):
        assert (on.out_dir / name).read_bytes() == (off.out_dir / name).read_bytes()
    check = json.loads((on.out_dir / "run.json").read_text())["robustness"]["final_check"]
    assert check["adopted"] is False and check["moved_images"] == []
    assert check["max_moved_sigma"] < 1.0 and check["sigma0_warm"] is None
    assert check_warnings(None) == []


def test_a_check_that_fails_leaves_the_run_standing(monkeypatch: pytest.MonkeyPatch) -> None:
    cam = PinholeCamera(f_px=1000.0, cx_px=500.0, cy_px=400.0, width_px=1000, height_px=800)
    checker = FinalChecker.of(SimultaneousAT(cam))
    assert checker is not None

    def fail(frames: object, start: object) -> None:
        raise EstimationError("adjustment diverges")

    monkeypatch.setattr(checker, "_adjust", fail)
    run = _solution([("a", [0.0] * 6, [1.0] * 6)])
    check, adopted, solution = checker.run([], run)
    assert adopted is None and solution is run
    assert check.failed == "cold: adjustment diverges" and check.max_moved_sigma is None
    assert check_summary(dataclasses.asdict(check)).startswith("no solution (cold: adjustment")


@pytest.mark.parametrize(("warm_z", "sigma0_warm", "diverged", "published"), [
    (0.0, 1.01, ((), ()), "run"),      # the run a minimum; cold better by 20 < 25: kept
    (0.0, 1.2, ((), ()), "cold"),      # ... by 440: the cold one
    (0.0, 1.2, ((), ("a",)), "run"),   # ... but it leaves out an image the warm one keeps
    (5.0, 0.99, ((), ()), "warm"),     # Sim leaves the run's EOPs; warm fits better
    (5.0, 1.01, ((), ()), "cold"),     # ... cold better, if only by 20
    (5.0, 0.99, (("b",), ()), "run"),  # ... the warm one leaves out an image cold keeps
], ids=["cold-not-better-enough", "cold", "cold-diverges-more", "warm", "cold-after-warm-left",
        "warm-diverges-more"])
def test_which_solution_the_check_publishes(monkeypatch: pytest.MonkeyPatch, warm_z: float,
                                            sigma0_warm: float,
                                            diverged: tuple[tuple[str, ...], ...],
                                            published: str) -> None:
    """Known answers of the decision: the cold adjustment (image b 10 sigma from the run)
    replaces the run when it fits better than the warm one by more than MIN_GAIN; when the
    warm one itself left the run's EOPs (``warm_z`` sigma), the better fitting of the two
    is published; never one that leaves out an image the other keeps."""
    from types import SimpleNamespace

    cam = PinholeCamera(f_px=1000.0, cx_px=500.0, cy_px=400.0, width_px=1000, height_px=800)
    checker = FinalChecker.of(SimultaneousAT(cam))
    assert checker is not None
    sig = [0.1] * 3 + [0.01] * 3
    run = _solution([("a", [0.0] * 6, sig), ("b", [0.0] * 6, sig)])
    cold = _solution([("a", [0.0] * 6, sig), ("b", [1.0] + [0.0] * 5, sig)], 1.0, 1000)
    warm = _solution([("a", [0.0] * 6, sig), ("b", [0.1 * warm_z] + [0.0] * 5, sig)],
                     sigma0_warm, 1000)
    est = {None: SimpleNamespace(diverged=list(diverged[1])),
           "warm": SimpleNamespace(diverged=list(diverged[0]))}
    monkeypatch.setattr(checker, "_adjust", lambda frames, start: (
        (est[None], cold) if start is None else (est["warm"], warm)))
    check, adopted, solution = checker.run([], run)
    assert check.moved_images == ("b",) and check.published == published
    assert check.adopted == (published != "run")
    assert check.warm_moved_images == (("b",) if warm_z > MOVED_SIGMA else ())
    assert solution is {"run": run, "cold": cold, "warm": warm}[published]
    assert adopted is {"run": None, "cold": est[None], "warm": est["warm"]}[published]
    if published != "run":
        assert check_warnings(check)[0].startswith("final check: the sequential solution was")
        assert check_summary(dataclasses.asdict(check)).startswith("wrong minimum")


def test_the_cold_start_is_the_gps_ins_but_for_a_dropout(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    cam = PinholeCamera(f_px=1000.0, cx_px=500.0, cy_px=400.0, width_px=1000, height_px=800)
    checker = FinalChecker.of(SimultaneousAT(cam))
    assert checker is not None
    seen: dict[str, object] = {}
    monkeypatch.setattr(SimultaneousAT, "add_frame",
                        lambda self, f: seen.__setitem__(f.image_id, f.initial_eop))
    monkeypatch.setattr(SimultaneousAT, "solution", lambda self: None)
    start = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.1])
    sigma = np.array([3.0, 3.0, 5.0, 0.1, 0.1, 0.2])
    frames = [Frame(image_id=i, nav_eop=np.zeros(6), nav_sigma=s, point_ids=(),
                    uv_px=np.zeros((0, 2)), sigma_px=1.0, initial_eop=start)
              for i, s in (("resected", sigma), ("dropout", np.r_[np.inf, np.inf, np.inf,
                                                                  sigma[3:]]))]
    checker._adjust(frames, None)
    assert seen["resected"] is None
    np.testing.assert_array_equal(seen["dropout"], start)
    checker._adjust(frames, {"resected": start + 1.0})
    np.testing.assert_array_equal(seen["resected"], start + 1.0)
    assert seen["dropout"] is None
